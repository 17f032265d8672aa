//! The displacement quick look: a coronal CT slice with |u| in viridis over the lungs,
//! in-plane arrows, a colour bar and a reference arrow.

use nalgebra::Vector3;
use rayon::prelude::*;

use super::draw::{canvas, draw_arrow, fill_rect, outline_rect};
use super::scale::{format_tick, format_value, nice_step, round_down, round_up, ticks};
use super::{ARROW_COLOUR, BLACK, OVERLAY_OPACITY, TEXT_SCALE, WHITE};
use crate::outputs::quicklook::{
    render_slice, HuWindow, RgbImage, SliceGrid, SlicePlane, MAX_IMAGE_SIDE,
};
use crate::outputs::raster_text::{draw_text, text_height_px, text_width_px};
use crate::volume::Volume;
use crate::{Error, Result};

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
    check_look_input(input)?;
    let colour_max_mm = colour_bar_top_mm(input)?;
    let slice = coronal_panel(input)?;
    let panel = slice.panel;
    let layout = look_layout(input, &panel, colour_max_mm)?;
    let mut image = canvas(layout.width, layout.height, WHITE);
    let voxels = PanelVoxels::new(input.ct, &panel);
    paint_slice_and_magnitude(&mut image, input, &slice, &voxels, colour_max_mm);
    let arrows = grid_arrows(input, &panel, &voxels, &layout);
    // Halos first, so no halo covers a neighbouring arrow.
    for a in &arrows {
        draw_arrow(&mut image, a.tail_px, a.head_px, 1.9, BLACK);
    }
    for a in &arrows {
        draw_arrow(&mut image, a.tail_px, a.head_px, 0.7, ARROW_COLOUR);
    }
    draw_look_annotations(&mut image, input.title, &panel, &layout, colour_max_mm);
    Ok(DisplacementLook {
        image,
        panel,
        arrows,
        colour_max_mm,
        arrow_px_per_mm: layout.arrow_px_per_mm,
    })
}

/// Refuses lung labels off the CT grid and a field of the wrong size or not finite.
fn check_look_input(input: &DisplacementLookInput) -> Result<()> {
    let g = &input.ct.geometry;
    if !input.lungs.geometry.same_grid(g, 1e-3) || input.lungs.as_slice().len() != g.voxel_count() {
        return Err(Error::argument(
            "displacement quick look",
            format!(
                "the lung labels ({:?}) are not on the CT grid ({:?})",
                input.lungs.geometry.dims, g.dims
            ),
        ));
    }
    if input.displacement_mm.len() != g.voxel_count() {
        return Err(Error::argument(
            "displacement quick look",
            format!(
                "{} displacements for {} CT voxels",
                input.displacement_mm.len(),
                g.voxel_count()
            ),
        ));
    }
    if let Some(i) = input
        .displacement_mm
        .par_iter()
        .position_any(|u| u.iter().any(|v| !v.is_finite()))
    {
        return Err(Error::argument(
            "displacement quick look",
            format!(
                "voxel {i} has a non-finite displacement {:?}",
                input.displacement_mm[i]
            ),
        ));
    }
    Ok(())
}

/// The colour bar's top, mm: the one asked for, else a round value above the largest
/// magnitude in the lungs.
fn colour_bar_top_mm(input: &DisplacementLookInput) -> Result<f32> {
    Ok(match input.colour_max_mm {
        Some(m) if m.is_finite() && m > 0.0 => m,
        Some(m) => {
            return Err(Error::argument(
                "displacement quick look",
                format!("colour-bar top {m} mm must be positive"),
            ))
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
    })
}

/// The CT slice of a quick look and where its refined pixels sit in the image.
struct CoronalPanel {
    /// The slice in lung window, one pixel per native slice pixel.
    base: RgbImage,
    /// Panel pixels per side of a `base` pixel.
    refine: usize,
    panel: SlicePanel,
}

/// The CT slice exactly as the ingest quick look draws it, then refined by an integer
/// factor so a coarse scan still leaves room for legible arrows.
fn coronal_panel(input: &DisplacementLookInput) -> Result<CoronalPanel> {
    let base = render_slice(
        input.ct,
        &[],
        SlicePlane::Coronal,
        input.coronal_y_mm,
        HuWindow::LUNG,
    )?;
    let native = SliceGrid::native(&input.ct.geometry, SlicePlane::Coronal, input.coronal_y_mm)?;
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
    Ok(CoronalPanel {
        base,
        refine,
        panel,
    })
}

/// Arrow scale, reference arrow, texts and image size of a quick look.
struct LookLayout {
    subtitle: String,
    /// Panel pixels between arrows.
    spacing_px: usize,
    arrow_px_per_mm: f64,
    /// Image column where the reference arrow starts.
    reference_left_px: usize,
    /// Length of the reference arrow, pixels.
    reference_px: f64,
    /// The reference arrow's meaning in words.
    note: String,
    note_left_px: usize,
    width: usize,
    height: usize,
}

/// Lays the quick look out around `panel`; refuses an image larger than
/// [`MAX_IMAGE_SIDE`] per side.
fn look_layout(
    input: &DisplacementLookInput,
    panel: &SlicePanel,
    colour_max_mm: f32,
) -> Result<LookLayout> {
    let (pw, ph, pixel_mm) = (panel.width_px, panel.height_px, panel.pixel_mm);
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
        return Err(Error::argument(
            "displacement quick look",
            format!(
                "it would be {width}×{height} pixels (more than \
             {MAX_IMAGE_SIDE} per side)"
            ),
        ));
    }
    Ok(LookLayout {
        subtitle,
        spacing_px,
        arrow_px_per_mm,
        reference_left_px,
        reference_px,
        note,
        note_left_px,
        width,
        height,
    })
}

