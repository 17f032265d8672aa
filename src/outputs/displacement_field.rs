//! From node displacements of the cubic mesh to a dense displacement field on the CT grid.
//!
//! The field's grid is the CT's own voxels, either all of them ([`FieldGrid::Ct`]) or, by
//! default, the box around the lungs ([`FieldGrid::LungBox`]): the CT's spacing and direction,
//! its origin moved to the box's first voxel, so every field voxel is a CT voxel and ITK,
//! SimpleITK, elastix and plastimatch place it from the file's own geometry. Outside the
//! lungs the field is zero, so the box loses nothing and spares writing the zeros (85 % of a
//! chest CT).
//!
//! Each lung voxel of the CT is located once in the element of its own lung that contains
//! it (the elements are cubes on one lattice) and keeps that element's index; its place in
//! the element, and so the eight trilinear weights (the element's own shape functions, so the
//! field is exactly the mesh's motion), is recomputed from its grid index each frame. A lung voxel whose cell holds no element (the mesh keeps cells at least
//! half inside the lung, so thin rims of voxels fall outside) takes the value at the nearest
//! point of the nearest element of the same lung within two cells; voxels outside the lungs
//! stay zero. Sampling a frame is then one pass of 8 multiply-adds per lung voxel.

use rayon::prelude::*;
use serde::{Deserialize, Serialize};

use crate::math::V3;
use crate::model::{CubeLattice, HexMesh};
use crate::volume::{Volume, VolumeGeometry};
use crate::{Error, Result};

/// How far (in cells) a lung voxel outside every element looks for one of its lung.
const SEARCH_RADIUS_CELLS: i64 = 2;

/// Steps the field's millimetres are rounded to (1/64 mm: at most 0.008 mm off, a twelfth
/// of the 0.1 mm interpolation tolerance). Rounded float32 values end in zero bits, which
/// gzip packs: a POPI end-inhale frame went from 31 MB to 10 MB at the same level.
pub const FIELD_STEPS_PER_MM: f32 = 64.0;

/// Zero voxels kept around the lungs in a [`FieldGrid::LungBox`] field, so that a reader
/// interpolating at the lung's edge finds the field's zero there, not the end of the image.
pub const LUNG_BOX_MARGIN_VOXELS: usize = 2;

/// Which voxels of the CT grid a displacement field covers.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum FieldGrid {
    /// The box around the lung voxels plus a margin of [`LUNG_BOX_MARGIN_VOXELS`].
    #[default]
    LungBox,
    /// Every voxel of the CT.
    Ct,
}

/// Precomputed interpolation from mesh nodes to the lung voxels of a field grid.
#[derive(Debug, Clone)]
pub struct FieldSampler {
    /// The field's grid (a sub-grid of the CT's).
    geometry: VolumeGeometry,
    /// The CT voxel that is the field's voxel (0, 0, 0).
    start: [usize; 3],
    voxel_count: usize,
    /// Linear field-grid index of each sampled lung voxel, increasing.
    voxels: Vec<u32>,
    /// Element interpolating each sampled voxel.
    element: Vec<u32>,
    /// Lattice coordinates (in element edges) of the field's voxel (0, 0, 0) and the step of
    /// one voxel along i, j and k: a voxel's place in its element is recomputed per frame
    /// rather than stored (8 bytes a lung voxel instead of 40: 90 MB less on POPI).
    lattice_at_first_voxel: V3,
    lattice_per_voxel: [V3; 3],
    /// Whether a step along the grid's i axis moves along the lattice's x axis only (the CT
    /// and the mesh share their axes), so the field along a row is linear inside an element.
    rows_along_lattice_x: bool,
    /// Lattice cell of each element (its first corner, in element edges).
    element_cell: Vec<V3>,
    /// Lung voxels with no element within the search radius (left at zero).
    pub uncovered_voxels: usize,
    /// Lung voxels outside every element, extrapolated from the nearest one.
    pub extrapolated_voxels: usize,
}

pub(crate) use crate::model::cube_lattice::CORNER_BITS;

/// Element, corner weights, and whether the point lies inside the element.
type Location = (u32, [f32; 8], bool);

