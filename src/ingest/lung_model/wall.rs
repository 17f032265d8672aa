//! The thoracic-cavity wall the lungs slide on: the signed Euclidean distance to the CT lung
//! surface on an LPS-aligned grid finer than the lattice, smoothed by a Gaussian of one CT
//! voxel (see the module doc, "Wall").

use std::sync::Arc;

use nalgebra::{Matrix3, Vector3};
use rayon::prelude::*;

use super::lattice::{nearest_index, CellLattice};
use super::report::StepClock;
use super::wall_distance::signed_distance;

use crate::ingest::Cancel;
use crate::model::SignedDistanceField;
use crate::volume::Volume;
use crate::{Error, Result};

/// Elements of margin between the lattice box and the wall field's border.
const WALL_MARGIN_CELLS: i64 = 2;

/// The wall field and what building it measured.
pub(super) struct WallBuild {
    /// Smoothed distance to the CT lung surface (shared with the constraints that slide on it).
    pub(super) wall: Arc<SignedDistanceField>,
    /// Lung voxels of the CT mask touching the other lung.
    pub(super) contact_voxels: usize,
}

/// The wall's sample grid: LPS-aligned, a whole number of samples per element edge.
struct WallGrid {
    /// LPS millimetres of sample (0, 0, 0).
    origin_mm: Vector3<f64>,
    /// Sample spacing in millimetres, the same along x, y, z.
    spacing_mm: f64,
    /// Samples along x, y, z.
    dims: [usize; 3],
}

impl WallGrid {
    /// The grid refining `lattice`, with `WALL_MARGIN_CELLS` elements of margin.
    fn refining(lattice: &CellLattice, finest_ct_mm: f64) -> Self {
        let h_mm = lattice.h_mm;
        // Samples per element edge: about the CT resolution, at least 2, at least 1 mm apart.
        let per_cell = ((h_mm / finest_ct_mm.max(1.0)).ceil() as usize).clamp(2, 8);
        let margin = WALL_MARGIN_CELLS;
        WallGrid {
            origin_mm: lattice.point_mm([-margin; 3]),
            spacing_mm: h_mm / per_cell as f64,
            dims: std::array::from_fn(|a| (lattice.cells[a] + 2 * margin as usize) * per_cell + 1),
        }
    }
}

/// A wall built earlier from the same lung mask and element size (the upload's stored
/// ingest, see [`crate::ingest::stored`]), with what the report says of it.
#[derive(Debug, Clone)]
pub struct PrebuiltWall {
    /// The smoothed distance field, metres.
    pub field: SignedDistanceField,
    /// Lung voxels of the CT mask touching the other lung.
    pub contact_voxels: usize,
}

/// Builds the wall over `lattice` from the CT lung mask, or takes `prebuilt` when it lies on
/// the very grid this build would sample (else the build is refused: a stale or foreign
/// field is never used).
pub(super) fn build_wall(
    lungs: &Volume<u8>,
    lattice: &CellLattice,
    steps: &mut StepClock,
    prebuilt: Option<PrebuiltWall>,
) -> Result<WallBuild> {
    let g = &lungs.geometry;
    let finest_ct_mm = g.spacing_mm.iter().cloned().fold(f64::INFINITY, f64::min);
    let coarsest_ct_mm = g.spacing_mm.iter().cloned().fold(0.0, f64::max);
    let grid = WallGrid::refining(lattice, finest_ct_mm);
    let s_mm = grid.spacing_mm;
    let s_m = s_mm * 1e-3;
    if let Some(prebuilt) = prebuilt {
        let f = &prebuilt.field;
        let origin_m = grid.origin_mm * 1e-3;
        if f.samples != grid.dims || f.spacing_m != [s_m; 3] || f.origin_m != origin_m {
            return Err(Error::Ingest(format!(
                "the stored wall field ({:?} samples of {:?} m from {:?} m) is not the one \
                 this lung mask gives ({:?} samples of {s_m} m from {:?} m)",
                f.samples,
                f.spacing_m,
                f.origin_m.as_slice(),
                grid.dims,
                origin_m.as_slice()
            )));
        }
        steps.mark("wall: stored field")?;
        return Ok(WallBuild {
            wall: Arc::new(prebuilt.field),
            contact_voxels: prebuilt.contact_voxels,
        });
    }
    let contact = contact_voxels(lungs);
    let inside = sample_inside(lungs, &contact, &grid, steps.cancel);
    steps.mark("wall: samples inside the lungs")?;

    // One CT voxel of Gaussian smoothing rounds the voxel staircase into continuous normals.
    let ct_sigma = (coarsest_ct_mm / s_mm).clamp(0.5, 4.0);
    let mut signed = signed_distance(&inside, grid.dims, steps.cancel)?;
    drop(inside);
    steps.mark("wall: signed distance")?;
    let weights = gaussian_weights(ct_sigma);
    blur_rows_and_columns(&mut signed, grid.dims, &weights);
    steps.mark("wall: smoothing")?;
    // The blur across slices writes the field's samples (in units of one sample spacing,
    // s_m metres each): one pass and one volume-sized buffer fewer than blurring in place.
    let anatomy_samples = blur_slices(&signed, grid.dims, &weights);
    drop(signed);
    let anatomy = SignedDistanceField::scaled(
        grid.origin_mm * 1e-3,
        [s_m; 3],
        grid.dims,
        anatomy_samples,
        s_m,
    )?;
    steps.mark("wall: field in metres")?;

    Ok(WallBuild {
        wall: Arc::new(anatomy),
        contact_voxels: contact.len(),
    })
}

