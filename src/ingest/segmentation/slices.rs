//! Voxel addressing on axial slices: in-slice axes, slice voxels, index triples, field-of-view
//! border.

use nalgebra::Vector3;
use rayon::prelude::*;

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
    let [a, b] = in_slice_axes(axial);
    let (na, nb) = (dims[a], dims[b]);
    (0..dims[axial]).into_par_iter().any(|s| {
        let edge = |u: usize, v: usize| labels[slice_voxel(dims, axial, s, u, v)] == label;
        (0..na).any(|u| edge(u, 0) || edge(u, nb - 1))
            || (0..nb).any(|v| edge(0, v) || edge(na - 1, v))
    })
}
