//! The ingest's quick looks, `quicklook-{axial,coronal,sagittal}.png`: the CT in lung window
//! with the lung outlines and constraint groups, each with a title, orientation letters and
//! a legend; the sagittal slice passes through the larger lung, not the mediastinum.
//!
//! Each PNG carries its slice as tEXt metadata (`Title`, `Description`, `lungmotion:plane`,
//! `lungmotion:position_lps_mm`, `lungmotion:through`, and where the slice and the legend
//! lie as `left,top,width,height` pixels: `lungmotion:slice_px`, `lungmotion:legend_px`),
//! read back with
//! [`read_png_text`](crate::outputs::quicklook::read_png_text).

use std::path::{Path, PathBuf};

use nalgebra::Vector3;

use crate::ingest::lung_model::{BoundaryCondition, ConstraintGroup};
use crate::outputs::ingest_files::{group_palette, LUNG_PALETTE};
use crate::outputs::plots::{render_labelled_slice, LabelledSliceInput, LegendEntry, PixelRect};
use crate::outputs::quicklook::{overview_pixel_mm, write_png_with_text, Overlay, SlicePlane};
use crate::volume::Volume;
use crate::{IoContext, IoOp, Result};

/// One quick look written: its file and the slice it shows.
#[derive(Debug, Clone, PartialEq)]
pub struct IngestQuicklook {
    /// The PNG file.
    pub path: PathBuf,
    /// The slice's plane.
    pub plane: SlicePlane,
    /// Its fixed LPS coordinate, mm.
    pub position_lps_mm: f64,
    /// Why it lies there, e.g. `the right lung's centroid`.
    pub through: String,
}

/// Writes `<out_dir>/quicklook-{axial,coronal,sagittal}.png`: axial and coronal through both
/// lungs' centroid, sagittal through the larger lung's.
pub fn write_ingest_quicklooks(
    out_dir: &Path,
    ct: &Volume<f32>,
    lungs: &Volume<u8>,
    groups: &Volume<u8>,
) -> Result<Vec<IngestQuicklook>> {
    std::fs::create_dir_all(out_dir).at(IoOp::CreateDir, out_dir)?;
    let palette = group_palette();
    let overlays = [
        Overlay {
            labels: lungs,
            palette: &LUNG_PALETTE,
            opacity: 1.0,
            outline_only: true,
        },
        Overlay {
            labels: groups,
            palette: &palette,
            opacity: 0.9,
            outline_only: false,
        },
    ];
    let legend = legend();
    let centroids = lung_centroids_lps_mm(lungs);
    let both = centroids.both.unwrap_or_else(|| grid_centre_lps_mm(ct));
    let (sagittal_x, sagittal_through) = match centroids.larger {
        Some((label, c)) => (c[0], format!("the {} lung's centroid", lung_name(label))),
        None => (both[0], "the scan's centre (no lung found)".to_string()),
    };
    let pixel_mm = overview_pixel_mm(&ct.geometry);
    let mut written = Vec::with_capacity(3);
    for plane in SlicePlane::ALL {
        let (position_lps_mm, through) = match plane {
            SlicePlane::Sagittal => (sagittal_x, sagittal_through.clone()),
            _ => (
                both[plane.normal_axis()],
                "both lungs' centroid".to_string(),
            ),
        };
        let title = format!(
            "Ingest: lung outlines and constraint groups, {} slice",
            plane.name()
        );
        let axis = ['x', 'y', 'z'][plane.normal_axis()];
        let subtitle = format!(
            "{axis} = {position_lps_mm:.1} mm (LPS), through {through}; lung window W 1500 L -600"
        );
        let look = render_labelled_slice(&LabelledSliceInput {
            ct,
            overlays: &overlays,
            plane,
            position_lps_mm,
            pixel_mm,
            title: &title,
            subtitle: &subtitle,
            legend: &legend,
        })?;
        let path = out_dir.join(format!("quicklook-{}.png", plane.name()));
        let text = [
            ("Title", title.clone()),
            ("Description", subtitle.clone()),
            ("lungmotion:plane", plane.name().to_string()),
            ("lungmotion:position_lps_mm", format!("{position_lps_mm}")),
            ("lungmotion:through", through.clone()),
            ("lungmotion:slice_px", rect_text(&look.panel)),
            ("lungmotion:legend_px", rect_text(&look.legend)),
        ];
        write_png_with_text(&path, &look.image, &text)?;
        written.push(IngestQuicklook {
            path,
            plane,
            position_lps_mm,
            through,
        });
    }
    Ok(written)
}

/// The legend of the ingest quick looks: the two lung outlines, then each group with what its
/// nodes do.
pub fn legend() -> Vec<LegendEntry> {
    let lungs = LUNG_PALETTE.iter().map(|&(label, colour)| LegendEntry {
        label: format!("{} lung (outline)", lung_name(label)),
        colour,
        outline: true,
    });
    let groups = group_palette().into_iter().filter_map(|(code, colour)| {
        let g = ConstraintGroup::from_code(code)?;
        let role = match g.boundary_condition() {
            BoundaryCondition::Fixed => "fixed",
            BoundaryCondition::SlidingOnWall => "slides on wall",
            BoundaryCondition::FollowsDiaphragm => "follows diaphragm",
        };
        Some(LegendEntry {
            label: format!("{} ({role})", g.name()),
            colour,
            outline: false,
        })
    });
    lungs.chain(groups).collect()
}

/// `left,top,width,height` in pixels.
fn rect_text(r: &PixelRect) -> String {
    format!("{},{},{},{}", r.left, r.top, r.width, r.height)
}

fn lung_name(label: u8) -> &'static str {
    match label {
        1 => "right",
        2 => "left",
        _ => "other",
    }
}

/// Centroids of the lung labels, LPS mm.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct LungCentroids {
    /// Of every lung voxel; `None` without any.
    pub both: Option<[f64; 3]>,
    /// The label with the most voxels (1 right, 2 left; the right on a tie) and its centroid.
    pub larger: Option<(u8, [f64; 3])>,
}

/// The lungs' centroid and the larger lung's (labels 1 and 2; other labels count as lung
/// for the first only).
pub fn lung_centroids_lps_mm(lungs: &Volume<u8>) -> LungCentroids {
    let g = &lungs.geometry;
    let [nx, ny, _] = g.dims;
    // Index sums per label: 0 every lung voxel, 1 right, 2 left.
    let mut sum = [Vector3::<f64>::zeros(); 3];
    let mut count = [0usize; 3];
    for (idx, &v) in lungs.as_slice().iter().enumerate() {
        if v == 0 {
            continue;
        }
        let ijk = Vector3::new(
            (idx % nx) as f64,
            ((idx / nx) % ny) as f64,
            (idx / (nx * ny)) as f64,
        );
        sum[0] += ijk;
        count[0] += 1;
        if matches!(v, 1 | 2) {
            sum[v as usize] += ijk;
            count[v as usize] += 1;
        }
    }
    let centroid =
        |l: usize| (count[l] > 0).then(|| g.voxel_to_lps_mm(sum[l] / count[l] as f64).into());
    let larger = if count[2] > count[1] { 2 } else { 1 };
    LungCentroids {
        both: centroid(0),
        larger: centroid(larger).map(|c| (larger as u8, c)),
    }
}

fn grid_centre_lps_mm(ct: &Volume<f32>) -> [f64; 3] {
    let g = &ct.geometry;
    g.voxel_to_lps_mm(Vector3::from(g.dims.map(|d| (d as f64 - 1.0) / 2.0)))
        .into()
}
