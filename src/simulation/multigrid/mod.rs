//! Geometric multigrid preconditioner for voxel-lattice meshes.
//!
//! Each level is a set of hexahedral cells with 24 × 24 small-strain stiffness matrices. The
//! fine level uses the element classes' matrices (springs and corrections) with the constraint
//! projections applied; each coarser level merges 2 × 2 × 2 cells and takes the Galerkin
//! product Pᵀ·K·P element by element, P being trilinear interpolation inside the coarse cell.
//! Because that interpolation is consistent across cell faces, the element-wise sum is the
//! exact global Galerkin operator, for any lung-shaped mask, with no boundary special cases.
//! Smoothing is Chebyshev-accelerated block Jacobi (parallel); the coarsest level is solved
//! by dense LU.
//!
//! Several bodies may share the lattice without sharing nodes (the two lungs touch along the
//! mediastinum): cells and nodes of every level are keyed by (body, lattice point), so no
//! level couples them. Coarse directions without stiffness (a coarse node whose fine nodes
//! are all fixed, or all slide on one plane) are constrained like the fine level's, since
//! inverting their round-off diagonal made the smoother diverge on the lungs.
//!
//! Cost: the fine level needs no assembled matrix (one shared 24 × 24 block per class), coarse
//! levels store 4.6 kB per distinct coarse cell matrix (cells with the same children, classes
//! and constraint projectors share one). Set-up is linear in the element count.
//!
//! Operator products are the hot path (≈ 9 per level per V-cycle, one fewer where the
//! smoother starts from zero). Every level scatters through a [`ChunkSchedule`], so a product
//! has 2–3 barriers instead of one per element colour, and needs neither a lock nor a copy of
//! the input: constraint projections are applied while gathering the few elements that touch
//! a constrained node. The fine level evaluates the springs four elements at a time (one
//! element per SIMD lane, AVX2 chosen at run time as in the force kernel); four consecutive
//! elements of a lattice row share their x-faces, so they load and store 20 nodes instead of
//! 32. With an hourglass correction (the default element), which the spring operator lacks,
//! the fine level is the dense class matrices assembled into a 27-point stencil per node (by
//! class and by which of the node's eight cells exist), applied node by node without scatter. Coarse cells are multiplied one at a time with fused multiply–adds (AVX2 + FMA), since
//! neighbouring cells may have different matrices.
//!
//! Layout: `lattice` recovers the voxel lattice of a mesh; `level` holds one level of the
//! hierarchy and its set-up; `springs` is the fine level's element operator; `stencil` its
//! node-wise form for dense classes; `batch` (with
//! `avx2`) moves lane batches between node vectors and SIMD lanes; `product` is a level's
//! operator product; `smoother` its Chebyshev smoothing; `coarsen` builds the next coarser
//! level; `preconditioner` is the hierarchy and its V-cycle.
//!
//! [`ChunkSchedule`]: super::forces::ChunkSchedule

#[cfg(target_arch = "x86_64")]
mod avx2;
mod batch;
mod coarsen;
mod lattice;
mod level;
mod preconditioner;
mod product;
mod smoother;
mod springs;
mod stencil;

use nalgebra::SMatrix;

pub use lattice::Lattice;
pub use level::{project_flat, sparse};
pub use preconditioner::{LevelCost, Multigrid};

/// A 24 × 24 cell matrix (8 corners × 3 displacement components).
type M24 = SMatrix<f64, 24, 24>;

/// Nodes per parallel task in the node-wise passes of a product.
const NODE_TASK: usize = 8192;