/// 1 at each wall sample whose nearest CT voxel is inside: a lung voxel not touching the
/// other lung (so touching lungs stay two surfaces); 0 elsewhere.
/// Once `cancel` is raised the remaining slabs are left empty (the caller's next step
/// check stops the build).
fn sample_inside(
    lungs: &Volume<u8>,
    contact: &[usize],
    grid: &WallGrid,
    cancel: Cancel<'_>,
) -> Vec<u8> {
    sample_inside_with(lungs, contact, grid, cancel, true)
}

/// [`sample_inside`], with `per_axis` = false forcing the per-sample mapping of an oblique CT
/// (to test that both give the same samples).
fn sample_inside_with(
    lungs: &Volume<u8>,
    contact: &[usize],
    grid: &WallGrid,
    cancel: Cancel<'_>,
    per_axis: bool,
) -> Vec<u8> {
    let g = &lungs.geometry;
    let [nx, ny, _] = grid.dims;
    let n_samples: usize = grid.dims.iter().product();
    let (origin_mm, s_mm) = (grid.origin_mm, grid.spacing_mm);
    let a = Matrix3::from_diagonal(&Vector3::from(g.spacing_mm.map(|s| 1.0 / s)))
        * g.direction().transpose();
    let b = -(a * g.origin());
    let [cnx, cny, cnz] = g.dims;
    // The CT's lung voxels minus the contact voxels, so a sample reads one byte.
    let mut lung_ct: Vec<u8> = lungs
        .as_slice()
        .par_iter()
        .map(|&l| (l != 0) as u8)
        .collect();
    for &c in contact {
        lung_ct[c] = 0;
    }
    let mut inside = vec![0u8; n_samples];
    let offsets = per_axis.then(|| axis_aligned_offsets(&a, &b, grid, g.dims));
    if let Some(offsets) = offsets.flatten() {
        // The usual CT grid is LPS-aligned (up to flips and axis order): each CT index then
        // follows from one sample index, the same product and rounding as below, per axis.
        let [oi, oj, ok] = &offsets;
        inside
            .par_chunks_mut(nx * ny)
            .zip(ok.par_iter())
            .for_each(|(slab, &ck)| {
                let Some(ck) = ck else { return };
                if cancel.raised() {
                    return;
                }
                for (row, &cj) in slab.chunks_mut(nx).zip(oj) {
                    let Some(cj) = cj else { continue };
                    for (s, &ci) in row.iter_mut().zip(oi) {
                        if let Some(ci) = ci {
                            *s = lung_ct[ci + cj + ck];
                        }
                    }
                }
            });
        return inside;
    }
    inside
        .par_chunks_mut(nx * ny)
        .enumerate()
        .for_each(|(k, slab)| {
            if cancel.raised() {
                return;
            }
            for j in 0..ny {
                for i in 0..nx {
                    let p = origin_mm + Vector3::new(i as f64, j as f64, k as f64) * s_mm;
                    let v = a * p + b;
                    let (Some(ci), Some(cj), Some(ck)) = (
                        nearest_index(v.x, cnx),
                        nearest_index(v.y, cny),
                        nearest_index(v.z, cnz),
                    ) else {
                        continue;
                    };
                    let idx = ci + cnx * (cj + cny * ck);
                    slab[i + nx * j] = lung_ct[idx];
                }
            }
        });
    inside
}

