//! PNG quick looks: CT slices with label overlays (lung mask, constraint groups) that a
//! medical physicist checks at a glance after an ingest.
//!
//! Convention: slices are planes of DICOM patient space (LPS mm), not of the voxel grid.
//! Each output pixel's LPS position is mapped into the CT through
//! [`VolumeGeometry::lps_mm_to_voxel`](crate::volume::VolumeGeometry::lps_mm_to_voxel), so
//! flipped and oblique scans display the same anatomy the same way. Images use the
//! **radiological display convention**:
//!
//! | plane | image left | image top | fixed coordinate |
//! | --- | --- | --- | --- |
//! | axial | patient right (−x) | anterior (−y) | z (superior) |
//! | coronal | patient right (−x) | superior (+z) | y (posterior) |
//! | sagittal | anterior (−y) | superior (+z) | x (left) |
//!
//! Pixels are square, of the CT's smallest spacing (the overview may use a finer pixel so a
//! coarse scan is legible); the image covers the LPS bounding box of the scan, outside the
//! scan is black. The CT is sampled trilinearly, labels by nearest voxel. Grey levels map
//! `level − width/2` to 0 and `level + width/2` to 255 (lung window: W 1500, L −600 HU).
//! PNG files are 8-bit RGB, rows top to bottom.

use std::io::Cursor;
use std::path::{Path, PathBuf};

use nalgebra::Vector3;
use rayon::prelude::*;

use crate::durable::write_atomic;
use crate::volume::{Volume, VolumeGeometry};
use crate::{Error, IoContext, IoOp, Result};

/// Largest image side in pixels (refused beyond: a sign of a wrong spacing or pixel size).
pub const MAX_IMAGE_SIDE: usize = 8192;

/// Smallest side in pixels the overview aims for, refining the pixel when the CT is coarse.
const OVERVIEW_MIN_SIDE: usize = 384;

/// A label volume drawn in colour over the CT.
#[derive(Debug, Clone, Copy)]
pub struct Overlay<'a> {
    /// Label codes (0 is usually background); may lie on another grid than the CT.
    pub labels: &'a Volume<u8>,
    /// Colour of each drawn label code; codes not listed are not drawn.
    pub palette: &'a [(u8, [u8; 3])],
    /// Blend weight of the colour, 0 (invisible) to 1 (opaque).
    pub opacity: f32,
    /// Draw only the label boundaries (pixels with a differently labelled 4-neighbour).
    pub outline_only: bool,
}

/// The patient plane a slice lies in.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SlicePlane {
    /// Constant z (superior), seen from the feet.
    Axial,
    /// Constant y (posterior), seen from the front.
    Coronal,
    /// Constant x (left), seen from the patient's left.
    Sagittal,
}

impl SlicePlane {
    /// The three planes in overview order.
    pub const ALL: [SlicePlane; 3] = [SlicePlane::Axial, SlicePlane::Coronal, SlicePlane::Sagittal];

    /// Lower-case name used in file names.
    pub fn name(self) -> &'static str {
        match self {
            SlicePlane::Axial => "axial",
            SlicePlane::Coronal => "coronal",
            SlicePlane::Sagittal => "sagittal",
        }
    }

    /// Letters of the patient directions at the image's left, right, top and bottom edges
    /// (radiological convention): R/L right and left, A/P anterior and posterior, S/I
    /// superior and inferior.
    pub fn edge_letters(self) -> [char; 4] {
        match self {
            SlicePlane::Axial => ['R', 'L', 'A', 'P'],
            SlicePlane::Coronal => ['R', 'L', 'S', 'I'],
            SlicePlane::Sagittal => ['A', 'P', 'S', 'I'],
        }
    }

    /// Index of the LPS axis the plane's position is measured along (x 0, y 1, z 2).
    pub fn normal_axis(self) -> usize {
        match self {
            SlicePlane::Axial => 2,
            SlicePlane::Coronal => 1,
            SlicePlane::Sagittal => 0,
        }
    }

    /// LPS unit vectors of the image's rightward column axis, downward row axis and the
    /// plane normal (whose coordinate is the slice position).
    fn frame(self) -> [Vector3<f64>; 3] {
        let (x, y, z) = (Vector3::x(), Vector3::y(), Vector3::z());
        match self {
            SlicePlane::Axial => [x, y, z],
            SlicePlane::Coronal => [x, -z, y],
            SlicePlane::Sagittal => [y, -z, x],
        }
    }
}

