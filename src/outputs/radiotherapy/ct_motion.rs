//! The motion of one output instant over the whole CT, both ways, sampled on a coarse grid:
//! the lungs' own motion inside them, a smooth decaying extension outside, and its inverse.
//!
//! Grid: the CT's own axes, one node every [`CtMotionSettings::grid_spacing_mm`] (4 mm by
//! default: 126 × 126 × 72 nodes, 13 MB per direction, for a 512² × 141 chest CT, against
//! 440 MB for a vector per CT voxel), plus one node of margin on every side.
//!
//! Forward map u(x) ("the tissue at x is at x + u(x)") at each node:
//! * inside an element of the lung mesh: the mesh's own trilinear interpolation of its node
//!   displacements, exactly what the displacement fields hold;
//! * outside: the displacement of the nearest lung node times a Gaussian decay
//!   exp(−d²/2L²) of the distance d to it, with L the decay length (15 mm by default) for the
//!   chest wall and mediastinum, and up to [`ABDOMEN_DECAY_FACTOR`] × L for nodes below the
//!   lungs (the weight goes with the square of the cosine between "down" and the direction
//!   from the nearest lung node): the liver and stomach under the diaphragm follow the
//!   diaphragm far more than the ribs follow the lung sliding along them. Then a few Jacobi
//!   passes average each outside node with its six neighbours (lung nodes held fixed), which
//!   smooths the jumps where the nearest lung node switches (between the lungs) and leaves
//!   no seam at the pleura: the extension starts at the lung surface's own value.
//!
//! Inverse map: at every node y, the source x with x + u(x) = y by fixed-point iteration
//! x ← y − u(x) (u trilinear on the grid), falling back to a damped step where the plain
//! one does not contract. Between nodes the resampler interpolates it, then takes one more
//! fixed-point step per voxel. Its residual |x + u(x) − y| is reported at the nodes and
//! between them (cell centres, where the interpolated inverse is furthest from a solved
//! node, with the resampler's own step), as
//! the largest value and the 99th percentile over lung tissue; nodes that did not converge
//! are counted, never hidden.

use rayon::prelude::*;
use serde::Serialize;

use super::mesh_motion::MeshLattice;
use super::PhaseMotion;
use crate::math::V3;
use crate::model::HexMesh;
use crate::outputs::displacement_field::{corner_weight, weights, CORNER_BITS};
use crate::volume::VolumeGeometry;
use crate::{Error, Result};

/// Default spacing of the motion grid, mm.
pub const DEFAULT_GRID_SPACING_MM: f64 = 4.0;
/// Default decay length of the motion outside the lungs, mm (the Gaussian's σ).
pub const DEFAULT_DECAY_LENGTH_MM: f64 = 15.0;
/// How much longer the decay is straight below the lungs (abdomen under the diaphragm).
pub const ABDOMEN_DECAY_FACTOR: f64 = 5.0;
/// Largest number of motion-grid nodes (about 1.2 GB of working memory at the limit).
const MAX_GRID_NODES: usize = 40_000_000;
/// A node is converged when its residual is below this, mm.
const INVERSE_TOLERANCE_MM: f64 = 0.01;
/// Plain fixed-point iterations before the damped fallback.
const PLAIN_ITERATIONS: usize = 40;
/// Damped iterations (step ½) where the plain ones did not converge.
const DAMPED_ITERATIONS: usize = 200;

/// How the motion over the CT is sampled and extended.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct CtMotionSettings {
    /// Spacing of the motion grid, mm.
    pub grid_spacing_mm: f64,
    /// Decay length (Gaussian σ) of the motion outside the lungs, mm.
    pub decay_length_mm: f64,
    /// Jacobi smoothing passes over the nodes outside the lungs.
    pub smoothing_passes: usize,
}

impl Default for CtMotionSettings {
    fn default() -> Self {
        CtMotionSettings {
            grid_spacing_mm: DEFAULT_GRID_SPACING_MM,
            decay_length_mm: DEFAULT_DECAY_LENGTH_MM,
            smoothing_passes: 6,
        }
    }
}

/// The motion grid laid over a CT: where its nodes are, which lie in a lung element (with
/// their corner weights) and, for the others, the nearest lung node and the decay weight.
/// The same for every instant of a run: built once.
pub struct CtMotionLayout {
    grid: CoarseGrid,
    /// Nodes inside the mesh, their element and its corner weights.
    lung_nodes: Vec<LungNode>,
    /// Per node: whether it lies in the lungs.
    in_lung: Vec<bool>,
    /// Per node outside the lungs: the nearest lung node (`u32::MAX`: none).
    nearest_lung: Vec<u32>,
    /// Per node outside the lungs: the decay weight of the nearest lung node's motion.
    decay: Vec<f32>,
    settings: CtMotionSettings,
}

