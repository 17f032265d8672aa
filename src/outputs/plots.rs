//! Pictures of a breathing run a medical physicist checks at a glance: the breathing curve
//! with the frames' targets and simulated volumes, and a coronal quick look of the
//! displacement field.
//!
//! Conventions. Images are 8-bit RGB ([`RgbImage`], rows top to bottom, written with
//! [`write_png`](crate::outputs::quicklook::write_png)); text uses the embedded font of
//! [`raster_text`](crate::outputs::raster_text), so no system font is needed. Continuous
//! pixel coordinates `[col, row]` put the centre of pixel (c, r) at (c, r).
//!
//! * Breathing curve: time (s) to the right, volume change (mL, relative to the CT's
//!   breathing state) upwards. The trace is a blue line, each frame's target volume an orange
//!   ring, each frame's simulated volume a red dot drawn on top (a dot centred in its ring is
//!   a frame that met its target).
//! * Displacement quick look: a coronal slice of the CT at a given LPS y, in lung window,
//!   with the radiological display convention of
//!   [`quicklook`](crate::outputs::quicklook) (patient's right on the image's left, superior
//!   at the top), the same pixel grid as
//!   [`render_slice`](crate::outputs::quicklook::render_slice) refined by an integer factor
//!   (each CT-slice pixel becomes a block). Inside the lungs the displacement magnitude
//!   |u| (mm, all three LPS components) is blended over the CT in the viridis colour map,
//!   with a colour bar in mm; arrows on a regular grid show the in-plane displacement (x to
//!   the image's right for +x = patient left, z upwards), magnified by a factor written in
//!   the image together with a reference arrow. The field is read per CT voxel (nearest
//!   voxel), as the pipeline samples it.

use nalgebra::Vector3;
use rayon::prelude::*;

use crate::outputs::quicklook::{
    render_slice, HuWindow, RgbImage, SliceGrid, SlicePlane, MAX_IMAGE_SIDE,
};
use crate::outputs::raster_text::{draw_text, draw_text_up, text_height_px, text_width_px};
use crate::volume::Volume;
use crate::{Error, Result};

/// Colour of the breathing trace line.
pub const TRACE_COLOUR: [u8; 3] = [31, 119, 180];
/// Colour of a frame's target-volume ring.
pub const TARGET_COLOUR: [u8; 3] = [255, 127, 14];
/// Colour of a frame's simulated-volume dot.
pub const SIMULATED_COLOUR: [u8; 3] = [214, 39, 40];
/// Colour of displacement arrows (over a black halo).
pub const ARROW_COLOUR: [u8; 3] = [255, 255, 255];
/// Weight of the magnitude colour over the CT grey inside the lungs.
pub const OVERLAY_OPACITY: f32 = 0.6;

const WHITE: [u8; 3] = [255, 255, 255];
const BLACK: [u8; 3] = [0, 0, 0];
const GRID_GREY: [u8; 3] = [225, 225, 225];
const FRAME_GREY: [u8; 3] = [120, 120, 120];
/// Text scale of every label (the 5×7 font doubled: 14 px high).
const TEXT_SCALE: usize = 2;

