//! A labelled CT slice a physicist can read on its own: a title, the slice's position,
//! orientation letters on the four edges of the slice and a legend of the overlay colours.

use super::draw::{canvas, fill_rect, outline_rect};
use super::{BLACK, TEXT_SCALE, WHITE};
use crate::outputs::quicklook::{
    render_slice_with_pixel, HuWindow, Overlay, RgbImage, SlicePlane, MAX_IMAGE_SIDE,
};
use crate::outputs::raster_text::{draw_text, text_height_px, text_width_px};
use crate::volume::Volume;
use crate::{Error, Result};

/// One line of a legend: a colour and what it means.
#[derive(Debug, Clone, PartialEq)]
pub struct LegendEntry {
    /// What the colour marks, e.g. `costal (slides on wall)`.
    pub label: String,
    /// The colour as drawn.
    pub colour: [u8; 3],
    /// Drawn as an outline in the image (the swatch is then a hollow square).
    pub outline: bool,
}

/// What to draw in a labelled slice.
#[derive(Debug, Clone, Copy)]
pub struct LabelledSliceInput<'a> {
    /// The CT (HU).
    pub ct: &'a Volume<f32>,
    /// Label overlays, drawn in order.
    pub overlays: &'a [Overlay<'a>],
    /// The slice's plane.
    pub plane: SlicePlane,
    /// Its fixed LPS coordinate, mm (z axial, y coronal, x sagittal).
    pub position_lps_mm: f64,
    /// Side of a slice pixel, mm.
    pub pixel_mm: f64,
    /// First line: what the picture shows.
    pub title: &'a str,
    /// Second line: where the slice lies and why.
    pub subtitle: &'a str,
    /// The overlay colours and their meaning.
    pub legend: &'a [LegendEntry],
}

/// A pixel rectangle of a picture.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PixelRect {
    /// First column.
    pub left: usize,
    /// First row.
    pub top: usize,
    /// Columns.
    pub width: usize,
    /// Rows.
    pub height: usize,
}

/// The rendered labelled slice and where its parts are.
#[derive(Debug, Clone)]
pub struct LabelledSlice {
    /// The picture.
    pub image: RgbImage,
    /// The CT slice.
    pub panel: PixelRect,
    /// The legend (swatches and labels).
    pub legend: PixelRect,
    /// The orientation letters' boxes: image left, right, top and bottom edge of the slice.
    pub orientation: [(char, PixelRect); 4],
}

const MARGIN_PX: usize = 40;
const PANEL_TOP_PX: usize = 76;
const BOTTOM_MARGIN_PX: usize = 40;
const LEGEND_GAP_PX: usize = 44;
const SWATCH_PX: usize = 16;
const LEGEND_ROW_PX: usize = 24;

