//! Closing, axial hole filling and largest-component selection of each lung.

use ndarray::parallel::prelude::*;
use ndarray::Zip;
use rayon::prelude::*;

use super::components::label_components;
use super::crop::Crop;
use super::disc::{close_by_disc, Disc, DiscScratch};
use super::morphology::{array_axis, fill_holes_slice, grid_view, grid_view_mut};
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
/// slices are not contiguous (each slice is gathered, worked whole, and scattered back).
fn close_and_fill(
    lung: &[u8],
    blocked: &[u8],
    cd: [usize; 3],
    spacing_mm: [f64; 3],
    r: f64,
    axial: usize,
) -> Vec<u8> {
    // Within a slice across `axial` the lower of the two other voxel axes runs fastest.
    let [u, v] = match axial {
        0 => [1, 2],
        1 => [0, 2],
        _ => [0, 1],
    };
    let dims = [cd[u], cd[v]];
    let disc = Disc::new(r, [spacing_mm[u], spacing_mm[v]], cd[v]);
    let (lung, blocked) = (grid_view(lung, cd), grid_view(blocked, cd));
    let across = array_axis(axial);
    let mut closed = vec![0u8; cd.iter().product()];
    grid_view_mut(&mut closed, cd)
        .axis_iter_mut(across)
        .into_par_iter()
        .enumerate()
        .for_each_init(SliceWork::default, |work, (s, mut out)| {
            work.lung.clear();
            work.lung.extend(lung.index_axis(across, s).iter());
            work.blocked.clear();
            work.blocked.extend(blocked.index_axis(across, s).iter());
            work.closed.resize(dims[0] * dims[1], 0);
            work.close_and_fill(dims, &disc);
            out.iter_mut().zip(&work.closed).for_each(|(o, &c)| *o = c);
        });
    closed
}

/// [`close_and_fill`] when the axial slices are contiguous (axial = k): every step of a slice
/// runs on one core while the slice is in cache. Each slice is worked on the rectangle of its
/// lung voxels grown by the closing's reach and one voxel more: beyond it nothing is taken
/// in, and its border is background, so the closing and the hole filling inside it are those
/// of the whole slice.
fn close_and_fill_axial_slices(
    lung: &[u8],
    blocked: &[u8],
    cd: [usize; 3],
    spacing_mm: [f64; 3],
    r: f64,
) -> Vec<u8> {
    let [nu, nv, _] = cd;
    let plane = nu * nv;
    let disc = Disc::new(r, [spacing_mm[0], spacing_mm[1]], nv);
    let margin = [0, 1].map(|a| (r / spacing_mm[a]).ceil() as usize + 1);
    let mut closed = vec![0u8; lung.len()];
    closed
        .par_chunks_mut(plane)
        .zip(lung.par_chunks(plane))
        .zip(blocked.par_chunks(plane))
        .for_each_init(SliceWork::default, |work, ((c, l), b)| {
            // A slice without lung stays empty: the closing and the filling add nothing.
            let Some(rect) = SliceRect::around_lung(l, nu, margin) else {
                return;
            };
            work.load(&rect, l, b, nu);
            work.close_and_fill([rect.nu, rect.nv], &disc);
            rect.store(&work.closed, c, nu);
        });
    closed
}

/// A rectangle of an axial slice: first column and row, width and height.
struct SliceRect {
    u0: usize,
    v0: usize,
    nu: usize,
    nv: usize,
}

impl SliceRect {
    /// The box of the lung voxels of slice `l` (rows of `nu`) grown by `margin`, clamped to
    /// the slice; `None` without a lung voxel.
    fn around_lung(l: &[u8], nu: usize, margin: [usize; 2]) -> Option<Self> {
        let rows = l.len() / nu;
        let mut bounds: Option<[usize; 4]> = None;
        for (v, row) in l.chunks(nu).enumerate() {
            let (Some(a), Some(z)) = (
                row.iter().position(|&x| x != 0),
                row.iter().rposition(|&x| x != 0),
            ) else {
                continue;
            };
            bounds = Some(match bounds {
                None => [a, z, v, v],
                Some([a0, z0, v0, _]) => [a0.min(a), z0.max(z), v0, v],
            });
        }
        let [a, z, v_first, v_last] = bounds?;
        let (u0, v0) = (
            a.saturating_sub(margin[0]),
            v_first.saturating_sub(margin[1]),
        );
        Some(SliceRect {
            u0,
            v0,
            nu: (z + margin[0]).min(nu - 1) - u0 + 1,
            nv: (v_last + margin[1]).min(rows - 1) - v0 + 1,
        })
    }

    /// The rectangle's rows of a slice of rows of `width`.
    fn rows<'a, T>(&'a self, slice: &'a [T], width: usize) -> impl Iterator<Item = &'a [T]> {
        slice[self.v0 * width..]
            .chunks(width)
            .take(self.nv)
            .map(|row| &row[self.u0..self.u0 + self.nu])
    }

    /// Writes `rect` (the rectangle's values, rows of `self.nu`) into `slice` (rows of `width`).
    fn store(&self, rect: &[u8], slice: &mut [u8], width: usize) {
        for (row, src) in slice[self.v0 * width..]
            .chunks_mut(width)
            .zip(rect.chunks(self.nu))
        {
            row[self.u0..self.u0 + self.nu].copy_from_slice(src);
        }
    }
}

