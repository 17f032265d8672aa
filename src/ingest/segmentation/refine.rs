//! Closing, axial hole filling and largest-component selection of each lung.

use ndarray::Zip;
use rayon::prelude::*;

use super::components::label_components;
use super::crop::Crop;
use super::morphology::{fill_holes_2d, grid_view, squared_distance_mm2};
use super::settings::SegmentationSettings;
use crate::volume::VolumeGeometry;

/// Closing, axial hole filling and largest-component selection of one lung, in place;
/// returns the number and voxels of fragments dropped.
pub(super) fn refine_lung(
    labels: &mut [u8],
    body: &[u8],
    label: u8,
    g: &VolumeGeometry,
    axial: usize,
    settings: &SegmentationSettings,
) -> (usize, usize) {
    let dims = g.dims;
    let Some((min, max)) = bounding_box(labels, dims, label) else {
        return (0, 0);
    };
    let r = settings.closing_radius_mm;
    // The closing acts within axial slices: no margin needed across them.
    let margin = [0, 1, 2].map(|a| {
        if a == axial {
            1
        } else {
            (r / g.spacing_mm[a]).ceil() as usize + 1
        }
    });
    let crop = Crop::around(min, max, margin, dims);
    let cd = crop.dims;
    let lung = crop.extract(labels, dims, |v| (v == label) as u8);
    let blocked = crop.extract_pair(labels, body, dims, |v, inside_body| {
        (v != 0 && v != label || inside_body == 0) as u8
    });
    let mut closed = if r > 0.0 {
        let r2 = (r * r) as f32;
        let to_lung = squared_distance_mm2(&lung, cd, g.spacing_mm, true, Some(axial));
        let dilated: Vec<u8> = to_lung.par_iter().map(|&d| (d <= r2) as u8).collect();
        drop(to_lung);
        let to_outside = squared_distance_mm2(&dilated, cd, g.spacing_mm, false, Some(axial));
        to_outside.par_iter().map(|&d| (d > r2) as u8).collect()
    } else {
        lung.clone()
    };
    let clean = |closed: &mut [u8]| {
        closed
            .par_iter_mut()
            .zip(&blocked)
            .zip(&lung)
            .for_each(|((c, &b), &l)| *c = l | (*c & (b == 0) as u8));
    };
    clean(&mut closed);
    fill_holes_2d(&mut closed, cd, axial);
    clean(&mut closed);
    let lab = label_components(&closed, cd);
    let removed: usize = lab.components.iter().skip(1).map(|c| c.voxels).sum();
    let removed_count = lab.components.len().saturating_sub(1);
    let kept = lab.paint(|c| (c == 0) as u8);
    Zip::from(crop.view_mut(labels, dims))
        .and(grid_view(&kept, cd))
        .par_for_each(|s, &keep| {
            if keep != 0 {
                *s = label;
            } else if *s == label {
                *s = 0;
            }
        });
    (removed_count, removed)
}

/// Smallest and largest voxel indices carrying `label`, if any.
fn bounding_box(labels: &[u8], dims: [usize; 3], label: u8) -> Option<([usize; 3], [usize; 3])> {
    let [nx, ny, _] = dims;
    labels
        .par_chunks(nx * ny)
        .enumerate()
        .filter_map(|(k, slice)| {
            let mut b: Option<([usize; 3], [usize; 3])> = None;
            for (j, row) in slice.chunks(nx).enumerate() {
                let first = row.iter().position(|&v| v == label);
                let last = row.iter().rposition(|&v| v == label);
                if let (Some(i0), Some(i1)) = (first, last) {
                    b = Some(match b {
                        None => ([i0, j, k], [i1, j, k]),
                        Some((lo, hi)) => (
                            [lo[0].min(i0), lo[1].min(j), k],
                            [hi[0].max(i1), hi[1].max(j), k],
                        ),
                    });
                }
            }
            b
        })
        .reduce_with(|a, b| {
            (
                [0, 1, 2].map(|x| a.0[x].min(b.0[x])),
                [0, 1, 2].map(|x| a.1[x].max(b.1[x])),
            )
        })
}