/// A grid node in a lung element.
struct LungNode {
    node: u32,
    element: u32,
    weights: [f32; 8],
}

/// The motion grid's nodes: the CT's axes, a node every `step_voxels` CT voxels, one node
/// of margin before the CT's first voxel.
#[derive(Debug, Clone, Copy)]
struct CoarseGrid {
    ct: VolumeGeometry,
    step_voxels: [f64; 3],
    dims: [usize; 3],
}

impl CoarseGrid {
    fn new(ct: &VolumeGeometry, spacing_mm: f64) -> Result<Self> {
        let step_voxels = [0, 1, 2].map(|a| spacing_mm / ct.spacing_mm[a]);
        // Nodes from index −1 to past the CT's last voxel, plus one.
        let dims = [0, 1, 2].map(|a| {
            let span = (ct.dims[a].max(1) - 1) as f64 / step_voxels[a];
            span.ceil() as usize + 3
        });
        let nodes = dims.iter().try_fold(1usize, |n, &d| n.checked_mul(d));
        if nodes.is_none_or(|n| n > MAX_GRID_NODES) {
            return Err(Error::argument(
                "motion grid",
                format!(
                    "a {spacing_mm} mm grid over a CT of {:?} voxels of {:?} mm needs {dims:?} \
                     nodes, more than {MAX_GRID_NODES}: use a coarser grid",
                    ct.dims, ct.spacing_mm
                ),
            ));
        }
        Ok(CoarseGrid {
            ct: *ct,
            step_voxels,
            dims,
        })
    }

    fn node_count(&self) -> usize {
        self.dims.iter().product()
    }

    fn index(&self, a: usize, b: usize, c: usize) -> usize {
        a + self.dims[0] * (b + self.dims[1] * c)
    }

    fn node_of(&self, n: usize) -> [usize; 3] {
        let a = n % self.dims[0];
        let b = (n / self.dims[0]) % self.dims[1];
        [a, b, n / (self.dims[0] * self.dims[1])]
    }

    /// LPS position of grid point `g` (grid index units, fractional allowed), mm.
    fn lps_mm(&self, g: V3) -> V3 {
        let ct_index = V3::new(
            (g.x - 1.0) * self.step_voxels[0],
            (g.y - 1.0) * self.step_voxels[1],
            (g.z - 1.0) * self.step_voxels[2],
        );
        self.ct.voxel_to_lps_mm(ct_index)
    }

    /// Grid index units of LPS point `p_mm`.
    fn grid_of(&self, p_mm: V3) -> V3 {
        let v = self.ct.lps_mm_to_voxel(p_mm);
        V3::new(
            v.x / self.step_voxels[0] + 1.0,
            v.y / self.step_voxels[1] + 1.0,
            v.z / self.step_voxels[2] + 1.0,
        )
    }

    /// Trilinear interpolation of `field` at grid point `g`, clamped to the grid.
    fn interpolate(&self, field: &[[f32; 3]], g: V3) -> V3 {
        let mut base = [0usize; 3];
        let mut t = [0.0f64; 3];
        for a in 0..3 {
            let x = g[a].clamp(0.0, (self.dims[a] - 1) as f64);
            let i = (x.floor() as usize).min(self.dims[a].saturating_sub(2));
            base[a] = i;
            t[a] = x - i as f64;
        }
        let mut out = V3::zeros();
        for (c, bits) in CORNER_BITS.iter().enumerate() {
            let w = corner_weight(V3::from(t), c);
            if w == 0.0 {
                continue;
            }
            let n = self.index(
                base[0] + usize::from(bits[0]),
                base[1] + usize::from(bits[1]),
                base[2] + usize::from(bits[2]),
            );
            let v = field[n];
            out += V3::new(f64::from(v[0]), f64::from(v[1]), f64::from(v[2])) * w;
        }
        out
    }

    /// The node nearest to grid point `g`.
    fn nearest_node(&self, g: V3) -> usize {
        let i = |a: usize| (g[a].round().max(0.0) as usize).min(self.dims[a] - 1);
        self.index(i(0), i(1), i(2))
    }
}

/// The element holding `p_m` in `lattice` and its eight corner weights (VTK order).
fn locate(lattice: &MeshLattice, p_m: V3) -> Option<(u32, [f32; 8])> {
    let (e, local) = lattice.locate(p_m)?;
    Some((e, weights(local)))
}

