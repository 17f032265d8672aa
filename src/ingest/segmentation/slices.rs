//! Voxel addressing on axial slices: in-slice axes, slice voxels, index triples, field-of-view
//! border.

use nalgebra::Vector3;
use ndarray::parallel::prelude::*;
use ndarray::ArrayView1;

use super::morphology::{array_axis, grid_view};

/// Voxel index triple of a linear index, as a vector for geometry maths.
pub(super) fn index_to_ijk(idx: usize, dims: [usize; 3]) -> Vector3<f64> {
    Vector3::new(
        (idx % dims[0]) as f64,
        ((idx / dims[0]) % dims[1]) as f64,
        (idx / (dims[0] * dims[1])) as f64,
    )
}

/// The two in-slice axes of slices across `axial`, in increasing order.
pub(super) fn in_slice_axes(axial: usize) -> [usize; 2] {
    match axial {
        0 => [1, 2],
        1 => [0, 2],
        _ => [0, 1],
    }
}

/// Linear index of in-slice position (u, v) on slice `s` across `axial`.
pub(super) fn slice_voxel(dims: [usize; 3], axial: usize, s: usize, u: usize, v: usize) -> usize {
    let [a, b] = in_slice_axes(axial);
    let mut ijk = [0usize; 3];
    ijk[axial] = s;
    ijk[a] = u;
    ijk[b] = v;
    ijk[0] + dims[0] * (ijk[1] + dims[1] * ijk[2])
}

/// Whether `label` reaches the in-slice border of any axial slice (the field of view cut it).
pub(super) fn touches_border(labels: &[u8], dims: [usize; 3], label: u8, axial: usize) -> bool {
    let on_edge = |line: ArrayView1<u8>| line.iter().any(|&v| v == label);
    grid_view(labels, dims)
        .axis_iter(array_axis(axial))
        .into_par_iter()
        .any(|slice| {
            let (last_row, last_column) = (slice.nrows() - 1, slice.ncols() - 1);
            on_edge(slice.row(0))
                || on_edge(slice.row(last_row))
                || on_edge(slice.column(0))
                || on_edge(slice.column(last_column))
        })
}