/// Per panel pixel: the nearest CT voxel (for the lung label and the field).
struct PanelVoxels<'a> {
    ct: &'a Volume<f32>,
    /// Continuous voxel index of the panel's first pixel.
    first: Vector3<f64>,
    per_col: Vector3<f64>,
    per_row: Vector3<f64>,
}

impl<'a> PanelVoxels<'a> {
    /// The voxel steps of one panel column and one panel row.
    fn new(ct: &'a Volume<f32>, panel: &SlicePanel) -> Self {
        let g = &ct.geometry;
        let pixel_mm = panel.pixel_mm;
        let origin =
            Vector3::from(panel.lps_of_image_px(panel.left_px as f64, panel.top_px as f64));
        let first = g.lps_mm_to_voxel(origin);
        let per_col = g.lps_mm_to_voxel(origin + Vector3::new(pixel_mm, 0.0, 0.0)) - first;
        let per_row = g.lps_mm_to_voxel(origin + Vector3::new(0.0, 0.0, -pixel_mm)) - first;
        PanelVoxels {
            ct,
            first,
            per_col,
            per_row,
        }
    }

    /// Linear index of the CT voxel nearest panel pixel (col, row); `None` off the grid.
    #[inline]
    fn at(&self, col: usize, row: usize) -> Option<usize> {
        nearest_voxel(
            self.ct,
            self.first + self.per_col * col as f64 + self.per_row * row as f64,
        )
    }
}

/// The refined CT slice into the panel, with |u| blended over it in the lungs.
fn paint_slice_and_magnitude(
    image: &mut RgbImage,
    input: &DisplacementLookInput,
    slice: &CoronalPanel,
    voxels: &PanelVoxels,
    colour_max_mm: f32,
) {
    let (panel, base, refine) = (&slice.panel, &slice.base, slice.refine);
    let (pw, ph) = (panel.width_px, panel.height_px);
    let width = image.width;
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
                let Some(v) = voxels.at(col, row) else {
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
}

/// Arrows at the grid points inside the lungs (shorter than 2 pixels left out).
fn grid_arrows(
    input: &DisplacementLookInput,
    panel: &SlicePanel,
    voxels: &PanelVoxels,
    layout: &LookLayout,
) -> Vec<Arrow> {
    let (pw, ph) = (panel.width_px, panel.height_px);
    let (spacing_px, arrow_px_per_mm) = (layout.spacing_px, layout.arrow_px_per_mm);
    let lungs = input.lungs.as_slice();
    let field = input.displacement_mm;
    let mut arrows = Vec::new();
    for row in (spacing_px / 2..ph).step_by(spacing_px) {
        for col in (spacing_px / 2..pw).step_by(spacing_px) {
            let Some(v) = voxels.at(col, row) else {
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
    arrows
}

/// Title, subtitle, orientation letters, colour bar and the reference arrow with the
/// magnification in words.
fn draw_look_annotations(
    image: &mut RgbImage,
    title: &str,
    panel: &SlicePanel,
    layout: &LookLayout,
    colour_max_mm: f32,
) {
    let (pw, ph) = (panel.width_px, panel.height_px);
    let text_h = text_height_px(TEXT_SCALE) as i64;
    let (pl, pt) = (panel.left_px as i64, panel.top_px as i64);
    let (pr, pb) = (pl + pw as i64, pt + ph as i64);
    draw_text(image, title, pl, 8, TEXT_SCALE, BLACK);
    draw_text(image, &layout.subtitle, pl, 30, TEXT_SCALE, BLACK);
    // Orientation letters: the radiological convention at a glance.
    let centre_col = (pl + pr) / 2;
    let centre_row = (pt + pb) / 2 - text_h / 2;
    draw_text(
        image,
        "S",
        centre_col - 5,
        pt - text_h - 4,
        TEXT_SCALE,
        BLACK,
    );
    draw_text(image, "I", centre_col - 5, pb + 4, TEXT_SCALE, BLACK);
    draw_text(image, "R", pl - 20, centre_row, TEXT_SCALE, BLACK);
    draw_text(image, "L", pr + 8, centre_row, TEXT_SCALE, BLACK);
    draw_colour_bar(image, pr + 40, pt, ph as i64, colour_max_mm);

    // Reference arrow with the magnification in words.
    let y = (pb + 24 + text_h / 2) as f64;
    let x0 = layout.reference_left_px as f64;
    let reference_px = layout.reference_px;
    draw_text(image, "arrows:", pl, pb + 24, TEXT_SCALE, BLACK);
    draw_arrow(image, [x0, y], [x0 + reference_px, y], 1.9, BLACK);
    draw_arrow(image, [x0, y], [x0 + reference_px, y], 0.7, [90, 90, 90]);
    let note_left = layout.note_left_px as i64;
    draw_text(image, &layout.note, note_left, pb + 24, TEXT_SCALE, BLACK);
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

#[cfg(test)]
mod tests {
    use super::*;

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