/// Outer and inner radius of a target ring, pixels.
const RING_RADII_PX: (f64, f64) = (7.0, 4.5);
/// Radius of a simulated-volume dot, pixels.
const DOT_RADIUS_PX: f64 = 3.5;

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
    let axes = PlotAxes {
        left_px: 100.0,
        right_px: (width - 30) as f64,
        top_px: 64.0,
        bottom_px: (height - 64) as f64,
        time_range_s: [t_lo, t_hi],
        volume_range_ml: [v_lo - pad_ml, v_hi + pad_ml],
    };
    let (left, right, top, bottom) = (axes.left_px, axes.right_px, axes.top_px, axes.bottom_px);
    let text_h = text_height_px(TEXT_SCALE) as i64;

    // Grid and tick labels first, so data are drawn over them.
    let t_step = nice_step(t_hi - t_lo, 8);
    for t in ticks(t_lo, t_hi, t_step) {
        let [x, _] = axes.to_pixel(t, 0.0);
        fill_rect(
            &mut image,
            x.round() as i64,
            top as i64,
            1,
            (bottom - top) as i64,
            GRID_GREY,
        );
        fill_rect(&mut image, x.round() as i64, bottom as i64, 1, 6, BLACK);
        let label = format_tick(t, t_step);
        let w = text_width_px(&label, TEXT_SCALE) as i64;
        draw_text(
            &mut image,
            &label,
            x.round() as i64 - w / 2,
            bottom as i64 + 10,
            TEXT_SCALE,
            BLACK,
        );
    }
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
        fill_rect(&mut image, left as i64, y, (right - left) as i64, 1, colour);
        fill_rect(&mut image, left as i64 - 6, y, 6, 1, BLACK);
        let label = format_tick(v, v_step);
        let w = text_width_px(&label, TEXT_SCALE) as i64;
        draw_text(
            &mut image,
            &label,
            left as i64 - 10 - w,
            y - text_h / 2,
            TEXT_SCALE,
            BLACK,
        );
    }

    let trace: Vec<[f64; 2]> = curve
        .trace_time_s
        .iter()
        .zip(curve.trace_volume_ml)
        .map(|(&t, &v)| axes.to_pixel(t, v))
        .collect();
    draw_polyline(&mut image, &trace, 1.1, TRACE_COLOUR);
    for (&t, &v) in curve.frame_time_s.iter().zip(curve.frame_target_ml) {
        let [x, y] = axes.to_pixel(t, v);
        fill_ring(
            &mut image,
            x,
            y,
            RING_RADII_PX.0,
            RING_RADII_PX.1,
            TARGET_COLOUR,
        );
    }
    for (&t, &v) in curve.frame_time_s.iter().zip(curve.frame_simulated_ml) {
        if v.is_finite() {
            let [x, y] = axes.to_pixel(t, v);
            fill_disk(&mut image, x, y, DOT_RADIUS_PX, SIMULATED_COLOUR);
        }
    }

    // Axes frame, drawn last over data that touch the edges.
    let (l, r, t, b) = (left as i64, right as i64, top as i64, bottom as i64);
    fill_rect(&mut image, l, t, r - l + 1, 1, BLACK);
    fill_rect(&mut image, l, b, r - l + 1, 1, BLACK);
    fill_rect(&mut image, l, t, 1, b - t + 1, BLACK);
    fill_rect(&mut image, r, t, 1, b - t + 1, BLACK);

    let x_label = "time (s)";
    let w = text_width_px(x_label, TEXT_SCALE) as i64;
    draw_text(
        &mut image,
        x_label,
        ((l + r) - w) / 2,
        height as i64 - 26,
        TEXT_SCALE,
        BLACK,
    );
    let y_label = "volume change (mL)";
    let w = text_width_px(y_label, TEXT_SCALE) as i64;
    draw_text_up(&mut image, y_label, 14, (t + b + w) / 2, TEXT_SCALE, BLACK);
    let w = text_width_px(curve.title, TEXT_SCALE) as i64;
    draw_text(
        &mut image,
        curve.title,
        (width as i64 - w).max(0) / 2,
        10,
        TEXT_SCALE,
        BLACK,
    );
    draw_curve_legend(
        &mut image,
        curve.frame_simulated_ml.iter().any(|v| v.is_finite()),
    );
    Ok(BreathingCurvePlot { image, axes })
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

fn check_curve(c: &BreathingCurve) -> Result<()> {
    let bad = |m: String| Err(Error::InvalidInput(format!("breathing-curve plot: {m}")));
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

/// The rendered displacement quick look and where things are in it.
#[derive(Debug, Clone)]
pub struct DisplacementLook {
    /// The picture.
    pub image: RgbImage,
    /// Where the CT slice sits in the image.
    pub panel: SlicePanel,
    /// Every arrow drawn, in image pixels.
    pub arrows: Vec<Arrow>,
    /// Displacement magnitude at the top of the colour bar, mm.
    pub colour_max_mm: f32,
    /// Arrow length per mm of in-plane displacement, pixels.
    pub arrow_px_per_mm: f64,
}

/// Placement of a coronal CT slice in an image: pixel ↔ LPS mm.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SlicePanel {
    /// Image column of the panel's first pixel.
    pub left_px: usize,
    /// Image row of the panel's first pixel.
    pub top_px: usize,
    /// Panel width, pixels.
    pub width_px: usize,
    /// Panel height, pixels.
    pub height_px: usize,
    /// Side of a (square) panel pixel, mm.
    pub pixel_mm: f64,
    /// LPS position of the centre of the panel's first pixel (its y is the slice's).
    pub first_pixel_lps_mm: [f64; 3],
}