/// The CT voxel where the box around the non-zero voxels of `labels` starts and its size,
/// grown by `margin` voxels on every side within the grid; the whole grid when none is set.
pub fn label_box(labels: &Volume<u8>, margin: usize) -> ([usize; 3], [usize; 3]) {
    let [nx, ny, nz] = labels.geometry.dims;
    let plane = nx * ny;
    let (lo, hi) = labels
        .as_slice()
        .par_chunks(plane)
        .enumerate()
        .filter_map(|(k, slice)| {
            let mut b: Option<([usize; 3], [usize; 3])> = None;
            for (n, _) in slice.iter().enumerate().filter(|(_, &l)| l != 0) {
                let p = [n % nx, n / nx, k];
                b = Some(match b {
                    None => (p, p),
                    Some((lo, hi)) => (
                        [lo[0].min(p[0]), lo[1].min(p[1]), k],
                        [hi[0].max(p[0]), hi[1].max(p[1]), k],
                    ),
                });
            }
            b
        })
        .reduce(
            || ([usize::MAX; 3], [0; 3]),
            |(alo, ahi), (blo, bhi)| {
                (
                    [alo[0].min(blo[0]), alo[1].min(blo[1]), alo[2].min(blo[2])],
                    [ahi[0].max(bhi[0]), ahi[1].max(bhi[1]), ahi[2].max(bhi[2])],
                )
            },
        );
    if lo[0] == usize::MAX {
        return ([0; 3], [nx, ny, nz]);
    }
    let dims = [nx, ny, nz];
    let start = [0, 1, 2].map(|a| lo[a].saturating_sub(margin));
    let end = [0, 1, 2].map(|a| (hi[a] + margin + 1).min(dims[a]));
    (start, [0, 1, 2].map(|a| end[a] - start[a]))
}

impl FieldSampler {
    /// Locates every lung voxel of `lungs` (non-zero labels) in the mesh; `element_lung` is the
    /// lung label of each element, so a voxel is never interpolated from the other lung. The
    /// field covers the voxels `grid` says.
    pub fn new(
        lungs: &Volume<u8>,
        mesh: &HexMesh,
        element_lung: &[u8],
        grid: FieldGrid,
    ) -> Result<Self> {
        let lattice = CubeLattice::of(mesh, element_lung)?;
        let g = lungs.geometry;
        let [nx, ny, _] = g.dims;
        let (start, dims) = match grid {
            FieldGrid::LungBox => label_box(lungs, LUNG_BOX_MARGIN_VOXELS),
            FieldGrid::Ct => ([0; 3], g.dims),
        };
        let geometry = g.sub_grid(start, dims);
        // CT voxel (i, j, k) is field voxel (i, j, k) − start: increasing with the CT index.
        let field_index = |i: usize, j: usize, k: usize| {
            geometry.index(i - start[0], j - start[1], k - start[2]) as u32
        };
        // (field index, element, 0 uncovered / 1 inside / 2 extrapolated): 12 bytes a voxel.
        let located: Vec<(u32, u32, u8)> = lungs
            .as_slice()
            .par_iter()
            .enumerate()
            .filter(|(_, &l)| l != 0)
            .map(|(idx, &label)| {
                let (i, j, k) = (idx % nx, (idx / nx) % ny, idx / (nx * ny));
                let p_m = g.voxel_to_lps_mm(V3::new(i as f64, j as f64, k as f64)) * 1e-3;
                let hit = locate(&lattice, p_m, label);
                let (e, how) = hit.map_or((0, 0), |(e, _, inside)| (e, 2 - u8::from(inside)));
                (field_index(i, j, k), e, how)
            })
            .collect();
        let covered = located.iter().filter(|h| h.2 != 0).count();
        let lattice_at = |v: [usize; 3]| {
            let ijk = V3::new(v[0] as f64, v[1] as f64, v[2] as f64);
            lattice.coords(g.voxel_to_lps_mm(ijk) * 1e-3)
        };
        let first = lattice_at(start);
        let step = |a: usize| {
            let mut v = start;
            v[a] += 1;
            lattice_at(v) - first
        };
        let mut sampler = FieldSampler {
            geometry,
            start,
            voxel_count: geometry.voxel_count(),
            voxels: Vec::with_capacity(covered),
            element: Vec::with_capacity(covered),
            lattice_at_first_voxel: first,
            lattice_per_voxel: [step(0), step(1), step(2)],
            rows_along_lattice_x: {
                let i_step = step(0);
                i_step.y.abs() < 1e-12 && i_step.z.abs() < 1e-12
            },
            element_cell: lattice
                .element_cell
                .iter()
                .map(|c| V3::new(c[0] as f64, c[1] as f64, c[2] as f64))
                .collect(),
            uncovered_voxels: located.len() - covered,
            extrapolated_voxels: located.iter().filter(|h| h.2 == 2).count(),
        };
        for (idx, e, _) in located.into_iter().filter(|h| h.2 != 0) {
            sampler.voxels.push(idx);
            sampler.element.push(e);
        }
        // `sample_mm` finds each grid chunk's voxels by binary search.
        debug_assert!(sampler.voxels.windows(2).all(|w| w[0] < w[1]));
        Ok(sampler)
    }

