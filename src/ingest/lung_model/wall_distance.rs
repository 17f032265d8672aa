//! The wall's signed distance on its sample grid: both exact Euclidean distance transforms
//! (outside samples to the nearest inside one, inside samples to the nearest outside one) in
//! one array and one sweep of the volume.
//!
//! Felzenszwalb & Huttenlocher's separable transform, reordered so the volume is read as
//! whole planes: the first pass, along k, is the binary one (distance to the nearest sample of
//! the other class in the same k-line: two streaming sweeps of whole planes, forward and
//! back); then each k-plane is finished by one core while it is in cache (the lower envelope
//! of parabolas along j, then along i, which writes the signed value). Each sample holds the
//! value of its own class's transform: for a sample of class X, the sources are the samples
//! of class X with their partial squared distance and the samples of the other class at 0,
//! and of those only the ones next to a class-X sample of the line can be nearest (any other
//! lies behind one of them). So a line costs one envelope over its samples instead of two.
//!
//! With unit spacing every squared distance is an integer below 2^24, exact in `f32`, and the
//! minimum over sources is the same whatever the pass order: the values are bit-identical to
//! two separate whole-volume transforms (a unit test compares them).

use ndarray::parallel::prelude::*;
use ndarray::Axis;
use rayon::prelude::*;

use crate::ingest::segmentation::morphology::grid_view_mut;
use crate::ingest::Cancel;
use crate::Result;

/// Distance cap for a sample with no sample of the other class anywhere, so the field stays
/// finite (squared samples).
const FAR: f32 = 1e12;

/// Rows of a k-plane per task of the k sweeps: 8 rows of a few hundred samples stream whole
/// cache lines, and a plane gives tens of tasks.
const SWEEP_ROWS: usize = 8;

/// Columns of a plane gathered per strip for the pass along j (16 f32 fill a cache line).
const STRIP_COLUMNS: usize = 16;

/// Signed Euclidean distance in samples to the boundary of `inside` (non-zero = inside):
/// outside samples `√d² − 0.5` to the nearest inside sample, inside samples `−(√d² − 0.5)`
/// to the nearest outside one, half a sample putting the surface between samples; `d²`
/// capped at 10^12 where the other class is absent.
pub(super) fn signed_distance(
    inside: &[u8],
    dims: [usize; 3],
    cancel: Cancel<'_>,
) -> Result<Vec<f32>> {
    const DURING: &str = "the wall's distance transform";
    let mut values = distance_along_k_to_other_class(inside, dims);
    cancel.check(DURING)?;
    let [nx, ny, _] = dims;
    let plane = nx * ny;
    values
        .par_chunks_mut(plane)
        .zip(inside.par_chunks(plane))
        .for_each_init(PlaneScratch::default, |scratch, (values, classes)| {
            if !cancel.raised() {
                finish_plane(values, classes, nx, scratch);
            }
        });
    cancel.check(DURING)?;
    Ok(values)
}

/// Per sample, the distance in samples along k to the nearest sample of the other class in
/// its k-line (∞ when there is none): a forward and a backward sweep over whole planes, each
/// task holding a band of rows of every plane.
fn distance_along_k_to_other_class(inside: &[u8], dims: [usize; 3]) -> Vec<f32> {
    let [nx, ny, nz] = dims;
    let plane = nx * ny;
    let mut values = vec![0f32; inside.len()];
    grid_view_mut(&mut values, dims)
        .axis_chunks_iter_mut(Axis(1), SWEEP_ROWS)
        .into_par_iter()
        .enumerate()
        .for_each_init(Vec::new, |run, (c, mut band)| {
            let offset = c * SWEEP_ROWS * nx;
            let width = band.len_of(Axis(1)) * nx;
            let classes = |k: usize| &inside[k * plane + offset..][..width];
            // `run[x]`: distance from the current plane back to the last change of class.
            run.clear();
            run.resize(width, f32::INFINITY);
            for k in 0..nz {
                let mut out = band.index_axis_mut(Axis(0), k);
                let out = out
                    .as_slice_mut()
                    .expect("a band of whole rows is contiguous");
                if k > 0 {
                    step_run(run, classes(k), classes(k - 1));
                }
                out.copy_from_slice(run);
            }
            run.fill(f32::INFINITY);
            for k in (0..nz).rev() {
                let mut out = band.index_axis_mut(Axis(0), k);
                let out = out
                    .as_slice_mut()
                    .expect("a band of whole rows is contiguous");
                if k + 1 < nz {
                    step_run(run, classes(k), classes(k + 1));
                }
                out.iter_mut()
                    .zip(run.iter())
                    .for_each(|(o, &r)| *o = o.min(r));
            }
        });
    values
}