impl SlicePanel {
    /// Continuous image pixel `[col, row]` of an LPS point projected on the slice.
    pub fn image_px_of_lps(&self, p_lps_mm: [f64; 3]) -> [f64; 2] {
        let f = self.first_pixel_lps_mm;
        [
            self.left_px as f64 + (p_lps_mm[0] - f[0]) / self.pixel_mm,
            self.top_px as f64 + (f[2] - p_lps_mm[2]) / self.pixel_mm,
        ]
    }

    /// LPS point (on the slice) at a continuous image pixel.
    pub fn lps_of_image_px(&self, col: f64, row: f64) -> [f64; 3] {
        let f = self.first_pixel_lps_mm;
        [
            f[0] + (col - self.left_px as f64) * self.pixel_mm,
            f[1],
            f[2] - (row - self.top_px as f64) * self.pixel_mm,
        ]
    }
}

/// One displacement arrow.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Arrow {
    /// Image pixel of the arrow's base (the grid point it describes).
    pub tail_px: [f64; 2],
    /// Image pixel of its tip.
    pub head_px: [f64; 2],
    /// Displacement of the voxel at the base, LPS mm.
    pub displacement_mm: [f32; 3],
}

/// What to draw in a displacement quick look.
#[derive(Debug, Clone, Copy)]
pub struct DisplacementLookInput<'a> {
    /// The CT (HU).
    pub ct: &'a Volume<f32>,
    /// Lung labels on the CT grid (non-zero is lung).
    pub lungs: &'a Volume<u8>,
    /// Displacement of every CT voxel, LPS mm (zero outside the lungs).
    pub displacement_mm: &'a [[f32; 3]],
    /// LPS y of the coronal slice, mm.
    pub coronal_y_mm: f64,
    /// Top of the colour bar, mm; `None` takes a round value above the field's largest
    /// magnitude (fix it to compare frames).
    pub colour_max_mm: Option<f32>,
    /// Title line at the top.
    pub title: &'a str,
}

/// The slice panel's shorter target side, pixels: coarse CTs are refined up to it.
const PANEL_MIN_SIDE_PX: usize = 480;
const PANEL_LEFT_PX: usize = 40;
const PANEL_TOP_PX: usize = 76;
const PANEL_BOTTOM_MARGIN_PX: usize = 64;
const PANEL_RIGHT_MARGIN_PX: usize = 150;
/// Arrows per panel side (about), on a regular grid.
const ARROWS_PER_SIDE: usize = 16;
/// Longest arrow (magnitude at the colour-bar top, all in plane) over the arrow spacing.
const ARROW_FILL: f64 = 0.9;

