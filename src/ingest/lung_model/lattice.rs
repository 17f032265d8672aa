//! The cubic lattice over the lungs, anchored in patient space, and each cell's lung by the
//! partial-volume rule.

use nalgebra::{Matrix3, Vector3};
use rayon::prelude::*;

use super::settings::{LEFT_LUNG, RIGHT_LUNG};
use crate::model::VoxelGrid;
use crate::volume::Volume;
use crate::{Error, Result};

/// Points per cell edge used to measure a cell's lung fraction.
pub(super) const SUPERSAMPLES: usize = 4;
/// Lattice cells of padding around the lungs' bounding box (keeps the border background).
const LATTICE_PAD_CELLS: i64 = 1;

/// The voxel index nearest to continuous index `x` on an axis of `n` voxels (halves rounded
/// away from zero, as `f64::round`), or `None` outside the axis. Bit for bit what
/// `x.round()` gives, without its library call, which dominated sampling the CT mask.
pub(super) fn nearest_index(x: f64, n: usize) -> Option<usize> {
    // Beyond ±2^52 every f64 is an integer; NaN fails both comparisons.
    if !(x > -0.5 && x < n as f64 - 0.5) {
        return None;
    }
    let whole = x as i64; // towards zero, exact here
    let rounded = if x - whole as f64 >= 0.5 {
        whole + 1
    } else {
        whole
    };
    Some(rounded as usize)
}

/// The cubic lattice: cells of `h_mm` whose lattice point (0, 0, 0) sits at LPS
/// `first · h_mm`, so cells are fixed in patient space whatever the CT grid.
pub(super) struct CellLattice {
    /// Lattice index of the box's first lattice point.
    first: [i64; 3],
    /// Cells along x, y, z.
    pub(super) cells: [usize; 3],
    /// Cell edge in millimetres.
    pub(super) h_mm: f64,
}

impl CellLattice {
    /// The lattice covering every lung voxel, padded by one cell.
    pub(super) fn covering(lungs: &Volume<u8>, h_mm: f64) -> Result<Self> {
        let g = &lungs.geometry;
        let [nx, ny, _] = g.dims;
        // Voxel-index box of the lung voxels, per slab then reduced.
        let (lo, hi) = lungs
            .as_slice()
            .par_chunks(nx * ny)
            .enumerate()
            .map(|(k, slab)| {
                let mut lo = [usize::MAX; 3];
                let mut hi = [0usize; 3];
                for (idx, &v) in slab.iter().enumerate() {
                    if v != 0 {
                        let ijk = [idx % nx, idx / nx, k];
                        for a in 0..3 {
                            lo[a] = lo[a].min(ijk[a]);
                            hi[a] = hi[a].max(ijk[a]);
                        }
                    }
                }
                (lo, hi)
            })
            .reduce(
                || ([usize::MAX; 3], [0usize; 3]),
                |a, b| {
                    (
                        std::array::from_fn(|i| a.0[i].min(b.0[i])),
                        std::array::from_fn(|i| a.1[i].max(b.1[i])),
                    )
                },
            );
        let mut min_mm = Vector3::repeat(f64::INFINITY);
        let mut max_mm = Vector3::repeat(f64::NEG_INFINITY);
        for corner in 0..8 {
            let ijk = Vector3::from_fn(|a, _| {
                if corner >> a & 1 == 1 {
                    hi[a] as f64 + 0.5
                } else {
                    lo[a] as f64 - 0.5
                }
            });
            let p = g.voxel_to_lps_mm(ijk);
            min_mm = min_mm.inf(&p);
            max_mm = max_mm.sup(&p);
        }
        let first: [i64; 3] =
            std::array::from_fn(|a| (min_mm[a] / h_mm).floor() as i64 - LATTICE_PAD_CELLS);
        let last: [i64; 3] =
            std::array::from_fn(|a| (max_mm[a] / h_mm).ceil() as i64 + LATTICE_PAD_CELLS);
        let cells: [usize; 3] = std::array::from_fn(|a| (last[a] - first[a]) as usize);
        if cells.iter().product::<usize>() > u32::MAX as usize / 8 {
            return Err(Error::settings(
                "lung model settings",
                format!(
                "{h_mm} mm elements over the lungs' {:.0} × {:.0} × {:.0} mm box make {cells:?} \
                 cells: too many",
                max_mm.x - min_mm.x,
                max_mm.y - min_mm.y,
                max_mm.z - min_mm.z
            ),
            ));
        }
        Ok(CellLattice { first, cells, h_mm })
    }