    /// The grid the field is sampled on: the CT's voxels from [`FieldSampler::start`].
    pub fn geometry(&self) -> &VolumeGeometry {
        &self.geometry
    }

    /// The CT voxel that is the field's voxel (0, 0, 0).
    pub fn start(&self) -> [usize; 3] {
        self.start
    }

    /// Number of lung voxels that receive a displacement.
    pub fn sampled_voxels(&self) -> usize {
        self.voxels.len()
    }

    /// Writes the displacement (node positions minus rest positions, metres) as millimetres,
    /// in steps of 1/[`FIELD_STEPS_PER_MM`], on every voxel of the field's grid: zero outside
    /// the lungs. `out` has one entry per
    /// voxel and is reused across frames: nothing grid-sized is allocated per call (only one
    /// displacement per mesh node).
    pub fn sample_mm(&self, mesh: &HexMesh, positions_m: &[V3], out: &mut [[f32; 3]]) {
        self.sample_into(mesh, positions_m, out, true);
    }

    /// [`FieldSampler::sample_mm`] writing the lung voxels only: `out` must hold zeros
    /// elsewhere (a buffer filled by an earlier sample, or zeroed), which spares rewriting
    /// the zeros of every frame (117 MB on a POPI lung box).
    pub fn sample_lung_voxels_mm(&self, mesh: &HexMesh, positions_m: &[V3], out: &mut [[f32; 3]]) {
        self.sample_into(mesh, positions_m, out, false);
    }

    fn sample_into(
        &self,
        mesh: &HexMesh,
        positions_m: &[V3],
        out: &mut [[f32; 3]],
        zero_the_rest: bool,
    ) {
        assert_eq!(
            out.len(),
            self.voxel_count,
            "output must cover the field's grid"
        );
        let [nx, ny, _] = self.geometry.dims;
        // Each node's displacement once per frame rather than once per voxel and corner (the
        // same subtraction, so the same bits).
        let displacement_m: Vec<V3> = positions_m
            .par_iter()
            .zip(&mesh.rest_positions_m)
            .map(|(x, r)| x - r)
            .collect();
        // Each chunk of the grid zeroes itself and fills its own lung voxels (`voxels` is
        // sorted), so the grid is written once, in parallel, without a staging buffer.
        out.par_chunks_mut(SAMPLE_CHUNK_VOXELS)
            .enumerate()
            .for_each(|(c, chunk)| {
                let start = c * SAMPLE_CHUNK_VOXELS;
                if zero_the_rest {
                    chunk.fill([0.0; 3]);
                }
                let lo = self.voxels.partition_point(|&v| (v as usize) < start);
                let hi = self
                    .voxels
                    .partition_point(|&v| (v as usize) < start + chunk.len());
                // Lung voxels come in runs along a grid row: the row's (j, k) is found by
                // division once per row, not per voxel.
                let (mut row_start, mut row_end) = (0, 0);
                let (mut j, mut k) = (0.0, 0.0);
                // Along a row inside one element of a lattice aligned with the grid's i axis
                // the trilinear field is linear in the local x: u = a + b·x, from the
                // element's four x edges once per run instead of eight corners per voxel.
                let mut run: Option<(usize, V3, V3)> = None;
                for s in lo..hi {
                    let v = self.voxels[s] as usize;
                    if v >= row_end {
                        let row = v / nx;
                        row_start = row * nx;
                        row_end = row_start + nx;
                        (j, k) = ((row % ny) as f64, (row / ny) as f64);
                        run = None;
                    }
                    let e = self.element[s] as usize;
                    let f = self.lattice_at_first_voxel
                        + self.lattice_per_voxel[0] * (v - row_start) as f64
                        + self.lattice_per_voxel[1] * j
                        + self.lattice_per_voxel[2] * k;
                    let unclamped = f - self.element_cell[e];
                    let inside = unclamped.iter().all(|t| (0.0..=1.0).contains(t));
                    let u = match run {
                        Some((run_e, a, b)) if run_e == e && inside => a + b * unclamped.x,
                        _ => {
                            // Inside its element the clamp changes nothing; a voxel beyond
                            // the mesh takes the element's nearest point.
                            let local = unclamped.map(|t| t.clamp(0.0, 1.0));
                            let corners = &mesh.elements[e];
                            if inside && self.rows_along_lattice_x {
                                let (a, b) = x_edges(corners, &displacement_m, local);
                                run = Some((e, a, b));
                                a + b * local.x
                            } else {
                                run = None;
                                let mut u = V3::zeros();
                                for (corner, &n) in corners.iter().enumerate() {
                                    u += displacement_m[n as usize] * corner_weight(local, corner);
                                }
                                u
                            }
                        }
                    };
                    let step = |m: f64| {
                        round_half_away(m as f32 * FIELD_STEPS_PER_MM) / FIELD_STEPS_PER_MM
                    };
                    chunk[v - start] = [step(u.x * 1e3), step(u.y * 1e3), step(u.z * 1e3)];
                }
            });
    }
}

