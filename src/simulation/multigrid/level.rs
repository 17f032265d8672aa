//! One level of the hierarchy: its cells, matrices and constraints, and the set-up that
//! derives the product's tables, the diagonal blocks and the smoother's spectral bound.

use nalgebra::{DMatrix, Matrix3};

use super::batch::ROW_LINES;
use super::lattice::Lattice;
use super::springs::{LaneSprings, LinearSprings};
use super::stencil::Stencil;
use super::M24;
use crate::math::V3;
use crate::model::HexMesh;
use crate::simulation::forces::ChunkSchedule;
use crate::simulation::lanes::{Lanes, LANES};
use crate::simulation::linalg::{nodes_mut, norm};

/// One level of the hierarchy.
pub(super) struct Level {
    /// Node count.
    pub(super) n_nodes: usize,
    /// The 8 corner nodes of each cell.
    pub(super) elements: Vec<[u32; 8]>,
    /// Per element, index into `matrices`.
    pub(super) matrix_of: Vec<u32>,
    /// Distinct 24 × 24 cell stiffness matrices (world frame).
    pub(super) matrices: Vec<M24>,
    /// Fine level only: the same operators as springs (cheaper than dense 24 × 24 products).
    pub(super) springs: Vec<LinearSprings>,
    /// `springs` replicated across SIMD lanes, one per class.
    pub(super) lane_springs: Vec<LaneSprings>,
    /// World → lattice rotation of the springs (row-major, per lane), `None` when axis-aligned.
    pub(super) rotation: Option<[Lanes; 9]>,
    /// Element colours: elements of one colour share no node (fallback scatter).
    pub(super) colors: Vec<Vec<u32>>,
    /// Race-free chunked scatter plan; `None` when the numbering lacks locality (use `colors`).
    pub(super) schedule: Option<ChunkSchedule>,
    /// Constraint projector per node (fine level only; `None` = free), for set-up.
    pub(super) projector: Vec<Option<Matrix3<f64>>>,
    /// The same, listed sparsely for the hot paths.
    pub(super) constrained: Vec<(u32, Matrix3<f64>)>,
    /// Per node, index into `constrained` or [`FREE`] (empty when nothing is constrained).
    pub(super) slot: Vec<u32>,
    /// Per element, whether a corner is constrained (empty when nothing is constrained).
    pub(super) touches_constraint: Vec<bool>,
    /// Per aligned quad of elements (4q … 4q + 3), whether they are consecutive along one
    /// lattice row, each sharing its +x face with the next (lattice-ordered meshes).
    pub(super) row_quad: Vec<bool>,
    /// Inverses of the shifted, projected diagonal blocks (the Jacobi smoother's D⁻¹).
    pub(super) diag_inv: Vec<Matrix3<f64>>,
    /// Diagonal 3 × 3 blocks of the stiffness, before shift and projection.
    pub(super) diag: Vec<Matrix3<f64>>,
    /// Lumped nodal mass (fine level: the mesh's; coarse: restricted), kg.
    pub(super) mass: Vec<f64>,
    /// Pseudo-transient shift σ: the level's operator is K + σ·M.
    pub(super) shift: f64,
    /// Spectral radius estimate of D⁻¹A, for the Chebyshev interval.
    pub(super) lambda_max: f64,
    /// Interpolation from the next coarser level: up to 8 (coarse node, weight) per node.
    pub(super) prolong: Vec<[(u32, f64); 8]>,
    /// Scratch of the two-phase dense product: each cell's 24 outputs (see `product.rs`).
    pub(super) cell_products: std::sync::Mutex<Vec<[f64; 24]>>,
    /// Dense fine level only: the nodes computed as a 27-point stencil (see `stencil.rs`).
    pub(super) stencil: Option<Stencil>,
}

/// `slot` of an unconstrained node.
pub(super) const FREE: u32 = u32::MAX;

