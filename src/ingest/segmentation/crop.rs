//! A sub-box of the grid around one lung, so the per-lung steps work on a small copy.

use rayon::prelude::*;

/// A sub-box of the grid: first voxel and size.
#[derive(Debug, Clone, Copy)]
pub(super) struct Crop {
    pub lo: [usize; 3],
    pub dims: [usize; 3],
}

impl Crop {
    /// The box `min..=max` grown by `margin` voxels per axis, clamped to the grid.
    pub fn around(min: [usize; 3], max: [usize; 3], margin: [usize; 3], grid: [usize; 3]) -> Self {
        let lo = [0, 1, 2].map(|a| min[a].saturating_sub(margin[a]));
        let hi = [0, 1, 2].map(|a| (max[a] + margin[a]).min(grid[a] - 1));
        Crop {
            lo,
            dims: [0, 1, 2].map(|a| hi[a] - lo[a] + 1),
        }
    }

    /// Copies the box out of `full`, mapping each value through `f`.
    pub fn extract<F: Fn(usize, u8) -> u8 + Sync>(
        &self,
        full: &[u8],
        grid: [usize; 3],
        f: F,
    ) -> Vec<u8> {
        let [cx, cy, cz] = self.dims;
        let mut out = vec![0u8; cx * cy * cz];
        out.par_chunks_mut(cx * cy)
            .enumerate()
            .for_each(|(k, slice)| {
                for j in 0..cy {
                    let base = self.lo[0] + grid[0] * (self.lo[1] + j + grid[1] * (self.lo[2] + k));
                    for i in 0..cx {
                        slice[i + cx * j] = f(base + i, full[base + i]);
                    }
                }
            });
        out
    }

    /// Visits, in parallel, each row of the box inside `full`: `f` gets the row's `cx` voxels
    /// of the full grid and the index of the row's first voxel in the cropped box.
    pub fn for_each_row_mut<F: Fn(&mut [u8], usize) + Sync>(
        &self,
        full: &mut [u8],
        grid: [usize; 3],
        f: F,
    ) {
        let [cx, cy, cz] = self.dims;
        full.par_chunks_mut(grid[0] * grid[1])
            .enumerate()
            .filter(|(k, _)| (self.lo[2]..self.lo[2] + cz).contains(k))
            .for_each(|(k, slice)| {
                let kc = k - self.lo[2];
                for j in 0..cy {
                    let base = self.lo[0] + grid[0] * (self.lo[1] + j);
                    f(&mut slice[base..base + cx], cx * (j + cy * kc));
                }
            });
    }
}