/// The trilinear field of an element with corner displacements from `displacement_m` at
/// local (y, z) of `local`, as `a + b·x` along its x edges (VTK corners 0–1, 3–2, 4–5, 7–6).
#[inline]
fn x_edges(corners: &[u32; 8], displacement_m: &[V3], local: V3) -> (V3, V3) {
    let d = |c: usize| displacement_m[corners[c] as usize];
    let (y, z) = (local.y, local.z);
    let mut a = V3::zeros();
    let mut b = V3::zeros();
    for (low, high, w) in [
        (0, 1, (1.0 - y) * (1.0 - z)),
        (3, 2, y * (1.0 - z)),
        (4, 5, (1.0 - y) * z),
        (7, 6, y * z),
    ] {
        a += d(low) * w;
        b += (d(high) - d(low)) * w;
    }
    (a, b)
}

/// `y.round()` without libm's `roundf` call (x86-64 has no rounding instruction before
/// SSE4.1, and three calls a lung voxel were a tenth of a POPI frame's CPU): the truncation
/// of `y` plus the largest `f32` below one half, with `y`'s sign, which is exact (a tie's sum
/// rounds to the next integer), keeping `y`'s sign on a zero. Beyond 2²³ every `f32` is an
/// integer; NaN stays NaN.
#[inline]
fn round_half_away(y: f32) -> f32 {
    const BELOW_HALF: f32 = 0.499_999_97;
    if y.abs() < 8_388_608.0 {
        ((y + BELOW_HALF.copysign(y)) as i32 as f32).copysign(y)
    } else {
        y
    }
}

/// Grid voxels per parallel task of [`FieldSampler::sample_mm`] (cache-sized, and enough
/// tasks to balance two to a few dozen cores).
const SAMPLE_CHUNK_VOXELS: usize = 1 << 14;

/// Interpolation from mesh nodes to user-given points (e.g. a tumour centre), for trajectories.
#[derive(Debug, Clone)]
pub struct PointSampler {
    element: Vec<u32>,
    weights: Vec<[f32; 8]>,
    inside: Vec<bool>,
}

impl PointSampler {
    /// Locates each LPS point (mm) in the element containing it, in either lung, or the
    /// nearest element within two cells; a point farther from the mesh is an error naming it.
    pub fn new(points_lps_mm: &[[f64; 3]], mesh: &HexMesh, element_lung: &[u8]) -> Result<Self> {
        let lattice = CubeLattice::of(mesh, element_lung)?;
        let mut labels: Vec<u8> = element_lung.to_vec();
        labels.sort_unstable();
        labels.dedup();
        let mut sampler = PointSampler {
            element: Vec::with_capacity(points_lps_mm.len()),
            weights: Vec::with_capacity(points_lps_mm.len()),
            inside: Vec::with_capacity(points_lps_mm.len()),
        };
        for (i, p) in points_lps_mm.iter().enumerate() {
            if p.iter().any(|v| !v.is_finite()) {
                return Err(Error::Points {
                    file: None,
                    point: Some(i + 1),
                    reason: format!("is not finite: {p:?}"),
                });
            }
            let p_m = V3::from(*p) * 1e-3;
            let inside = labels
                .iter()
                .find_map(|&l| locate(&lattice, p_m, l).filter(|h| h.2));
            let hit = inside.or_else(|| {
                labels
                    .iter()
                    .filter_map(|&l| locate(&lattice, p_m, l))
                    .min_by(|a, b| {
                        let da = distance_outside(&lattice, mesh, a.0, p_m);
                        let db = distance_outside(&lattice, mesh, b.0, p_m);
                        da.total_cmp(&db)
                    })
            });
            let Some((e, w, inside)) = hit else {
                return Err(Error::Points {
                    file: None,
                    point: Some(i + 1),
                    reason: format!(
                        "at LPS ({:.1}, {:.1}, {:.1}) mm is outside the lungs' mesh",
                        p[0], p[1], p[2]
                    ),
                });
            };
            sampler.element.push(e);
            sampler.weights.push(w);
            sampler.inside.push(inside);
        }
        Ok(sampler)
    }