/// For a CT whose voxel axes are the grid's (each row of the LPS → voxel map `a` has one
/// non-zero entry), the linear CT offset that each sample index along grid axis x, y, z
/// contributes (`None`: outside the CT); `None` for an oblique CT.
#[allow(clippy::type_complexity)]
fn axis_aligned_offsets(
    a: &Matrix3<f64>,
    b: &Vector3<f64>,
    grid: &WallGrid,
    ct_dims: [usize; 3],
) -> Option<[Vec<Option<usize>>; 3]> {
    let strides = [1, ct_dims[0], ct_dims[0] * ct_dims[1]];
    let mut offsets: [Vec<Option<usize>>; 3] = Default::default();
    let mut seen = [false; 3];
    for r in 0..3 {
        let nonzero: Vec<usize> = (0..3).filter(|&c| a[(r, c)] != 0.0).collect();
        let [c] = nonzero[..] else { return None };
        if std::mem::replace(&mut seen[c], true) {
            return None;
        }
        // Exactly `(a * p + b)[r]`: the other two terms of the row are exact zeros.
        offsets[c] = (0..grid.dims[c])
            .map(|q| {
                let p = grid.origin_mm[c] + q as f64 * grid.spacing_mm;
                nearest_index(a[(r, c)] * p + b[r], ct_dims[r]).map(|v| v * strides[r])
            })
            .collect();
    }
    Some(offsets)
}

/// Linear indices, ascending, of the lung voxels of the CT mask with a 26-neighbour in the
/// other lung. Per axial slice, the labels of the slices above and below are gathered into
/// one bit map and dilated in-plane, so each voxel is tested once instead of 26 times.
fn contact_voxels(lungs: &Volume<u8>) -> Vec<usize> {
    let [nx, ny, nz] = lungs.geometry.dims;
    let plane = nx * ny;
    let labels = lungs.as_slice();
    // Bit 0: the right lung (label 1) is near; bit 1: the left lung (label 2) is near.
    let bit = |label: u8| match label {
        1 => 1u8,
        2 => 2,
        _ => 0,
    };
    let per_slice: Vec<Vec<usize>> = (0..nz)
        .into_par_iter()
        .map_init(
            || (vec![0u8; plane], vec![0u8; plane]),
            |(near, rows), k| {
                near.fill(0);
                for kk in k.saturating_sub(1)..(k + 2).min(nz) {
                    let slice = &labels[kk * plane..(kk + 1) * plane];
                    near.iter_mut().zip(slice).for_each(|(n, &l)| *n |= bit(l));
                }
                dilate_rows(near, rows, nx);
                dilate_columns(rows, near, nx);
                let slice = &labels[k * plane..(k + 1) * plane];
                slice
                    .iter()
                    .zip(near.iter())
                    .enumerate()
                    .filter(|&(_, (&l, &n))| matches!(l, 1 | 2) && n & bit(3 - l) != 0)
                    .map(|(idx, _)| idx + k * plane)
                    .collect()
            },
        )
        .collect();
    per_slice.concat()
}

/// `out[i] = in[i − 1] | in[i] | in[i + 1]` within each row of `nx`.
fn dilate_rows(input: &[u8], out: &mut [u8], nx: usize) {
    for (row_in, row_out) in input.chunks(nx).zip(out.chunks_mut(nx)) {
        for (i, o) in row_out.iter_mut().enumerate() {
            *o = row_in[i.saturating_sub(1)] | row_in[i] | row_in[(i + 1).min(nx - 1)];
        }
    }
}

/// `out[j] = in[j − 1] | in[j] | in[j + 1]` along the columns of a plane of rows of `nx`.
fn dilate_columns(input: &[u8], out: &mut [u8], nx: usize) {
    let ny = input.len() / nx;
    for j in 0..ny {
        let (lo, hi) = (j.saturating_sub(1), (j + 1).min(ny - 1));
        let row_out = &mut out[j * nx..(j + 1) * nx];
        row_out.copy_from_slice(&input[j * nx..(j + 1) * nx]);
        for r in [lo, hi] {
            row_out
                .iter_mut()
                .zip(&input[r * nx..(r + 1) * nx])
                .for_each(|(o, &v)| *o |= v);
        }
    }
}

/// Normalised taps `w_0 … w_radius` of a Gaussian of `sigma` samples (radius 2.5 σ).
fn gaussian_weights(sigma: f64) -> Vec<f32> {
    let radius = (2.5 * sigma).ceil() as usize;
    let weights: Vec<f32> = (0..=radius)
        .map(|r| (-((r * r) as f64) / (2.0 * sigma * sigma)).exp() as f32)
        .collect();
    let total: f32 = weights[0] + 2.0 * weights[1..].iter().sum::<f32>();
    weights.iter().map(|w| w / total).collect()
}