impl Level {
    /// The fine level: the mesh's cells with its classes' matrices and springs, and the
    /// constraint projector of each node (`None` = free).
    pub(super) fn fine(
        mesh: &HexMesh,
        lattice: &Lattice,
        projector: Vec<Option<Matrix3<f64>>>,
    ) -> Level {
        // Element matrices are in the element frame; the products work in world coordinates,
        // so rotate them by the lattice axes (R·K·Rᵀ per corner block) for the diagonal, the
        // Galerkin products and the coarse solve to describe the same operator.
        let mut r24 = M24::zeros();
        for n in 0..8 {
            r24.fixed_view_mut::<3, 3>(3 * n, 3 * n)
                .copy_from(&lattice.axes);
        }
        let class_k: Vec<M24> = mesh
            .classes
            .iter()
            .map(|c| r24 * c.linear_stiffness() * r24.transpose())
            .collect();
        let mut fine = Level {
            n_nodes: mesh.node_count(),
            elements: mesh.elements.clone(),
            matrix_of: mesh.element_class.clone(),
            matrices: class_k,
            // The spring operator carries no hourglass correction: with one, the fine level
            // multiplies by the classes' dense matrices (which do), as the coarse levels do
            // (an hourglass term in the lane kernel, tried, was slower than the dense product).
            springs: if mesh.classes.iter().any(|c| c.hourglass.is_some()) {
                Vec::new()
            } else {
                mesh.classes
                    .iter()
                    .map(|c| LinearSprings::new(c, &lattice.axes))
                    .collect()
            },
            lane_springs: Vec::new(),
            rotation: None,
            colors: mesh.colors.clone(),
            schedule: None,
            constrained: sparse(&projector),
            projector,
            slot: Vec::new(),
            touches_constraint: Vec::new(),
            row_quad: Vec::new(),
            diag_inv: Vec::new(),
            diag: Vec::new(),
            mass: mesh.node_mass_kg.clone(),
            shift: 0.0,
            lambda_max: 0.0,
            prolong: Vec::new(),
            cell_products: Default::default(),
            stencil: None,
        };
        if fine.springs.is_empty() {
            fine.stencil = Stencil::new(
                fine.n_nodes,
                &fine.elements,
                &fine.matrix_of,
                &fine.matrices,
                &fine.projector,
            );
        }
        fine.finish();
        fine
    }

    /// A coarse level of `elements` with `matrices` (indexed by `matrix_of`), element colours
    /// and lumped mass, before its null directions are constrained and its set-up finished.
    pub(super) fn coarse(
        elements: Vec<[u32; 8]>,
        matrix_of: Vec<u32>,
        matrices: Vec<M24>,
        colors: Vec<Vec<u32>>,
        mass: Vec<f64>,
    ) -> Level {
        let n_nodes = mass.len();
        Level {
            n_nodes,
            matrix_of,
            elements,
            matrices,
            springs: Vec::new(),
            lane_springs: Vec::new(),
            rotation: None,
            colors,
            schedule: None,
            projector: vec![None; n_nodes],
            constrained: Vec::new(),
            slot: Vec::new(),
            touches_constraint: Vec::new(),
            row_quad: Vec::new(),
            diag: Vec::new(),
            mass,
            shift: 0.0,
            diag_inv: Vec::new(),
            lambda_max: 0.0,
            prolong: Vec::new(),
            cell_products: Default::default(),
            stencil: None,
        }
    }

    /// Derives the product's lookup tables (lane kernels, constraint slots, scatter schedule)
    /// from the level's elements, springs and constraints.
    pub(super) fn plan(&mut self) {
        self.lane_springs = self.springs.iter().map(LaneSprings::splat).collect();
        self.rotation = self
            .springs
            .first()
            .and_then(|s| s.to_lattice)
            .map(|r| std::array::from_fn(|i| Lanes::splat(r[(i / 3, i % 3)])));
        if self.constrained.is_empty() {
            self.slot = Vec::new();
            self.touches_constraint = Vec::new();
        } else {
            self.slot = vec![FREE; self.n_nodes];
            for (i, (n, _)) in self.constrained.iter().enumerate() {
                self.slot[*n as usize] = i as u32;
            }
            self.touches_constraint = self
                .elements
                .iter()
                .map(|cs| cs.iter().any(|&c| self.slot[c as usize] != FREE))
                .collect();
        }
        self.schedule = ChunkSchedule::new(&self.elements, self.n_nodes);
        self.row_quad = self
            .elements
            .chunks_exact(LANES)
            .map(|q| {
                q.windows(2)
                    .all(|p| ROW_LINES.iter().all(|&(a, b)| p[0][b] == p[1][a]))
            })
            .collect();
    }

    /// Diagonal blocks, their inverses and the spectral radius of D⁻¹A (power iteration).
    pub(super) fn finish(&mut self) {
        self.plan();
        self.diag = self.diagonal_blocks();
        self.update_diag_inv();
        // Power iteration for λmax(D⁻¹A).
        let n3 = 3 * self.n_nodes;
        let mut v: Vec<f64> = (0..n3)
            .map(|i| ((i * 7919) % 1000) as f64 / 1000.0 - 0.5)
            .collect();
        let (mut av, mut z) = (vec![0.0; n3], vec![0.0; n3]);
        let mut lambda = 1.0;
        // 20 steps: with 8 the λmax estimate was low enough to double the Krylov iterations.
        for _ in 0..20 {
            let nv = norm(&v).max(f64::MIN_POSITIVE);
            v.iter_mut().for_each(|x| *x /= nv);
            self.apply(&v, &mut av);
            self.jacobi(&av, &mut z);
            lambda = norm(&z);
            std::mem::swap(&mut v, &mut z);
        }
        self.lambda_max = lambda.max(1e-12);
    }