    /// Whether each point lies inside an element (else it follows the nearest element's
    /// boundary, within two cells of the mesh).
    pub fn inside_mesh(&self) -> &[bool] {
        &self.inside
    }

    /// Displacement of each point in mm (LPS components).
    pub fn displacements_mm(&self, mesh: &HexMesh, positions_m: &[V3]) -> Vec<[f64; 3]> {
        let mut out = vec![[0.0; 3]; self.element.len()];
        self.displacements_into(mesh, positions_m, &mut out);
        out
    }

    /// Displacement of each point in mm (LPS components) into `out`, one entry per point,
    /// for callers that reuse a buffer across frames.
    pub fn displacements_into(&self, mesh: &HexMesh, positions_m: &[V3], out: &mut [[f64; 3]]) {
        assert_eq!(
            out.len(),
            self.element.len(),
            "one output per tracked point"
        );
        let rest = &mesh.rest_positions_m;
        for ((&e, w), o) in self.element.iter().zip(&self.weights).zip(out.iter_mut()) {
            let mut u = V3::zeros();
            for (c, &n) in mesh.elements[e as usize].iter().enumerate() {
                let n = n as usize;
                u += (positions_m[n] - rest[n]) * f64::from(w[c]);
            }
            *o = (u * 1e3).into();
        }
    }
}

/// Distance from `p_m` to the box of element `e`, metres.
fn distance_outside(lattice: &CubeLattice, mesh: &HexMesh, e: u32, p_m: V3) -> f64 {
    let x0 = mesh.rest_positions_m[mesh.elements[e as usize][0] as usize];
    let d = p_m - x0;
    (0..3)
        .map(|a| {
            let t = d.dot(&lattice.axes[a]);
            let out = (t.clamp(0.0, lattice.edge_m) - t).abs();
            out * out
        })
        .sum::<f64>()
        .sqrt()
}

/// The element of lung `label` containing `p_m` (or the nearest within the search radius),
/// its corner weights, and whether the point was inside it.
fn locate(lattice: &CubeLattice, p_m: V3, label: u8) -> Option<Location> {
    let (c, f) = lattice.cell_of(p_m);
    if let Some(e) = lattice.element_at(c, label) {
        let local = f - V3::new(c[0] as f64, c[1] as f64, c[2] as f64);
        return Some((e, weights(local), true));
    }
    let mut best: Option<(f64, u32, V3)> = None;
    let r = SEARCH_RADIUS_CELLS;
    for dz in -r..=r {
        for dy in -r..=r {
            for dx in -r..=r {
                let cell = [c[0] + dx, c[1] + dy, c[2] + dz];
                if let Some(e) = lattice.element_at(cell, label) {
                    let corner = V3::new(cell[0] as f64, cell[1] as f64, cell[2] as f64);
                    let local = (f - corner).map(|v| v.clamp(0.0, 1.0));
                    let d = (f - corner - local).norm();
                    if best.is_none_or(|(bd, _, _)| d < bd) {
                        best = Some((d, e, local));
                    }
                }
            }
        }
    }
    best.map(|(_, e, local)| (e, weights(local), false))
}

/// The trilinear weight of element corner `corner` (VTK order) at `local` (0…1 per axis).
#[inline]
pub(crate) fn corner_weight(local: V3, corner: usize) -> f64 {
    let bits = CORNER_BITS[corner];
    let w = |a: usize| if bits[a] { local[a] } else { 1.0 - local[a] };
    w(0) * w(1) * w(2)
}

