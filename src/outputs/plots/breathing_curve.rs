//! The breathing-curve plot: the trace, each frame's target ring and simulated dot.

use super::draw::{canvas, draw_polyline, draw_segment, fill_disk, fill_rect, fill_ring};
use super::scale::{format_tick, min_max, nice_step, ticks, widen_if_flat};
use super::{
    BLACK, DOT_RADIUS_PX, FRAME_GREY, GRID_GREY, RING_RADII_PX, SIMULATED_COLOUR, TARGET_COLOUR,
    TEXT_SCALE, TRACE_COLOUR, WHITE,
};
use crate::outputs::quicklook::RgbImage;
use crate::outputs::raster_text::{draw_text, draw_text_up, text_height_px, text_width_px};
use crate::{Error, Result};

/// The data of a breathing-curve plot; frames' simulated volumes may be empty (not yet
/// simulated) or hold NaN for a frame without a result.
#[derive(Debug, Clone, Copy)]
pub struct BreathingCurve<'a> {
    /// Trace sample times, seconds, increasing.
    pub trace_time_s: &'a [f64],
    /// Trace volume change at each sample, mL.
    pub trace_volume_ml: &'a [f64],
    /// Output frame times, seconds.
    pub frame_time_s: &'a [f64],
    /// Volume change each frame was driven to, mL.
    pub frame_target_ml: &'a [f64],
    /// Volume change the simulation reached at each frame, mL.
    pub frame_simulated_ml: &'a [f64],
    /// Title line at the top.
    pub title: &'a str,
}

/// Where the data of a plot lie in its image.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PlotAxes {
    /// Pixel column of the left edge of the plot area (time `time_range_s[0]`).
    pub left_px: f64,
    /// Pixel column of the right edge (time `time_range_s[1]`).
    pub right_px: f64,
    /// Pixel row of the top edge (volume `volume_range_ml[1]`).
    pub top_px: f64,
    /// Pixel row of the bottom edge (volume `volume_range_ml[0]`).
    pub bottom_px: f64,
    /// Time at the left and right edges, seconds.
    pub time_range_s: [f64; 2],
    /// Volume change at the bottom and top edges, mL.
    pub volume_range_ml: [f64; 2],
}

impl PlotAxes {
    /// Continuous pixel `[col, row]` of a (time, volume) point.
    pub fn to_pixel(&self, time_s: f64, volume_ml: f64) -> [f64; 2] {
        let [t0, t1] = self.time_range_s;
        let [v0, v1] = self.volume_range_ml;
        [
            self.left_px + (time_s - t0) / (t1 - t0) * (self.right_px - self.left_px),
            self.bottom_px - (volume_ml - v0) / (v1 - v0) * (self.bottom_px - self.top_px),
        ]
    }
}

/// A rendered breathing-curve plot.
#[derive(Debug, Clone)]
pub struct BreathingCurvePlot {
    /// The picture.
    pub image: RgbImage,
    /// Data-to-pixel map of its plot area.
    pub axes: PlotAxes,
}

/// Width of the breathing-curve image, pixels.
pub const CURVE_WIDTH_PX: usize = 960;
/// Height of the breathing-curve image, pixels.
pub const CURVE_HEIGHT_PX: usize = 540;

/// Draws the breathing curve; refuses empty, mismatched or non-finite inputs with a message
/// naming the series.
pub fn render_breathing_curve(curve: &BreathingCurve) -> Result<BreathingCurvePlot> {
    check_curve(curve)?;
    let (width, height) = (CURVE_WIDTH_PX, CURVE_HEIGHT_PX);
    let mut image = canvas(width, height, WHITE);
    let axes = curve_axes(curve, width, height);
    // Grid and tick labels first, so data are drawn over them.
    draw_time_grid(&mut image, &axes);
    draw_volume_grid(&mut image, &axes);
    draw_curve_data(&mut image, curve, &axes);
    draw_axes_frame_and_labels(&mut image, &axes, curve.title);
    draw_curve_legend(
        &mut image,
        curve.frame_simulated_ml.iter().any(|v| v.is_finite()),
    );
    Ok(BreathingCurvePlot { image, axes })
}