/// One plane further along a sweep: 1 where the class changed from the previous plane, one
/// more than before where it did not (∞ stays ∞).
fn step_run(run: &mut [f32], here: &[u8], before: &[u8]) {
    run.iter_mut()
        .zip(here.iter().zip(before))
        .for_each(|(r, (&a, &b))| {
            *r = if (a != 0) != (b != 0) { 1.0 } else { *r + 1.0 };
        });
}

/// Per-core scratch of [`finish_plane`].
#[derive(Default)]
struct PlaneScratch {
    strip: Vec<f32>,
    strip_classes: Vec<u8>,
    envelope: Envelope,
}

/// The passes along j and i of one k-plane (`values` from the k sweep, distances along k),
/// ending in the signed distance.
fn finish_plane(values: &mut [f32], classes: &[u8], nx: usize, s: &mut PlaneScratch) {
    let ny = values.len() / nx;
    values.iter_mut().for_each(|v| *v *= *v);
    // Along j: strips of columns gathered contiguous, transformed, put back.
    s.strip.resize(STRIP_COLUMNS * ny, 0.0);
    s.strip_classes.resize(STRIP_COLUMNS * ny, 0);
    for c0 in (0..nx).step_by(STRIP_COLUMNS) {
        let w = STRIP_COLUMNS.min(nx - c0);
        for j in 0..ny {
            let row = j * nx + c0;
            for c in 0..w {
                s.strip[c * ny + j] = values[row + c];
                s.strip_classes[c * ny + j] = classes[row + c];
            }
        }
        for c in 0..w {
            let line = &mut s.strip[c * ny..(c + 1) * ny];
            let line_classes = &s.strip_classes[c * ny..(c + 1) * ny];
            s.envelope.transform(line, line_classes);
        }
        for j in 0..ny {
            let row = j * nx + c0;
            for c in 0..w {
                values[row + c] = s.strip[c * ny + j];
            }
        }
    }
    // Along i: rows in place, then the signed distance.
    for (row, row_classes) in values.chunks_mut(nx).zip(classes.chunks(nx)) {
        s.envelope.transform(row, row_classes);
        row.iter_mut().zip(row_classes).for_each(|(v, &class)| {
            let d = v.min(FAR).sqrt() - 0.5;
            *v = if class != 0 { -d } else { d };
        });
    }
}

/// Scratch of the two-class 1-D transform: the lower envelope's parabolas (position, value)
/// and the positions where each starts.
#[derive(Default)]
struct Envelope {
    vertices: Vec<(f32, f32)>,
    bounds: Vec<f32>,
}

impl Envelope {
    /// One exact 1-D pass of both transforms along a line, in place: each sample of class X
    /// gets `min_p (f(p) + (q − p)²)` over the samples p of class X (their `line` value, ∞ =
    /// no source) and over the samples of the other class (0). Of the latter only those next
    /// to a class-X sample can be nearest, so only they enter the envelope.
    fn transform(&mut self, line: &mut [f32], classes: &[u8]) {
        let first = classes[0] != 0;
        let uniform = classes.iter().all(|&c| (c != 0) == first);
        if uniform {
            // No other class on the line: a plain envelope of the values, unless none is a
            // source.
            if line.iter().any(|v| v.is_finite()) {
                self.one_class(line, classes, first);
            }
            return;
        }
        self.one_class(line, classes, false);
        self.one_class(line, classes, true);
    }

    /// The pass for the samples of class `inside` only (the others are left as they are).
    fn one_class(&mut self, line: &mut [f32], classes: &[u8], inside: bool) {
        let n = line.len();
        let is_class = |q: usize| (classes[q] != 0) == inside;
        self.vertices.clear();
        self.bounds.clear();
        for (q, &value) in line.iter().enumerate() {
            let fq = if is_class(q) {
                value
            } else if (q > 0 && is_class(q - 1)) || (q + 1 < n && is_class(q + 1)) {
                0.0
            } else {
                continue;
            };
            if fq.is_finite() {
                self.push(q as f32, fq);
            }
        }
        if self.vertices.is_empty() {
            (0..n)
                .filter(|&q| is_class(q))
                .for_each(|q| line[q] = f32::INFINITY);
            return;
        }
        let mut v = 0;
        for (q, out) in line.iter_mut().enumerate() {
            if !is_class(q) {
                continue;
            }
            let x = q as f32;
            while v + 1 < self.vertices.len() && self.bounds[v + 1] < x {
                v += 1;
            }
            let (p, fp) = self.vertices[v];
            let d = x - p;
            *out = d * d + fp;
        }
    }