    /// LPS millimetres of lattice point `l` (may lie outside the box).
    pub(super) fn point_mm(&self, l: [i64; 3]) -> Vector3<f64> {
        Vector3::from_fn(|a, _| (self.first[a] + l[a]) as f64 * self.h_mm)
    }

    /// The lung (0, 1, 2) of each cell by the partial-volume rule.
    pub(super) fn classify_cells(&self, lungs: &Volume<u8>, threshold: f64) -> Vec<u8> {
        let g = &lungs.geometry;
        let [nx, ny, nz] = self.cells;
        // Continuous voxel index = A · p_mm + b; sample offsets precomputed through A.
        let a = Matrix3::from_diagonal(&Vector3::from(g.spacing_mm.map(|s| 1.0 / s)))
            * g.direction().transpose();
        let b = -(a * g.origin());
        let offsets: Vec<Vector3<f64>> = (0..SUPERSAMPLES.pow(3))
            .map(|s| {
                let f = |q: usize| (q as f64 + 0.5) / SUPERSAMPLES as f64 * self.h_mm;
                a * Vector3::new(
                    f(s % SUPERSAMPLES),
                    f(s / SUPERSAMPLES % SUPERSAMPLES),
                    f(s / (SUPERSAMPLES * SUPERSAMPLES)),
                )
            })
            .collect();
        let needed = (threshold * offsets.len() as f64 - 1e-9).ceil() as usize;
        let dims = g.dims;
        let labels = lungs.as_slice();
        let mut out = vec![0u8; nx * ny * nz];
        out.par_chunks_mut(nx * ny)
            .enumerate()
            .for_each(|(k, slab)| {
                for j in 0..ny {
                    for i in 0..nx {
                        let corner = a * self.point_mm([i as i64, j as i64, k as i64]) + b;
                        let mut count = [0usize; 3];
                        for o in &offsets {
                            let v = corner + o;
                            if let (Some(ci), Some(cj), Some(ck)) = (
                                nearest_index(v.x, dims[0]),
                                nearest_index(v.y, dims[1]),
                                nearest_index(v.z, dims[2]),
                            ) {
                                let label = labels[ci + dims[0] * (cj + dims[1] * ck)];
                                count[label.min(2) as usize] += 1;
                            }
                        }
                        let (r, l) = (count[1], count[2]);
                        slab[i + nx * j] = if r >= needed && r >= l {
                            RIGHT_LUNG
                        } else if l >= needed && l > r {
                            LEFT_LUNG
                        } else {
                            0
                        };
                    }
                }
            });
        out
    }

    /// The lattice as a [`VoxelGrid`] in metres with `active` cells (axes along LPS).
    pub(super) fn grid(&self, active: Vec<bool>) -> VoxelGrid {
        let h_m = self.h_mm * 1e-3;
        VoxelGrid {
            cells: self.cells,
            cell_size_m: [h_m; 3],
            origin_m: self.point_mm([0, 0, 0]) * 1e-3,
            axes: Matrix3::identity(),
            active,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::nearest_index;

    #[test]
    fn nearest_index_is_what_round_gives_inside_the_axis_and_none_outside() {
        let round = |x: f64, n: usize| {
            let r = x.round();
            (r >= 0.0 && r < n as f64).then_some(r as usize)
        };
        let special = [
            -0.5,
            -0.5000000000000001,
            -0.49999999999999994,
            -0.0,
            0.49999999999999994,
            0.5,
            1.5,
            2.5,
            9.5,
            9.499999999999998,
            10.0,
            1e300,
            -1e300,
            f64::NAN,
            f64::INFINITY,
            f64::NEG_INFINITY,
        ];
        let spread = (0..20_000).map(|q| q as f64 * 0.000_631 - 1.3);
        for x in special.into_iter().chain(spread) {
            assert_eq!(nearest_index(x, 10), round(x, 10), "{x}");
        }
    }
}