/// A grey-level window over Hounsfield units.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HuWindow {
    /// Range of HU spread over the 256 grey levels.
    pub width_hu: f32,
    /// HU shown mid-grey.
    pub level_hu: f32,
}

impl HuWindow {
    /// Lung window: W 1500, L −600 HU (−1350 HU black, 150 HU white).
    pub const LUNG: HuWindow = HuWindow {
        width_hu: 1500.0,
        level_hu: -600.0,
    };

    /// Soft-tissue (mediastinum) window: W 400, L 40 HU.
    pub const MEDIASTINUM: HuWindow = HuWindow {
        width_hu: 400.0,
        level_hu: 40.0,
    };

    /// Grey level of a CT number.
    #[inline]
    pub fn grey(&self, hu: f32) -> u8 {
        let t = (hu - (self.level_hu - 0.5 * self.width_hu)) / self.width_hu;
        (t.clamp(0.0, 1.0) * 255.0).round() as u8
    }
}

impl Default for HuWindow {
    fn default() -> Self {
        HuWindow::LUNG
    }
}

/// An 8-bit RGB image, rows top to bottom.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RgbImage {
    /// Pixels per row.
    pub width: usize,
    /// Number of rows.
    pub height: usize,
    /// `3·width·height` bytes, R G B per pixel, row-major from the top-left.
    pub pixels: Vec<u8>,
}

impl RgbImage {
    /// Colour of the pixel in column `col`, row `row` (from the top-left).
    pub fn pixel(&self, col: usize, row: usize) -> [u8; 3] {
        let o = 3 * (row * self.width + col);
        [self.pixels[o], self.pixels[o + 1], self.pixels[o + 2]]
    }
}

/// Renders the slice of `plane` at `position_lps_mm` (its fixed coordinate: z for axial, y
/// for coronal, x for sagittal) with square pixels of the CT's smallest spacing.
pub fn render_slice(
    ct: &Volume<f32>,
    overlays: &[Overlay],
    plane: SlicePlane,
    position_lps_mm: f64,
    window: HuWindow,
) -> Result<RgbImage> {
    let pixel_mm = smallest_spacing_mm(&ct.geometry);
    render_slice_with_pixel(ct, overlays, plane, position_lps_mm, window, pixel_mm)
}

/// Writes `<stem>-axial.png`, `<stem>-coronal.png` and `<stem>-sagittal.png` through
/// `centre_lps_mm` into `out_dir` (created if missing), in the lung window; coarse CTs are
/// sampled on a finer pixel so each image is at least a few hundred pixels wide.
pub fn write_overview(
    ct: &Volume<f32>,
    overlays: &[Overlay],
    centre_lps_mm: [f64; 3],
    out_dir: &Path,
    stem: &str,
) -> Result<Vec<PathBuf>> {
    if stem.is_empty() || stem.contains(['/', '\\']) {
        return Err(argument(
            "quick-look file stem",
            format!("{stem:?} must be a plain non-empty name"),
        ));
    }
    std::fs::create_dir_all(out_dir).at(IoOp::CreateDir, out_dir)?;
    let pixel_mm = overview_pixel_mm(&ct.geometry);
    let mut paths = Vec::with_capacity(3);
    for plane in SlicePlane::ALL {
        let image = render_slice_with_pixel(
            ct,
            overlays,
            plane,
            centre_lps_mm[plane.normal_axis()],
            HuWindow::LUNG,
            pixel_mm,
        )?;
        let path = out_dir.join(format!("{stem}-{}.png", plane.name()));
        write_png(&path, &image)?;
        paths.push(path);
    }
    Ok(paths)
}

/// The pixel of an overview of a scan of `geometry`, mm: its smallest spacing, refined so a
/// coarse scan's largest extent still spans a few hundred pixels.
pub fn overview_pixel_mm(geometry: &VolumeGeometry) -> f64 {
    let spacing = smallest_spacing_mm(geometry);
    let extent_px = geometry
        .dims
        .iter()
        .zip(&geometry.spacing_mm)
        .map(|(&n, &s)| n as f64 * s / spacing)
        .fold(1.0, f64::max);
    let refine = (OVERVIEW_MIN_SIDE as f64 / extent_px)
        .ceil()
        .clamp(1.0, 8.0);
    spacing / refine
}

/// Writes an 8-bit RGB PNG atomically.
pub fn write_png(path: &Path, image: &RgbImage) -> Result<()> {
    write_png_with_text(path, image, &[])
}

