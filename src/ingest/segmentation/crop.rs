//! A sub-box of the grid around one lung, so the per-lung steps work on a small copy.

use ndarray::{s, ArrayView3, ArrayViewMut3, Zip};

use super::morphology::{grid_view, grid_view_mut};

/// A sub-box of the grid: first voxel and size.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Crop {
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

    /// The box inside `full` (voxels of a `grid`, i fastest), indexed `[k, j, i]`.
    pub fn view<'a, T>(&self, full: &'a [T], grid: [usize; 3]) -> ArrayView3<'a, T> {
        let ([i0, j0, k0], [ni, nj, nk]) = (self.lo, self.dims);
        grid_view(full, grid).slice_move(s![k0..k0 + nk, j0..j0 + nj, i0..i0 + ni])
    }

    /// The box inside `full`, writable.
    pub fn view_mut<'a, T>(&self, full: &'a mut [T], grid: [usize; 3]) -> ArrayViewMut3<'a, T> {
        let ([i0, j0, k0], [ni, nj, nk]) = (self.lo, self.dims);
        grid_view_mut(full, grid).slice_move(s![k0..k0 + nk, j0..j0 + nj, i0..i0 + ni])
    }

    /// Copies the box out of `full`, mapping each value through `f`.
    pub fn extract<F: Fn(u8) -> u8 + Sync>(&self, full: &[u8], grid: [usize; 3], f: F) -> Vec<u8> {
        self.extract_pair(full, full, grid, |v, _| f(v))
    }

    /// Copies the box out of two volumes on the same grid, combining their voxels with `f`.
    pub fn extract_pair<F: Fn(u8, u8) -> u8 + Sync>(
        &self,
        a: &[u8],
        b: &[u8],
        grid: [usize; 3],
        f: F,
    ) -> Vec<u8> {
        let [ni, nj, nk] = self.dims;
        let mut out = vec![0u8; ni * nj * nk];
        Zip::from(grid_view_mut(&mut out, self.dims))
            .and(self.view(a, grid))
            .and(self.view(b, grid))
            .par_for_each(|o, &x, &y| *o = f(x, y));
        out
    }
}
