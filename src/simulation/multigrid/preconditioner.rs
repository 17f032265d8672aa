//! The multigrid preconditioner: the hierarchy built level by level, the V-cycle, and the
//! coarsest level's dense solve.

use nalgebra::{DMatrix, Matrix3};
use rayon::prelude::*;

use super::coarsen::coarsen;
use super::lattice::Lattice;
use super::level::Level;
use super::NODE_TASK;
use crate::math::V3;
use crate::model::HexMesh;
use crate::simulation::linalg::{nodes, nodes_mut};

/// Dense LU of the coarsest level, with a tiny diagonal lift so a singular operator
/// (a mechanism) still factors; the outer Krylov method absorbs the difference.
fn coarse_factor(level: &Level) -> nalgebra::LU<f64, nalgebra::Dyn, nalgebra::Dyn> {
    let dense = level.dense();
    let lift = 1e-12 * dense.diagonal().amax().max(f64::MIN_POSITIVE);
    let n = dense.nrows();
    (dense + DMatrix::identity(n, n) * lift).lu()
}

/// Size and measured cost of one multigrid level.
#[derive(Debug, Clone, serde::Serialize)]
pub struct LevelCost {
    /// Nodes of the level.
    pub nodes: usize,
    /// Cells (elements) of the level.
    pub cells: usize,
    /// Distinct 24 × 24 cell matrices stored (0 on the fine level, applied through springs).
    pub distinct_matrices: usize,
    /// Fraction of the nodes whose product is a 27-point stencil (fine level; else 0).
    pub stencil_fraction: f64,
    /// Median wall time of one operator product, milliseconds.
    pub product_ms: f64,
}

/// A V-cycle preconditioner for the small-strain stiffness of a lattice mesh.
pub struct Multigrid {
    pub(super) levels: Vec<Level>,
    coarse_lu: nalgebra::LU<f64, nalgebra::Dyn, nalgebra::Dyn>,
    degree: usize,
    scratch: Vec<Vec<Vec<f64>>>,
}

/// Stop coarsening when a level has at most this many nodes (dense LU below).
const COARSEST_NODES: usize = 150;

impl Multigrid {
    /// Builds the hierarchy; `projector[n]` is the constraint projection of node n (None = free).
    pub fn new(mesh: &HexMesh, lattice: &Lattice, projector: Vec<Option<Matrix3<f64>>>) -> Self {
        let mut levels = vec![Level::fine(mesh, lattice, projector)];
        // Lattice point and body of each cell and node: coarse entities are keyed by both.
        let mut node_ijk: Vec<[u32; 4]> = lattice
            .node
            .iter()
            .zip(&lattice.body)
            .map(|(p, &b)| [p[0], p[1], p[2], b])
            .collect();
        let mut cells: Vec<[u32; 4]> = lattice
            .cell
            .iter()
            .zip(&mesh.elements)
            .map(|(p, corners)| [p[0], p[1], p[2], lattice.body[corners[0] as usize]])
            .collect();
        while levels.last().is_some_and(|l| l.n_nodes > COARSEST_NODES) {
            let fine = levels.last_mut().expect("non-empty");
            let (coarse, c_cells, c_nodes) = coarsen(fine, &cells, &node_ijk);
            if coarse.n_nodes >= fine.n_nodes {
                break;
            }
            levels.push(coarse);
            cells = c_cells;
            node_ijk = c_nodes;
        }
        let coarse_lu = coarse_factor(levels.last().expect("non-empty"));
        let scratch = levels
            .iter()
            .map(|l| (0..6).map(|_| vec![0.0; 3 * l.n_nodes]).collect())
            .collect();
        Multigrid {
            levels,
            coarse_lu,
            degree: 4,
            scratch,
        }
    }

    /// Sets the pseudo-transient shift σ (operator K + σ·M on every level) and refactors.
    pub fn set_shift(&mut self, shift: f64) {
        for l in &mut self.levels {
            l.shift = shift;
            l.update_diag_inv();
        }
        self.coarse_lu = coarse_factor(self.levels.last().expect("non-empty"));
    }

    /// Chebyshev smoothing steps before and after each coarse correction (4 by default).
    pub fn set_smoothing_degree(&mut self, degree: usize) {
        self.degree = degree;
    }

    /// Number of levels, the fine one included.
    pub fn level_count(&self) -> usize {
        self.levels.len()
    }

