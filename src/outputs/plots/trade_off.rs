//! The time–error plot of an element-size study: one labelled point per element size, run
//! time (s) to the right and error (mm) upwards, both on decade (log₁₀) axes, one colour per
//! case.

use super::draw::{canvas, draw_polyline, draw_segment, fill_disk, fill_rect, outline_rect};
use super::{BLACK, FRAME_GREY, GRID_GREY, TEXT_SCALE, WHITE};
use crate::outputs::quicklook::RgbImage;
use crate::outputs::raster_text::{draw_text, draw_text_up, text_height_px, text_width_px};
use crate::{Error, Result};

/// Width of the time–error plot, pixels.
pub const TRADE_OFF_WIDTH_PX: usize = 900;
/// Height of the time–error plot, pixels.
pub const TRADE_OFF_HEIGHT_PX: usize = 600;

/// Colours of the cases, in order (repeated beyond four).
const CASE_COLOURS: [[u8; 3]; 4] = [
    [31, 119, 180],
    [214, 39, 40],
    [44, 160, 44],
    [148, 103, 189],
];

/// One element size of a case: its run time and its error.
#[derive(Debug, Clone)]
pub struct TradeOffPoint {
    /// Label beside the point (e.g. `6 mm`).
    pub label: String,
    /// Run time, s (> 0).
    pub time_s: f64,
    /// Error, mm (> 0; a zero error is drawn at the axis floor).
    pub error_mm: f64,
}

/// One case's points, joined in the order given.
#[derive(Debug, Clone)]
pub struct TradeOffSeries {
    /// Legend name of the case.
    pub name: String,
    /// Points, coarsest first.
    pub points: Vec<TradeOffPoint>,
}

/// Renders the plot; refuses an empty plot or a non-positive time.
pub fn render_trade_off(
    title: &str,
    error_label: &str,
    series: &[TradeOffSeries],
) -> Result<RgbImage> {
    let points = || series.iter().flat_map(|s| s.points.iter());
    if points().next().is_none() {
        return Err(Error::InvalidModel("time–error plot: no points".into()));
    }
    if let Some(p) = points().find(|p| !(p.time_s > 0.0 && p.time_s.is_finite())) {
        return Err(Error::InvalidModel(format!(
            "time–error plot: point {} has run time {} s",
            p.label, p.time_s
        )));
    }
    let decades = |v: &mut dyn Iterator<Item = f64>| {
        let (lo, hi) = v.fold((f64::MAX, f64::MIN), |(a, b), x| (a.min(x), b.max(x)));
        (
            lo.log10().floor(),
            hi.log10().ceil().max(lo.log10().floor() + 1.0),
        )
    };
    let (t_lo, t_hi) = decades(&mut points().map(|p| p.time_s));
    let positive: Vec<f64> = points()
        .map(|p| p.error_mm)
        .filter(|e| *e > 0.0 && e.is_finite())
        .collect();
    let (e_lo, e_hi) = if positive.is_empty() {
        (-3.0, 0.0)
    } else {
        decades(&mut positive.iter().copied())
    };
    let mut image = canvas(TRADE_OFF_WIDTH_PX, TRADE_OFF_HEIGHT_PX, WHITE);
    let (left, right, top, bottom) = (
        90.0,
        TRADE_OFF_WIDTH_PX as f64 - 200.0,
        50.0,
        TRADE_OFF_HEIGHT_PX as f64 - 70.0,
    );
    let px = |t: f64| left + (t.log10() - t_lo) / (t_hi - t_lo) * (right - left);
    let py = |e: f64| {
        let l = if e > 0.0 { e.log10().max(e_lo) } else { e_lo };
        bottom - (l - e_lo) / (e_hi - e_lo) * (bottom - top)
    };
    let th = text_height_px(TEXT_SCALE) as i64;
    for d in t_lo as i64..=t_hi as i64 {
        let x = px(10f64.powi(d as i32));
        draw_segment(&mut image, [x, top], [x, bottom], 0.5, GRID_GREY);
        let label = decade_label(d, "s");
        let w = text_width_px(&label, TEXT_SCALE) as i64;
        draw_text(
            &mut image,
            &label,
            x as i64 - w / 2,
            bottom as i64 + 8,
            TEXT_SCALE,
            BLACK,
        );
    }
    for d in e_lo as i64..=e_hi as i64 {
        let y = py(10f64.powi(d as i32));
        draw_segment(&mut image, [left, y], [right, y], 0.5, GRID_GREY);
        let label = decade_label(d, "mm");
        let w = text_width_px(&label, TEXT_SCALE) as i64;
        draw_text(
            &mut image,
            &label,
            left as i64 - 8 - w,
            y as i64 - th / 2,
            TEXT_SCALE,
            BLACK,
        );
    }
    outline_rect(
        &mut image,
        left as i64,
        top as i64,
        (right - left) as i64 + 1,
        (bottom - top) as i64 + 1,
        FRAME_GREY,
    );
    let x_label = "run time (s)";
    let w = text_width_px(x_label, TEXT_SCALE) as i64;
    draw_text(
        &mut image,
        x_label,
        ((left + right) / 2.0) as i64 - w / 2,
        bottom as i64 + 14 + th,
        TEXT_SCALE,
        BLACK,
    );
    let w = text_width_px(error_label, TEXT_SCALE) as i64;
    draw_text_up(
        &mut image,
        error_label,
        12,
        ((top + bottom) / 2.0) as i64 + w / 2,
        TEXT_SCALE,
        BLACK,
    );
    draw_text(&mut image, title, left as i64, 14, TEXT_SCALE, BLACK);
    for (k, s) in series.iter().enumerate() {
        let colour = CASE_COLOURS[k % CASE_COLOURS.len()];
        let at: Vec<[f64; 2]> = s
            .points
            .iter()
            .map(|p| [px(p.time_s), py(p.error_mm)])
            .collect();
        draw_polyline(&mut image, &at, 1.0, colour);
        for (p, xy) in s.points.iter().zip(&at) {
            fill_disk(&mut image, xy[0], xy[1], 5.0, colour);
            draw_text(
                &mut image,
                &p.label,
                xy[0] as i64 + 8,
                xy[1] as i64 - th - 2,
                TEXT_SCALE,
                colour,
            );
        }
        let y = top as i64 + 10 + k as i64 * (th + 10);
        fill_rect(&mut image, right as i64 + 20, y + 2, 16, th - 4, colour);
        draw_text(&mut image, &s.name, right as i64 + 44, y, TEXT_SCALE, BLACK);
    }
    Ok(image)
}