/// Writes an 8-bit RGB PNG atomically with `text` as tEXt chunks (keyword, Latin-1 text):
/// metadata image viewers show and scripts read back with [`read_png_text`].
pub fn write_png_with_text(path: &Path, image: &RgbImage, text: &[(&str, String)]) -> Result<()> {
    let bad = |m: String| argument("PNG image", m);
    if image.width == 0 || image.height == 0 {
        return Err(bad(format!("empty image {}×{}", image.width, image.height)));
    }
    if image.width > MAX_IMAGE_SIDE || image.height > MAX_IMAGE_SIDE {
        return Err(bad(format!(
            "image {}×{} exceeds {MAX_IMAGE_SIDE} pixels per side",
            image.width, image.height
        )));
    }
    if image.pixels.len() != 3 * image.width * image.height {
        return Err(bad(format!(
            "{} bytes for a {}×{} RGB image",
            image.pixels.len(),
            image.width,
            image.height
        )));
    }
    let mut bytes = Vec::new();
    {
        let mut encoder = png::Encoder::new(&mut bytes, image.width as u32, image.height as u32);
        encoder.set_color(png::ColorType::Rgb);
        encoder.set_depth(png::BitDepth::Eight);
        let failed = |e: png::EncodingError| Error::Format {
            path: path.to_path_buf(),
            reason: format!("PNG encoding failed: {e}"),
        };
        for (keyword, value) in text {
            encoder
                .add_text_chunk(keyword.to_string(), value.clone())
                .map_err(failed)?;
        }
        let mut writer = encoder.write_header().map_err(failed)?;
        writer.write_image_data(&image.pixels).map_err(failed)?;
        writer.finish().map_err(failed)?;
    }
    write_atomic(path, &bytes)
}

/// Reads a PNG as 8-bit RGB (grey and alpha channels are converted; 16-bit is reduced).
pub fn read_png(path: &Path) -> Result<RgbImage> {
    let bad = |reason: String| Error::Format {
        path: path.to_path_buf(),
        reason,
    };
    let bytes = std::fs::read(path).at(IoOp::Read, path)?;
    let mut decoder = png::Decoder::new(Cursor::new(bytes));
    decoder.set_transformations(png::Transformations::normalize_to_color8());
    let mut reader = decoder
        .read_info()
        .map_err(|e| bad(format!("not a readable PNG: {e}")))?;
    let size = reader
        .output_buffer_size()
        .ok_or_else(|| bad("PNG too large".into()))?;
    let mut buf = vec![0u8; size];
    let info = reader
        .next_frame(&mut buf)
        .map_err(|e| bad(format!("corrupt PNG data: {e}")))?;
    let (width, height) = (info.width as usize, info.height as usize);
    let channels = match info.color_type {
        png::ColorType::Grayscale => 1,
        png::ColorType::GrayscaleAlpha => 2,
        png::ColorType::Rgb => 3,
        png::ColorType::Rgba => 4,
        png::ColorType::Indexed => return Err(bad("palette PNG was not expanded".into())),
    };
    let mut pixels = Vec::with_capacity(3 * width * height);
    for row in buf.chunks_exact(info.line_size).take(height) {
        for px in row[..width * channels].chunks_exact(channels) {
            if channels < 3 {
                pixels.extend_from_slice(&[px[0]; 3]);
            } else {
                pixels.extend_from_slice(&px[..3]);
            }
        }
    }
    Ok(RgbImage {
        width,
        height,
        pixels,
    })
}

/// The tEXt chunks of a PNG as (keyword, text) pairs, in file order.
pub fn read_png_text(path: &Path) -> Result<Vec<(String, String)>> {
    let bytes = std::fs::read(path).at(IoOp::Read, path)?;
    let reader = png::Decoder::new(Cursor::new(bytes))
        .read_info()
        .map_err(|e| Error::Format {
            path: path.to_path_buf(),
            reason: format!("not a readable PNG: {e}"),
        })?;
    Ok(reader
        .info()
        .uncompressed_latin1_text
        .iter()
        .map(|t| (t.keyword.clone(), t.text.clone()))
        .collect())
}

/// The pixel grid of a slice image in LPS mm: square pixels covering the scan's LPS bounding
/// box in the slice plane, centred on it, oriented by the display convention of the module
/// doc. [`render_slice`] draws on [`SliceGrid::native`]; other pictures use the same grid to
/// put their own pixels on the same anatomy.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SliceGrid {
    /// Pixels per row.
    pub width_px: usize,
    /// Number of rows.
    pub height_px: usize,
    /// Side of a (square) pixel, mm.
    pub pixel_mm: f64,
    /// LPS position of pixel (0, 0)'s centre, mm.
    pub first_pixel_lps_mm: [f64; 3],
    /// LPS step from one column to the next (towards the image's right), mm.
    pub column_step_lps_mm: [f64; 3],
    /// LPS step from one row to the next (downwards), mm.
    pub row_step_lps_mm: [f64; 3],
}

