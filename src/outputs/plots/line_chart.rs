//! A line chart on linear axes: several named series of (x, y) points, each a polyline in its
//! own colour with a dot at every point (or a dashed line without dots, for a reference
//! curve), an optional note at its last point (where a series stopped), a legend at the
//! right. The pressure–volume curves of the validation report are drawn with it.

use super::draw::{canvas, draw_segment, fill_disk, fill_rect, outline_rect};
use super::scale::{format_tick, min_max, nice_step, ticks, widen_if_flat};
use super::{BLACK, FRAME_GREY, GRID_GREY, TEXT_SCALE, WHITE};
use crate::outputs::quicklook::RgbImage;
use crate::outputs::raster_text::{draw_text, draw_text_up, text_height_px, text_width_px};
use crate::{Error, Result};

/// Width of a line chart, pixels.
pub const LINE_CHART_WIDTH_PX: usize = 1000;
/// Height of a line chart, pixels.
pub const LINE_CHART_HEIGHT_PX: usize = 620;

/// Colours of the series, in order (repeated beyond eight).
pub const SERIES_COLOURS: [[u8; 3]; 8] = [
    [31, 119, 180],
    [214, 39, 40],
    [44, 160, 44],
    [148, 103, 189],
    [255, 127, 14],
    [90, 90, 90],
    [23, 190, 207],
    [140, 86, 75],
];

/// One named series of a line chart.
#[derive(Debug, Clone)]
pub struct LineSeries {
    /// Legend name (printable ASCII; other characters show as boxes).
    pub name: String,
    /// Points in data units, joined in the order given.
    pub points: Vec<[f64; 2]>,
    /// A dashed line without dots (a reference curve) instead of a solid line with dots.
    pub dashed: bool,
    /// Written beside the last point, with a cross on it (e.g. why the series stopped).
    pub end_note: Option<String>,
}

/// The plot area of a line chart and its data ranges.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ChartAxes {
    /// Pixel column of the plot area's left edge (x = `x_range[0]`).
    pub left_px: f64,
    /// Pixel column of its right edge.
    pub right_px: f64,
    /// Pixel row of its top edge (y = `y_range[1]`).
    pub top_px: f64,
    /// Pixel row of its bottom edge.
    pub bottom_px: f64,
    /// x at the left and right edges.
    pub x_range: [f64; 2],
    /// y at the bottom and top edges.
    pub y_range: [f64; 2],
}

impl ChartAxes {
    /// Continuous pixel `[col, row]` of a data point.
    pub fn to_pixel(&self, x: f64, y: f64) -> [f64; 2] {
        let [x0, x1] = self.x_range;
        let [y0, y1] = self.y_range;
        [
            self.left_px + (x - x0) / (x1 - x0) * (self.right_px - self.left_px),
            self.bottom_px - (y - y0) / (y1 - y0) * (self.bottom_px - self.top_px),
        ]
    }
}