impl CtMotionLayout {
    /// Lays the motion grid over the CT of `ct_geometry` and locates its nodes in `mesh`
    /// (rest positions, metres, LPS).
    pub fn new(
        ct_geometry: &VolumeGeometry,
        mesh: &HexMesh,
        settings: CtMotionSettings,
    ) -> Result<Self> {
        check_settings(&settings)?;
        ct_geometry.validate("the CT under the motion grid")?;
        let grid = CoarseGrid::new(ct_geometry, settings.grid_spacing_mm)?;
        let lattice = MeshLattice::of(mesh)?;
        let located: Vec<Option<(u32, [f32; 8])>> = (0..grid.node_count())
            .into_par_iter()
            .map(|n| {
                let [a, b, c] = grid.node_of(n);
                let p_mm = grid.lps_mm(V3::new(a as f64, b as f64, c as f64));
                locate(&lattice, p_mm * 1e-3)
            })
            .collect();
        let in_lung: Vec<bool> = located.iter().map(Option::is_some).collect();
        let lung_nodes: Vec<LungNode> = located
            .iter()
            .enumerate()
            .filter_map(|(n, l)| {
                l.map(|(element, weights)| LungNode {
                    node: n as u32,
                    element,
                    weights,
                })
            })
            .collect();
        drop(located);
        let nearest_lung = nearest_seeds(&grid, &in_lung);
        let decay = decay_weights(&grid, &in_lung, &nearest_lung, &settings);
        Ok(CtMotionLayout {
            grid,
            lung_nodes,
            in_lung,
            nearest_lung,
            decay,
            settings,
        })
    }

    /// The settings it was laid with.
    pub fn settings(&self) -> &CtMotionSettings {
        &self.settings
    }

    /// Nodes of the motion grid along i, j, k.
    pub fn grid_dims(&self) -> [usize; 3] {
        self.grid.dims
    }

    /// Nodes of the motion grid that lie in the lungs.
    pub fn lung_node_count(&self) -> usize {
        self.lung_nodes.len()
    }

    /// Bytes the layout holds, and each instant's motion will hold besides.
    pub fn approximate_bytes(&self) -> (u64, u64) {
        let n = self.grid.node_count() as u64;
        let layout = n * (1 + 4 + 4) + self.lung_nodes.len() as u64 * 40;
        (layout, n * 24)
    }

    /// The motion of the instant whose mesh nodes are at `positions_m` (metres, LPS, one per
    /// node of the mesh the layout was built on).
    pub fn motion(&self, mesh: &HexMesh, positions_m: &[V3]) -> Result<CtGridMotion> {
        if positions_m.len() != mesh.rest_positions_m.len() {
            return Err(Error::argument(
                "motion over the CT",
                format!(
                    "{} node positions for a mesh of {} nodes",
                    positions_m.len(),
                    mesh.rest_positions_m.len()
                ),
            ));
        }
        let forward = self.forward_field(mesh, positions_m);
        let (inverse, report) = invert(&self.grid, &forward, &self.in_lung);
        Ok(CtGridMotion {
            grid: self.grid,
            forward_mm: forward,
            inverse_mm: inverse,
            report,
        })
    }

    /// u at every node: the mesh's inside, the decayed and smoothed extension outside.
    fn forward_field(&self, mesh: &HexMesh, positions_m: &[V3]) -> Vec<[f32; 3]> {
        let mut u = vec![[0.0f32; 3]; self.grid.node_count()];
        let rest = &mesh.rest_positions_m;
        for l in &self.lung_nodes {
            let mut d = V3::zeros();
            for (c, &n) in mesh.elements[l.element as usize].iter().enumerate() {
                let n = n as usize;
                d += (positions_m[n] - rest[n]) * f64::from(l.weights[c]);
            }
            let d = d * 1e3;
            u[l.node as usize] = [d.x as f32, d.y as f32, d.z as f32];
        }
        let lung_u = u.clone();
        u.par_iter_mut().enumerate().for_each(|(n, v)| {
            let s = self.nearest_lung[n];
            if !self.in_lung[n] && s != u32::MAX {
                let w = self.decay[n];
                *v = lung_u[s as usize].map(|x| x * w);
            }
        });
        drop(lung_u);
        smooth_outside(
            &self.grid,
            &self.in_lung,
            &mut u,
            self.settings.smoothing_passes,
        );
        u
    }
}