/// The eight trilinear corner weights (VTK order) at `local` (0…1 per axis).
pub(crate) fn weights(local: V3) -> [f32; 8] {
    let mut w = [0.0f32; 8];
    for (c, bits) in CORNER_BITS.iter().enumerate() {
        let mut v = 1.0;
        for a in 0..3 {
            v *= if bits[a] { local[a] } else { 1.0 - local[a] };
        }
        w[c] = v as f32;
    }
    w
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::{Material, VoxelGrid};

    /// A 4×3×2 block of 10 mm cubes from (−20, −10, 0) mm.
    fn block_mesh() -> HexMesh {
        VoxelGrid::filled_box([4, 3, 2], [0.01; 3], V3::new(-0.02, -0.01, 0.0))
            .to_mesh(Material::LUNG)
            .unwrap()
            .mesh
    }

    #[test]
    fn rounding_without_libm_equals_f32_round() {
        let mut cases = vec![
            0.0f32,
            -0.0,
            0.5,
            -0.5,
            1.5,
            -1.5,
            2.5,
            0.499_999_97,
            -0.499_999_97,
        ];
        cases.extend([
            8_388_607.5f32,
            -8_388_607.5,
            8_388_608.0,
            1e9,
            -1e9,
            f32::MAX,
        ]);
        cases.extend([f32::INFINITY, f32::NEG_INFINITY, f32::MIN_POSITIVE]);
        // Every tie and its neighbours up to ±8192, and a sweep of ordinary values.
        for n in -8192..8192 {
            let tie = n as f32 + 0.5;
            cases.extend([
                tie,
                f32::from_bits(tie.to_bits() + 1),
                f32::from_bits(tie.to_bits() - 1),
            ]);
        }
        cases.extend((0..200_000).map(|i| (i as f32 - 100_000.0) * 0.013_7));
        for y in cases {
            assert_eq!(round_half_away(y).to_bits(), y.round().to_bits(), "{y}");
        }
        assert!(round_half_away(f32::NAN).is_nan());
    }

    #[test]
    fn an_affine_motion_is_reproduced_at_every_lung_voxel_and_zero_elsewhere() {
        // CT of 2.5 mm voxels over the block.
        let mesh = block_mesh();
        let geometry = VolumeGeometry::axis_aligned([24, 20, 12], [2.5; 3], [-28.0, -18.0, -5.0]);
        let mut lungs = Volume::filled(geometry, 0u8).unwrap();
        let mut inside = 0;
        for k in 0..12 {
            for j in 0..20 {
                for i in 0..24 {
                    let p = geometry.voxel_to_lps_mm(V3::new(i as f64, j as f64, k as f64));
                    if p.x > -20.0
                        && p.x < 20.0
                        && p.y > -10.0
                        && p.y < 20.0
                        && p.z > 0.0
                        && p.z < 20.0
                    {
                        lungs.as_slice_mut()[geometry.index(i, j, k)] = 1;
                        inside += 1;
                    }
                }
            }
        }
        let sampler =
            FieldSampler::new(&lungs, &mesh, &vec![1; mesh.elements.len()], FieldGrid::Ct).unwrap();
        assert_eq!(sampler.sampled_voxels(), inside);
        assert_eq!(sampler.extrapolated_voxels, 0);
        let a = nalgebra::Matrix3::new(0.01, 0.02, -0.03, 0.0, 0.05, 0.01, -0.02, 0.0, 0.04);
        let b = V3::new(1e-3, -2e-3, 3e-3);
        let moved: Vec<V3> = mesh
            .rest_positions_m
            .iter()
            .map(|x| x + a * x + b)
            .collect();
        let mut field = vec![[f32::NAN; 3]; geometry.voxel_count()];
        sampler.sample_mm(&mesh, &moved, &mut field);
        // Writing the lung voxels alone into a zeroed buffer gives the same field.
        let mut lung_only = vec![[0.0f32; 3]; geometry.voxel_count()];
        sampler.sample_lung_voxels_mm(&mesh, &moved, &mut lung_only);
        assert_eq!(lung_only, field);
        for (idx, u) in field.iter().enumerate() {
            let (i, j, k) = (idx % 24, (idx / 24) % 20, idx / 480);
            let p_m = geometry.voxel_to_lps_mm(V3::new(i as f64, j as f64, k as f64)) * 1e-3;
            let expected = if lungs.as_slice()[idx] != 0 {
                (a * p_m + b) * 1e3
            } else {
                V3::zeros()
            };
            for c in 0..3 {
                assert!(
                    (u[c] as f64 - expected[c]).abs() <= 0.5 / f64::from(FIELD_STEPS_PER_MM) + 1e-6,
                    "{idx}: {u:?} vs {expected}"
                );
                assert_eq!(
                    (u[c] * FIELD_STEPS_PER_MM).fract(),
                    0.0,
                    "{u:?}: not in steps"
                );
            }
        }
        // The lung box holds the same values at the same LPS places, and only the zeros
        // beyond its margin are left out.
        let boxed = FieldSampler::new(
            &lungs,
            &mesh,
            &vec![1; mesh.elements.len()],
            FieldGrid::LungBox,
        )
        .unwrap();
        let (start, bg) = (boxed.start(), *boxed.geometry());
        assert!(bg.voxel_count() < geometry.voxel_count(), "{:?}", bg.dims);
        let mut in_box = vec![[f32::NAN; 3]; bg.voxel_count()];
        boxed.sample_mm(&mesh, &moved, &mut in_box);
        let mut lung_voxels_in_box = 0;
        for k in 0..bg.dims[2] {
            for j in 0..bg.dims[1] {
                for i in 0..bg.dims[0] {
                    let ct = [i + start[0], j + start[1], k + start[2]];
                    let ct_index = geometry.index(ct[0], ct[1], ct[2]);
                    assert_eq!(in_box[bg.index(i, j, k)], field[ct_index]);
                    let at = |g: &VolumeGeometry, v: [usize; 3]| {
                        g.voxel_to_lps_mm(V3::new(v[0] as f64, v[1] as f64, v[2] as f64))
                    };
                    assert!((at(&bg, [i, j, k]) - at(&geometry, ct)).norm() < 1e-9);
                    lung_voxels_in_box += usize::from(lungs.as_slice()[ct_index] != 0);
                }
            }
        }
        assert_eq!(lung_voxels_in_box, inside);
    }

    #[test]
    fn the_lung_box_is_the_labels_extent_plus_the_margin_within_the_grid() {
        let g = VolumeGeometry::axis_aligned([10, 8, 6], [1.0; 3], [0.0; 3]);
        let mut labels = Volume::filled(g, 0u8).unwrap();
        labels.as_slice_mut()[g.index(3, 1, 2)] = 1;
        labels.as_slice_mut()[g.index(6, 4, 4)] = 2;
        assert_eq!(label_box(&labels, 2), ([1, 0, 0], [8, 7, 6]));
        assert_eq!(label_box(&labels, 0), ([3, 1, 2], [4, 4, 3]));
        let empty = Volume::filled(g, 0u8).unwrap();
        assert_eq!(label_box(&empty, 2), ([0; 3], [10, 8, 6]));
    }

    #[test]
    fn tracked_points_follow_the_mesh_and_far_points_are_refused() {
        let gm = VoxelGrid::filled_box([2, 2, 2], [0.01; 3], V3::zeros())
            .to_mesh(Material::LUNG)
            .unwrap();
        let mesh = gm.mesh;
        let lungs = vec![1u8; mesh.elements.len()];
        let points = [[5.0, 5.0, 5.0], [12.5, 17.5, 3.0], [21.0, 10.0, 10.0]];
        let sampler = PointSampler::new(&points, &mesh, &lungs).unwrap();
        let moved: Vec<V3> = mesh
            .rest_positions_m
            .iter()
            .map(|x| x + V3::new(0.0, 0.0, -0.1 * x.y))
            .collect();
        let u = sampler.displacements_mm(&mesh, &moved);
        assert!((u[0][2] + 0.5).abs() < 1e-6, "{u:?}");
        assert!((u[1][2] + 1.75).abs() < 1e-6, "{u:?}");
        // 1 mm outside the block: the nearest point of the mesh (y = 10 mm).
        assert!((u[2][2] + 1.0).abs() < 1e-6, "{u:?}");
        assert_eq!(sampler.inside_mesh(), [true, true, false]);
        let e = PointSampler::new(&[[200.0, 0.0, 0.0]], &mesh, &lungs).unwrap_err();
        assert!(e.to_string().contains("point 1 at LPS (200.0"), "{e}");
        assert!(PointSampler::new(&[[f64::NAN, 0.0, 0.0]], &mesh, &lungs).is_err());
    }

    #[test]
    fn a_non_affine_motion_matches_the_point_sampler_on_straight_and_oblique_grids() {
        // Rows of a straight grid take the per-row form inside an element, an oblique grid's
        // the eight corners: both must give the trilinear field the points get.
        let mesh = block_mesh();
        let lung_of = vec![1u8; mesh.elements.len()];
        // Every node moves its own way (a hash of its index, up to ±4 mm per axis).
        let moved: Vec<V3> = mesh
            .rest_positions_m
            .iter()
            .enumerate()
            .map(|(n, x)| {
                let h = |a: usize| ((n * 7919 + a * 104_729) % 1000) as f64 / 1000.0 - 0.5;
                x + V3::new(h(0), h(1), h(2)) * 8e-3
            })
            .collect();
        let (c, s) = (0.3f64.cos(), 0.3f64.sin());
        for direction in [
            [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
            [[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]],
        ] {
            let geometry = VolumeGeometry {
                dims: [22, 18, 10],
                spacing_mm: [1.7, 1.9, 2.1],
                origin_lps_mm: [-19.0, -9.0, 0.5],
                direction_lps: direction,
            };
            let mut lungs = Volume::filled(geometry, 0u8).unwrap();
            let mut centres = Vec::new();
            for idx in 0..geometry.voxel_count() {
                let (i, j, k) = (idx % 22, (idx / 22) % 18, idx / (22 * 18));
                let p = geometry.voxel_to_lps_mm(V3::new(i as f64, j as f64, k as f64));
                if p.x > -19.5 && p.x < 19.5 && p.y > -9.5 && p.y < 19.5 && p.z > 0.5 && p.z < 19.5
                {
                    lungs.as_slice_mut()[idx] = 1;
                    centres.push((idx, [p.x, p.y, p.z]));
                }
            }
            let sampler = FieldSampler::new(&lungs, &mesh, &lung_of, FieldGrid::Ct).unwrap();
            assert_eq!(sampler.extrapolated_voxels, 0);
            let mut field = vec![[f32::NAN; 3]; geometry.voxel_count()];
            sampler.sample_mm(&mesh, &moved, &mut field);
            let points: Vec<[f64; 3]> = centres.iter().map(|c| c.1).collect();
            let at_points = PointSampler::new(&points, &mesh, &lung_of)
                .unwrap()
                .displacements_mm(&mesh, &moved);
            for ((idx, _), expected) in centres.iter().zip(&at_points) {
                for a in 0..3 {
                    let got = field[*idx][a] as f64;
                    assert!(
                        (got - expected[a]).abs() <= 0.5 / f64::from(FIELD_STEPS_PER_MM) + 1e-4,
                        "{direction:?} voxel {idx}: {:?} vs {expected:?}",
                        field[*idx]
                    );
                }
            }
        }
    }

    #[test]
    fn a_lung_voxel_beyond_the_mesh_takes_the_nearest_element_of_its_own_lung() {
        let gm = VoxelGrid::filled_box([2, 1, 1], [0.01; 3], V3::zeros())
            .to_mesh(Material::LUNG)
            .unwrap();
        let mesh = gm.mesh;
        // Element 0 is the "right lung" (label 1), element 1 the "left lung" (label 2).
        let lung_of = [1u8, 2];
        let geometry = VolumeGeometry::axis_aligned([3, 1, 1], [10.0; 3], [5.0, 5.0, 5.0]);
        // Voxel centres at x = 5, 15, 25 mm; the last is outside the mesh but labelled left.
        let lungs = Volume::from_data(geometry, vec![1u8, 1, 2]).unwrap();
        let sampler = FieldSampler::new(&lungs, &mesh, &lung_of, FieldGrid::Ct).unwrap();
        assert_eq!(sampler.extrapolated_voxels, 2);
        let moved: Vec<V3> = mesh
            .rest_positions_m
            .iter()
            .map(|x| x + V3::new(x.x, 0.0, 0.0) * 0.1)
            .collect();
        let mut field = vec![[0.0f32; 3]; 3];
        sampler.sample_mm(&mesh, &moved, &mut field);
        // Voxel 1 (x = 15 mm, label 1) lies in element 1 but is the right lung's: clamped to
        // element 0's face at x = 10 mm → 1 mm. Voxel 2 clamps to x = 20 mm → 2 mm.
        assert!((field[0][0] - 0.5).abs() < 1e-5, "{field:?}");
        assert!((field[1][0] - 1.0).abs() < 1e-5, "{field:?}");
        assert!((field[2][0] - 2.0).abs() < 1e-5, "{field:?}");
    }
}