/// Draws the chart; refuses a chart without points or with a non-finite point, naming the
/// series.
pub fn render_line_chart(
    title: &str,
    x_label: &str,
    y_label: &str,
    series: &[LineSeries],
) -> Result<(RgbImage, ChartAxes)> {
    if series.iter().all(|s| s.points.is_empty()) {
        return Err(Error::Argument {
            what: "line chart".into(),
            reason: "no points to draw".into(),
        });
    }
    if let Some(s) = series
        .iter()
        .find(|s| s.points.iter().flatten().any(|v| !v.is_finite()))
    {
        return Err(Error::Argument {
            what: "line chart".into(),
            reason: format!("series {} has a non-finite point", s.name),
        });
    }
    let all = || series.iter().flat_map(|s| s.points.iter());
    let (x_lo, x_hi) = min_max(all().map(|p| p[0]));
    let (y_lo, y_hi) = min_max(all().map(|p| p[1]));
    let (x_lo, x_hi) = widen_if_flat(x_lo, x_hi, 1.0);
    let (y_lo, y_hi) = widen_if_flat(y_lo, y_hi, 1.0);
    let (x_pad, y_pad) = (0.04 * (x_hi - x_lo), 0.05 * (y_hi - y_lo));
    let legend_w = series
        .iter()
        .map(|s| text_width_px(&s.name, TEXT_SCALE))
        .max()
        .unwrap_or(0) as f64;
    let axes = ChartAxes {
        left_px: 100.0,
        right_px: (LINE_CHART_WIDTH_PX as f64 - 70.0 - legend_w).max(400.0),
        top_px: 50.0,
        bottom_px: LINE_CHART_HEIGHT_PX as f64 - 70.0,
        x_range: [x_lo - x_pad, x_hi + x_pad],
        y_range: [y_lo - y_pad, y_hi + y_pad],
    };
    let mut image = canvas(LINE_CHART_WIDTH_PX, LINE_CHART_HEIGHT_PX, WHITE);
    draw_grid(&mut image, &axes);
    let mut notes = Vec::new();
    for (k, s) in series.iter().enumerate() {
        let colour = SERIES_COLOURS[k % SERIES_COLOURS.len()];
        draw_series(&mut image, &axes, s, colour, &mut notes);
    }
    let (l, r, t, b) = (
        axes.left_px as i64,
        axes.right_px as i64,
        axes.top_px as i64,
        axes.bottom_px as i64,
    );
    outline_rect(&mut image, l, t, r - l + 1, b - t + 1, BLACK);
    let th = text_height_px(TEXT_SCALE) as i64;
    let w = text_width_px(x_label, TEXT_SCALE) as i64;
    draw_text(
        &mut image,
        x_label,
        (l + r - w) / 2,
        b + 16 + th,
        TEXT_SCALE,
        BLACK,
    );
    let w = text_width_px(y_label, TEXT_SCALE) as i64;
    draw_text_up(&mut image, y_label, 14, (t + b + w) / 2, TEXT_SCALE, BLACK);
    draw_text(&mut image, title, l, 16, TEXT_SCALE, BLACK);
    for (k, s) in series.iter().enumerate() {
        let colour = SERIES_COLOURS[k % SERIES_COLOURS.len()];
        let y = t + 10 + k as i64 * (th + 12);
        let x = r + 16;
        if s.dashed {
            for d in 0..3 {
                fill_rect(&mut image, x + d * 7, y + th / 2 - 1, 4, 3, colour);
            }
        } else {
            fill_rect(&mut image, x, y + th / 2 - 1, 18, 3, colour);
            fill_disk(&mut image, (x + 9) as f64, (y + th / 2) as f64, 4.0, colour);
        }
        draw_text(&mut image, &s.name, x + 26, y, TEXT_SCALE, BLACK);
    }
    Ok((image, axes))
}

/// Grid lines at round values with tick labels; the zero lines darker.
fn draw_grid(image: &mut RgbImage, axes: &ChartAxes) {
    let (l, r, t, b) = (axes.left_px, axes.right_px, axes.top_px, axes.bottom_px);
    let th = text_height_px(TEXT_SCALE) as i64;
    let [x0, x1] = axes.x_range;
    let step = nice_step(x1 - x0, 8);
    for v in ticks(x0, x1, step) {
        let [x, _] = axes.to_pixel(v, axes.y_range[0]);
        let colour = if v.abs() < 1e-9 * step {
            FRAME_GREY
        } else {
            GRID_GREY
        };
        fill_rect(image, x.round() as i64, t as i64, 1, (b - t) as i64, colour);
        let label = format_tick(v, step);
        let w = text_width_px(&label, TEXT_SCALE) as i64;
        draw_text(
            image,
            &label,
            x.round() as i64 - w / 2,
            b as i64 + 8,
            TEXT_SCALE,
            BLACK,
        );
    }
    let [y0, y1] = axes.y_range;
    let step = nice_step(y1 - y0, 6);
    for v in ticks(y0, y1, step) {
        let [_, y] = axes.to_pixel(axes.x_range[0], v);
        let colour = if v.abs() < 1e-9 * step {
            FRAME_GREY
        } else {
            GRID_GREY
        };
        fill_rect(image, l as i64, y.round() as i64, (r - l) as i64, 1, colour);
        let label = format_tick(v, step);
        let w = text_width_px(&label, TEXT_SCALE) as i64;
        draw_text(
            image,
            &label,
            l as i64 - 8 - w,
            y.round() as i64 - th / 2,
            TEXT_SCALE,
            BLACK,
        );
    }
}