/// `1e-2 mm`-style label of the decade 10^`d`, plain for −1…3.
fn decade_label(d: i64, unit: &str) -> String {
    match d {
        -1 => format!("0.1 {unit}"),
        0..=3 => format!("{} {unit}", 10i64.pow(d as u32)),
        _ => format!("1e{d} {unit}"),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn pixel(image: &RgbImage, x: f64, y: f64) -> [u8; 3] {
        let o = 3 * (y.round() as usize * image.width + x.round() as usize);
        [image.pixels[o], image.pixels[o + 1], image.pixels[o + 2]]
    }

    #[test]
    fn points_land_on_their_decades_in_their_case_colour() {
        let series = [TradeOffSeries {
            name: "CIP".into(),
            points: vec![
                TradeOffPoint {
                    label: "8 mm".into(),
                    time_s: 1.0,
                    error_mm: 1.0,
                },
                TradeOffPoint {
                    label: "4 mm".into(),
                    time_s: 100.0,
                    error_mm: 0.01,
                },
            ],
        }];
        let image = render_trade_off("t", "error (mm)", &series).unwrap();
        // Time decades 10^0…10^2 span x 90…700; error decades 10^-2…10^0 span y 530…50.
        assert_eq!(pixel(&image, 90.0, 50.0), CASE_COLOURS[0]);
        assert_eq!(pixel(&image, 700.0, 530.0), CASE_COLOURS[0]);
        assert_eq!(
            pixel(&image, 395.0, 290.0),
            CASE_COLOURS[0],
            "the line between them"
        );
        assert_eq!(
            pixel(&image, 300.0, 100.0),
            WHITE,
            "off the line and the grid"
        );
    }

    #[test]
    fn an_empty_plot_or_a_zero_time_is_refused() {
        assert!(render_trade_off("t", "e", &[]).is_err());
        let zero = [TradeOffSeries {
            name: "x".into(),
            points: vec![TradeOffPoint {
                label: "a".into(),
                time_s: 0.0,
                error_mm: 1.0,
            }],
        }];
        let e = render_trade_off("t", "e", &zero).unwrap_err().to_string();
        assert!(e.contains("point a has run time 0 s"), "{e}");
    }
}