/// Draws the coronal displacement quick look (see the module doc for the conventions).
pub fn render_displacement_look(input: &DisplacementLookInput) -> Result<DisplacementLook> {
    let ct = input.ct;
    let g = &ct.geometry;
    if !input.lungs.geometry.same_grid(g, 1e-3) || input.lungs.as_slice().len() != g.voxel_count() {
        return Err(Error::InvalidInput(format!(
            "displacement quick look: the lung labels ({:?}) are not on the CT grid ({:?})",
            input.lungs.geometry.dims, g.dims
        )));
    }
    if input.displacement_mm.len() != g.voxel_count() {
        return Err(Error::InvalidInput(format!(
            "displacement quick look: {} displacements for {} CT voxels",
            input.displacement_mm.len(),
            g.voxel_count()
        )));
    }
    if let Some(i) = input
        .displacement_mm
        .par_iter()
        .position_any(|u| u.iter().any(|v| !v.is_finite()))
    {
        return Err(Error::InvalidInput(format!(
            "displacement quick look: voxel {i} has a non-finite displacement {:?}",
            input.displacement_mm[i]
        )));
    }
    let colour_max_mm = match input.colour_max_mm {
        Some(m) if m.is_finite() && m > 0.0 => m,
        Some(m) => {
            return Err(Error::InvalidInput(format!(
                "displacement quick look: colour-bar top {m} mm must be positive"
            )))
        }
        None => {
            let largest = input
                .displacement_mm
                .par_iter()
                .zip(input.lungs.as_slice())
                .filter(|(_, &l)| l != 0)
                .map(|(u, _)| magnitude(u))
                .reduce(|| 0.0, f32::max);
            round_up(largest as f64) as f32
        }
    };

    // The CT slice exactly as the ingest quick look draws it, then refined by an integer
    // factor so a coarse scan still leaves room for legible arrows.
    let base = render_slice(
        ct,
        &[],
        SlicePlane::Coronal,
        input.coronal_y_mm,
        HuWindow::LUNG,
    )?;
    let native = SliceGrid::native(g, SlicePlane::Coronal, input.coronal_y_mm)?;
    let refine = PANEL_MIN_SIDE_PX
        .div_ceil(base.width.max(base.height))
        .clamp(1, 8);
    let (pw, ph) = (base.width * refine, base.height * refine);
    let pixel_mm = native.pixel_mm / refine as f64;
    let shift = 0.5 * (pixel_mm - native.pixel_mm);
    let panel = SlicePanel {
        left_px: PANEL_LEFT_PX,
        top_px: PANEL_TOP_PX,
        width_px: pw,
        height_px: ph,
        pixel_mm,
        first_pixel_lps_mm: [
            native.first_pixel_lps_mm[0] + shift,
            input.coronal_y_mm,
            native.first_pixel_lps_mm[2] - shift,
        ],
    };
    let subtitle = format!(
        "coronal y = {:.1} mm (LPS), lung window",
        input.coronal_y_mm
    );
    // Arrows: a regular grid of panel pixels; the colour-bar top fills most of a cell.
    let spacing_px = (pw.max(ph) / ARROWS_PER_SIDE).max(16);
    let arrow_px_per_mm = ARROW_FILL * spacing_px as f64 / colour_max_mm as f64;
    let reference_mm = round_down(colour_max_mm as f64);
    let reference_left_px = PANEL_LEFT_PX + text_width_px("arrows:", TEXT_SCALE) + 12;
    let reference_px = reference_mm * arrow_px_per_mm;
    let note = format!(
        "= {} mm in plane (x{:.1} true length)",
        format_value(reference_mm),
        arrow_px_per_mm * pixel_mm
    );
    let note_left_px = reference_left_px + reference_px.round() as usize + 10;
    let width = (PANEL_LEFT_PX + pw + PANEL_RIGHT_MARGIN_PX)
        .max(text_width_px(input.title, TEXT_SCALE) + 2 * PANEL_LEFT_PX)
        .max(text_width_px(&subtitle, TEXT_SCALE) + 2 * PANEL_LEFT_PX)
        .max(note_left_px + text_width_px(&note, TEXT_SCALE) + PANEL_LEFT_PX);
    let height = PANEL_TOP_PX + ph + PANEL_BOTTOM_MARGIN_PX;
    if width > MAX_IMAGE_SIDE || height > MAX_IMAGE_SIDE {
        return Err(Error::InvalidInput(format!(
            "displacement quick look would be {width}×{height} pixels (more than \
             {MAX_IMAGE_SIDE} per side)"
        )));
    }
    let mut image = canvas(width, height, WHITE);

    // Per panel pixel: the nearest CT voxel (for the lung label and the field).
    let origin = Vector3::from(panel.lps_of_image_px(panel.left_px as f64, panel.top_px as f64));
    let v0 = g.lps_mm_to_voxel(origin);
    let per_col = g.lps_mm_to_voxel(origin + Vector3::new(pixel_mm, 0.0, 0.0)) - v0;
    let per_row = g.lps_mm_to_voxel(origin + Vector3::new(0.0, 0.0, -pixel_mm)) - v0;
    let voxel_at = |col: usize, row: usize| {
        nearest_voxel(ct, v0 + per_col * col as f64 + per_row * row as f64)
    };
    let lungs = input.lungs.as_slice();
    let field = input.displacement_mm;
    image
        .pixels
        .par_chunks_mut(3 * width)
        .skip(panel.top_px)
        .take(ph)
        .enumerate()
        .for_each(|(row, line)| {
            let cells = line[3 * panel.left_px..3 * (panel.left_px + pw)].chunks_exact_mut(3);
            for (col, px) in cells.enumerate() {
                let grey = base.pixel(col / refine, row / refine);
                px.copy_from_slice(&grey);
                let Some(v) = voxel_at(col, row) else {
                    continue;
                };
                if lungs[v] == 0 {
                    continue;
                }
                let colour = viridis(magnitude(&field[v]) / colour_max_mm);
                for (p, c) in px.iter_mut().zip(colour) {
                    *p = (*p as f32 * (1.0 - OVERLAY_OPACITY) + c as f32 * OVERLAY_OPACITY).round()
                        as u8;
                }
            }
        });

    // Arrows at the grid points inside the lungs.
    let mut arrows = Vec::new();
    for row in (spacing_px / 2..ph).step_by(spacing_px) {
        for col in (spacing_px / 2..pw).step_by(spacing_px) {
            let Some(v) = voxel_at(col, row) else {
                continue;
            };
            if lungs[v] == 0 {
                continue;
            }
            let u = field[v];
            // Image columns follow +x (patient left); rows follow −z (superior up).
            let d = [
                u[0] as f64 * arrow_px_per_mm,
                -(u[2] as f64) * arrow_px_per_mm,
            ];
            if d[0].hypot(d[1]) < 2.0 {
                continue;
            }
            let tail = [(panel.left_px + col) as f64, (panel.top_px + row) as f64];
            arrows.push(Arrow {
                tail_px: tail,
                head_px: [tail[0] + d[0], tail[1] + d[1]],
                displacement_mm: u,
            });
        }
    }
    // Halos first, so no halo covers a neighbouring arrow.
    for a in &arrows {
        draw_arrow(&mut image, a.tail_px, a.head_px, 1.9, BLACK);
    }
    for a in &arrows {
        draw_arrow(&mut image, a.tail_px, a.head_px, 0.7, ARROW_COLOUR);
    }

    let text_h = text_height_px(TEXT_SCALE) as i64;
    let (pl, pt) = (panel.left_px as i64, panel.top_px as i64);
    let (pr, pb) = (pl + pw as i64, pt + ph as i64);
    draw_text(&mut image, input.title, pl, 8, TEXT_SCALE, BLACK);
    draw_text(&mut image, &subtitle, pl, 30, TEXT_SCALE, BLACK);
    // Orientation letters: the radiological convention at a glance.
    let centre_col = (pl + pr) / 2;
    let centre_row = (pt + pb) / 2 - text_h / 2;
    draw_text(
        &mut image,
        "S",
        centre_col - 5,
        pt - text_h - 4,
        TEXT_SCALE,
        BLACK,
    );
    draw_text(&mut image, "I", centre_col - 5, pb + 4, TEXT_SCALE, BLACK);
    draw_text(&mut image, "R", pl - 20, centre_row, TEXT_SCALE, BLACK);
    draw_text(&mut image, "L", pr + 8, centre_row, TEXT_SCALE, BLACK);
    draw_colour_bar(&mut image, pr + 40, pt, ph as i64, colour_max_mm);

    // Reference arrow with the magnification in words.
    let y = (pb + 24 + text_h / 2) as f64;
    let x0 = reference_left_px as f64;
    draw_text(&mut image, "arrows:", pl, pb + 24, TEXT_SCALE, BLACK);
    draw_arrow(&mut image, [x0, y], [x0 + reference_px, y], 1.9, BLACK);
    draw_arrow(
        &mut image,
        [x0, y],
        [x0 + reference_px, y],
        0.7,
        [90, 90, 90],
    );
    let note_left = note_left_px as i64;
    draw_text(&mut image, &note, note_left, pb + 24, TEXT_SCALE, BLACK);
    Ok(DisplacementLook {
        image,
        panel,
        arrows,
        colour_max_mm,
        arrow_px_per_mm,
    })
}