impl SliceGrid {
    /// The grid of `plane` at `position_lps_mm` (its fixed coordinate) through the scan of
    /// `geometry`, with pixels of `pixel_mm`; fails if the slice misses the scan or the image
    /// would exceed [`MAX_IMAGE_SIDE`].
    pub fn new(
        geometry: &VolumeGeometry,
        plane: SlicePlane,
        position_lps_mm: f64,
        pixel_mm: f64,
    ) -> Result<SliceGrid> {
        if !(pixel_mm.is_finite() && pixel_mm > 0.0) {
            return Err(argument(
                "quick-look slice",
                format!(
                    "{} slice pixel {pixel_mm} mm must be positive and finite",
                    plane.name()
                ),
            ));
        }
        let [col_dir, row_dir, normal] = plane.frame();
        // LPS bounding box of the scan: its 8 outer voxel corners projected on the frame axes.
        let g = geometry;
        let mut lo = [f64::MAX; 3];
        let mut hi = [f64::MIN; 3];
        for corner in 0..8 {
            let ijk = Vector3::from_fn(|a, _| {
                if (corner >> a) & 1 == 1 {
                    g.dims[a] as f64 - 0.5
                } else {
                    -0.5
                }
            });
            let p = g.voxel_to_lps_mm(ijk);
            for (a, axis) in [col_dir, row_dir, normal].iter().enumerate() {
                lo[a] = lo[a].min(axis.dot(&p));
                hi[a] = hi[a].max(axis.dot(&p));
            }
        }
        if !position_lps_mm.is_finite() || position_lps_mm < lo[2] || position_lps_mm > hi[2] {
            return Err(argument(
                "quick-look slice",
                format!(
                    "{} slice at {position_lps_mm} mm is outside the scan ({:.1} to {:.1} mm)",
                    plane.name(),
                    lo[2],
                    hi[2]
                ),
            ));
        }
        let side = |a: usize| ((hi[a] - lo[a]) / pixel_mm - 1e-6).ceil().max(1.0) as usize;
        let (width, height) = (side(0), side(1));
        if width > MAX_IMAGE_SIDE || height > MAX_IMAGE_SIDE {
            return Err(argument(
                "quick-look slice",
                format!(
                    "{} slice would be {width}×{height} pixels (more than {MAX_IMAGE_SIDE} per \
                     side)",
                    plane.name()
                ),
            ));
        }
        // The image is centred on the scan's box.
        let margin = |a: usize, n: usize| 0.5 * ((hi[a] - lo[a]) - n as f64 * pixel_mm);
        let first = col_dir * (lo[0] + margin(0, width) + 0.5 * pixel_mm)
            + row_dir * (lo[1] + margin(1, height) + 0.5 * pixel_mm)
            + normal * position_lps_mm;
        Ok(SliceGrid {
            width_px: width,
            height_px: height,
            pixel_mm,
            first_pixel_lps_mm: first.into(),
            column_step_lps_mm: (col_dir * pixel_mm).into(),
            row_step_lps_mm: (row_dir * pixel_mm).into(),
        })
    }

    /// The grid [`render_slice`] draws on: pixels of the scan's smallest spacing.
    pub fn native(
        geometry: &VolumeGeometry,
        plane: SlicePlane,
        position_lps_mm: f64,
    ) -> Result<SliceGrid> {
        SliceGrid::new(
            geometry,
            plane,
            position_lps_mm,
            smallest_spacing_mm(geometry),
        )
    }

    /// LPS position of the centre of pixel (`col`, `row`), mm (fractional pixels allowed).
    pub fn lps_mm(&self, col: f64, row: f64) -> [f64; 3] {
        let (f, c, r) = (
            self.first_pixel_lps_mm,
            self.column_step_lps_mm,
            self.row_step_lps_mm,
        );
        [0, 1, 2].map(|a| f[a] + c[a] * col + r[a] * row)
    }
}

/// The scan's smallest voxel spacing, mm: the pixel that loses no resolution in any plane.
fn smallest_spacing_mm(g: &VolumeGeometry) -> f64 {
    g.spacing_mm.iter().cloned().fold(f64::MAX, f64::min)
}

