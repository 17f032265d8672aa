//! Morphology on voxel masks in physical units: exact Euclidean distance transforms in
//! millimetres (so erosion, dilation and closing use balls of a radius in mm whatever the
//! spacing) and slice-wise hole filling.
//!
//! The distance transform is Felzenszwalb & Huttenlocher's separable lower envelope of
//! parabolas: one exact 1-D pass per axis, each line independent, so every pass runs on all
//! cores. Lines along j and k are reached through ndarray views of the mask, one plane per
//! task, without copying the volume.

use ndarray::parallel::prelude::*;
use ndarray::{ArrayView3, ArrayViewMut2, ArrayViewMut3, Axis};
use rayon::prelude::*;

use crate::ingest::Cancel;
use crate::Result;

/// The voxel axis closest to the patient's z (cranio-caudal) axis, and whether LPS z grows
/// with the index along it (superior = higher index).
pub(crate) fn axial_axis(direction_lps: &[[f64; 3]; 3]) -> (usize, bool) {
    let axis = (0..3)
        .max_by(|&a, &b| {
            direction_lps[a][2]
                .abs()
                .total_cmp(&direction_lps[b][2].abs())
        })
        .unwrap_or(2);
    (axis, direction_lps[axis][2] >= 0.0)
}

/// `data` (i fastest) as an array indexed `[k, j, i]`.
pub(crate) fn grid_view_mut<T>(data: &mut [T], dims: [usize; 3]) -> ArrayViewMut3<'_, T> {
    let [nx, ny, nz] = dims;
    ArrayViewMut3::from_shape((nz, ny, nx), data).expect("a mask's length matches its grid")
}

/// `data` (i fastest) as an array indexed `[k, j, i]`.
pub(crate) fn grid_view<T>(data: &[T], dims: [usize; 3]) -> ArrayView3<'_, T> {
    let [nx, ny, nz] = dims;
    ArrayView3::from_shape((nz, ny, nx), data).expect("a mask's length matches its grid")
}

/// The array axis of voxel axis `axis` (i, j, k → 2, 1, 0).
pub(crate) fn array_axis(axis: usize) -> Axis {
    Axis(2 - axis)
}

/// Applies `f(line, scratch)` to every line of `data` along `axis`, in parallel; the line is a
/// contiguous copy written back afterwards unless `f` returns false for the whole strip of
/// lines (nothing changed); rows along i are passed in place.
pub(crate) fn for_each_line<T, S, I, F>(
    data: &mut [T],
    dims: [usize; 3],
    axis: usize,
    init: I,
    f: F,
) where
    T: Copy + Send + Sync + Default,
    S: Send,
    I: Fn() -> S + Sync + Send,
    F: Fn(&mut [T], &mut S) -> bool + Sync + Send,
{
    if axis == 0 {
        data.par_chunks_mut(dims[0]).for_each_init(&init, |s, row| {
            f(row, s);
        });
        return;
    }
    // Each line along j lies in one k-plane and each line along k in one j-plane: planes are
    // disjoint, so they go to the cores whole; within a plane the lines are the columns of
    // rows along i.
    let plane_axis = if axis == 1 { Axis(0) } else { Axis(1) };
    grid_view_mut(data, dims)
        .axis_iter_mut(plane_axis)
        .into_par_iter()
        .for_each_init(
            || (Vec::new(), init()),
            |(strip, s), mut plane| for_each_column(&mut plane, strip, s, &f),
        );
}

/// Lines gathered per strip in [`for_each_column`]: 16 values of a row fill a cache line of
/// f32, so each row is read and written whole once per strip instead of once per column.
const STRIP_COLUMNS: usize = 16;