/// LPS centroid of the non-zero labels (mm), e.g. to choose the coronal slice; `None`
/// without any.
pub fn lung_centroid_lps_mm(lungs: &Volume<u8>) -> Option<[f64; 3]> {
    let [nx, ny, _] = lungs.geometry.dims;
    let (sum, count) = lungs
        .as_slice()
        .par_iter()
        .enumerate()
        .filter(|(_, &l)| l != 0)
        .map(|(idx, _)| {
            let ijk = Vector3::new(
                (idx % nx) as f64,
                ((idx / nx) % ny) as f64,
                (idx / (nx * ny)) as f64,
            );
            (ijk, 1usize)
        })
        .reduce(|| (Vector3::zeros(), 0), |a, b| (a.0 + b.0, a.1 + b.1));
    (count > 0).then(|| lungs.geometry.voxel_to_lps_mm(sum / count as f64).into())
}

/// The viridis colour of `t` in 0–1 (clamped): dark blue to yellow, perceptually uniform.
pub fn viridis(t: f32) -> [u8; 3] {
    // Nine evenly spaced samples of matplotlib's viridis, linearly interpolated.
    const STOPS: [[f32; 3]; 9] = [
        [68.0, 1.0, 84.0],
        [71.0, 44.0, 122.0],
        [59.0, 81.0, 139.0],
        [44.0, 113.0, 142.0],
        [33.0, 144.0, 141.0],
        [39.0, 173.0, 129.0],
        [92.0, 200.0, 99.0],
        [170.0, 220.0, 50.0],
        [253.0, 231.0, 37.0],
    ];
    let x = if t.is_nan() { 0.0 } else { t.clamp(0.0, 1.0) } * 8.0;
    let i = (x.floor() as usize).min(7);
    let f = x - i as f32;
    let (a, b) = (STOPS[i], STOPS[i + 1]);
    [0, 1, 2].map(|c| (a[c] + (b[c] - a[c]) * f).round() as u8)
}