/// The plot area of a `width` × `height` image and the data ranges it spans: every time,
/// every finite volume, the volume range padded by 8 % on both sides.
fn curve_axes(curve: &BreathingCurve, width: usize, height: usize) -> PlotAxes {
    let times = curve.trace_time_s.iter().chain(curve.frame_time_s);
    let (t_lo, t_hi) = min_max(times.copied());
    let volumes = curve
        .trace_volume_ml
        .iter()
        .chain(curve.frame_target_ml)
        .chain(curve.frame_simulated_ml.iter().filter(|v| v.is_finite()));
    let (v_lo, v_hi) = min_max(volumes.copied());
    let (t_lo, t_hi) = widen_if_flat(t_lo, t_hi, 1.0);
    let (v_lo, v_hi) = widen_if_flat(v_lo, v_hi, 10.0);
    let pad_ml = 0.08 * (v_hi - v_lo);
    PlotAxes {
        left_px: 100.0,
        right_px: (width - 30) as f64,
        top_px: 64.0,
        bottom_px: (height - 64) as f64,
        time_range_s: [t_lo, t_hi],
        volume_range_ml: [v_lo - pad_ml, v_hi + pad_ml],
    }
}

/// Vertical grid lines at round times, with ticks and labels under the plot area.
fn draw_time_grid(image: &mut RgbImage, axes: &PlotAxes) {
    let (top, bottom) = (axes.top_px, axes.bottom_px);
    let [t_lo, t_hi] = axes.time_range_s;
    let t_step = nice_step(t_hi - t_lo, 8);
    for t in ticks(t_lo, t_hi, t_step) {
        let [x, _] = axes.to_pixel(t, 0.0);
        fill_rect(
            image,
            x.round() as i64,
            top as i64,
            1,
            (bottom - top) as i64,
            GRID_GREY,
        );
        fill_rect(image, x.round() as i64, bottom as i64, 1, 6, BLACK);
        let label = format_tick(t, t_step);
        let w = text_width_px(&label, TEXT_SCALE) as i64;
        draw_text(
            image,
            &label,
            x.round() as i64 - w / 2,
            bottom as i64 + 10,
            TEXT_SCALE,
            BLACK,
        );
    }
}

/// Horizontal grid lines at round volumes (the scanned volume darker), with ticks and
/// labels left of the plot area.
fn draw_volume_grid(image: &mut RgbImage, axes: &PlotAxes) {
    let (left, right) = (axes.left_px, axes.right_px);
    let t_lo = axes.time_range_s[0];
    let text_h = text_height_px(TEXT_SCALE) as i64;
    let [v0, v1] = axes.volume_range_ml;
    let v_step = nice_step(v1 - v0, 6);
    for v in ticks(v0, v1, v_step) {
        let [_, y] = axes.to_pixel(t_lo, v);
        let y = y.round() as i64;
        let colour = if v.abs() < 1e-9 * v_step {
            FRAME_GREY
        } else {
            GRID_GREY
        };
        fill_rect(image, left as i64, y, (right - left) as i64, 1, colour);
        fill_rect(image, left as i64 - 6, y, 6, 1, BLACK);
        let label = format_tick(v, v_step);
        let w = text_width_px(&label, TEXT_SCALE) as i64;
        draw_text(
            image,
            &label,
            left as i64 - 10 - w,
            y - text_h / 2,
            TEXT_SCALE,
            BLACK,
        );
    }
}

/// The trace line, then the frames' target rings, then their simulated dots on top.
fn draw_curve_data(image: &mut RgbImage, curve: &BreathingCurve, axes: &PlotAxes) {
    let trace: Vec<[f64; 2]> = curve
        .trace_time_s
        .iter()
        .zip(curve.trace_volume_ml)
        .map(|(&t, &v)| axes.to_pixel(t, v))
        .collect();
    draw_polyline(image, &trace, 1.1, TRACE_COLOUR);
    for (&t, &v) in curve.frame_time_s.iter().zip(curve.frame_target_ml) {
        let [x, y] = axes.to_pixel(t, v);
        fill_ring(image, x, y, RING_RADII_PX.0, RING_RADII_PX.1, TARGET_COLOUR);
    }
    for (&t, &v) in curve.frame_time_s.iter().zip(curve.frame_simulated_ml) {
        if v.is_finite() {
            let [x, y] = axes.to_pixel(t, v);
            fill_disk(image, x, y, DOT_RADIUS_PX, SIMULATED_COLOUR);
        }
    }
}

