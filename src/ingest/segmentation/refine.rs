//! Closing, axial hole filling and largest-component selection of each lung.

use ndarray::Zip;
use rayon::prelude::*;

use super::components::label_components;
use super::crop::Crop;
use super::morphology::{
    fill_holes_2d, fill_holes_slice, grid_view, squared_distance_mm2, squared_distance_slice_mm2,
    SliceScratch,
};
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
    let closed = if axial == 2 {
        close_and_fill_axial_slices(&lung, &blocked, cd, g.spacing_mm, r)
    } else {
        close_and_fill(&lung, &blocked, cd, g.spacing_mm, r, axial)
    };
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

/// Where a voxel may be added to the lung: the lung itself, or a voxel the closing or the
/// hole filling took in that is neither the other lung nor outside the body.
fn keep_allowed(closed: &mut [u8], blocked: &[u8], lung: &[u8]) {
    closed
        .iter_mut()
        .zip(blocked)
        .zip(lung)
        .for_each(|((c, &b), &l)| *c = l | (*c & (b == 0) as u8));
}

/// Closing by a disc of `r` mm within each slice across `axial`, then hole filling in those
/// slices, each followed by [`keep_allowed`]: the whole-volume form, for grids whose axial
/// slices are not contiguous.
fn close_and_fill(
    lung: &[u8],
    blocked: &[u8],
    cd: [usize; 3],
    spacing_mm: [f64; 3],
    r: f64,
    axial: usize,
) -> Vec<u8> {
    let mut closed = if r > 0.0 {
        let r2 = (r * r) as f32;
        let to_lung = squared_distance_mm2(lung, cd, spacing_mm, true, Some(axial));
        let dilated: Vec<u8> = to_lung.par_iter().map(|&d| (d <= r2) as u8).collect();
        drop(to_lung);
        let to_outside = squared_distance_mm2(&dilated, cd, spacing_mm, false, Some(axial));
        to_outside.par_iter().map(|&d| (d > r2) as u8).collect()
    } else {
        lung.to_vec()
    };
    let clean = |closed: &mut [u8]| {
        closed
            .par_chunks_mut(cd[0] * cd[1])
            .zip(blocked.par_chunks(cd[0] * cd[1]))
            .zip(lung.par_chunks(cd[0] * cd[1]))
            .for_each(|((c, b), l)| keep_allowed(c, b, l));
    };
    clean(&mut closed);
    fill_holes_2d(&mut closed, cd, axial);
    clean(&mut closed);
    closed
}

/// [`close_and_fill`] when the axial slices are contiguous (axial = k): every step of a slice
/// runs on one core while the slice is in cache, with the same arithmetic, so the same bits.
fn close_and_fill_axial_slices(
    lung: &[u8],
    blocked: &[u8],
    cd: [usize; 3],
    spacing_mm: [f64; 3],
    r: f64,
) -> Vec<u8> {
    let [nu, nv, _] = cd;
    let plane = nu * nv;
    let (su, sv) = (spacing_mm[0] as f32, spacing_mm[1] as f32);
    let r2 = (r * r) as f32;
    let mut closed = vec![0u8; lung.len()];
    closed
        .par_chunks_mut(plane)
        .zip(lung.par_chunks(plane))
        .zip(blocked.par_chunks(plane))
        .for_each_init(
            || (vec![0f32; plane], SliceScratch::default(), Vec::new()),
            |(dist, scratch, stack), ((c, l), b)| {
                // A slice without lung stays empty: the closing and the filling add nothing.
                if !l.contains(&1) {
                    return;
                }
                if r > 0.0 {
                    squared_distance_slice_mm2(l, [nu, nv], [su, sv], true, dist, scratch);
                    c.iter_mut()
                        .zip(dist.iter())
                        .for_each(|(c, &d)| *c = (d <= r2) as u8);
                    squared_distance_slice_mm2(c, [nu, nv], [su, sv], false, dist, scratch);
                    c.iter_mut()
                        .zip(dist.iter())
                        .for_each(|(c, &d)| *c = (d > r2) as u8);
                } else {
                    c.copy_from_slice(l);
                }
                keep_allowed(c, b, l);
                fill_holes_slice(c, nu, nv, stack);
                keep_allowed(c, b, l);
            },
        );
    closed
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn slice_by_slice_closing_equals_the_whole_volume_one_bit_for_bit() {
        // A speckled blob with notches and holes, and a blocked band through it.
        let cd = [23, 19, 7];
        let n: usize = cd.iter().product();
        let ijk = |x: usize| (x % cd[0], x / cd[0] % cd[1], x / (cd[0] * cd[1]));
        let lung: Vec<u8> = (0..n)
            .map(|x| {
                let (i, j, k) = ijk(x);
                let r2 = (i as i64 - 11).pow(2) + (j as i64 - 9).pow(2) * 2;
                let hash = x.wrapping_mul(2_654_435_761) % 17;
                u8::from(k != 3 && r2 <= 60 && hash > 2 && (i + j) % 7 != 0)
            })
            .collect();
        let blocked: Vec<u8> = (0..n).map(|x| u8::from(ijk(x).0 == 4)).collect();
        for r in [0.0, 1.5, 3.0] {
            let spacing = [0.7, 0.9, 2.0];
            let whole = close_and_fill(&lung, &blocked, cd, spacing, r, 2);
            let sliced = close_and_fill_axial_slices(&lung, &blocked, cd, spacing, r);
            assert_eq!(sliced, whole, "r = {r}");
            let added = whole.iter().zip(&lung).filter(|(&w, &l)| w > l).count();
            assert!(r == 0.0 || added > 0, "r = {r}: the closing added nothing");
        }
    }
}