/// Per-core buffers of the slice-wise closing: one slice's (or rectangle's) lung, blocked,
/// dilated and closed voxels, and the disc's and flood's scratch.
#[derive(Default)]
struct SliceWork {
    lung: Vec<u8>,
    blocked: Vec<u8>,
    dilated: Vec<u8>,
    closed: Vec<u8>,
    scratch: DiscScratch,
    stack: Vec<u32>,
}

impl SliceWork {
    /// Copies the rectangle of the slice's lung and blocked voxels.
    fn load(&mut self, rect: &SliceRect, l: &[u8], b: &[u8], width: usize) {
        self.lung.clear();
        rect.rows(l, width)
            .for_each(|r| self.lung.extend_from_slice(r));
        self.blocked.clear();
        rect.rows(b, width)
            .for_each(|r| self.blocked.extend_from_slice(r));
        self.closed.resize(rect.nu * rect.nv, 0);
    }

    /// Closing by `disc`, hole filling, each followed by [`keep_allowed`], on the loaded
    /// slice or rectangle of `nu × nv` voxels.
    fn close_and_fill(&mut self, [nu, nv]: [usize; 2], disc: &Disc) {
        let (c, l, b) = (&mut self.closed, &self.lung, &self.blocked);
        close_by_disc(l, [nu, nv], disc, c, &mut self.dilated, &mut self.scratch);
        keep_allowed(c, b, l);
        fill_holes_slice(c, nu, nv, &mut self.stack);
        keep_allowed(c, b, l);
    }
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

    #[test]
    fn slices_across_i_or_j_are_closed_as_the_same_slices_stored_axially() {
        // The lung of the rectangle test's kind, stored with its axial axis first or second:
        // gathered slice by slice it must close exactly as when stored with k axial.
        let axial_dims = [29, 21, 5];
        let n: usize = axial_dims.iter().product();
        let lung: Vec<u8> = (0..n)
            .map(|x| {
                let (u, v, s) = (x % 29, x / 29 % 21, x / (29 * 21));
                let r2 = (u as i64 - 14).pow(2) + (v as i64 - 10).pow(2);
                let hash = x.wrapping_mul(2_654_435_761) % 13;
                u8::from((10..=60).contains(&r2) && hash > 2 && s != 3)
            })
            .collect();
        let blocked: Vec<u8> = (0..n).map(|x| u8::from(x % 29 == 20)).collect();
        let spacing = [0.7, 0.9, 2.0];
        let expected = close_and_fill_axial_slices(&lung, &blocked, axial_dims, spacing, 2.5);
        assert!(expected.iter().zip(&lung).any(|(&c, &l)| c > l));
        for axial in [0, 1] {
            // (u, v, s) of the axial storage become voxel axes: s → `axial`, u and v the others
            // in order.
            let [a_u, a_v] = if axial == 0 { [1, 2] } else { [0, 2] };
            let mut dims = [0; 3];
            let mut sp = [0.0; 3];
            for (from, to) in [(0, a_u), (1, a_v), (2, axial)] {
                dims[to] = axial_dims[from];
                sp[to] = spacing[from];
            }
            let index = |x: usize| {
                let uvs = [x % 29, x / 29 % 21, x / (29 * 21)];
                let mut ijk = [0; 3];
                for (from, to) in [(0, a_u), (1, a_v), (2, axial)] {
                    ijk[to] = uvs[from];
                }
                ijk[0] + dims[0] * (ijk[1] + dims[1] * ijk[2])
            };
            let mut l = vec![0u8; n];
            let mut b = vec![0u8; n];
            for x in 0..n {
                l[index(x)] = lung[x];
                b[index(x)] = blocked[x];
            }
            let closed = close_and_fill(&l, &b, dims, sp, 2.5, axial);
            for x in 0..n {
                assert_eq!(closed[index(x)], expected[x], "axial {axial}, voxel {x}");
            }
        }
    }

    #[test]
    fn closing_on_each_slices_lung_rectangle_equals_the_whole_slice_bit_for_bit() {
        // Small speckled blobs in a large slice: one at a corner (the rectangle clamped), one
        // in the middle with a ring around a hole, slices with one, both or none.
        let cd = [61, 47, 6];
        let n: usize = cd.iter().product();
        let ijk = |x: usize| (x % cd[0], x / cd[0] % cd[1], x / (cd[0] * cd[1]));
        let lung: Vec<u8> = (0..n)
            .map(|x| {
                let (i, j, k) = ijk(x);
                let hash = x.wrapping_mul(2_654_435_761) % 13;
                let corner = i < 9 && j < 7 && hash > 3 && k != 1;
                let r2 = (i as i64 - 35).pow(2) + (j as i64 - 22).pow(2);
                let ring = (12..=40).contains(&r2) && hash > 2 && k % 3 != 2;
                let speck = k == 4 && (i, j) == (50, 40);
                u8::from(corner || ring || speck)
            })
            .collect();
        let blocked: Vec<u8> = (0..n).map(|x| u8::from(ijk(x).1 == 25)).collect();
        for r in [0.0, 1.2, 2.5, 4.0] {
            for spacing in [[0.7, 0.9, 2.0], [1.3, 0.6, 1.0]] {
                let whole = close_and_fill(&lung, &blocked, cd, spacing, r, 2);
                let sliced = close_and_fill_axial_slices(&lung, &blocked, cd, spacing, r);
                assert_eq!(sliced, whole, "r = {r}, {spacing:?}");
            }
        }
    }
}