/// Builds the motion over the CT for one instant in one call (the layout is rebuilt: runs
/// with several instants build a [`CtMotionLayout`] once and call
/// [`CtMotionLayout::motion`]).
pub fn ct_grid_motion(
    ct_geometry: &VolumeGeometry,
    mesh: &HexMesh,
    positions_m: &[V3],
    settings: CtMotionSettings,
) -> Result<CtGridMotion> {
    CtMotionLayout::new(ct_geometry, mesh, settings)?.motion(mesh, positions_m)
}

fn check_settings(s: &CtMotionSettings) -> Result<()> {
    if !(s.grid_spacing_mm.is_finite() && (0.5..=20.0).contains(&s.grid_spacing_mm)) {
        return Err(Error::argument(
            "motion grid spacing",
            format!("{} mm is not within 0.5–20 mm", s.grid_spacing_mm),
        ));
    }
    if !(s.decay_length_mm.is_finite() && (1.0..=500.0).contains(&s.decay_length_mm)) {
        return Err(Error::argument(
            "decay length outside the lungs",
            format!("{} mm is not within 1–500 mm", s.decay_length_mm),
        ));
    }
    if s.smoothing_passes > 100 {
        return Err(Error::argument(
            "smoothing passes outside the lungs",
            format!("{} is more than 100", s.smoothing_passes),
        ));
    }
    Ok(())
}

/// For every node, the nearest seed (lung node) by vector propagation: raster passes
/// forward and backward, each node taking the nearest of its visited neighbours' seeds.
/// Exact on most nodes and within a fraction of a node spacing elsewhere, in O(nodes).
fn nearest_seeds(grid: &CoarseGrid, seeds: &[bool]) -> Vec<u32> {
    let mut nearest: Vec<u32> = seeds
        .iter()
        .enumerate()
        .map(|(n, &s)| if s { n as u32 } else { u32::MAX })
        .collect();
    if !seeds.iter().any(|&s| s) {
        return nearest;
    }
    let [nx, ny, nz] = grid.dims.map(|d| d as i64);
    let offsets: Vec<[i64; 3]> = (-1..=1)
        .flat_map(|dz| (-1..=1).flat_map(move |dy| (-1..=1).map(move |dx| [dx, dy, dz])))
        .filter(|&[dx, dy, dz]| (dz, dy, dx) < (0, 0, 0))
        .collect();
    let distance2 = |n: i64, s: u32| {
        let [a, b, c] = grid.node_of(n as usize).map(|v| v as i64);
        let [sa, sb, sc] = grid.node_of(s as usize).map(|v| v as i64);
        (a - sa).pow(2) + (b - sb).pow(2) + (c - sc).pow(2)
    };
    for _round in 0..2 {
        for backward in [false, true] {
            let sign = if backward { -1 } else { 1 };
            for step in 0..nx * ny * nz {
                let n = if backward {
                    nx * ny * nz - 1 - step
                } else {
                    step
                };
                let (a, b, c) = (n % nx, (n / nx) % ny, n / (nx * ny));
                let mut best = nearest[n as usize];
                let mut best_d = if best == u32::MAX {
                    i64::MAX
                } else {
                    distance2(n, best)
                };
                for o in &offsets {
                    let (a2, b2, c2) = (a + sign * o[0], b + sign * o[1], c + sign * o[2]);
                    if a2 < 0 || b2 < 0 || c2 < 0 || a2 >= nx || b2 >= ny || c2 >= nz {
                        continue;
                    }
                    let s = nearest[(a2 + nx * (b2 + ny * c2)) as usize];
                    if s != u32::MAX {
                        let d = distance2(n, s);
                        if d < best_d {
                            best = s;
                            best_d = d;
                        }
                    }
                }
                nearest[n as usize] = best;
            }
        }
    }
    nearest
}

/// The decay weight of each node outside the lungs: exp(−d²/2L²), L lengthened below the
/// lungs by up to [`ABDOMEN_DECAY_FACTOR`] with the squared cosine of the downward angle.
fn decay_weights(
    grid: &CoarseGrid,
    in_lung: &[bool],
    nearest: &[u32],
    settings: &CtMotionSettings,
) -> Vec<f32> {
    (0..grid.node_count())
        .into_par_iter()
        .map(|n| {
            let s = nearest[n];
            if in_lung[n] || s == u32::MAX {
                return 1.0;
            }
            let at = |m: usize| {
                let [a, b, c] = grid.node_of(m);
                grid.lps_mm(V3::new(a as f64, b as f64, c as f64))
            };
            let v = at(n) - at(s as usize);
            let d = v.norm();
            // LPS +z is superior: a node below its nearest lung node has v.z < 0.
            let down = if d > 0.0 { (-v.z / d).max(0.0) } else { 0.0 };
            let length =
                settings.decay_length_mm * (1.0 + (ABDOMEN_DECAY_FACTOR - 1.0) * down * down);
            (-(d * d) / (2.0 * length * length)).exp() as f32
        })
        .collect()
}