    /// Diagonal 3 × 3 blocks of the level's stiffness (before shift and projection).
    pub(super) fn diagonal_blocks(&self) -> Vec<Matrix3<f64>> {
        let mut diag = vec![Matrix3::zeros(); self.n_nodes];
        for (e, corners) in self.elements.iter().enumerate() {
            let k = &self.matrices[self.matrix_of[e] as usize];
            for (c, &n) in corners.iter().enumerate() {
                diag[n as usize] += k.fixed_view::<3, 3>(3 * c, 3 * c).into_owned();
            }
        }
        diag
    }

    /// Inverts the shifted, projected diagonal blocks.
    pub(super) fn update_diag_inv(&mut self) {
        self.diag_inv = self
            .diag
            .iter()
            .zip(&self.mass)
            .enumerate()
            .map(|(n, (d, m))| {
                let d = d + Matrix3::identity() * (self.shift * m);
                let d = match self.projector.get(n).copied().flatten() {
                    Some(p) => p * d * p + (Matrix3::identity() - p),
                    None => d,
                };
                d.try_inverse().unwrap_or_else(|| {
                    let s = d.diagonal().amax().max(f64::MIN_POSITIVE);
                    (d + Matrix3::identity() * 1e-9 * s)
                        .try_inverse()
                        .unwrap_or_else(Matrix3::identity)
                })
            })
            .collect();
    }

    /// The level's assembled operator (shift and projections included), for the coarsest
    /// level's dense solve.
    pub(super) fn dense(&self) -> DMatrix<f64> {
        let n3 = 3 * self.n_nodes;
        let mut a = DMatrix::zeros(n3, n3);
        for (e, corners) in self.elements.iter().enumerate() {
            let k = &self.matrices[self.matrix_of[e] as usize];
            for (ci, &ni) in corners.iter().enumerate() {
                for (cj, &nj) in corners.iter().enumerate() {
                    for r in 0..3 {
                        for c in 0..3 {
                            a[(3 * ni as usize + r, 3 * nj as usize + c)] +=
                                k[(3 * ci + r, 3 * cj + c)];
                        }
                    }
                }
            }
        }
        for (n, m) in self.mass.iter().enumerate() {
            for r in 0..3 {
                a[(3 * n + r, 3 * n + r)] += self.shift * m;
            }
        }
        for (n, p) in self.projector.iter().enumerate() {
            if let Some(p) = p {
                // Project rows and columns of node n: A ← Π A Π + (I − Π) on that node.
                for c in 0..n3 {
                    let col = V3::new(a[(3 * n, c)], a[(3 * n + 1, c)], a[(3 * n + 2, c)]);
                    let pc = p * col;
                    for r in 0..3 {
                        a[(3 * n + r, c)] = pc[r];
                    }
                }
                for r in 0..n3 {
                    let row = V3::new(a[(r, 3 * n)], a[(r, 3 * n + 1)], a[(r, 3 * n + 2)]);
                    let pr = p.transpose() * row;
                    for c in 0..3 {
                        a[(r, 3 * n + c)] = pr[c];
                    }
                }
                let q = Matrix3::identity() - p;
                for r in 0..3 {
                    for c in 0..3 {
                        a[(3 * n + r, 3 * n + c)] += q[(r, c)];
                    }
                }
            }
        }
        a
    }

    /// Π v for node `n` (v itself when the node is free).
    #[inline]
    pub(super) fn project_node(&self, n: usize, v: V3) -> V3 {
        match self.slot.get(n) {
            Some(&s) if s != FREE => self.constrained[s as usize].1 * v,
            _ => v,
        }
    }

    /// Π v in place on the constrained nodes.
    pub(super) fn project(&self, v: &mut [f64]) {
        let vn = nodes_mut(v);
        for (n, p) in &self.constrained {
            vn[*n as usize] = p * vn[*n as usize];
        }
    }
}

/// The constrained nodes of a dense projector list, with their projectors.
pub fn sparse(projector: &[Option<Matrix3<f64>>]) -> Vec<(u32, Matrix3<f64>)> {
    projector
        .iter()
        .enumerate()
        .filter_map(|(n, p)| p.map(|p| (n as u32, p)))
        .collect()
}

/// Applies each node's projector to a flat vector (unlisted nodes are free).
pub fn project_flat(constrained: &[(u32, Matrix3<f64>)], v: &mut [f64]) {
    let vn = nodes_mut(v);
    for (n, p) in constrained {
        vn[*n as usize] = p * vn[*n as usize];
    }
}