/// The plot area's frame, the axis labels and the title.
fn draw_axes_frame_and_labels(image: &mut RgbImage, axes: &PlotAxes, title: &str) {
    let (width, height) = (image.width, image.height);
    // Axes frame, drawn last over data that touch the edges.
    let (l, r, t, b) = (
        axes.left_px as i64,
        axes.right_px as i64,
        axes.top_px as i64,
        axes.bottom_px as i64,
    );
    fill_rect(image, l, t, r - l + 1, 1, BLACK);
    fill_rect(image, l, b, r - l + 1, 1, BLACK);
    fill_rect(image, l, t, 1, b - t + 1, BLACK);
    fill_rect(image, r, t, 1, b - t + 1, BLACK);

    let x_label = "time (s)";
    let w = text_width_px(x_label, TEXT_SCALE) as i64;
    draw_text(
        image,
        x_label,
        ((l + r) - w) / 2,
        height as i64 - 26,
        TEXT_SCALE,
        BLACK,
    );
    let y_label = "volume change (mL)";
    let w = text_width_px(y_label, TEXT_SCALE) as i64;
    draw_text_up(image, y_label, 14, (t + b + w) / 2, TEXT_SCALE, BLACK);
    let w = text_width_px(title, TEXT_SCALE) as i64;
    draw_text(
        image,
        title,
        (width as i64 - w).max(0) / 2,
        10,
        TEXT_SCALE,
        BLACK,
    );
}

/// One legend row under the title: line, ring and dot with their meaning.
fn draw_curve_legend(image: &mut RgbImage, with_simulated: bool) {
    let mut entries: Vec<(&str, u8)> = vec![("breathing trace", 0), ("frame target", 1)];
    if with_simulated {
        entries.push(("simulated", 2));
    }
    let sample_px = 28i64;
    let gap_px = 30i64;
    let total: i64 = entries
        .iter()
        .map(|(label, _)| sample_px + 8 + text_width_px(label, TEXT_SCALE) as i64)
        .sum::<i64>()
        + gap_px * (entries.len() as i64 - 1);
    let mut x = (image.width as i64 - total) / 2;
    let y = 36i64;
    let mid = (y + text_height_px(TEXT_SCALE) as i64 / 2) as f64;
    for (label, kind) in entries {
        let cx = (x + sample_px / 2) as f64;
        match kind {
            0 => draw_segment(
                image,
                [x as f64, mid],
                [(x + sample_px) as f64, mid],
                1.1,
                TRACE_COLOUR,
            ),
            1 => fill_ring(
                image,
                cx,
                mid,
                RING_RADII_PX.0,
                RING_RADII_PX.1,
                TARGET_COLOUR,
            ),
            _ => fill_disk(image, cx, mid, DOT_RADIUS_PX, SIMULATED_COLOUR),
        }
        draw_text(image, label, x + sample_px + 8, y, TEXT_SCALE, BLACK);
        x += sample_px + 8 + text_width_px(label, TEXT_SCALE) as i64 + gap_px;
    }
}

/// Refuses series that are empty, of mismatched lengths, non-finite or not increasing in time.
fn check_curve(c: &BreathingCurve) -> Result<()> {
    let bad = |m: String| Err(Error::argument("breathing-curve plot", m));
    if c.trace_time_s.len() != c.trace_volume_ml.len() {
        return bad(format!(
            "{} trace times for {} trace volumes",
            c.trace_time_s.len(),
            c.trace_volume_ml.len()
        ));
    }
    if c.trace_time_s.len() < 2 {
        return bad("the trace needs at least two samples".into());
    }
    if c.frame_time_s.len() != c.frame_target_ml.len() {
        return bad(format!(
            "{} frame times for {} frame targets",
            c.frame_time_s.len(),
            c.frame_target_ml.len()
        ));
    }
    if !c.frame_simulated_ml.is_empty() && c.frame_simulated_ml.len() != c.frame_time_s.len() {
        return bad(format!(
            "{} simulated volumes for {} frames",
            c.frame_simulated_ml.len(),
            c.frame_time_s.len()
        ));
    }
    for (name, series) in [
        ("trace time", c.trace_time_s),
        ("trace volume", c.trace_volume_ml),
        ("frame time", c.frame_time_s),
        ("frame target", c.frame_target_ml),
    ] {
        if let Some(i) = series.iter().position(|v| !v.is_finite()) {
            return bad(format!("{name} {} is {}", i + 1, series[i]));
        }
    }
    if let Some(i) = c.frame_simulated_ml.iter().position(|v| v.is_infinite()) {
        return bad(format!("simulated volume {} is infinite", i + 1));
    }
    if let Some(i) = c.trace_time_s.windows(2).position(|w| w[1] <= w[0]) {
        return bad(format!(
            "trace times must increase: sample {} at {} s follows {} s",
            i + 2,
            c.trace_time_s[i + 1],
            c.trace_time_s[i]
        ));
    }
    Ok(())
}