/// Jacobi passes averaging each node outside the lungs with its six neighbours (clamped at
/// the grid's border); lung nodes keep their values.
fn smooth_outside(grid: &CoarseGrid, in_lung: &[bool], u: &mut Vec<[f32; 3]>, passes: usize) {
    let [nx, ny, nz] = grid.dims;
    let mut next = u.clone();
    for _ in 0..passes {
        next.par_chunks_mut(nx * ny)
            .enumerate()
            .for_each(|(c, slice)| {
                for b in 0..ny {
                    for a in 0..nx {
                        let n = grid.index(a, b, c);
                        if in_lung[n] {
                            slice[a + nx * b] = u[n];
                            continue;
                        }
                        let neighbours = [
                            grid.index(a.saturating_sub(1), b, c),
                            grid.index((a + 1).min(nx - 1), b, c),
                            grid.index(a, b.saturating_sub(1), c),
                            grid.index(a, (b + 1).min(ny - 1), c),
                            grid.index(a, b, c.saturating_sub(1)),
                            grid.index(a, b, (c + 1).min(nz - 1)),
                        ];
                        let mut sum = [0.0f32; 3];
                        for m in neighbours {
                            for (s, v) in sum.iter_mut().zip(u[m]) {
                                *s += v;
                            }
                        }
                        slice[a + nx * b] = sum.map(|s| s / 6.0);
                    }
                }
            });
        std::mem::swap(u, &mut next);
    }
}

/// How well the inverse map undoes the forward one.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct InverseReport {
    /// Largest |x + u(x) − y| at the grid nodes whose source lies in the lungs, mm.
    pub lung_node_max_mm: f64,
    /// Its 99th percentile, mm.
    pub lung_node_p99_mm: f64,
    /// Largest residual at any node, mm.
    pub all_node_max_mm: f64,
    /// Largest residual of the interpolated maps at the cell centres whose source lies in the
    /// lungs (between nodes: what a resampler sees), mm.
    pub lung_cell_max_mm: f64,
    /// Its 99th percentile, mm.
    pub lung_cell_p99_mm: f64,
    /// Nodes whose residual stayed above the tolerance (0.01 mm) after all iterations.
    pub unconverged_nodes: usize,
    /// Nodes solved with the damped fallback.
    pub damped_nodes: usize,
}

/// Largest value and 99th percentile of `values` (0 for none).
fn max_and_p99(mut values: Vec<f32>) -> (f64, f64) {
    if values.is_empty() {
        return (0.0, 0.0);
    }
    let max = values.iter().copied().fold(0.0f32, f32::max);
    let k = ((values.len() - 1) as f64 * 0.99).round() as usize;
    let (_, p99, _) = values.select_nth_unstable_by(k, f32::total_cmp);
    (f64::from(max), f64::from(*p99))
}

/// Solves x + u(x) = y at every node; returns the inverse displacement x − y per node.
fn invert(
    grid: &CoarseGrid,
    forward: &[[f32; 3]],
    in_lung: &[bool],
) -> (Vec<[f32; 3]>, InverseReport) {
    let solved: Vec<([f32; 3], f32, bool, bool)> = (0..grid.node_count())
        .into_par_iter()
        .map(|n| {
            let [a, b, c] = grid.node_of(n);
            let y = V3::new(a as f64, b as f64, c as f64);
            let (x, residual, damped) = solve_source(grid, forward, grid.lps_mm(y));
            let lung = in_lung[grid.nearest_node(grid.grid_of(x))];
            let v = x - grid.lps_mm(y);
            (
                [v.x as f32, v.y as f32, v.z as f32],
                residual as f32,
                lung,
                damped,
            )
        })
        .collect();
    let inverse: Vec<[f32; 3]> = solved.iter().map(|s| s.0).collect();
    let unconverged_nodes = solved
        .iter()
        .filter(|s| f64::from(s.1) > INVERSE_TOLERANCE_MM)
        .count();
    let damped_nodes = solved.iter().filter(|s| s.3).count();
    let all_node_max_mm = solved.iter().map(|s| f64::from(s.1)).fold(0.0, f64::max);
    let (lung_node_max_mm, lung_node_p99_mm) =
        max_and_p99(solved.iter().filter(|s| s.2).map(|s| s.1).collect());
    drop(solved);
    let cells = cell_centre_residuals(grid, forward, &inverse, in_lung);
    let (lung_cell_max_mm, lung_cell_p99_mm) = max_and_p99(cells);
    (
        inverse,
        InverseReport {
            lung_node_max_mm,
            lung_node_p99_mm,
            all_node_max_mm,
            lung_cell_max_mm,
            lung_cell_p99_mm,
            unconverged_nodes,
            damped_nodes,
        },
    )
}