/// Draws the slice with its title, orientation letters and legend.
pub fn render_labelled_slice(input: &LabelledSliceInput) -> Result<LabelledSlice> {
    let slice = render_slice_with_pixel(
        input.ct,
        input.overlays,
        input.plane,
        input.position_lps_mm,
        HuWindow::LUNG,
        input.pixel_mm,
    )?;
    let text_h = text_height_px(TEXT_SCALE);
    let panel = PixelRect {
        left: MARGIN_PX,
        top: PANEL_TOP_PX,
        width: slice.width,
        height: slice.height,
    };
    let legend_w = input
        .legend
        .iter()
        .map(|e| SWATCH_PX + 10 + text_width_px(&e.label, TEXT_SCALE))
        .chain([text_width_px("Legend", TEXT_SCALE)])
        .max()
        .unwrap_or(0);
    let legend = PixelRect {
        left: panel.left + panel.width + LEGEND_GAP_PX,
        top: panel.top,
        width: legend_w,
        height: LEGEND_ROW_PX * (input.legend.len() + 1),
    };
    let width = (legend.left + legend.width + MARGIN_PX)
        .max(text_width_px(input.title, TEXT_SCALE) + 2 * MARGIN_PX)
        .max(text_width_px(input.subtitle, TEXT_SCALE) + 2 * MARGIN_PX);
    let height = PANEL_TOP_PX + panel.height.max(legend.height) + BOTTOM_MARGIN_PX;
    if width > MAX_IMAGE_SIDE || height > MAX_IMAGE_SIDE {
        return Err(Error::argument(
            "labelled quick look",
            format!("it would be {width}×{height} pixels (more than {MAX_IMAGE_SIDE} per side)"),
        ));
    }
    let mut image = canvas(width, height, WHITE);
    paste(&mut image, &slice, panel.left, panel.top);
    draw_text(
        &mut image,
        input.title,
        MARGIN_PX as i64,
        8,
        TEXT_SCALE,
        BLACK,
    );
    draw_text(
        &mut image,
        input.subtitle,
        MARGIN_PX as i64,
        30,
        TEXT_SCALE,
        BLACK,
    );
    let orientation = orientation_boxes(input.plane, &panel, text_h);
    for (letter, b) in &orientation {
        let s = letter.to_string();
        draw_text(
            &mut image,
            &s,
            b.left as i64,
            b.top as i64,
            TEXT_SCALE,
            BLACK,
        );
    }
    draw_legend(&mut image, input.legend, &legend);
    Ok(LabelledSlice {
        image,
        panel,
        legend,
        orientation,
    })
}

/// Copies `slice` into `image` with its top-left pixel at (`left`, `top`).
fn paste(image: &mut RgbImage, slice: &RgbImage, left: usize, top: usize) {
    let row_bytes = 3 * slice.width;
    for row in 0..slice.height {
        let from = &slice.pixels[row * row_bytes..(row + 1) * row_bytes];
        let at = 3 * ((top + row) * image.width + left);
        image.pixels[at..at + row_bytes].copy_from_slice(from);
    }
}

/// Where the letters of the patient directions at the slice's four edges go, in the order
/// image left, right, top, bottom.
fn orientation_boxes(
    plane: SlicePlane,
    panel: &PixelRect,
    text_h: usize,
) -> [(char, PixelRect); 4] {
    let letters = plane.edge_letters();
    let glyph_w = text_width_px("M", TEXT_SCALE);
    let mid_col = panel.left + panel.width / 2 - glyph_w / 2;
    let mid_row = panel.top + panel.height / 2 - text_h / 2;
    let rect = |left, top| PixelRect {
        left,
        top,
        width: glyph_w,
        height: text_h,
    };
    [
        (letters[0], rect(panel.left - glyph_w - 12, mid_row)),
        (letters[1], rect(panel.left + panel.width + 12, mid_row)),
        (letters[2], rect(mid_col, panel.top - text_h - 6)),
        (letters[3], rect(mid_col, panel.top + panel.height + 6)),
    ]
}

/// A "Legend" header, then one swatch (filled, or hollow for outlines) and label per row.
fn draw_legend(image: &mut RgbImage, entries: &[LegendEntry], at: &PixelRect) {
    let (left, top) = (at.left as i64, at.top as i64);
    draw_text(image, "Legend", left, top, TEXT_SCALE, BLACK);
    let text_h = text_height_px(TEXT_SCALE) as i64;
    let swatch = SWATCH_PX as i64;
    for (n, e) in entries.iter().enumerate() {
        let row_top = top + LEGEND_ROW_PX as i64 * (n as i64 + 1);
        if e.outline {
            for inset in 0..3 {
                outline_rect(
                    image,
                    left + inset,
                    row_top + inset,
                    swatch - 2 * inset,
                    swatch - 2 * inset,
                    e.colour,
                );
            }
        } else {
            fill_rect(image, left, row_top, swatch, swatch, e.colour);
            outline_rect(image, left, row_top, swatch, swatch, BLACK);
        }
        let text_top = row_top + (swatch - text_h) / 2;
        draw_text(
            image,
            &e.label,
            left + swatch + 10,
            text_top,
            TEXT_SCALE,
            BLACK,
        );
    }
}