/// Applies `f(column, scratch)` to every column of `plane` (rows contiguous), in strips of
/// [`STRIP_COLUMNS`] columns transposed into `strip` and back.
fn for_each_column<T, S, F>(plane: &mut ArrayViewMut2<'_, T>, strip: &mut Vec<T>, s: &mut S, f: &F)
where
    T: Copy + Default,
    F: Fn(&mut [T], &mut S) -> bool,
{
    let (n, width) = plane.dim();
    strip.resize(STRIP_COLUMNS * n, T::default());
    for c0 in (0..width).step_by(STRIP_COLUMNS) {
        let w = STRIP_COLUMNS.min(width - c0);
        for (q, row) in plane.rows().into_iter().enumerate() {
            let row = row.to_slice().expect("rows along i are contiguous");
            for (c, &v) in row[c0..c0 + w].iter().enumerate() {
                strip[c * n + q] = v;
            }
        }
        let mut changed = false;
        for column in strip.chunks_mut(n).take(w) {
            changed |= f(column, s);
        }
        if changed {
            for (q, row) in plane.rows_mut().into_iter().enumerate() {
                let row = row.into_slice().expect("rows along i are contiguous");
                for (c, v) in row[c0..c0 + w].iter_mut().enumerate() {
                    *v = strip[c * n + q];
                }
            }
        }
    }
}

/// Scratch of the 1-D distance transform.
#[derive(Default)]
struct EnvelopeScratch {
    input: Vec<f32>,
    vertices: Vec<usize>,
    bounds: Vec<f32>,
}

/// Exact 1-D squared distance transform in place: `line[q] ← min_p (line[p] + ((q − p)·s)²)`,
/// infinite entries being no source; returns false when the line is left as it was (no
/// source at all, or sources only), so a strided line need not be written back.
fn envelope_line(line: &mut [f32], spacing: f32, s: &mut EnvelopeScratch) -> bool {
    // A line with no source stays infinite and one of sources only stays zero: the bulk of
    // the lines far from (or deep inside) a mask, skipped without building an envelope.
    if line.iter().all(|v| !v.is_finite()) || line.iter().all(|&v| v == 0.0) {
        return false;
    }
    s.input.clear();
    s.input.extend_from_slice(line);
    s.vertices.clear();
    s.bounds.clear();
    let f = &s.input;
    for (q, &fq) in f.iter().enumerate() {
        if !fq.is_finite() {
            continue;
        }
        let pq = q as f32 * spacing;
        loop {
            let Some(&p) = s.vertices.last() else {
                s.vertices.push(q);
                s.bounds.push(f32::NEG_INFINITY);
                break;
            };
            let pp = p as f32 * spacing;
            let cross = ((fq + pq * pq) - (f[p] + pp * pp)) / (2.0 * (pq - pp));
            if cross <= s.bounds[s.bounds.len() - 1] {
                s.vertices.pop();
                s.bounds.pop();
            } else {
                s.vertices.push(q);
                s.bounds.push(cross);
                break;
            }
        }
    }
    if s.vertices.is_empty() {
        line.fill(f32::INFINITY);
        return true;
    }
    let mut v = 0;
    for (q, out) in line.iter_mut().enumerate() {
        let x = q as f32 * spacing;
        while v + 1 < s.vertices.len() && s.bounds[v + 1] < x {
            v += 1;
        }
        let p = s.vertices[v];
        let d = x - p as f32 * spacing;
        *out = d * d + f[p];
    }
    true
}

/// Squared Euclidean distance in mm² from each voxel to the nearest feature voxel, a feature
/// being a voxel whose `(mask != 0) == feature_is_set`; infinite when there is none. With
/// `in_slices_across = Some(axis)` distances are measured within each slice across `axis`
/// (2-D transform, one pass fewer).
pub(crate) fn squared_distance_mm2(
    mask: &[u8],
    dims: [usize; 3],
    spacing_mm: [f64; 3],
    feature_is_set: bool,
    in_slices_across: Option<usize>,
) -> Vec<f32> {
    squared_distance_mm2_cancellable(
        mask,
        dims,
        spacing_mm,
        feature_is_set,
        in_slices_across,
        Cancel::NEVER,
    )
    .expect("a transform nothing cancels ends")
}

/// [`squared_distance_mm2`], stopped with [`crate::Error::Cancelled`] once `cancel` is
/// raised: each row and line looks at it first (and is skipped once it is up), so a large
/// transform stops within one line's work per thread.
pub(crate) fn squared_distance_mm2_cancellable(
    mask: &[u8],
    dims: [usize; 3],
    spacing_mm: [f64; 3],
    feature_is_set: bool,
    in_slices_across: Option<usize>,
    cancel: Cancel<'_>,
) -> Result<Vec<f32>> {
    const DURING: &str = "a distance transform";
    let mut d = vec![0f32; mask.len()];
    let [nx, ny, _] = dims;
    if in_slices_across == Some(2) {
        // Axial storage: each slice is contiguous and transformed whole by one core, in cache.
        let (su, sv) = (spacing_mm[0] as f32, spacing_mm[1] as f32);
        d.par_chunks_mut(nx * ny)
            .zip(mask.par_chunks(nx * ny))
            .for_each_init(SliceScratch::default, |scratch, (out, m)| {
                if !cancel.raised() {
                    squared_distance_slice_mm2(m, [nx, ny], [su, sv], feature_is_set, out, scratch)
                }
            });
        cancel.check(DURING)?;
        return Ok(d);
    }
    d.par_iter_mut()
        .zip(mask)
        .for_each(|(d, &m)| *d = feature_seed(m, feature_is_set));
    let sx = spacing_mm[0] as f32;
    let wanted = |axis: usize| in_slices_across != Some(axis);
    if wanted(0) {
        d.par_chunks_mut(nx).for_each(|row| {
            if !cancel.raised() {
                row_distance_to_zeros(row, sx)
            }
        });
    }
    cancel.check(DURING)?;
    // Without the i pass the values are still squared distances: 0 or ∞.
    for (axis, &spacing) in spacing_mm.iter().enumerate().skip(1) {
        if dims[axis] > 1 && wanted(axis) {
            // A cancelled line is left as it is: the transform is thrown away.
            for_each_line(&mut d, dims, axis, EnvelopeScratch::default, |line, s| {
                !cancel.raised() && envelope_line(line, spacing as f32, s)
            });
            cancel.check(DURING)?;
        }
    }
    Ok(d)
}

/// 0 at a feature voxel, ∞ elsewhere: the input of the transform.
fn feature_seed(m: u8, feature_is_set: bool) -> f32 {
    if (m != 0) == feature_is_set {
        0.0
    } else {
        f32::INFINITY
    }
}

/// The pass along i, where the input is binary (0 or ∞): two sweeps give the squared distance
/// to the nearest zero of the row, cheaper than the parabola envelope.
fn row_distance_to_zeros(row: &mut [f32], sx: f32) {
    let mut last = None;
    for (i, v) in row.iter_mut().enumerate() {
        if *v == 0.0 {
            last = Some(i);
        } else if let Some(l) = last {
            *v = (i - l) as f32 * sx;
        }
    }
    last = None;
    for (i, v) in row.iter_mut().enumerate().rev() {
        if *v == 0.0 {
            last = Some(i);
        } else {
            let back = last.map_or(f32::INFINITY, |l| (l - i) as f32 * sx);
            let d = v.min(back);
            *v = d * d;
        }
    }
}

/// Per-core scratch of [`squared_distance_slice_mm2`].
#[derive(Default)]
pub(crate) struct SliceScratch {
    strip: Vec<f32>,
    envelope: EnvelopeScratch,
}

/// [`squared_distance_mm2`] within one contiguous slice of `nu × nv` voxels (u fastest) of
/// spacing `su × sv` mm, into `out`: the same passes and arithmetic, so the same bits.
pub(crate) fn squared_distance_slice_mm2(
    mask: &[u8],
    [nu, nv]: [usize; 2],
    [su, sv]: [f32; 2],
    feature_is_set: bool,
    out: &mut [f32],
    scratch: &mut SliceScratch,
) {
    out.iter_mut()
        .zip(mask)
        .for_each(|(d, &m)| *d = feature_seed(m, feature_is_set));
    out.chunks_mut(nu)
        .for_each(|row| row_distance_to_zeros(row, su));
    if nv < 2 {
        return;
    }
    let mut plane = ArrayViewMut2::from_shape((nv, nu), out).expect("a slice is nu × nv");
    for_each_column(
        &mut plane,
        &mut scratch.strip,
        &mut scratch.envelope,
        &|c, e| envelope_line(c, sv, e),
    );
}

/// Fills, in every slice across `axis`, the background regions not connected (4-neighbour)
/// to the slice border: the holes of a mask as a radiologist sees them on axial images.
pub(crate) fn fill_holes_2d(mask: &mut [u8], dims: [usize; 3], axis: usize) {
    let [nx, ny, nz] = dims;
    if axis == 2 {
        // Axial storage: each slice is contiguous and filled in place.
        mask.par_chunks_mut(nx * ny)
            .for_each_init(Vec::new, |stack, s| fill_holes_slice(s, nx, ny, stack));
        return;
    }
    // A slice across j is (k, i), across i is (k, j): copied out, filled, copied back.
    let nu = if axis == 1 { nx } else { ny };
    grid_view_mut(mask, dims)
        .axis_iter_mut(array_axis(axis))
        .into_par_iter()
        .for_each_init(
            || (Vec::with_capacity(nu * nz), Vec::new()),
            |(buf, stack), mut slice| {
                buf.clear();
                buf.extend(slice.iter());
                fill_holes_slice(buf, nu, nz, stack);
                slice.iter_mut().zip(buf.iter()).for_each(|(v, &b)| *v = b);
            },
        );
}

/// Hole filling of one 2-D slice (`nu` fastest): flood the background from the border, then
/// everything not reached is inside.
pub(crate) fn fill_holes_slice(s: &mut [u8], nu: usize, nv: usize, stack: &mut Vec<u32>) {
    const OUTSIDE: u8 = 2;
    stack.clear();
    let seed = |s: &mut [u8], idx: usize, stack: &mut Vec<u32>| {
        if s[idx] == 0 {
            s[idx] = OUTSIDE;
            stack.push(idx as u32);
        }
    };
    for u in 0..nu {
        seed(s, u, stack);
        seed(s, u + nu * (nv - 1), stack);
    }
    for v in 0..nv {
        seed(s, nu * v, stack);
        seed(s, nu - 1 + nu * v, stack);
    }
    while let Some(idx) = stack.pop() {
        let idx = idx as usize;
        let (u, v) = (idx % nu, idx / nu);
        if u > 0 {
            seed(s, idx - 1, stack);
        }
        if u + 1 < nu {
            seed(s, idx + 1, stack);
        }
        if v > 0 {
            seed(s, idx - nu, stack);
        }
        if v + 1 < nv {
            seed(s, idx + nu, stack);
        }
    }
    for x in s.iter_mut() {
        *x = (*x != OUTSIDE) as u8;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Brute-force squared distance to the nearest feature voxel.
    fn brute(mask: &[u8], dims: [usize; 3], sp: [f64; 3]) -> Vec<f32> {
        let [nx, ny, nz] = dims;
        let mut out = vec![f32::INFINITY; mask.len()];
        for k in 0..nz {
            for j in 0..ny {
                for i in 0..nx {
                    let mut best = f64::INFINITY;
                    for (f, &m) in mask.iter().enumerate() {
                        if m != 0 {
                            let (fi, fj, fk) = (f % nx, (f / nx) % ny, f / (nx * ny));
                            let d = ((fi as f64 - i as f64) * sp[0]).powi(2)
                                + ((fj as f64 - j as f64) * sp[1]).powi(2)
                                + ((fk as f64 - k as f64) * sp[2]).powi(2);
                            best = best.min(d);
                        }
                    }
                    out[i + nx * (j + ny * k)] = best as f32;
                }
            }
        }
        out
    }

    #[test]
    fn distance_transform_matches_brute_force_on_an_anisotropic_grid() {
        let dims = [9, 7, 6];
        let sp = [0.7, 1.3, 2.5];
        let n = dims.iter().product();
        // A pseudo-random sparse set of features.
        let mask: Vec<u8> = (0..n)
            .map(|x: usize| (x.wrapping_mul(2_654_435_761) % 97 < 4) as u8)
            .collect();
        assert!(mask.iter().any(|&m| m != 0));
        let fast = squared_distance_mm2(&mask, dims, sp, true, None);
        let slow = brute(&mask, dims, sp);
        for (a, b) in fast.iter().zip(&slow) {
            assert!((a - b).abs() <= 1e-3 * b.max(1.0), "{a} vs {b}");
        }
        // In-slice distances: brute force slice by slice along each axis.
        for axis in 0..3 {
            let fast = squared_distance_mm2(&mask, dims, sp, true, Some(axis));
            for s in 0..dims[axis] {
                let mut sub_dims = dims;
                sub_dims[axis] = 1;
                let mut sub = Vec::new();
                let mut where_ = Vec::new();
                for (idx, &m) in mask.iter().enumerate() {
                    let ijk = [idx % 9, (idx / 9) % 7, idx / 63];
                    if ijk[axis] == s {
                        sub.push(m);
                        where_.push(idx);
                    }
                }
                let slow = brute(&sub, sub_dims, sp);
                for (b, &idx) in slow.iter().zip(&where_) {
                    let a = fast[idx];
                    assert!(
                        (a == *b) || (a - b).abs() <= 1e-3 * b.max(1.0),
                        "axis {axis}: {a} vs {b}"
                    );
                }
            }
        }
        let none = squared_distance_mm2(&vec![0u8; n], dims, sp, true, None);
        assert!(none.iter().all(|d| d.is_infinite()));
    }

    #[test]
    fn unit_spacing_distances_to_set_and_to_unset_voxels_equal_brute_force_exactly() {
        // The lung model's wall measures in samples (unit spacing) on both sides of the
        // surface: the squared distances are whole numbers, so they must match bit for bit.
        let dims = [11, 8, 9];
        let n = dims.iter().product();
        // A ball with pseudo-random holes, so both sides have near and far voxels.
        let mask: Vec<u8> = (0..n)
            .map(|x: usize| {
                let (i, j, k) = (x % 11, x / 11 % 8, x / 88);
                let r2 = (i as i64 - 5).pow(2) + (j as i64 - 4).pow(2) + (k as i64 - 4).pow(2);
                u8::from(r2 <= 12 && !x.wrapping_mul(2_654_435_761).is_multiple_of(13))
            })
            .collect();
        assert!(mask.contains(&0) && mask.contains(&1));
        let unit = [1.0; 3];
        let to_set = squared_distance_mm2(&mask, dims, unit, true, None);
        assert_eq!(to_set, brute(&mask, dims, unit));
        let inverted: Vec<u8> = mask.iter().map(|&m| u8::from(m == 0)).collect();
        let to_unset = squared_distance_mm2(&mask, dims, unit, false, None);
        assert_eq!(to_unset, brute(&inverted, dims, unit));
    }

    #[test]
    fn each_line_along_every_axis_is_visited_once_in_strips_of_columns() {
        // 37 columns: two whole strips and a partial one.
        let dims = [37, 5, 4];
        let n: usize = dims.iter().product();
        let data: Vec<u32> = (0..n as u32).collect();
        for axis in 0..3 {
            let mut reversed = data.clone();
            for_each_line(
                &mut reversed,
                dims,
                axis,
                || (),
                |line, _| {
                    line.reverse();
                    true
                },
            );
            for (idx, &v) in reversed.iter().enumerate() {
                let mut ijk = [idx % 37, idx / 37 % 5, idx / 185];
                ijk[axis] = dims[axis] - 1 - ijk[axis];
                assert_eq!(
                    v as usize,
                    ijk[0] + 37 * (ijk[1] + 5 * ijk[2]),
                    "axis {axis}"
                );
            }
            // A pass that reports no change writes nothing back.
            let mut kept = data.clone();
            for_each_line(
                &mut kept,
                dims,
                axis,
                || (),
                |line, _| {
                    line.fill(0);
                    false
                },
            );
            assert!(axis == 0 || kept == data, "axis {axis}");
        }
    }

    #[test]
    fn holes_are_filled_in_each_slice_along_every_axis() {
        // A hollow 5×5 square ring in each plane across `axis`, open nowhere.
        for axis in 0..3 {
            let dims = [6, 6, 6];
            let mut mask = vec![0u8; 216];
            let mut hole = 0;
            for a in 0..6 {
                for b in 0..5 {
                    for c in 0..5 {
                        let ring = b == 0 || b == 4 || c == 0 || c == 4;
                        let mut ijk = [0; 3];
                        let others: Vec<usize> = (0..3).filter(|&x| x != axis).collect();
                        ijk[axis] = a;
                        ijk[others[0]] = b;
                        ijk[others[1]] = c;
                        let idx = ijk[0] + 6 * (ijk[1] + 6 * ijk[2]);
                        if ring {
                            mask[idx] = 1;
                        } else if a == 0 {
                            hole = idx;
                        }
                    }
                }
            }
            let before = mask.iter().filter(|&&m| m != 0).count();
            fill_holes_2d(&mut mask, dims, axis);
            let after = mask.iter().filter(|&&m| m != 0).count();
            assert_eq!(after - before, 6 * 9, "axis {axis}");
            assert_eq!(mask[hole], 1);
            // The background touching the border stays background.
            assert_eq!(mask[5 + 6 * (5 + 6 * 5)], 0);
        }
    }

    #[test]
    fn axial_axis_is_found_on_reordered_and_flipped_grids() {
        let id = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
        assert_eq!(axial_axis(&id), (2, true));
        let coronal = [[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]];
        assert_eq!(axial_axis(&coronal), (1, false));
    }
}