/// Linear map from output pixel (column, row) to continuous voxel index of one grid.
struct PixelToVoxel {
    first: Vector3<f64>,
    per_col: Vector3<f64>,
    per_row: Vector3<f64>,
}

impl PixelToVoxel {
    fn new(
        g: &VolumeGeometry,
        first_lps_mm: Vector3<f64>,
        col_mm: Vector3<f64>,
        row_mm: Vector3<f64>,
    ) -> Self {
        let first = g.lps_mm_to_voxel(first_lps_mm);
        PixelToVoxel {
            first,
            per_col: g.lps_mm_to_voxel(first_lps_mm + col_mm) - first,
            per_row: g.lps_mm_to_voxel(first_lps_mm + row_mm) - first,
        }
    }

    #[inline]
    fn at(&self, col: usize, row: usize) -> Vector3<f64> {
        self.first + self.per_col * col as f64 + self.per_row * row as f64
    }
}

/// A refused quick-look request.
fn argument(what: &str, reason: String) -> Error {
    Error::Argument {
        what: what.to_string(),
        reason,
    }
}

fn check_volume<T>(v: &Volume<T>, what: &str) -> Result<()> {
    v.geometry.validate(what)?;
    if v.as_slice().len() != v.geometry.voxel_count() {
        return Err(argument(
            what,
            format!(
                "{} voxels for a grid of {:?}",
                v.as_slice().len(),
                v.geometry.dims
            ),
        ));
    }
    Ok(())
}

/// [`render_slice`] with square pixels of `pixel_mm`.
pub fn render_slice_with_pixel(
    ct: &Volume<f32>,
    overlays: &[Overlay],
    plane: SlicePlane,
    position_lps_mm: f64,
    window: HuWindow,
    pixel_mm: f64,
) -> Result<RgbImage> {
    check_volume(ct, "quick-look CT")?;
    for (n, o) in overlays.iter().enumerate() {
        check_volume(o.labels, &format!("quick-look overlay {n}"))?;
        if !(0.0..=1.0).contains(&o.opacity) {
            return Err(argument(
                "quick-look overlay",
                format!("overlay {n} opacity {} is outside 0–1", o.opacity),
            ));
        }
    }
    if !(window.width_hu.is_finite() && window.width_hu > 0.0 && window.level_hu.is_finite()) {
        return Err(argument(
            "quick-look window",
            format!("HU window {window:?} needs a positive finite width and a finite level"),
        ));
    }
    let grid = SliceGrid::new(&ct.geometry, plane, position_lps_mm, pixel_mm)?;
    let (width, height) = (grid.width_px, grid.height_px);
    let first = Vector3::from(grid.first_pixel_lps_mm);
    let col_mm = Vector3::from(grid.column_step_lps_mm);
    let row_mm = Vector3::from(grid.row_step_lps_mm);

    let ct_map = PixelToVoxel::new(&ct.geometry, first, col_mm, row_mm);
    let mut pixels = vec![0u8; 3 * width * height];
    pixels
        .par_chunks_mut(3 * width)
        .enumerate()
        .for_each(|(row, line)| {
            for (col, px) in line.chunks_exact_mut(3).enumerate() {
                if let Some(hu) = sample_trilinear(ct, ct_map.at(col, row)) {
                    px.fill(window.grey(hu));
                }
            }
        });

    let mut labels = vec![0u8; width * height];
    for o in overlays {
        let map = PixelToVoxel::new(&o.labels.geometry, first, col_mm, row_mm);
        labels
            .par_chunks_mut(width)
            .enumerate()
            .for_each(|(row, line)| {
                for (col, l) in line.iter_mut().enumerate() {
                    *l = sample_nearest(o.labels, map.at(col, row));
                }
            });
        let mut colour_of = [None::<[u8; 3]>; 256];
        for &(code, rgb) in o.palette {
            colour_of[code as usize] = Some(rgb);
        }
        let labels = &labels;
        pixels
            .par_chunks_mut(3 * width)
            .enumerate()
            .for_each(|(row, line)| {
                for (col, px) in line.chunks_exact_mut(3).enumerate() {
                    let l = labels[row * width + col];
                    let Some(rgb) = colour_of[l as usize] else {
                        continue;
                    };
                    if o.outline_only {
                        let differs = |c: usize, r: usize| labels[r * width + c] != l;
                        let edge = (col > 0 && differs(col - 1, row))
                            || (col + 1 < width && differs(col + 1, row))
                            || (row > 0 && differs(col, row - 1))
                            || (row + 1 < height && differs(col, row + 1));
                        if !edge {
                            continue;
                        }
                    }
                    for (p, c) in px.iter_mut().zip(rgb) {
                        *p = (*p as f32 * (1.0 - o.opacity) + c as f32 * o.opacity).round() as u8;
                    }
                }
            });
    }
    Ok(RgbImage {
        width,
        height,
        pixels,
    })
}