    /// Nodes per level, finest first.
    pub fn level_sizes(&self) -> Vec<usize> {
        self.levels.iter().map(|l| l.n_nodes).collect()
    }

    /// Per level: (nodes, cells, distinct cell matrices, median ms of one operator product over
    /// `repeats`): the preconditioner's cost model.
    pub fn profile(&self, repeats: usize) -> Vec<LevelCost> {
        self.levels
            .iter()
            .map(|l| {
                let x: Vec<f64> = (0..3 * l.n_nodes).map(|i| (i as f64).sin()).collect();
                let mut y = vec![0.0; x.len()];
                let mut times: Vec<f64> = (0..repeats.max(1))
                    .map(|_| {
                        let t = std::time::Instant::now();
                        l.apply(&x, &mut y);
                        t.elapsed().as_secs_f64() * 1e3
                    })
                    .collect();
                times.sort_by(f64::total_cmp);
                LevelCost {
                    nodes: l.n_nodes,
                    cells: l.elements.len(),
                    distinct_matrices: if l.springs.is_empty() {
                        l.matrices.len()
                    } else {
                        0
                    },
                    stencil_fraction: l.stencil.as_ref().map_or(0.0, |s| s.coverage()),
                    product_ms: times[times.len() / 2],
                }
            })
            .collect()
    }

    /// y = A·x with the fine level's operator (projected stiffness plus shift, identity on the
    /// constrained directions): the operator the V-cycle approximately inverts.
    pub fn apply_operator(&self, x: &[f64], y: &mut [f64]) {
        self.levels[0].apply(x, y);
    }

    /// z ≈ A⁻¹·r by one V-cycle.
    pub fn apply(&mut self, r: &[f64], z: &mut [f64]) {
        self.vcycle(0, r, z);
    }

    /// Solves A·x ≈ b on level `l`: smoothing, coarse correction from level l + 1, smoothing
    /// (the coarsest level by its dense LU).
    fn vcycle(&mut self, l: usize, b: &[f64], x: &mut [f64]) {
        x.iter_mut().for_each(|v| *v = 0.0);
        if l + 1 == self.levels.len() {
            let sol = self
                .coarse_lu
                .solve(&nalgebra::DVector::from_column_slice(b))
                .unwrap_or_else(|| nalgebra::DVector::zeros(b.len()));
            x.copy_from_slice(sol.as_slice());
            if !self.levels[l].constrained.is_empty() {
                self.levels[l].project(x);
            }
            return;
        }
        let mut scratch = std::mem::take(&mut self.scratch[l]);
        let level = &self.levels[l];
        level.smooth(b, x, true, self.degree, &mut scratch[..3]);
        // Residual, projected and restricted in one pass. The coarse right-hand side and
        // solution live in the coarse level's spare scratch vectors (no allocation per cycle).
        let r = &mut scratch[0];
        level.apply(x, r);
        let mut rc = std::mem::take(&mut self.scratch[l + 1][3]);
        let mut xc = std::mem::take(&mut self.scratch[l + 1][5]);
        rc.fill(0.0);
        {
            let (rcn, rn, bn) = (nodes_mut(&mut rc), nodes(r), nodes(b));
            for (n, row) in level.prolong.iter().enumerate() {
                let rn = level.project_node(n, bn[n] - rn[n]);
                for &(c, w) in row {
                    if w != 0.0 {
                        rcn[c as usize] += rn * w;
                    }
                }
            }
        }
        self.vcycle(l + 1, &rc, &mut xc);
        let level = &self.levels[l];
        {
            // Prolongation, projection and correction in one parallel pass.
            let xcn = nodes(&xc);
            let xn = nodes_mut(x);
            xn.par_chunks_mut(NODE_TASK)
                .zip(level.prolong.par_chunks(NODE_TASK))
                .enumerate()
                .for_each(|(t, (x, rows))| {
                    for (i, (x, row)) in x.iter_mut().zip(rows).enumerate() {
                        let c: V3 = row.iter().map(|&(i, w)| xcn[i as usize] * w).sum();
                        *x += level.project_node(t * NODE_TASK + i, c);
                    }
                });
        }
        self.scratch[l + 1][3] = rc;
        self.scratch[l + 1][5] = xc;
        level.smooth(b, x, false, self.degree, &mut scratch[..3]);
        self.scratch[l] = scratch;
    }
}