/// The source x of `y_mm` (LPS), its residual, and whether the damped fallback was needed.
fn solve_source(grid: &CoarseGrid, forward: &[[f32; 3]], y_mm: V3) -> (V3, f64, bool) {
    let residual = |x: V3| x + grid.interpolate(forward, grid.grid_of(x)) - y_mm;
    let mut x = y_mm - grid.interpolate(forward, grid.grid_of(y_mm));
    let mut r = residual(x);
    for _ in 0..PLAIN_ITERATIONS {
        if r.norm() <= INVERSE_TOLERANCE_MM * 0.1 {
            return (x, r.norm(), false);
        }
        x -= r;
        r = residual(x);
    }
    if r.norm() <= INVERSE_TOLERANCE_MM {
        return (x, r.norm(), false);
    }
    // Where u's gradient exceeds 1 the plain step overshoots; half steps converge wherever
    // the map does not fold. Restart from the better of y − u(y) and where the plain
    // iteration ended.
    let start = y_mm - grid.interpolate(forward, grid.grid_of(y_mm));
    if residual(start).norm() < r.norm() {
        x = start;
        r = residual(x);
    }
    for _ in 0..DAMPED_ITERATIONS {
        if r.norm() <= INVERSE_TOLERANCE_MM * 0.1 {
            break;
        }
        x -= r * 0.5;
        r = residual(x);
    }
    (x, r.norm(), true)
}

/// The source of `y_mm` the resampler uses: the interpolated inverse, then one fixed-point
/// step x ← y − u(x) on the forward grid. Interpolating the inverse between nodes errs where
/// the forward map bends (the pleura, where the extension takes over); the one step shrinks
/// that error by the displacement's gradient (about 0.1–0.3) for one more interpolation.
fn refined_source(grid: &CoarseGrid, forward: &[[f32; 3]], inverse: &[[f32; 3]], y_mm: V3) -> V3 {
    let g = grid.grid_of(y_mm);
    let x0 = y_mm + grid.interpolate(inverse, g);
    y_mm - grid.interpolate(forward, grid.grid_of(x0))
}

/// Residuals of the resampler's source map ([`refined_source`]) then the forward map at
/// every cell centre whose source lies in the lungs.
fn cell_centre_residuals(
    grid: &CoarseGrid,
    forward: &[[f32; 3]],
    inverse: &[[f32; 3]],
    in_lung: &[bool],
) -> Vec<f32> {
    let [nx, ny, nz] = grid.dims;
    (0..nz.saturating_sub(1))
        .into_par_iter()
        .flat_map_iter(|c| {
            (0..ny - 1).flat_map(move |b| {
                (0..nx - 1).filter_map(move |a| {
                    let g = V3::new(a as f64 + 0.5, b as f64 + 0.5, c as f64 + 0.5);
                    let y = grid.lps_mm(g);
                    let x = refined_source(grid, forward, inverse, y);
                    let gx = grid.grid_of(x);
                    if !in_lung[grid.nearest_node(gx)] {
                        return None;
                    }
                    Some((x + grid.interpolate(forward, gx) - y).norm() as f32)
                })
            })
        })
        .collect()
}

/// One instant's motion over the whole CT, forward and inverse, on the motion grid.
pub struct CtGridMotion {
    grid: CoarseGrid,
    forward_mm: Vec<[f32; 3]>,
    inverse_mm: Vec<[f32; 3]>,
    report: InverseReport,
}

impl CtGridMotion {
    /// How well the inverse undoes the forward map.
    pub fn inverse_report(&self) -> &InverseReport {
        &self.report
    }

    /// The forward displacement u at LPS `rest_lps_mm`, mm.
    pub fn displacement_mm(&self, rest_lps_mm: [f64; 3]) -> [f64; 3] {
        let u = self
            .grid
            .interpolate(&self.forward_mm, self.grid.grid_of(V3::from(rest_lps_mm)));
        u.into()
    }
}