/// The first two passes of the separable Gaussian blur (along i, then j), edges clamped, in
/// place: one k-slab per task, its columns blurred a whole row at a time (contiguous and
/// vectorisable, unlike gathering each strided column).
fn blur_rows_and_columns(values: &mut [f32], dims: [usize; 3], weights: &[f32]) {
    let [nx, ny, _] = dims;
    values.par_chunks_mut(nx * ny).for_each_init(
        || (Vec::new(), Vec::new()),
        |(line_input, slab_input), slab| {
            for row in slab.chunks_mut(nx) {
                blur_line(row, line_input, weights);
            }
            slab_input.clear();
            slab_input.extend_from_slice(slab);
            blur_planes(slab, slab_input, nx, weights);
        },
    );
}

/// The last pass of the blur (along k), edges clamped, from `values` into a new field: slab
/// by slab, each slab summed from whole neighbouring slabs.
fn blur_slices(values: &[f32], dims: [usize; 3], weights: &[f32]) -> Vec<f32> {
    let [nx, ny, nz] = dims;
    let plane = nx * ny;
    let mut out = vec![0f32; values.len()];
    out.par_chunks_mut(plane)
        .enumerate()
        .for_each(|(k, out_slab)| {
            blur_one_plane(
                out_slab,
                |q| &values[q * plane..(q + 1) * plane],
                k,
                nz,
                weights,
            );
        });
    out
}

/// Blurs the `n = input.len() / len` consecutive planes of `len` values of `input` across
/// planes into `out` (same layout): the column pass of one k-slab, rows being the planes.
fn blur_planes(out: &mut [f32], input: &[f32], len: usize, weights: &[f32]) {
    let n = input.len() / len;
    for (q, out_plane) in out.chunks_mut(len).enumerate() {
        blur_one_plane(out_plane, |p| &input[p * len..(p + 1) * len], q, n, weights);
    }
}

/// Plane `q` of `n` blurred across planes: `out = w0·in(q) + Σ_r w_r·(in(q − r) + in(q + r))`,
/// plane indices clamped, summed in order of r: for every value the same operations in the
/// same order as [`blur_line`] on its line, so the same bits.
fn blur_one_plane<'a, P>(out: &mut [f32], plane: P, q: usize, n: usize, weights: &[f32])
where
    P: Fn(usize) -> &'a [f32],
{
    out.iter_mut()
        .zip(plane(q))
        .for_each(|(o, &x)| *o = weights[0] * x);
    for (r, &w) in weights.iter().enumerate().skip(1) {
        let (below, above) = (plane(q.saturating_sub(r)), plane((q + r).min(n - 1)));
        out.iter_mut()
            .zip(below.iter().zip(above))
            .for_each(|(o, (&a, &b))| *o += w * (a + b));
    }
}