/// Vertical colour bar (0 at the bottom, `max_mm` at the top) with mm tick labels.
fn draw_colour_bar(image: &mut RgbImage, left: i64, top: i64, panel_h: i64, max_mm: f32) {
    let bar_h = (panel_h * 3 / 4).clamp(100, 360);
    let bar_top = top + (panel_h - bar_h) / 2;
    let bar_w = 22;
    let text_h = text_height_px(TEXT_SCALE) as i64;
    for r in 0..bar_h {
        let t = 1.0 - r as f32 / (bar_h - 1) as f32;
        fill_rect(image, left, bar_top + r, bar_w, 1, viridis(t));
    }
    outline_rect(image, left - 1, bar_top - 1, bar_w + 2, bar_h + 2, BLACK);
    draw_text(
        image,
        "|u| (mm)",
        left - 12,
        bar_top - text_h - 8,
        TEXT_SCALE,
        BLACK,
    );
    let step = nice_step(max_mm as f64, 5);
    for v in ticks(0.0, max_mm as f64, step) {
        let y = bar_top + ((1.0 - v / max_mm as f64) * (bar_h - 1) as f64).round() as i64;
        fill_rect(image, left + bar_w, y, 5, 1, BLACK);
        let label = format_tick(v, step);
        draw_text(
            image,
            &label,
            left + bar_w + 8,
            y - text_h / 2,
            TEXT_SCALE,
            BLACK,
        );
    }
}

/// Linear index of the voxel nearest a continuous voxel index; `None` outside the grid.
#[inline]
fn nearest_voxel(v: &Volume<f32>, ijk: Vector3<f64>) -> Option<usize> {
    let d = v.geometry.dims;
    let mut idx = [0usize; 3];
    for a in 0..3 {
        let r = ijk[a].round();
        if !(0.0..d[a] as f64).contains(&r) {
            return None;
        }
        idx[a] = r as usize;
    }
    Some(v.geometry.index(idx[0], idx[1], idx[2]))
}

#[inline]
fn magnitude(u: &[f32; 3]) -> f32 {
    (u[0] * u[0] + u[1] * u[1] + u[2] * u[2]).sqrt()
}

fn canvas(width: usize, height: usize, colour: [u8; 3]) -> RgbImage {
    RgbImage {
        width,
        height,
        pixels: colour.repeat(width * height),
    }
}

fn fill_rect(image: &mut RgbImage, left: i64, top: i64, w: i64, h: i64, colour: [u8; 3]) {
    let x0 = left.max(0);
    let x1 = (left + w).min(image.width as i64);
    for y in top.max(0)..(top + h).min(image.height as i64) {
        for x in x0..x1 {
            put(image, x, y, colour);
        }
    }
}

