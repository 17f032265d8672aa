//! The thoracic-cavity wall the lungs slide on: the signed Euclidean distance to the CT lung
//! surface on an LPS-aligned grid finer than the lattice, smoothed by a Gaussian of one CT
//! voxel (see the module doc, "Wall").

use nalgebra::{Matrix3, Vector3};
use rayon::prelude::*;

use super::lattice::CellLattice;
use crate::ingest::segmentation::morphology::{for_each_line, squared_distance_mm2};
use crate::model::SignedDistanceField;
use crate::volume::Volume;
use crate::Result;

/// Elements of margin between the lattice box and the wall field's border.
const WALL_MARGIN_CELLS: i64 = 2;

/// The wall field and what building it measured.
pub(super) struct WallBuild {
    /// Smoothed distance to the CT lung surface.
    pub(super) wall: SignedDistanceField,
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

/// Builds the wall over `lattice` from the CT lung mask.
pub(super) fn build_wall(lungs: &Volume<u8>, lattice: &CellLattice) -> Result<WallBuild> {
    let g = &lungs.geometry;
    let finest_ct_mm = g.spacing_mm.iter().cloned().fold(f64::INFINITY, f64::min);
    let coarsest_ct_mm = g.spacing_mm.iter().cloned().fold(0.0, f64::max);
    let grid = WallGrid::refining(lattice, finest_ct_mm);
    let inside = sample_inside(lungs, &grid);
    let contact_voxels = count_contact_voxels(lungs);

    // One CT voxel of Gaussian smoothing rounds the voxel staircase into continuous normals.
    let s_mm = grid.spacing_mm;
    let s_m = s_mm * 1e-3;
    let ct_sigma = (coarsest_ct_mm / s_mm).clamp(0.5, 4.0);
    let anatomy_m: Vec<f64> = smoothed_signed_distance(&inside, grid.dims, ct_sigma)
        .iter()
        .map(|&v| v as f64 * s_m)
        .collect();
    drop(inside);
    let anatomy = SignedDistanceField::new(grid.origin_mm * 1e-3, [s_m; 3], grid.dims, anatomy_m)?;

    Ok(WallBuild {
        wall: anatomy,
        contact_voxels,
    })
}

/// 1 at each wall sample whose nearest CT voxel is inside: a lung voxel not touching the
/// other lung (so touching lungs stay two surfaces); 0 elsewhere.
fn sample_inside(lungs: &Volume<u8>, grid: &WallGrid) -> Vec<u8> {
    let g = &lungs.geometry;
    let [nx, ny, _] = grid.dims;
    let n_samples: usize = grid.dims.iter().product();
    let (origin_mm, s_mm) = (grid.origin_mm, grid.spacing_mm);
    let a = Matrix3::from_diagonal(&Vector3::from(g.spacing_mm.map(|s| 1.0 / s)))
        * g.direction().transpose();
    let b = -(a * g.origin());
    let ct_dims = g.dims;
    let mut inside = vec![0u8; n_samples];
    inside
        .par_chunks_mut(nx * ny)
        .enumerate()
        .for_each(|(k, slab)| {
            for j in 0..ny {
                for i in 0..nx {
                    let p = origin_mm + Vector3::new(i as f64, j as f64, k as f64) * s_mm;
                    let v = a * p + b;
                    let idx = [v.x.round(), v.y.round(), v.z.round()];
                    if (0..3).all(|q| idx[q] >= 0.0 && idx[q] < ct_dims[q] as f64) {
                        let (ci, cj, ck) = (idx[0] as usize, idx[1] as usize, idx[2] as usize);
                        let lung = lungs.get(ci, cj, ck);
                        slab[i + nx * j] =
                            u8::from(lung != 0 && !touches_other_lung(lungs, ci, cj, ck, lung));
                    }
                }
            }
        });
    inside
}

/// Lung voxels of the CT mask with a 26-neighbour in the other lung.
fn count_contact_voxels(lungs: &Volume<u8>) -> usize {
    let [cnx, cny, _] = lungs.geometry.dims;
    lungs
        .as_slice()
        .par_chunks(cnx * cny)
        .enumerate()
        .map(|(k, slab)| {
            slab.iter()
                .enumerate()
                .filter(|(idx, &v)| v != 0 && touches_other_lung(lungs, idx % cnx, idx / cnx, k, v))
                .count()
        })
        .sum()
}

/// Whether CT voxel (i, j, k) of `lung` has a 26-neighbour in the other lung.
fn touches_other_lung(lungs: &Volume<u8>, i: usize, j: usize, k: usize, lung: u8) -> bool {
    let ct_dims = lungs.geometry.dims;
    let other = 3 - lung;
    for dk in -1i64..=1 {
        for dj in -1i64..=1 {
            for di in -1i64..=1 {
                let (x, y, z) = (i as i64 + di, j as i64 + dj, k as i64 + dk);
                if x >= 0
                    && y >= 0
                    && z >= 0
                    && (x as usize) < ct_dims[0]
                    && (y as usize) < ct_dims[1]
                    && (z as usize) < ct_dims[2]
                    && lungs.get(x as usize, y as usize, z as usize) == other
                {
                    return true;
                }
            }
        }
    }
    false
}

/// Signed Euclidean distance in samples to the boundary of `inside` (negative inside; half
/// a sample puts the surface between samples), smoothed by a Gaussian of `sigma` samples.
fn smoothed_signed_distance(inside: &[u8], dims: [usize; 3], sigma: f64) -> Vec<f32> {
    // Unit spacing measures in samples, where the squared distances are exact integers.
    // Without a sample on one side the distance is capped rather than infinite, so the
    // field stays finite.
    const FAR: f32 = 1e12;
    let to_inside = squared_distance_mm2(inside, dims, [1.0; 3], true, None);
    let to_outside = squared_distance_mm2(inside, dims, [1.0; 3], false, None);
    let mut signed: Vec<f32> = inside
        .par_iter()
        .zip(to_inside.par_iter().zip(to_outside.par_iter()))
        .map(|(&i, (&din, &dout))| {
            if i != 0 {
                -(dout.min(FAR).sqrt() - 0.5)
            } else {
                din.min(FAR).sqrt() - 0.5
            }
        })
        .collect();
    drop(to_inside);
    drop(to_outside);
    gaussian_smooth(&mut signed, dims, sigma);
    signed
}

/// Separable Gaussian blur of `sigma` samples, edges clamped.
fn gaussian_smooth(values: &mut [f32], dims: [usize; 3], sigma: f64) {
    let radius = (2.5 * sigma).ceil() as usize;
    let weights: Vec<f32> = (0..=radius)
        .map(|r| (-((r * r) as f64) / (2.0 * sigma * sigma)).exp() as f32)
        .collect();
    let total: f32 = weights[0] + 2.0 * weights[1..].iter().sum::<f32>();
    let weights: Vec<f32> = weights.iter().map(|w| w / total).collect();
    let blur_line = |line: &mut [f32], input: &mut Vec<f32>| {
        input.clear();
        input.extend_from_slice(line);
        let n = input.len();
        for (q, out) in line.iter_mut().enumerate() {
            let mut acc = weights[0] * input[q];
            for (r, &w) in weights.iter().enumerate().skip(1) {
                let lo = q.saturating_sub(r);
                let hi = (q + r).min(n - 1);
                acc += w * (input[lo] + input[hi]);
            }
            *out = acc;
        }
    };
    for axis in 0..3 {
        for_each_line(values, dims, axis, Vec::new, blur_line);
    }
}