/// One line of the blur: `out[q] = w0·in[q] + Σ_r w_r·(in[q − r] + in[q + r])`, indices
/// clamped to the line, summed in order of r. Tap by tap over the whole line, so the
/// unclamped middle is a plain vectorisable loop; each sample sees the same operations in the
/// same order as a sample-by-sample sum.
fn blur_line(line: &mut [f32], input: &mut Vec<f32>, weights: &[f32]) {
    input.clear();
    input.extend_from_slice(line);
    let n = input.len();
    line.iter_mut()
        .zip(input.iter())
        .for_each(|(o, &x)| *o = weights[0] * x);
    for (r, &w) in weights.iter().enumerate().skip(1) {
        // q < r reaches below 0, q ≥ n − r beyond n − 1: those are clamped.
        let middle_start = r.min(n);
        let middle_end = n.saturating_sub(r).max(middle_start);
        for q in (0..middle_start).chain(middle_end..n) {
            let lo = q.saturating_sub(r);
            let hi = (q + r).min(n - 1);
            line[q] += w * (input[lo] + input[hi]);
        }
        let below = &input[middle_start - r.min(middle_start)..];
        let above = &input[(middle_start + r).min(n)..];
        line[middle_start..middle_end]
            .iter_mut()
            .zip(below.iter().zip(above))
            .for_each(|(o, (&a, &b))| *o += w * (a + b));
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::volume::VolumeGeometry;

    #[test]
    fn tap_by_tap_blur_equals_the_sample_by_sample_sum_bit_for_bit() {
        let weights = [0.4f32, 0.2, 0.07, 0.03];
        for n in [1usize, 2, 3, 5, 6, 7, 8, 13, 40] {
            let data: Vec<f32> = (0..n).map(|q| ((q * 37 % 11) as f32 - 4.3) * 1.7).collect();
            let mut line = data.clone();
            blur_line(&mut line, &mut Vec::new(), &weights);
            let reference: Vec<f32> = (0..n)
                .map(|q| {
                    let mut acc = weights[0] * data[q];
                    for (r, &w) in weights.iter().enumerate().skip(1) {
                        acc += w * (data[q.saturating_sub(r)] + data[(q + r).min(n - 1)]);
                    }
                    acc
                })
                .collect();
            assert_eq!(line, reference, "n = {n}");
        }
    }

    #[test]
    fn slab_wise_blur_equals_the_line_by_line_blur_bit_for_bit() {
        use crate::ingest::segmentation::morphology::for_each_line;
        // Radius 4 against axes of 3 to 9 samples: clamping at both ends, and in the middle.
        let weights = gaussian_weights(1.5);
        assert_eq!(weights.len(), 5);
        for dims in [[9, 7, 6], [3, 11, 4]] {
            let n: usize = dims.iter().product();
            let data: Vec<f32> = (0..n)
                .map(|q| ((q * 37 % 23) as f32 - 9.7) * 0.31)
                .collect();
            let mut reference = data.clone();
            for axis in 0..3 {
                for_each_line(&mut reference, dims, axis, Vec::new, |line, input| {
                    blur_line(line, input, &weights);
                    true
                });
            }
            let mut values = data;
            blur_rows_and_columns(&mut values, dims, &weights);
            let slabs = blur_slices(&values, dims, &weights);
            assert_eq!(slabs, reference, "{dims:?}");
        }
    }

    #[test]
    fn per_axis_sampling_equals_the_per_sample_mapping_on_aligned_flipped_and_permuted_cts() {
        let dims = [23, 19, 17];
        let n: usize = dims.iter().product();
        // Two speckled lungs, apart except where the speckles bridge them.
        let labels: Vec<u8> = (0..n)
            .map(|x| {
                let (i, j, k) = (x % 23, x / 23 % 19, x / (23 * 19));
                let r2 = (j as i64 - 9).pow(2) + (k as i64 - 8).pow(2);
                let hash = x.wrapping_mul(2_654_435_761) % 13;
                match i {
                    _ if hash == 5 => 2,
                    2..=9 if r2 < 40 && hash != 0 => 1,
                    13..=20 if r2 < 30 && hash != 0 => 2,
                    _ => 0,
                }
            })
            .collect();
        let directions = [
            [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
            [[-1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, -1.0]],
            [[0.0, 1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]],
        ];
        for direction_lps in directions {
            let mut g = VolumeGeometry::axis_aligned(dims, [0.7, 1.3, 2.1], [-5.3, 2.9, 11.7]);
            g.direction_lps = direction_lps;
            let lungs = Volume::from_data(g, labels.clone()).unwrap();
            let lattice = CellLattice::covering(&lungs, 3.0).unwrap();
            let grid = WallGrid::refining(&lattice, 0.7);
            let contact = contact_voxels(&lungs);
            let fast = sample_inside_with(&lungs, &contact, &grid, Cancel::NEVER, true);
            let slow = sample_inside_with(&lungs, &contact, &grid, Cancel::NEVER, false);
            assert!(fast.contains(&1) && fast.contains(&0));
            assert_eq!(fast, slow, "{direction_lps:?}");
        }
    }

    #[test]
    fn contact_voxels_are_the_lung_voxels_with_a_26_neighbour_in_the_other_lung() {
        let dims = [7, 6, 5];
        let g = VolumeGeometry::axis_aligned(dims, [1.0; 3], [0.0; 3]);
        let n: usize = dims.iter().product();
        let labels: Vec<u8> = (0..n)
            .map(|x| ((x * 7919 + x / 3 * 31) % 5).min(3) as u8 % 3)
            .collect();
        let lungs = Volume::from_data(g, labels.clone()).unwrap();
        let brute: Vec<usize> = (0..n)
            .filter(|&x| {
                let l = labels[x];
                let (i, j, k) = (x % 7, x / 7 % 6, x / 42);
                l != 0
                    && (0..27).any(|o| {
                        let q = [i + o % 3, j + o / 3 % 3, k + o / 9];
                        (0..3).all(|a| q[a] >= 1 && q[a] <= dims[a])
                            && labels[q[0] - 1 + 7 * (q[1] - 1 + 6 * (q[2] - 1))] == 3 - l
                    })
            })
            .collect();
        assert!(!brute.is_empty() && brute.len() < n / 2, "{}", brute.len());
        assert_eq!(contact_voxels(&lungs), brute);
    }
}