fn outline_rect(image: &mut RgbImage, left: i64, top: i64, w: i64, h: i64, colour: [u8; 3]) {
    fill_rect(image, left, top, w, 1, colour);
    fill_rect(image, left, top + h - 1, w, 1, colour);
    fill_rect(image, left, top, 1, h, colour);
    fill_rect(image, left + w - 1, top, 1, h, colour);
}

#[inline]
fn put(image: &mut RgbImage, x: i64, y: i64, colour: [u8; 3]) {
    if x >= 0 && y >= 0 && (x as usize) < image.width && (y as usize) < image.height {
        let o = 3 * (y as usize * image.width + x as usize);
        image.pixels[o..o + 3].copy_from_slice(&colour);
    }
}

/// Pixels whose centre lies within `radius` of the segment a–b.
fn draw_segment(image: &mut RgbImage, a: [f64; 2], b: [f64; 2], radius: f64, colour: [u8; 3]) {
    let (dx, dy) = (b[0] - a[0], b[1] - a[1]);
    let len2 = dx * dx + dy * dy;
    let x0 = (a[0].min(b[0]) - radius).floor() as i64;
    let x1 = (a[0].max(b[0]) + radius).ceil() as i64;
    let y0 = (a[1].min(b[1]) - radius).floor() as i64;
    let y1 = (a[1].max(b[1]) + radius).ceil() as i64;
    let x0 = x0.max(0);
    let y0 = y0.max(0);
    let x1 = x1.min(image.width as i64 - 1);
    let y1 = y1.min(image.height as i64 - 1);
    for y in y0..=y1 {
        for x in x0..=x1 {
            let (px, py) = (x as f64 - a[0], y as f64 - a[1]);
            let t = if len2 > 0.0 {
                ((px * dx + py * dy) / len2).clamp(0.0, 1.0)
            } else {
                0.0
            };
            let (ex, ey) = (px - t * dx, py - t * dy);
            if ex * ex + ey * ey <= radius * radius {
                put(image, x, y, colour);
            }
        }
    }
}

fn draw_polyline(image: &mut RgbImage, points: &[[f64; 2]], radius: f64, colour: [u8; 3]) {
    for w in points.windows(2) {
        draw_segment(image, w[0], w[1], radius, colour);
    }
}

/// Shaft from tail to head and two barbs at the head, all `radius` thick.
fn draw_arrow(image: &mut RgbImage, tail: [f64; 2], head: [f64; 2], radius: f64, colour: [u8; 3]) {
    let (dx, dy) = (head[0] - tail[0], head[1] - tail[1]);
    let len = dx.hypot(dy);
    if len == 0.0 {
        return;
    }
    let (ux, uy) = (dx / len, dy / len);
    let barb = (0.35 * len).clamp(3.0, 8.0);
    let (c, s) = (30f64.to_radians().cos(), 30f64.to_radians().sin());
    draw_segment(image, tail, head, radius, colour);
    for side in [-1.0, 1.0] {
        // The reversed direction turned by ±30°.
        let bx = -(ux * c - side * uy * s);
        let by = -(uy * c + side * ux * s);
        draw_segment(
            image,
            head,
            [head[0] + barb * bx, head[1] + barb * by],
            radius,
            colour,
        );
    }
}

fn fill_disk(image: &mut RgbImage, cx: f64, cy: f64, radius: f64, colour: [u8; 3]) {
    fill_ring(image, cx, cy, radius, -1.0, colour);
}

/// Pixels whose centre is within `outer` of (cx, cy) and farther than `inner`.
fn fill_ring(image: &mut RgbImage, cx: f64, cy: f64, outer: f64, inner: f64, colour: [u8; 3]) {
    let inner2 = if inner > 0.0 { inner * inner } else { -1.0 };
    for y in (cy - outer).floor() as i64..=(cy + outer).ceil() as i64 {
        for x in (cx - outer).floor() as i64..=(cx + outer).ceil() as i64 {
            let r2 = (x as f64 - cx).powi(2) + (y as f64 - cy).powi(2);
            if r2 <= outer * outer && r2 > inner2 {
                put(image, x, y, colour);
            }
        }
    }
}

fn min_max(values: impl Iterator<Item = f64>) -> (f64, f64) {
    values.fold((f64::MAX, f64::MIN), |(lo, hi), v| (lo.min(v), hi.max(v)))
}