/// One series: its line (dashed or solid with dots) and its end note, moved down below the
/// notes already in `notes` (boxes `[left, top, right, bottom]`) that it would cover.
fn draw_series(
    image: &mut RgbImage,
    axes: &ChartAxes,
    s: &LineSeries,
    colour: [u8; 3],
    notes: &mut Vec<[i64; 4]>,
) {
    let at: Vec<[f64; 2]> = s.points.iter().map(|p| axes.to_pixel(p[0], p[1])).collect();
    for w in at.windows(2) {
        if s.dashed {
            let (dx, dy) = (w[1][0] - w[0][0], w[1][1] - w[0][1]);
            let len = dx.hypot(dy);
            let dashes = (len / 8.0).ceil().max(1.0) as usize;
            for k in (0..dashes).step_by(2) {
                let (t0, t1) = (
                    k as f64 / dashes as f64,
                    ((k + 1) as f64 / dashes as f64).min(1.0),
                );
                draw_segment(
                    image,
                    [w[0][0] + t0 * dx, w[0][1] + t0 * dy],
                    [w[0][0] + t1 * dx, w[0][1] + t1 * dy],
                    1.3,
                    colour,
                );
            }
        } else {
            draw_segment(image, w[0], w[1], 1.3, colour);
        }
    }
    if !s.dashed {
        for p in &at {
            fill_disk(image, p[0], p[1], 3.5, colour);
        }
    }
    if let (Some(note), Some(&[x, y])) = (&s.end_note, at.last()) {
        draw_segment(image, [x - 7.0, y - 7.0], [x + 7.0, y + 7.0], 1.5, colour);
        draw_segment(image, [x - 7.0, y + 7.0], [x + 7.0, y - 7.0], 1.5, colour);
        let th = text_height_px(TEXT_SCALE) as i64;
        let w = text_width_px(note, TEXT_SCALE) as i64;
        // Left of the cross when it would run past the plot area.
        let left = if x as i64 + 12 + w > axes.right_px as i64 {
            x as i64 - 12 - w
        } else {
            x as i64 + 12
        };
        let mut top = y as i64 - th - 4;
        while notes
            .iter()
            .any(|b| left < b[2] && b[0] < left + w && top < b[3] && b[1] < top + th)
        {
            top += th + 4;
        }
        notes.push([left, top, left + w, top + th]);
        draw_text(image, note, left, top, TEXT_SCALE, colour);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pixel(image: &RgbImage, p: [f64; 2]) -> [u8; 3] {
        let o = 3 * (p[1].round() as usize * image.width + p[0].round() as usize);
        [image.pixels[o], image.pixels[o + 1], image.pixels[o + 2]]
    }

    #[test]
    fn points_and_lines_land_where_the_axes_put_them() {
        let series = [
            LineSeries {
                name: "model".into(),
                points: vec![[0.0, 0.0], [100.0, 200.0], [300.0, 400.0]],
                dashed: false,
                end_note: Some("stops".into()),
            },
            LineSeries {
                name: "reference".into(),
                points: vec![[0.0, 0.0], [400.0, 300.0]],
                dashed: true,
                end_note: None,
            },
        ];
        let (image, axes) =
            render_line_chart("P-V", "pressure (Pa)", "volume (mL)", &series).unwrap();
        assert_eq!(image.width, LINE_CHART_WIDTH_PX);
        assert!(axes.x_range[0] < 0.0 && axes.x_range[1] > 400.0);
        assert!(axes.y_range[0] < 0.0 && axes.y_range[1] > 400.0);
        assert_eq!(
            pixel(&image, axes.to_pixel(100.0, 200.0)),
            SERIES_COLOURS[0]
        );
        assert_eq!(
            pixel(&image, axes.to_pixel(200.0, 300.0)),
            SERIES_COLOURS[0],
            "on the line"
        );
        // The dashed reference has ink near its start and a gap somewhere along it.
        let along: Vec<[u8; 3]> = (0..200)
            .map(|k| {
                pixel(
                    &image,
                    axes.to_pixel(400.0 * k as f64 / 200.0, 300.0 * k as f64 / 200.0),
                )
            })
            .collect();
        assert!(along.contains(&SERIES_COLOURS[1]));
        assert!(
            along.iter().any(|c| *c != SERIES_COLOURS[1]),
            "dashed, not solid"
        );
        assert_eq!(
            pixel(&image, axes.to_pixel(330.0, 70.0)),
            WHITE,
            "off every line"
        );
    }

    #[test]
    fn an_empty_chart_or_a_non_finite_point_is_refused() {
        assert!(render_line_chart("t", "x", "y", &[]).is_err());
        let bad = [LineSeries {
            name: "linear".into(),
            points: vec![[0.0, f64::NAN]],
            dashed: false,
            end_note: None,
        }];
        let e = render_line_chart("t", "x", "y", &bad)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("series linear") && e.contains("non-finite"),
            "{e}"
        );
    }
}