/// The resampler's source map ([`refined_source`]) worked in index units for the CT voxels
/// of one row, for warping a whole CT: the CT and the motion grid share their axes, so LPS
/// never needs to be formed, the interpolated inverse is collapsed once per row to a line of
/// nodes along i, and mm turn into index units by one fixed 3 × 3 map.
#[derive(Debug, Clone, Copy)]
pub struct RowSourceMap {
    grid_dims: [usize; 3],
    step_voxels: [f64; 3],
    /// LPS mm → motion-grid index units (D^T over the grid spacing per axis).
    mm_to_grid: [[f64; 3]; 3],
    /// LPS mm → CT voxel index units (D^T over the CT spacing per axis).
    mm_to_voxel: [[f64; 3]; 3],
}

/// The cell of a clamped coordinate `x` along an axis of `n` ≥ 2 nodes, and the fraction
/// into it (as [`CoarseGrid::interpolate`] clamps).
#[inline]
fn cell_of(x: f64, n: usize) -> (usize, f64) {
    let x = x.clamp(0.0, (n - 1) as f64);
    let i = (x.floor() as usize).min(n - 2);
    (i, x - i as f64)
}

/// `m · v` for a row-major 3 × 3 `m`.
#[inline]
fn apply(m: &[[f64; 3]; 3], v: [f64; 3]) -> [f64; 3] {
    m.map(|r| r[0] * v[0] + r[1] * v[1] + r[2] * v[2])
}

/// Clamped trilinear interpolation of a node field (i fastest) at grid point `g`, in the
/// lerp form (the same value as [`CoarseGrid::interpolate`] up to rounding, at a fraction of
/// its cost: this runs twice per CT voxel).
#[inline]
fn interpolate_nodes(field: &[[f32; 3]], dims: [usize; 3], g: [f64; 3]) -> [f64; 3] {
    let (a, ta) = cell_of(g[0], dims[0]);
    let (b, tb) = cell_of(g[1], dims[1]);
    let (c, tc) = cell_of(g[2], dims[2]);
    let (sy, sz) = (dims[0], dims[0] * dims[1]);
    let n = a + sy * b + sz * c;
    let at = |m: usize, axis: usize| f64::from(field[m][axis]);
    let lerp = |p: f64, q: f64, t: f64| p + (q - p) * t;
    [0, 1, 2].map(|x| {
        let l00 = lerp(at(n, x), at(n + 1, x), ta);
        let l10 = lerp(at(n + sy, x), at(n + sy + 1, x), ta);
        let l01 = lerp(at(n + sz, x), at(n + sz + 1, x), ta);
        let l11 = lerp(at(n + sy + sz, x), at(n + sy + sz + 1, x), ta);
        lerp(lerp(l00, l10, tb), lerp(l01, l11, tb), tc)
    })
}

impl RowSourceMap {
    /// Nodes of the motion grid along i (the length of the line [`Self::sources_of_row`]
    /// collapses the inverse to).
    pub fn line_len(&self) -> usize {
        self.grid_dims[0]
    }

    /// The sources of the CT voxels (0…, j, k) of one row, in CT voxel index units, into
    /// `sources` (one per voxel of the row); `line` is scratch of [`Self::line_len`] nodes.
    pub fn sources_of_row(
        &self,
        motion: &CtGridMotion,
        j: usize,
        k: usize,
        line: &mut [[f64; 3]],
        sources: &mut [[f64; 3]],
    ) {
        let dims = self.grid_dims;
        let gy = j as f64 / self.step_voxels[1] + 1.0;
        let gz = k as f64 / self.step_voxels[2] + 1.0;
        let (b, tb) = cell_of(gy, dims[1]);
        let (c, tc) = cell_of(gz, dims[2]);
        let inverse = &motion.inverse_mm;
        for (a, node) in line.iter_mut().enumerate() {
            let n = a + dims[0] * (b + dims[1] * c);
            let (sy, sz) = (dims[0], dims[0] * dims[1]);
            *node = [0, 1, 2].map(|x| {
                let at = |m: usize| f64::from(inverse[m][x]);
                let l0 = at(n) + (at(n + sy) - at(n)) * tb;
                let l1 = at(n + sz) + (at(n + sy + sz) - at(n + sz)) * tb;
                l0 + (l1 - l0) * tc
            });
        }
        for (i, source) in sources.iter_mut().enumerate() {
            let gx = i as f64 / self.step_voxels[0] + 1.0;
            let (a, ta) = cell_of(gx, dims[0]);
            let v = [0, 1, 2].map(|x| line[a][x] + (line[a + 1][x] - line[a][x]) * ta);
            let dg = apply(&self.mm_to_grid, v);
            let g0 = [gx + dg[0], gy + dg[1], gz + dg[2]];
            let u = interpolate_nodes(&motion.forward_mm, dims, g0);
            let dv = apply(&self.mm_to_voxel, u);
            *source = [i as f64 - dv[0], j as f64 - dv[1], k as f64 - dv[2]];
        }
    }
}