/// Opens a flat range around its value so the axis has a span.
fn widen_if_flat(lo: f64, hi: f64, half_span: f64) -> (f64, f64) {
    if hi - lo > 1e-9 * (lo.abs() + hi.abs()).max(1.0) {
        (lo, hi)
    } else {
        (lo - half_span, hi + half_span)
    }
}

/// A 1, 2 or 5 × 10ⁿ step giving about `target` intervals over `range`.
fn nice_step(range: f64, target: usize) -> f64 {
    let raw = (range / target as f64).max(f64::MIN_POSITIVE);
    let magnitude = 10f64.powf(raw.log10().floor());
    let f = raw / magnitude;
    let nice = if f <= 1.0 {
        1.0
    } else if f <= 2.0 {
        2.0
    } else if f <= 5.0 {
        5.0
    } else {
        10.0
    };
    nice * magnitude
}

/// Multiples of `step` within [lo, hi].
fn ticks(lo: f64, hi: f64, step: f64) -> impl Iterator<Item = f64> {
    let first = (lo / step - 1e-9).ceil() as i64;
    let last = (hi / step + 1e-9).floor() as i64;
    (first..=last).map(move |k| k as f64 * step)
}

/// A tick value with as many decimals as its step needs.
fn format_tick(v: f64, step: f64) -> String {
    let decimals = (-step.log10().floor()).max(0.0) as usize;
    let v = if v.abs() < 0.5 * step { 0.0 } else { v };
    format!("{v:.decimals$}")
}

/// A value with at most two significant decimals, no trailing zeros.
fn format_value(v: f64) -> String {
    let s = format!("{v:.2}");
    s.trim_end_matches('0').trim_end_matches('.').to_string()
}

/// Round numbers a colour bar may end on, per decade.
const ROUND_STEPS: [f64; 10] = [1.0, 1.5, 2.0, 2.5, 3.0, 4.0, 5.0, 6.0, 8.0, 10.0];

/// The smallest round number ≥ `v` (1 for nothing to show).
fn round_up(v: f64) -> f64 {
    if v.is_nan() || v <= 0.0 {
        return 1.0;
    }
    let decade = 10f64.powf(v.log10().floor());
    ROUND_STEPS
        .iter()
        .map(|s| s * decade)
        .find(|&r| r >= v * (1.0 - 1e-9))
        .unwrap_or(10.0 * decade)
}

/// The largest round number ≤ `v`.
fn round_down(v: f64) -> f64 {
    let decade = 10f64.powf(v.log10().floor());
    ROUND_STEPS
        .iter()
        .rev()
        .map(|s| s * decade)
        .find(|&r| r <= v * (1.0 + 1e-9))
        .unwrap_or(decade)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_numbers_bracket_the_value() {
        assert_eq!(round_up(10.1), 15.0);
        assert_eq!(round_up(0.37), 0.4);
        assert_eq!(round_up(20.0), 20.0);
        assert_eq!(round_down(17.0), 15.0);
        assert_eq!(round_down(0.9), 0.8);
        assert_eq!(nice_step(100.0, 5), 20.0);
        assert_eq!(nice_step(7.0, 8), 1.0);
        assert_eq!(
            ticks(-12.0, 41.0, 10.0).collect::<Vec<_>>(),
            [-10.0, 0.0, 10.0, 20.0, 30.0, 40.0]
        );
        assert_eq!(format_tick(0.5, 0.5), "0.5");
        assert_eq!(format_tick(-1e-17, 0.1), "0.0");
        assert_eq!(format_value(2.5), "2.5");
        assert_eq!(format_value(10.0), "10");
    }

    #[test]
    fn viridis_runs_from_dark_purple_to_yellow_with_rising_lightness() {
        assert_eq!(viridis(0.0), [68, 1, 84]);
        assert_eq!(viridis(1.0), [253, 231, 37]);
        assert_eq!(viridis(2.0), viridis(1.0));
        let luma = |c: [u8; 3]| 0.3 * c[0] as f32 + 0.59 * c[1] as f32 + 0.11 * c[2] as f32;
        for i in 0..20 {
            let (a, b) = (viridis(i as f32 / 20.0), viridis((i + 1) as f32 / 20.0));
            assert!(luma(b) > luma(a), "{i}: {a:?} → {b:?}");
        }
    }
}