/// Trilinear CT value at a continuous voxel index; `None` outside the scan (beyond the
/// outer voxels' half-width).
#[inline]
fn sample_trilinear(v: &Volume<f32>, ijk: Vector3<f64>) -> Option<f32> {
    let d = v.geometry.dims;
    let mut base = [0usize; 3];
    let mut frac = [0f32; 3];
    for a in 0..3 {
        let x = ijk[a];
        let n = d[a] as f64;
        if !(-0.5..=n - 0.5).contains(&x) {
            return None;
        }
        // Half a voxel of edge padding repeats the outer voxel.
        let x = x.clamp(0.0, n - 1.0);
        let i0 = (x.floor() as usize).min(d[a].saturating_sub(2));
        base[a] = i0;
        frac[a] = (x - i0 as f64) as f32;
    }
    let step = [
        usize::from(d[0] > 1),
        usize::from(d[1] > 1) * d[0],
        usize::from(d[2] > 1) * d[0] * d[1],
    ];
    let i = v.geometry.index(base[0], base[1], base[2]);
    let lerp = |a: f32, b: f32, t: f32| a + (b - a) * t;
    let x00 = lerp(v.as_slice()[i], v.as_slice()[i + step[0]], frac[0]);
    let x10 = lerp(
        v.as_slice()[i + step[1]],
        v.as_slice()[i + step[1] + step[0]],
        frac[0],
    );
    let x01 = lerp(
        v.as_slice()[i + step[2]],
        v.as_slice()[i + step[2] + step[0]],
        frac[0],
    );
    let x11 = lerp(
        v.as_slice()[i + step[2] + step[1]],
        v.as_slice()[i + step[2] + step[1] + step[0]],
        frac[0],
    );
    Some(lerp(
        lerp(x00, x10, frac[1]),
        lerp(x01, x11, frac[1]),
        frac[2],
    ))
}

/// Label of the voxel nearest a continuous voxel index; 0 outside the grid.
#[inline]
fn sample_nearest(v: &Volume<u8>, ijk: Vector3<f64>) -> u8 {
    let d = v.geometry.dims;
    let mut idx = [0usize; 3];
    for a in 0..3 {
        let r = ijk[a].round();
        if !(0.0..d[a] as f64).contains(&r) {
            return 0;
        }
        idx[a] = r as usize;
    }
    v.get(idx[0], idx[1], idx[2])
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn coronal_grid_is_centred_on_the_scan_with_the_display_orientation() {
        // 10 × 4 × 6 voxels of 2 × 3 × 2.5 mm: x spans −1…19 mm, z spans −1.25…13.75 mm.
        let g = VolumeGeometry::axis_aligned([10, 4, 6], [2.0, 3.0, 2.5], [0.0, 0.0, 0.0]);
        let grid = SliceGrid::native(&g, SlicePlane::Coronal, 4.5).unwrap();
        assert_eq!(grid.pixel_mm, 2.0);
        // 20 mm in x → 10 pixels; 15 mm in z → 8 pixels (16 mm), half a pixel over each end.
        assert_eq!((grid.width_px, grid.height_px), (10, 8));
        let first = grid.lps_mm(0.0, 0.0);
        assert!((first[0] - 0.0).abs() < 1e-12, "{first:?}");
        assert!((first[1] - 4.5).abs() < 1e-12, "{first:?}");
        assert!((first[2] - 13.25).abs() < 1e-12, "{first:?}");
        // Columns go to the patient's left (+x), rows downwards (−z).
        let last = grid.lps_mm(9.0, 7.0);
        assert!((last[0] - 18.0).abs() < 1e-12 && (last[2] + 0.75).abs() < 1e-12);
        let outside = SliceGrid::native(&g, SlicePlane::Coronal, 20.0).unwrap_err();
        assert!(
            outside.to_string().contains("outside the scan"),
            "{outside}"
        );
        assert!(SliceGrid::new(&g, SlicePlane::Axial, 1.0, 0.0).is_err());
        assert!(SliceGrid::new(&g, SlicePlane::Axial, 1.0, 1e-3).is_err());
    }
}