impl CtGridMotion {
    /// The index-space form of [`PhaseMotion::source_lps_mm`] over the CT the motion was
    /// laid on.
    pub fn row_source_map(&self) -> RowSourceMap {
        let g = &self.grid;
        let d = g.ct.direction();
        let row = |a: usize, per_mm: f64| [d[(0, a)], d[(1, a)], d[(2, a)]].map(|x| x * per_mm);
        RowSourceMap {
            grid_dims: g.dims,
            step_voxels: g.step_voxels,
            mm_to_grid: [0, 1, 2].map(|a| row(a, 1.0 / (g.ct.spacing_mm[a] * g.step_voxels[a]))),
            mm_to_voxel: [0, 1, 2].map(|a| row(a, 1.0 / g.ct.spacing_mm[a])),
        }
    }

    /// The CT grid the motion was laid on.
    pub fn ct_geometry(&self) -> &VolumeGeometry {
        &self.grid.ct
    }
}

impl PhaseMotion for CtGridMotion {
    fn moved_lps_mm(&self, rest_lps_mm: [f64; 3]) -> [f64; 3] {
        let x = V3::from(rest_lps_mm);
        (x + self
            .grid
            .interpolate(&self.forward_mm, self.grid.grid_of(x)))
        .into()
    }

    fn source_lps_mm(&self, moved_lps_mm: [f64; 3]) -> [f64; 3] {
        refined_source(
            &self.grid,
            &self.forward_mm,
            &self.inverse_mm,
            V3::from(moved_lps_mm),
        )
        .into()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn nearest_seeds_find_the_closest_lung_node() {
        let ct = VolumeGeometry::axis_aligned([20, 12, 9], [1.0; 3], [0.0; 3]);
        let grid = CoarseGrid::new(&ct, 1.0).unwrap();
        let mut seeds = vec![false; grid.node_count()];
        let s1 = grid.index(3, 3, 3);
        let s2 = grid.index(17, 9, 7);
        seeds[s1] = true;
        seeds[s2] = true;
        let nearest = nearest_seeds(&grid, &seeds);
        for (n, &found) in nearest.iter().enumerate() {
            let p = grid.node_of(n).map(|v| v as i64);
            let d = |s: usize| {
                let q = grid.node_of(s).map(|v| v as i64);
                (0..3).map(|a| (p[a] - q[a]).pow(2)).sum::<i64>()
            };
            let expected = d(s1).min(d(s2));
            assert_eq!(d(found as usize), expected, "node {p:?}");
        }
    }

    #[test]
    fn the_grid_covers_the_ct_with_a_margin_and_interpolates_linear_fields_exactly() {
        let ct = VolumeGeometry::axis_aligned([50, 40, 30], [0.8, 0.8, 2.5], [-20.0, 5.0, 7.0]);
        let grid = CoarseGrid::new(&ct, 4.0).unwrap();
        let first = grid.lps_mm(V3::zeros());
        assert!(first.x < -20.0 && first.y < 5.0 && first.z < 7.0, "{first}");
        let last = grid.lps_mm(V3::new(
            (grid.dims[0] - 1) as f64,
            (grid.dims[1] - 1) as f64,
            (grid.dims[2] - 1) as f64,
        ));
        let ct_last = ct.voxel_to_lps_mm(V3::new(49.0, 39.0, 29.0));
        assert!((0..3).all(|a| last[a] > ct_last[a]), "{last} vs {ct_last}");
        let field: Vec<[f32; 3]> = (0..grid.node_count())
            .map(|n| {
                let [a, b, c] = grid.node_of(n);
                let p = grid.lps_mm(V3::new(a as f64, b as f64, c as f64));
                [(0.1 * p.x) as f32, (-0.05 * p.z) as f32, 2.0]
            })
            .collect();
        let p = V3::new(-3.3, 20.7, 41.1);
        let u = grid.interpolate(&field, grid.grid_of(p));
        assert!(
            (u.x - 0.1 * p.x).abs() < 1e-4 && (u.y + 0.05 * p.z).abs() < 1e-4,
            "{u}"
        );
    }
}