    /// Adds the parabola of source `pq` (value `fq`) at the right end of the envelope,
    /// dropping those it hides.
    fn push(&mut self, pq: f32, fq: f32) {
        while let Some(&(pp, fp)) = self.vertices.last() {
            let cross = ((fq + pq * pq) - (fp + pp * pp)) / (2.0 * (pq - pp));
            if cross <= self.bounds[self.bounds.len() - 1] {
                self.vertices.pop();
                self.bounds.pop();
            } else {
                self.vertices.push((pq, fq));
                self.bounds.push(cross);
                return;
            }
        }
        self.vertices.push((pq, fq));
        self.bounds.push(f32::NEG_INFINITY);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ingest::segmentation::morphology::squared_distance_mm2;

    /// The signed distance from two whole-volume transforms, as the wall was built before.
    fn two_transforms(inside: &[u8], dims: [usize; 3]) -> Vec<f32> {
        let to_inside = squared_distance_mm2(inside, dims, [1.0; 3], true, None);
        let to_outside = squared_distance_mm2(inside, dims, [1.0; 3], false, None);
        inside
            .iter()
            .zip(to_inside.iter().zip(&to_outside))
            .map(|(&i, (&din, &dout))| {
                if i != 0 {
                    -(dout.min(FAR).sqrt() - 0.5)
                } else {
                    din.min(FAR).sqrt() - 0.5
                }
            })
            .collect()
    }

    /// A pseudo-random mask: an ellipsoid with holes and specks, optionally cut by the grid's
    /// border.
    fn speckled(dims: [usize; 3], centre: [i64; 3], r2_max: i64, seed: usize) -> Vec<u8> {
        let n: usize = dims.iter().product();
        (0..n)
            .map(|x| {
                let (i, j, k) = (x % dims[0], x / dims[0] % dims[1], x / (dims[0] * dims[1]));
                let r2 = (i as i64 - centre[0]).pow(2)
                    + (j as i64 - centre[1]).pow(2) * 2
                    + (k as i64 - centre[2]).pow(2);
                let hash = (x + seed).wrapping_mul(2_654_435_761) % 29;
                u8::from((r2 <= r2_max && hash != 0) || hash == 7)
            })
            .collect()
    }

    #[test]
    fn one_sweep_equals_two_whole_volume_transforms_bit_for_bit() {
        let cases = [
            ([17, 13, 11], [8, 6, 5], 30),
            ([9, 20, 7], [4, 10, 3], 30),
            ([40, 37, 23], [20, 18, 11], 150),
            // Cut by the border on every side, and a large one beyond 16 columns.
            ([33, 19, 21], [0, 0, 20], 400),
            ([5, 3, 2], [2, 1, 1], 2),
        ];
        for (seed, (dims, centre, r2)) in cases.into_iter().enumerate() {
            let inside = speckled(dims, centre, r2, seed);
            let got = signed_distance(&inside, dims, Cancel::NEVER).unwrap();
            let want = two_transforms(&inside, dims);
            let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
            assert_eq!(bits(&got), bits(&want), "{dims:?}");
        }
    }

    #[test]
    fn without_one_class_the_distance_is_capped() {
        let empty = signed_distance(&[0u8; 8], [2, 2, 2], Cancel::NEVER).unwrap();
        assert!(empty.iter().all(|&d| d == 1e6 - 0.5), "{empty:?}");
        let full = signed_distance(&[1u8; 12], [3, 2, 2], Cancel::NEVER).unwrap();
        assert!(full.iter().all(|&d| d == -(1e6 - 0.5)), "{full:?}");
    }

    #[test]
    fn a_raised_cancel_stops_the_transform() {
        use std::sync::atomic::AtomicBool;
        let flag = AtomicBool::new(true);
        let inside = speckled([9, 8, 7], [4, 4, 3], 10, 0);
        assert!(signed_distance(&inside, [9, 8, 7], Cancel::new(Some(&flag))).is_err());
    }
}
