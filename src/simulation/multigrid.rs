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
//! 32. Coarse cells are multiplied one at a time with fused multiply–adds (AVX2 + FMA), since
//! neighbouring cells may have different matrices.

use std::collections::HashMap;

use nalgebra::{DMatrix, Matrix3, SMatrix};
use rayon::prelude::*;

use super::forces::{ChunkSchedule, PARALLEL_MIN_ELEMENTS};
use super::lanes::{ElementSource, LaneV3, Lanes, LANES};
use super::linalg::{nodes, nodes_mut};
use crate::math::V3;
use crate::model::element::CORNER_SIGNS;
use crate::model::HexMesh;

type M24 = SMatrix<f64, 24, 24>;

/// Lattice coordinates of a mesh whose elements are equal bricks on one regular grid.
///
/// The mesh may hold several bodies (connected components through shared element nodes)
/// that touch on the lattice without sharing nodes, such as the two lungs: two nodes may then
/// sit at one lattice point, and every level of the hierarchy keeps the bodies apart.
#[derive(Debug, Clone)]
pub struct Lattice {
    /// Lattice point of each node.
    pub node: Vec<[u32; 3]>,
    /// Lattice cell of each element.
    pub cell: Vec<[u32; 3]>,
    /// Body (connected component, numbered from 0 in node order) of each node.
    pub body: Vec<u32>,
    /// World directions of the lattice axes, as columns.
    pub axes: Matrix3<f64>,
}

impl Lattice {
    /// Recovers the lattice from geometry, or `None` if the elements are not equal bricks
    /// aligned on one grid, or two nodes of one body share a lattice point (the solver then
    /// falls back to block Jacobi).
    pub fn infer(mesh: &HexMesh) -> Option<Lattice> {
        let shape = mesh.classes.first()?.shape;
        if mesh.classes.iter().any(|c| c.shape != shape) {
            return None;
        }
        let p = &mesh.rest_positions_m;
        let e0 = mesh.elements[0];
        let axes = [
            (p[e0[1] as usize] - p[e0[0] as usize]).normalize(),
            (p[e0[3] as usize] - p[e0[0] as usize]).normalize(),
            (p[e0[4] as usize] - p[e0[0] as usize]).normalize(),
        ];
        let origin = p[e0[0] as usize];
        let h = shape.edges_m;
        let mut raw = Vec::with_capacity(p.len());
        for x in p {
            let mut c = [0i64; 3];
            for a in 0..3 {
                let t = (x - origin).dot(&axes[a]) / h[a];
                let r = t.round();
                if (t - r).abs() > 1e-6 {
                    return None;
                }
                c[a] = r as i64;
            }
            raw.push(c);
        }
        let min: [i64; 3] = std::array::from_fn(|a| raw.iter().map(|c| c[a]).min().unwrap_or(0));
        let node: Vec<[u32; 3]> = raw
            .iter()
            .map(|c| std::array::from_fn(|a| (c[a] - min[a]) as u32))
            .collect();
        let mut cell = Vec::with_capacity(mesh.elements.len());
        for corners in &mesh.elements {
            let base = node[corners[0] as usize];
            for (k, signs) in CORNER_SIGNS.iter().enumerate() {
                let want: [u32; 3] = std::array::from_fn(|a| base[a] + (signs[a] > 0.0) as u32);
                if node[corners[k] as usize] != want {
                    return None;
                }
            }
            cell.push(base);
        }
        // Coarse levels identify nodes by (body, lattice point): two bodies touching on the
        // lattice (the two lungs, meshed without shared nodes) must not be glued there, where
        // their sliding surfaces face opposite ways. Within one body a lattice point is one node.
        let body = node_bodies(mesh);
        let mut seen = std::collections::HashSet::with_capacity(node.len());
        if !node.iter().zip(&body).all(|(c, &b)| seen.insert((*c, b))) {
            return None;
        }
        Some(Lattice {
            node,
            cell,
            body,
            axes: Matrix3::from_columns(&axes),
        })
    }
}

/// Connected component of each node through shared element nodes, numbered in order of
/// first node; a node in no element is a body of its own.
fn node_bodies(mesh: &HexMesh) -> Vec<u32> {
    fn root(parent: &mut [u32], mut n: u32) -> u32 {
        while parent[n as usize] != n {
            // Path halving keeps the trees shallow without recursion.
            let up = parent[parent[n as usize] as usize];
            parent[n as usize] = up;
            n = up;
        }
        n
    }
    let mut parent: Vec<u32> = (0..mesh.node_count() as u32).collect();
    for corners in &mesh.elements {
        let a = root(&mut parent, corners[0]);
        for &c in &corners[1..] {
            let b = root(&mut parent, c);
            if b != a {
                parent[b as usize] = a;
            }
        }
    }
    let mut number = vec![u32::MAX; parent.len()];
    let mut next = 0;
    (0..parent.len() as u32)
        .map(|n| {
            let r = root(&mut parent, n) as usize;
            if number[r] == u32::MAX {
                number[r] = next;
                next += 1;
            }
            number[r]
        })
        .collect()
}

/// One level of the hierarchy.
struct Level {
    n_nodes: usize,
    elements: Vec<[u32; 8]>,
    /// Per element, index into `matrices`.
    matrix_of: Vec<u32>,
    matrices: Vec<M24>,
    /// Fine level only: the same operators as springs (cheaper than dense 24 × 24 products).
    springs: Vec<LinearSprings>,
    /// `springs` replicated across SIMD lanes, one per class.
    lane_springs: Vec<LaneSprings>,
    /// World → lattice rotation of the springs (row-major, per lane), `None` when axis-aligned.
    rotation: Option<[Lanes; 9]>,
    colors: Vec<Vec<u32>>,
    /// Race-free chunked scatter plan; `None` when the numbering lacks locality (use `colors`).
    schedule: Option<ChunkSchedule>,
    /// Constraint projector per node (fine level only; `None` = free), for set-up.
    projector: Vec<Option<Matrix3<f64>>>,
    /// The same, listed sparsely for the hot paths.
    constrained: Vec<(u32, Matrix3<f64>)>,
    /// Per node, index into `constrained` or [`FREE`] (empty when nothing is constrained).
    slot: Vec<u32>,
    /// Per element, whether a corner is constrained (empty when nothing is constrained).
    touches_constraint: Vec<bool>,
    /// Per aligned quad of elements (4q … 4q + 3), whether they are consecutive along one
    /// lattice row, each sharing its +x face with the next (lattice-ordered meshes).
    row_quad: Vec<bool>,
    diag_inv: Vec<Matrix3<f64>>,
    /// Diagonal 3 × 3 blocks of the stiffness, before shift and projection.
    diag: Vec<Matrix3<f64>>,
    /// Lumped nodal mass (fine level: the mesh's; coarse: restricted), kg.
    mass: Vec<f64>,
    /// Pseudo-transient shift σ: the level's operator is K + σ·M.
    shift: f64,
    lambda_max: f64,
    /// Interpolation from the next coarser level: up to 8 (coarse node, weight) per node.
    prolong: Vec<[(u32, f64); 8]>,
}

/// `slot` of an unconstrained node.
const FREE: u32 = u32::MAX;

/// Row-major 3 × 3 matrix times a lane vector, summed left to right like nalgebra's product.
#[inline(always)]
fn mat_vec(m: &[Lanes; 9], v: &LaneV3) -> LaneV3 {
    std::array::from_fn(|r| m[3 * r] * v[0] + m[3 * r + 1] * v[1] + m[3 * r + 2] * v[2])
}

/// Transposed row-major 3 × 3 matrix times a lane vector.
#[inline(always)]
fn mat_t_vec(m: &[Lanes; 9], v: &LaneV3) -> LaneV3 {
    std::array::from_fn(|r| m[r] * v[0] + m[3 + r] * v[1] + m[6 + r] * v[2])
}

/// Where element products are added: one chunk's node window of the output, or (fallback)
/// the whole output shared by the elements of one colour.
trait Sink {
    /// The three output values of `node`.
    fn node(&mut self, node: u32) -> &mut [f64; 3];
}

/// A chunk's own window `out[3·lo..]` of the output.
struct Window<'a> {
    lo: u32,
    out: &'a mut [f64],
}

impl Sink for Window<'_> {
    #[inline(always)]
    fn node(&mut self, node: u32) -> &mut [f64; 3] {
        // A node below the window wraps to a huge index and panics on the bounds check.
        let b = 3 * node.wrapping_sub(self.lo) as usize;
        (&mut self.out[b..b + 3]).try_into().expect("3 values")
    }
}

#[derive(Clone, Copy)]
struct Shared(*mut f64, usize);
// SAFETY: used only colour by colour; elements of one colour share no node.
unsafe impl Send for Shared {}
unsafe impl Sync for Shared {}

impl Sink for Shared {
    #[inline(always)]
    fn node(&mut self, node: u32) -> &mut [f64; 3] {
        let b = 3 * node as usize;
        assert!(b + 3 <= self.1, "node {node} beyond the output");
        // SAFETY: in bounds (checked above); no other thread touches this node while the
        // colour is processed (the element colouring guarantees it).
        unsafe { &mut *(self.0.add(b) as *mut [f64; 3]) }
    }
}

/// The corners of [`LANES`] elements as lane vectors (`AVX2`: the caller is compiled for AVX2).
#[inline(always)]
fn gather<const AVX2: bool>(
    x: &[f64],
    corners: &[&[u32; 8]; LANES],
    row: bool,
    u: &mut [LaneV3; 8],
) {
    #[cfg(target_arch = "x86_64")]
    if AVX2 {
        // SAFETY: `AVX2` is only set inside functions compiled for AVX2, which run only after
        // the CPU was checked for it.
        unsafe {
            if row {
                avx2::gather_row(x, corners, u);
            } else {
                avx2::gather(x, corners, u);
            }
        }
        return;
    }
    let _ = row;
    let node = |c: u32| -> &[f64; 3] {
        let b = 3 * c as usize;
        x[b..b + 3].try_into().expect("3 coordinates")
    };
    for (n, un) in u.iter_mut().enumerate() {
        // Array literals, not `map`: `map` is not reliably inlined into the hot loop.
        let p = [
            node(corners[0][n]),
            node(corners[1][n]),
            node(corners[2][n]),
            node(corners[3][n]),
        ];
        for (i, v) in un.iter_mut().enumerate() {
            *v = Lanes([p[0][i], p[1][i], p[2][i], p[3][i]]);
        }
    }
}

/// Adds lane `l < count` of `f` to the corners of element `l`, corner by corner.
#[inline(always)]
fn scatter<const AVX2: bool, S: Sink>(
    f: &[LaneV3; 8],
    corners: &[&[u32; 8]; LANES],
    count: usize,
    row: bool,
    sink: &mut S,
) {
    #[cfg(target_arch = "x86_64")]
    if AVX2 {
        // SAFETY: as in `gather`.
        unsafe {
            if row {
                avx2::scatter_row(f, corners, sink);
            } else {
                avx2::scatter(f, corners, count, sink);
            }
        }
        return;
    }
    let _ = row;
    for (n, fc) in f.iter().enumerate() {
        for (l, cs) in corners.iter().enumerate().take(count) {
            let o = sink.node(cs[n]);
            for i in 0..3 {
                o[i] += fc[i].0[l];
            }
        }
    }
}

/// K·u on [`LANES`] cells at once, `k(i)` giving entry i of the column-major 24 × 24 K per
/// lane. Each row sums its columns in order, like the one-cell column-by-column product.
#[inline(always)]
fn dense_lanes(k: impl Fn(usize) -> Lanes, u: &[LaneV3; 8], f: &mut [LaneV3; 8]) {
    for (r, fr) in f.as_flattened_mut().iter_mut().enumerate() {
        let mut acc = Lanes::ZERO;
        for (j, uj) in u.as_flattened().iter().enumerate() {
            acc = acc + k(24 * j + r) * *uj;
        }
        *fr = acc;
    }
}

/// AVX2 forms of the batch gather and scatter (node triples ↔ lane vectors by shuffles).
#[cfg(target_arch = "x86_64")]
mod avx2 {
    use super::super::lanes::{LaneV3, Lanes, LANES};
    use super::Sink;
    use std::arch::x86_64::*;

    #[inline(always)]
    fn to_lanes(v: __m256d) -> Lanes {
        // SAFETY: both are 32 bytes of four f64.
        unsafe { std::mem::transmute::<__m256d, Lanes>(v) }
    }

    #[inline(always)]
    fn from_lanes(v: Lanes) -> __m256d {
        // SAFETY: both are 32 bytes of four f64.
        unsafe { std::mem::transmute::<Lanes, __m256d>(v) }
    }

    /// See `super::gather`. Not itself marked AVX2, so that it can be forced inline into its
    /// AVX2 caller (where the intrinsics then inline too).
    ///
    /// # Safety
    /// The CPU must support AVX2.
    #[inline(always)]
    pub(super) unsafe fn gather(x: &[f64], corners: &[&[u32; 8]; LANES], u: &mut [LaneV3; 8]) {
        for (n, un) in u.iter_mut().enumerate() {
            // Array literals, not `map`: `map` is not reliably inlined into the hot loop.
            let nodes = [corners[0][n], corners[1][n], corners[2][n], corners[3][n]];
            *un = load_lanes(x, &nodes).map(to_lanes);
        }
    }

    /// `gather` for a row quad: corner b of lane l is corner a of lane l + 1, so each x line
    /// loads 5 nodes instead of 8 and shifts lanes for the other corner.
    ///
    /// # Safety
    /// The CPU must support AVX2.
    #[inline(always)]
    pub(super) unsafe fn gather_row(x: &[f64], corners: &[&[u32; 8]; LANES], u: &mut [LaneV3; 8]) {
        for &(a, b) in &super::ROW_LINES {
            let nodes = [corners[0][a], corners[1][a], corners[2][a], corners[3][a]];
            let ua = load_lanes(x, &nodes);
            let last = corners[3][b] as usize;
            let tail = &x[3 * last..3 * last + 3];
            for (i, va) in ua.iter().enumerate() {
                // Lanes 1, 2, 3 of corner a become lanes 0, 1, 2 of corner b.
                let down = _mm256_permute4x64_pd::<0b00_11_10_01>(*va);
                u[b][i] = to_lanes(_mm256_blend_pd::<0b1000>(down, _mm256_set1_pd(tail[i])));
                u[a][i] = to_lanes(*va);
            }
        }
    }

    /// The 3 coordinates of 4 nodes as x, y and z lane vectors.
    ///
    /// # Safety
    /// The CPU must support AVX2.
    #[inline(always)]
    unsafe fn load_lanes(x: &[f64], nodes: &[u32; LANES]) -> [__m256d; 3] {
        let node = |c: u32| -> *const f64 {
            let b = 3 * c as usize;
            x[b..b + 3].as_ptr()
        };
        let p = [
            node(nodes[0]),
            node(nodes[1]),
            node(nodes[2]),
            node(nodes[3]),
        ];
        // SAFETY: each p[l] points at 3 readable f64 (sliced just above).
        unsafe {
            let lo = _mm256_insertf128_pd::<1>(
                _mm256_castpd128_pd256(_mm_loadu_pd(p[0])),
                _mm_loadu_pd(p[2]),
            );
            let hi = _mm256_insertf128_pd::<1>(
                _mm256_castpd128_pd256(_mm_loadu_pd(p[1])),
                _mm_loadu_pd(p[3]),
            );
            let z01 = _mm_loadh_pd(_mm_load_sd(p[0].add(2)), p[1].add(2));
            let z23 = _mm_loadh_pd(_mm_load_sd(p[2].add(2)), p[3].add(2));
            [
                _mm256_unpacklo_pd(lo, hi),
                _mm256_unpackhi_pd(lo, hi),
                _mm256_insertf128_pd::<1>(_mm256_castpd128_pd256(z01), z23),
            ]
        }
    }

    /// `scatter` for a row quad: along each x line, lane l's corner b is lane l + 1's corner a,
    /// so the two are summed in registers first and the line takes 5 node updates, not 8.
    ///
    /// # Safety
    /// The CPU must support AVX2.
    #[inline(always)]
    pub(super) unsafe fn scatter_row<S: Sink>(
        f: &[LaneV3; 8],
        corners: &[&[u32; 8]; LANES],
        sink: &mut S,
    ) {
        for &(a, b) in &super::ROW_LINES {
            let mut g = [_mm256_setzero_pd(); 3];
            for (g, (fa, fb)) in g.iter_mut().zip(f[a].iter().zip(&f[b])) {
                // fb moved up one lane (lane 0 ← 0): corner b of lane l is corner a of l + 1.
                let up = _mm256_blend_pd::<0b0001>(
                    _mm256_permute4x64_pd::<0b10_01_00_00>(from_lanes(*fb)),
                    _mm256_setzero_pd(),
                );
                *g = _mm256_add_pd(from_lanes(*fa), up);
            }
            let nodes = [corners[0][a], corners[1][a], corners[2][a], corners[3][a]];
            add_lanes(sink, &nodes, LANES, g);
            let o = sink.node(corners[3][b]);
            for (o, fb) in o.iter_mut().zip(&f[b]) {
                *o += fb.0[3];
            }
        }
    }

    /// See `super::scatter`; same order of additions. Inlined like `gather`.
    ///
    /// # Safety
    /// The CPU must support AVX2.
    #[inline(always)]
    pub(super) unsafe fn scatter<S: Sink>(
        f: &[LaneV3; 8],
        corners: &[&[u32; 8]; LANES],
        count: usize,
        sink: &mut S,
    ) {
        for (n, fc) in f.iter().enumerate() {
            let nodes = [corners[0][n], corners[1][n], corners[2][n], corners[3][n]];
            add_lanes(sink, &nodes, count, fc.map(from_lanes));
        }
    }

    /// Adds lane l of the component vectors `v` to `nodes[l]`, for l < `count`.
    ///
    /// # Safety
    /// The CPU must support AVX2.
    #[inline(always)]
    unsafe fn add_lanes<S: Sink>(
        sink: &mut S,
        nodes: &[u32; LANES],
        count: usize,
        v: [__m256d; 3],
    ) {
        let [vx, vy, vz] = v;
        let t0 = _mm256_unpacklo_pd(vx, vy); // x0 y0 x2 y2
        let t1 = _mm256_unpackhi_pd(vx, vy); // x1 y1 x3 y3
        let xy = [
            _mm256_castpd256_pd128(t0),
            _mm256_castpd256_pd128(t1),
            _mm256_extractf128_pd::<1>(t0),
            _mm256_extractf128_pd::<1>(t1),
        ];
        let z01 = _mm256_castpd256_pd128(vz);
        let z23 = _mm256_extractf128_pd::<1>(vz);
        let z = [
            z01,
            _mm_unpackhi_pd(z01, z01),
            z23,
            _mm_unpackhi_pd(z23, z23),
        ];
        for (l, &c) in nodes.iter().enumerate().take(count) {
            let p = sink.node(c).as_mut_ptr();
            // SAFETY: `p` points at the node's 3 writable f64.
            unsafe {
                _mm_storeu_pd(p, _mm_add_pd(_mm_loadu_pd(p), xy[l]));
                _mm_store_sd(p.add(2), _mm_add_sd(_mm_load_sd(p.add(2)), z[l]));
            }
        }
    }
}

/// Corner pairs (a, b) joined by the element's x edges: corner b of an element is corner a
/// of the next element along its row.
const ROW_LINES: [(usize, usize); 4] = [(0, 1), (3, 2), (4, 5), (7, 6)];

/// Nodes per parallel task in the node-wise passes of a product.
const NODE_TASK: usize = 8192;

impl Level {
    /// y = A·x on this level.
    fn apply(&self, x: &[f64], y: &mut [f64]) {
        self.apply_with(x, y, true);
    }

    /// `apply`, with `simd` = false forcing the portable kernels (to test them on any CPU).
    fn apply_with(&self, x: &[f64], y: &mut [f64], simd: bool) {
        assert_eq!(x.len(), 3 * self.n_nodes);
        assert_eq!(y.len(), 3 * self.n_nodes);
        let parallel =
            rayon::current_num_threads() > 1 && self.elements.len() >= PARALLEL_MIN_ELEMENTS;
        // Start from the shift term σ·M·(Π x), so the element sums need no zeroed output.
        let init = |(y, (x, m)): (&mut [f64], (&[f64], &[f64]))| {
            if self.shift > 0.0 {
                for ((y, x), m) in y.chunks_exact_mut(3).zip(x.chunks_exact(3)).zip(m) {
                    let s = self.shift * m;
                    y[0] = x[0] * s;
                    y[1] = x[1] * s;
                    y[2] = x[2] * s;
                }
            } else {
                y.fill(0.0);
            }
        };
        if parallel {
            y.par_chunks_mut(3 * NODE_TASK)
                .zip(
                    x.par_chunks(3 * NODE_TASK)
                        .zip(self.mass.par_chunks(NODE_TASK)),
                )
                .for_each(init);
        } else {
            init((y, (x, &self.mass[..])));
        }
        if self.shift > 0.0 {
            let (yn, xn) = (nodes_mut(y), nodes(x));
            for (n, p) in &self.constrained {
                let n = *n as usize;
                yn[n] = (p * xn[n]) * (self.shift * self.mass[n]);
            }
        }
        match &self.schedule {
            Some(schedule) => schedule.for_each_chunk(y, 3, parallel, |elements, lo, window| {
                let mut sink = Window {
                    lo: lo as u32,
                    out: window,
                };
                let mut batch = elements.start as u32..elements.end as u32;
                self.scatter(x, &mut batch, &mut sink, simd);
            }),
            None => {
                let shared = Shared(y.as_mut_ptr(), y.len());
                for colour in &self.colors {
                    let run =
                        |task: &[u32]| self.scatter(x, &mut task.iter(), &mut { shared }, simd);
                    if parallel && colour.len() >= 512 {
                        colour.par_chunks(128).for_each(run);
                    } else {
                        run(colour);
                    }
                }
            }
        }
        if !self.constrained.is_empty() {
            let (yn, xn) = (nodes_mut(y), nodes(x));
            for (n, p) in &self.constrained {
                let n = *n as usize;
                yn[n] = p * yn[n] + (xn[n] - p * xn[n]);
            }
        }
    }

    /// Adds the element products of `elements` (applied to Π x) into `sink`, with the widest
    /// vector instructions the CPU offers.
    fn scatter<E: ElementSource, S: Sink>(
        &self,
        x: &[f64],
        elements: &mut E,
        sink: &mut S,
        simd: bool,
    ) {
        #[cfg(target_arch = "x86_64")]
        if simd {
            #[target_feature(enable = "avx2")]
            unsafe fn avx2<E: ElementSource, S: Sink>(
                level: &Level,
                x: &[f64],
                elements: &mut E,
                sink: &mut S,
            ) {
                level.batches::<true, E, S>(x, elements, sink)
            }
            #[target_feature(enable = "avx2,fma")]
            unsafe fn avx2_fma<E: ElementSource, S: Sink>(
                level: &Level,
                x: &[f64],
                elements: &mut E,
                sink: &mut S,
            ) {
                let mut ids = [0u32; LANES];
                while let Some(count) = elements.next_batch(&mut ids) {
                    for &e in &ids[..count] {
                        // SAFETY: compiled for, and called on, a CPU with AVX2 and FMA.
                        unsafe { level.dense_cell(x, e as usize, sink) };
                    }
                }
            }
            if std::arch::is_x86_feature_detected!("avx2") {
                if self.lane_springs.is_empty() && std::arch::is_x86_feature_detected!("fma") {
                    // SAFETY: the CPU supports AVX2 and FMA (checked just above).
                    unsafe { avx2_fma(self, x, elements, sink) };
                } else {
                    // SAFETY: the CPU supports AVX2 (checked just above).
                    unsafe { avx2(self, x, elements, sink) };
                }
                return;
            }
        }
        #[cfg(not(target_arch = "x86_64"))]
        let _ = simd;
        self.batches::<false, E, S>(x, elements, sink)
    }

    /// One cell's dense product, column by column with fused multiply–adds, the cell's input
    /// broadcast straight from `x` and its 24 outputs kept in six registers: per cell rather
    /// than per batch since neighbouring cells may have different matrices.
    ///
    /// # Safety
    /// The CPU must support AVX2 and FMA; only call from functions compiled for both.
    #[cfg(target_arch = "x86_64")]
    #[inline(always)]
    unsafe fn dense_cell<S: Sink>(&self, x: &[f64], e: usize, sink: &mut S) {
        use std::arch::x86_64::*;
        let corners = &self.elements[e];
        let k = self.matrices[self.matrix_of[e] as usize].as_slice();
        assert_eq!(k.len(), 576);
        // Constrained corners are read from projected local copies, the others from `x`.
        let project = self.touches_constraint.get(e).copied().unwrap_or(false);
        let mut local = [[0.0; 3]; 8];
        let mut is_local = [false; 8];
        if project {
            for ((&n, l), is) in corners.iter().zip(&mut local).zip(&mut is_local) {
                if self.slot[n as usize] != FREE {
                    *l = self.projected_input(x, n, true).into();
                    *is = true;
                }
            }
        }
        let mut p = [std::ptr::null::<f64>(); 8];
        for (c, (&n, p)) in corners.iter().zip(&mut p).enumerate() {
            let b = 3 * n as usize;
            *p = if is_local[c] {
                local[c].as_ptr()
            } else {
                x[b..b + 3].as_ptr()
            };
        }
        #[repr(C, align(32))]
        struct Out([f64; 24]);
        let mut ye = Out([0.0; 24]);
        // SAFETY: every p[c] points at 3 readable f64 (sliced or local above), `k` holds 576
        // f64 (asserted), `ye` is 32-byte aligned; AVX2 and FMA are the caller's contract.
        unsafe {
            let mut acc = [_mm256_setzero_pd(); 6];
            for j in 0..24 {
                let xj = _mm256_broadcast_sd(&*p[j / 3].add(j % 3));
                let col = k.as_ptr().add(24 * j);
                for (r, a) in acc.iter_mut().enumerate() {
                    *a = _mm256_fmadd_pd(_mm256_loadu_pd(col.add(4 * r)), xj, *a);
                }
            }
            for (r, a) in acc.iter().enumerate() {
                _mm256_store_pd(ye.0.as_mut_ptr().add(4 * r), *a);
            }
        }
        for (&n, y) in corners.iter().zip(ye.0.chunks_exact(3)) {
            sink.node(n).iter_mut().zip(y).for_each(|(o, y)| *o += y);
        }
    }

    /// The batch loop: gather [`LANES`] elements' corners, apply the springs or the cell
    /// matrix, scatter. `AVX2`: the caller is compiled for AVX2, so intrinsics may be used.
    #[inline(always)]
    fn batches<const AVX2: bool, E: ElementSource, S: Sink>(
        &self,
        x: &[f64],
        elements: &mut E,
        sink: &mut S,
    ) {
        let mut ids = [0u32; LANES];
        let mut mixed: Option<LaneSprings> = None;
        // Reused (not returned) so that no batch zeroes or copies them.
        let mut u = [[Lanes::ZERO; 3]; 8];
        let mut f = u;
        while let Some(count) = elements.next_batch(&mut ids) {
            let corners: [&[u32; 8]; LANES] = [
                &self.elements[ids[0] as usize],
                &self.elements[ids[1] as usize],
                &self.elements[ids[2] as usize],
                &self.elements[ids[3] as usize],
            ];
            let projected = !self.touches_constraint.is_empty()
                && ids.iter().any(|&e| self.touches_constraint[e as usize]);
            // Only the AVX2 kernels exploit the nodes shared along a row.
            let row = AVX2 && count == LANES && self.is_row_quad(&ids);
            if projected {
                self.gather_projected(x, &corners, &ids, &mut u);
            } else {
                gather::<AVX2>(x, &corners, row, &mut u);
            }
            let m0 = self.matrix_of[ids[0] as usize];
            let uniform = ids[1..].iter().all(|&e| self.matrix_of[e as usize] == m0);
            if self.lane_springs.is_empty() {
                if uniform {
                    let k = self.matrices[m0 as usize].as_slice();
                    dense_lanes(|i| Lanes::splat(k[i]), &u, &mut f);
                } else {
                    let k = [0, 1, 2, 3].map(|l| {
                        self.matrices[self.matrix_of[ids[l] as usize] as usize].as_slice()
                    });
                    dense_lanes(|i| Lanes([k[0][i], k[1][i], k[2][i], k[3][i]]), &u, &mut f);
                }
            } else {
                let kernel = if uniform {
                    &self.lane_springs[m0 as usize]
                } else {
                    let classes = ids.map(|e| self.matrix_of[e as usize]);
                    &*mixed.insert(LaneSprings::gather(&self.lane_springs, &classes))
                };
                kernel.apply(self.rotation.as_ref(), &mut u, &mut f);
            }
            scatter::<AVX2, S>(&f, &corners, count, row, sink);
        }
    }

    /// Whether the batch is one whole row quad (see `row_quad`).
    #[inline(always)]
    fn is_row_quad(&self, ids: &[u32; LANES]) -> bool {
        let q = ids[0] as usize / LANES;
        (ids[0] as usize).is_multiple_of(LANES)
            && ids[3] == ids[0] + 3
            && self.row_quad.get(q).copied().unwrap_or(false)
    }

    /// Node `c` of the input, projected when `project` and the node is constrained.
    #[inline(always)]
    fn projected_input(&self, x: &[f64], c: u32, project: bool) -> V3 {
        let b = 3 * c as usize;
        let v = V3::new(x[b], x[b + 1], x[b + 2]);
        match self.slot[c as usize] {
            s if project && s != FREE => self.constrained[s as usize].1 * v,
            _ => v,
        }
    }

    /// The lanes of a batch with constrained corners, projected (the rare, slow path).
    #[inline(never)]
    fn gather_projected(
        &self,
        x: &[f64],
        corners: &[&[u32; 8]; LANES],
        ids: &[u32; LANES],
        u: &mut [LaneV3; 8],
    ) {
        let project = ids.map(|e| self.touches_constraint[e as usize]);
        for (n, un) in u.iter_mut().enumerate() {
            // Whole lane vectors, not single lanes: see `gather`.
            let p = [
                self.projected_input(x, corners[0][n], project[0]),
                self.projected_input(x, corners[1][n], project[1]),
                self.projected_input(x, corners[2][n], project[2]),
                self.projected_input(x, corners[3][n], project[3]),
            ];
            for (i, v) in un.iter_mut().enumerate() {
                *v = Lanes([p[0][i], p[1][i], p[2][i], p[3][i]]);
            }
        }
    }

    /// Π v for node `n` (v itself when the node is free).
    #[inline]
    fn project_node(&self, n: usize, v: V3) -> V3 {
        match self.slot.get(n) {
            Some(&s) if s != FREE => self.constrained[s as usize].1 * v,
            _ => v,
        }
    }

    fn project(&self, v: &mut [f64]) {
        let vn = nodes_mut(v);
        for (n, p) in &self.constrained {
            vn[*n as usize] = p * vn[*n as usize];
        }
    }

    fn jacobi(&self, r: &[f64], z: &mut [f64]) {
        let (rn, zn) = (nodes(r), nodes_mut(z));
        zn.par_iter_mut()
            .zip(rn.par_iter())
            .zip(self.diag_inv.par_iter())
            .for_each(|((z, r), d)| *z = d * r);
    }

    /// Chebyshev iteration on D⁻¹A over [λmax/ratio, 1.1·λmax], improving x for A·x = b;
    /// `x_is_zero` skips the first product (A·0 = 0 exactly).
    fn smooth(
        &self,
        b: &[f64],
        x: &mut [f64],
        x_is_zero: bool,
        degree: usize,
        scratch: &mut [Vec<f64>],
    ) {
        // Interval measured on pressurised blocks: degree 4 over [λmax/30, 1.1·λmax] needed the
        // fewest fine-level products per digit of residual.
        let (upper, lower) = (1.1 * self.lambda_max, self.lambda_max / 30.0);
        let theta = 0.5 * (upper + lower);
        let delta = 0.5 * (upper - lower);
        let sigma = theta / delta;
        let [r, z, d, ..] = scratch else {
            unreachable!()
        };
        if x_is_zero {
            r.fill(0.0);
        } else {
            self.apply(x, r);
        }
        if degree == 0 {
            return;
        }
        // One pass per step over all vectors (r ← b − r, z ← D⁻¹r, d, x ← x + d) instead of
        // one per operation: the same arithmetic, a quarter of the memory traffic.
        self.sweep(b, r, d, x, |dinv, b, r, d, x| {
            *r = b - *r;
            *d = (dinv * *r) / theta;
            *x += *d;
        });
        let mut rho = 1.0 / sigma;
        for _ in 1..degree {
            self.apply(d, z);
            let rho_new = 1.0 / (2.0 * sigma - rho);
            let (keep, gain) = (rho_new * rho, 2.0 * rho_new / delta);
            self.sweep(z, r, d, x, |dinv, z, r, d, x| {
                *r -= z;
                *d = *d * keep + (dinv * *r) * gain;
                *x += *d;
            });
            rho = rho_new;
        }
    }

    /// Runs `f(D⁻¹ block, s, r, d, x)` node by node, in parallel on long levels.
    fn sweep<F>(&self, s: &[f64], r: &mut [f64], d: &mut [f64], x: &mut [f64], f: F)
    where
        F: Fn(&Matrix3<f64>, V3, &mut V3, &mut V3, &mut V3) + Sync,
    {
        let run = |s: &[V3], r: &mut [V3], d: &mut [V3], x: &mut [V3], dinv: &[Matrix3<f64>]| {
            for ((s, r), (d, (x, dinv))) in s
                .iter()
                .zip(r)
                .zip(d.iter_mut().zip(x.iter_mut().zip(dinv)))
            {
                f(dinv, *s, r, d, x);
            }
        };
        let (s, r, d, x) = (nodes(s), nodes_mut(r), nodes_mut(d), nodes_mut(x));
        let dinv = &self.diag_inv[..];
        if self.n_nodes >= SWEEP_PARALLEL_NODES && rayon::current_num_threads() > 1 {
            s.par_chunks(NODE_TASK)
                .zip(r.par_chunks_mut(NODE_TASK))
                .zip(
                    d.par_chunks_mut(NODE_TASK)
                        .zip(x.par_chunks_mut(NODE_TASK).zip(dinv.par_chunks(NODE_TASK))),
                )
                .for_each(|((s, r), (d, (x, dinv)))| run(s, r, d, x, dinv));
        } else {
            run(s, r, d, x, dinv);
        }
    }
}

/// Levels with at least this many nodes sweep their vectors in parallel.
const SWEEP_PARALLEL_NODES: usize = 4 * NODE_TASK;

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
    /// Median wall time of one operator product, milliseconds.
    pub product_ms: f64,
}

/// A V-cycle preconditioner for the small-strain stiffness of a lattice mesh.
pub struct Multigrid {
    levels: Vec<Level>,
    coarse_lu: nalgebra::LU<f64, nalgebra::Dyn, nalgebra::Dyn>,
    degree: usize,
    scratch: Vec<Vec<Vec<f64>>>,
}

/// Stiffness below this fraction of a level's largest diagonal block is round-off: the
/// direction is treated as constrained (see `Level::constrain_null_directions`).
const NULL_STIFFNESS_FRACTION: f64 = 1e-10;

/// Stop coarsening when a level has at most this many nodes (dense LU below).
const COARSEST_NODES: usize = 150;

impl Multigrid {
    /// Builds the hierarchy; `projector[n]` is the constraint projection of node n (None = free).
    pub fn new(mesh: &HexMesh, lattice: &Lattice, projector: Vec<Option<Matrix3<f64>>>) -> Self {
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
            springs: mesh
                .classes
                .iter()
                .map(|c| LinearSprings::new(c, &lattice.axes))
                .collect(),
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
        };
        fine.finish();
        let mut levels = vec![fine];
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

impl Level {
    /// Derives the product's lookup tables (lane kernels, constraint slots, scatter schedule)
    /// from the level's elements, springs and constraints.
    fn plan(&mut self) {
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
    fn finish(&mut self) {
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
            let nv = super::linalg::norm(&v).max(f64::MIN_POSITIVE);
            v.iter_mut().for_each(|x| *x /= nv);
            self.apply(&v, &mut av);
            self.jacobi(&av, &mut z);
            lambda = super::linalg::norm(&z);
            std::mem::swap(&mut v, &mut z);
        }
        self.lambda_max = lambda.max(1e-12);
    }

    /// Diagonal 3 × 3 blocks of the level's stiffness (before shift and projection).
    fn diagonal_blocks(&self) -> Vec<Matrix3<f64>> {
        let mut diag = vec![Matrix3::zeros(); self.n_nodes];
        for (e, corners) in self.elements.iter().enumerate() {
            let k = &self.matrices[self.matrix_of[e] as usize];
            for (c, &n) in corners.iter().enumerate() {
                diag[n as usize] += k.fixed_view::<3, 3>(3 * c, 3 * c).into_owned();
            }
        }
        diag
    }

    /// Constrains a coarse level's directions of zero stiffness.
    ///
    /// A coarse node whose fine nodes are all fixed, or all slide on one plane, has no
    /// stiffness along the blocked directions: in exact arithmetic its rows there are zero,
    /// but round-off leaves ~1e-16 of the block, which the inverted diagonal block (and the
    /// coarsest LU) then amplifies by ~1e16 and the smoother diverges (it did on the lungs,
    /// where planes with varied normals meet). Such directions are treated as constrained,
    /// exactly as the fine level treats its fixed and sliding nodes.
    fn constrain_null_directions(&mut self) {
        let diag = self.diagonal_blocks();
        let eigen: Vec<_> = diag.iter().map(|d| d.symmetric_eigen()).collect();
        let scale = eigen
            .iter()
            .map(|e| e.eigenvalues.amax())
            .fold(0.0, f64::max);
        // Round-off is ~1e-16 of the largest block; genuine weak couplings (a coarse node
        // seen through one fine corner at weight 1/8) are ~1e-2 of it.
        let null = NULL_STIFFNESS_FRACTION * scale;
        self.projector = eigen
            .iter()
            .map(|e| {
                let mut p = Matrix3::identity();
                let mut any = false;
                for (k, &value) in e.eigenvalues.iter().enumerate() {
                    if value <= null {
                        let v = e.eigenvectors.column(k);
                        p -= v * v.transpose();
                        any = true;
                    }
                }
                any.then_some(p)
            })
            .collect();
        self.constrained = sparse(&self.projector);
    }

    /// Inverts the shifted, projected diagonal blocks.
    fn update_diag_inv(&mut self) {
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

    fn dense(&self) -> DMatrix<f64> {
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
}

/// The small-strain element operator K·u evaluated through the springs and corrections in the
/// lattice frame, where an edge spring couples one displacement component and the diagonals
/// have fixed directions: ≈ 200 flops instead of 1152 for the dense 24 × 24 product.
#[derive(Debug, Clone)]
struct LinearSprings {
    edge_k: [f64; 3],
    diag_k: f64,
    /// Unit direction of each body diagonal (corner a → corner b) in the lattice frame.
    diag_dir: [V3; 4],
    /// World → lattice rotation (transpose of the lattice axes), `None` when they coincide.
    to_lattice: Option<Matrix3<f64>>,
    correction_map: Matrix3<f64>,
}

/// Body diagonals (a, b) of the element: the last four of `element::SPRINGS`.
const DIAGONALS: [(usize, usize); 4] = {
    let s = &crate::model::element::SPRINGS;
    [
        (s[12].0, s[12].1),
        (s[13].0, s[13].1),
        (s[14].0, s[14].1),
        (s[15].0, s[15].1),
    ]
};

impl LinearSprings {
    fn new(c: &crate::model::BrickCoefficients, axes: &Matrix3<f64>) -> Self {
        let offsets = c.corner_offsets_m();
        let to_lattice = if (axes - Matrix3::identity()).amax() < 1e-14 {
            None
        } else {
            Some(axes.transpose())
        };
        LinearSprings {
            edge_k: c.edge_stiffness_n_per_m,
            diag_k: c.diagonal_stiffness_n_per_m,
            diag_dir: DIAGONALS.map(|(a, b)| (offsets[b] - offsets[a]).normalize()),
            to_lattice,
            correction_map: c.correction_map,
        }
    }

    /// K·u for the 8 corner displacements u (K = −∂force/∂u), world frame in and out: the
    /// one-element reference for [`LaneSprings::apply`].
    #[cfg(test)]
    fn apply(&self, u_world: &[V3; 8]) -> [V3; 8] {
        let u = match &self.to_lattice {
            Some(r) => u_world.map(|v| r * v),
            None => *u_world,
        };
        // Spring forces of displacement u, lattice frame.
        let mut f = [V3::zeros(); 8];
        for &(a, b, kind) in &crate::model::element::SPRINGS {
            let crate::model::element::SpringKind::Edge(i) = kind else {
                continue;
            };
            let t = self.edge_k[i] * (u[b][i] - u[a][i]);
            f[a][i] += t;
            f[b][i] -= t;
        }
        for (d, &(a, b)) in self.diag_dir.iter().zip(&DIAGONALS) {
            let t = d * (self.diag_k * d.dot(&(u[b] - u[a])));
            f[a] += t;
            f[b] -= t;
        }
        let mut axial = V3::zeros();
        for (n, signs) in CORNER_SIGNS.iter().enumerate() {
            for i in 0..3 {
                axial[i] -= 0.5 * signs[i] * f[n][i];
            }
        }
        let w = self.correction_map * axial;
        for (n, signs) in CORNER_SIGNS.iter().enumerate() {
            for i in 0..3 {
                f[n][i] = -(f[n][i] + signs[i] * w[i]);
            }
        }
        match &self.to_lattice {
            Some(r) => f.map(|v| r.transpose() * v),
            None => f,
        }
    }
}

/// [`LinearSprings`] replicated across lanes (or gathered, for batches mixing classes).
#[derive(Debug, Clone)]
struct LaneSprings {
    edge_k: [Lanes; 3],
    diag_k: Lanes,
    diag_dir: [LaneV3; 4],
    /// Row-major correction map W.
    correction_map: [Lanes; 9],
}

impl LaneSprings {
    fn splat(s: &LinearSprings) -> Self {
        LaneSprings {
            edge_k: s.edge_k.map(Lanes::splat),
            diag_k: Lanes::splat(s.diag_k),
            diag_dir: s.diag_dir.map(|d| [d.x, d.y, d.z].map(Lanes::splat)),
            correction_map: std::array::from_fn(|r| Lanes::splat(s.correction_map[(r / 3, r % 3)])),
        }
    }

    /// Lane `l` taken from `kernels[classes[l]]`.
    fn gather(kernels: &[LaneSprings], classes: &[u32; LANES]) -> Self {
        let pick = |get: &dyn Fn(&LaneSprings) -> Lanes| {
            Lanes(std::array::from_fn(|l| {
                get(&kernels[classes[l] as usize]).0[l]
            }))
        };
        LaneSprings {
            edge_k: std::array::from_fn(|i| pick(&|k| k.edge_k[i])),
            diag_k: pick(&|k| k.diag_k),
            diag_dir: std::array::from_fn(|d| std::array::from_fn(|i| pick(&|k| k.diag_dir[d][i]))),
            correction_map: std::array::from_fn(|r| pick(&|k| k.correction_map[r])),
        }
    }

    /// `LinearSprings::apply` on [`LANES`] elements at once (`rotation`: world → lattice,
    /// row-major). Same operations in the same order, except that the axial resultants are
    /// summed before the exact scaling by −½, which leaves them bit-for-bit unchanged.
    /// `u` (world frame) is rotated in place; `f` is overwritten.
    #[inline(always)]
    fn apply(&self, rotation: Option<&[Lanes; 9]>, u: &mut [LaneV3; 8], f: &mut [LaneV3; 8]) {
        if let Some(r) = rotation {
            for v in u.iter_mut() {
                *v = mat_vec(r, v);
            }
        }
        // `element::SPRINGS`' edges spelled out with constant indices (a loop over the table indexes
        // memory). Every corner has exactly one edge along each axis, so the edges initialise
        // all of `f` (0 + t and 0 − t, as the accumulating form computes them).
        macro_rules! edge {
            ($(($a:literal, $b:literal, $i:literal)),*) => {$(
                let t = self.edge_k[$i] * (u[$b][$i] - u[$a][$i]);
                f[$a][$i] = Lanes::ZERO + t;
                f[$b][$i] = Lanes::ZERO - t;
            )*};
        }
        edge!(
            (0, 1, 0),
            (3, 2, 0),
            (4, 5, 0),
            (7, 6, 0),
            (0, 3, 1),
            (1, 2, 1),
            (4, 7, 1),
            (5, 6, 1),
            (0, 4, 2),
            (1, 5, 2),
            (2, 6, 2),
            (3, 7, 2)
        );
        macro_rules! diagonal {
            ($(($d:literal, $a:literal, $b:literal)),*) => {$(
                let d = &self.diag_dir[$d];
                let du: LaneV3 = [
                    u[$b][0] - u[$a][0],
                    u[$b][1] - u[$a][1],
                    u[$b][2] - u[$a][2],
                ];
                let s = self.diag_k * (d[0] * du[0] + d[1] * du[1] + d[2] * du[2]);
                for i in 0..3 {
                    let t = d[i] * s;
                    f[$a][i] = f[$a][i] + t;
                    f[$b][i] = f[$b][i] - t;
                }
            )*};
        }
        diagonal!((0, 0, 6), (1, 1, 7), (2, 2, 4), (3, 3, 5));
        // axial_i = −½ Σ_n s_n,i f_n,i (scaling by ±½ is exact, so it can come last).
        let mut g = [Lanes::ZERO; 3];
        for (n, signs) in CORNER_SIGNS.iter().enumerate() {
            for i in 0..3 {
                g[i] = if signs[i] > 0.0 {
                    g[i] + f[n][i]
                } else {
                    g[i] - f[n][i]
                };
            }
        }
        let half = Lanes::splat(-0.5);
        let axial = [half * g[0], half * g[1], half * g[2]];
        let w = mat_vec(&self.correction_map, &axial);
        // f ← −(f + s·w), written as (−f) ∓ w: negation is exact.
        for (n, signs) in CORNER_SIGNS.iter().enumerate() {
            for i in 0..3 {
                let neg = Lanes::ZERO - f[n][i];
                f[n][i] = if signs[i] > 0.0 {
                    neg - w[i]
                } else {
                    neg + w[i]
                };
            }
        }
        if let Some(r) = rotation {
            for v in f.iter_mut() {
                *v = mat_t_vec(r, v);
            }
        }
    }
}

/// Trilinear interpolation from a coarse cell's 8 corners to the 8 corners of its child
/// `offset` (each component 0 or 1), as a 24 × 24 matrix (fine DOF × coarse DOF).
fn child_interpolation(offset: [u32; 3]) -> M24 {
    let mut p = M24::zeros();
    for (fc, fs) in CORNER_SIGNS.iter().enumerate() {
        let t: [f64; 3] =
            std::array::from_fn(|a| (offset[a] as f64 + (fs[a] > 0.0) as u32 as f64) / 2.0);
        for (cc, cs) in CORNER_SIGNS.iter().enumerate() {
            let w: f64 = (0..3)
                .map(|a| if cs[a] > 0.0 { t[a] } else { 1.0 - t[a] })
                .product();
            for i in 0..3 {
                p[(3 * fc + i, 3 * cc + i)] = w;
            }
        }
    }
    p
}

/// The next coarser level of `fine`, whose cells and nodes are given as (lattice i, j, k,
/// body); returns it with its own cells and nodes in the same form.
fn coarsen(
    fine: &mut Level,
    cells: &[[u32; 4]],
    node_ijk: &[[u32; 4]],
) -> (Level, Vec<[u32; 4]>, Vec<[u32; 4]>) {
    let interp: Vec<M24> = (0..8)
        .map(|o| child_interpolation([o & 1, (o >> 1) & 1, (o >> 2) & 1]))
        .collect();
    let mut cell_index: HashMap<[u32; 4], u32> = HashMap::new();
    let mut c_cells: Vec<[u32; 4]> = Vec::new();
    let mut children: Vec<Vec<(u32, usize)>> = Vec::new();
    for (e, c) in cells.iter().enumerate() {
        let parent = [c[0] / 2, c[1] / 2, c[2] / 2, c[3]];
        let o = ((c[0] & 1) | ((c[1] & 1) << 1) | ((c[2] & 1) << 2)) as usize;
        let idx = *cell_index.entry(parent).or_insert_with(|| {
            c_cells.push(parent);
            children.push(Vec::new());
            (c_cells.len() - 1) as u32
        });
        children[idx as usize].push((e as u32, o));
    }
    let mut node_index: HashMap<[u32; 4], u32> = HashMap::new();
    let mut c_nodes: Vec<[u32; 4]> = Vec::new();
    let c_elements: Vec<[u32; 8]> = c_cells
        .iter()
        .map(|c| {
            CORNER_SIGNS.map(|s| {
                let l: [u32; 4] = std::array::from_fn(|a| {
                    if a < 3 {
                        c[a] + (s[a] > 0.0) as u32
                    } else {
                        c[3]
                    }
                });
                *node_index.entry(l).or_insert_with(|| {
                    c_nodes.push(l);
                    (c_nodes.len() - 1) as u32
                })
            })
        })
        .collect();
    // Prolongation rows of the fine nodes.
    fine.prolong = node_ijk
        .iter()
        .map(|p| {
            let mut row = [(0u32, 0.0f64); 8];
            let mut k = 0;
            let opts = |v: u32| -> [(u32, f64); 2] {
                if v.is_multiple_of(2) {
                    [(v / 2, 1.0), (v / 2, 0.0)]
                } else {
                    [(v / 2, 0.5), (v / 2 + 1, 0.5)]
                }
            };
            let (ox, oy, oz) = (opts(p[0]), opts(p[1]), opts(p[2]));
            for &(i, wi) in &ox {
                for &(j, wj) in &oy {
                    for &(l, wl) in &oz {
                        let w = wi * wj * wl;
                        if w != 0.0 {
                            let c = node_index
                                .get(&[i, j, l, p[3]])
                                .copied()
                                .expect("every fine node lies in an active coarse cell");
                            row[k] = (c, w);
                            k += 1;
                        }
                    }
                }
            }
            row
        })
        .collect();
    // Galerkin coarse element matrices. A coarse cell's matrix depends only on its children's
    // offsets, classes and corner projectors; cells agreeing on all three (the interior, and
    // runs along flat constrained faces) share one computed matrix, which keeps the level's
    // matrices few enough to stay in cache during products.
    let mut projector_id: HashMap<[u64; 9], u32> = HashMap::new();
    let node_projector: Vec<u32> = fine
        .projector
        .iter()
        .map(|p| match p {
            None => 0,
            Some(p) => {
                let bits: [u64; 9] = std::array::from_fn(|i| p.as_slice()[i].to_bits());
                let next = projector_id.len() as u32 + 1;
                *projector_id.entry(bits).or_insert(next)
            }
        })
        .collect();
    let mut by_children: HashMap<Vec<(usize, u32, [u32; 8])>, u32> = HashMap::new();
    let mut matrices: Vec<M24> = Vec::new();
    let mut matrix_of: Vec<u32> = Vec::with_capacity(children.len());
    for kids in &children {
        let mut key: Vec<(usize, u32, [u32; 8])> = kids
            .iter()
            .map(|&(e, o)| {
                let e = e as usize;
                let p =
                    fine.elements[e].map(|n| node_projector.get(n as usize).copied().unwrap_or(0));
                (o, fine.matrix_of[e], p)
            })
            .collect();
        key.sort_unstable();
        if let Some(&m) = by_children.get(&key) {
            matrix_of.push(m);
            continue;
        }
        let mut kc = M24::zeros();
        for &(e, o) in kids {
            let e = e as usize;
            let k = &fine.matrices[fine.matrix_of[e] as usize];
            let mut q = interp[o];
            for (c, &n) in fine.elements[e].iter().enumerate() {
                if let Some(p) = fine.projector.get(n as usize).copied().flatten() {
                    let rows = p * q.fixed_view::<3, 24>(3 * c, 0);
                    q.fixed_view_mut::<3, 24>(3 * c, 0).copy_from(&rows);
                }
            }
            kc += q.transpose() * k * q;
        }
        matrices.push(kc);
        let m = (matrices.len() - 1) as u32;
        by_children.insert(key, m);
        matrix_of.push(m);
    }
    let n_c = c_nodes.len();
    let colors = crate::model::mesh::color_elements(&c_elements, n_c);
    let mut level = Level {
        n_nodes: n_c,
        matrix_of,
        elements: c_elements,
        matrices,
        springs: Vec::new(),
        lane_springs: Vec::new(),
        rotation: None,
        colors,
        schedule: None,
        projector: vec![None; n_c],
        constrained: Vec::new(),
        slot: Vec::new(),
        touches_constraint: Vec::new(),
        row_quad: Vec::new(),
        diag: Vec::new(),
        mass: {
            let mut m = vec![0.0; n_c];
            for (row, mf) in fine.prolong.iter().zip(&fine.mass) {
                for &(c, w) in row {
                    m[c as usize] += w * mf;
                }
            }
            m
        },
        shift: 0.0,
        diag_inv: Vec::new(),
        lambda_max: 0.0,
        prolong: Vec::new(),
    };
    level.constrain_null_directions();
    level.finish();
    (level, c_cells, c_nodes)
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

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::{BrickCoefficients, BrickShape, Material};
    use nalgebra::Rotation3;

    #[test]
    fn spring_operator_equals_dense_element_stiffness() {
        let rotated = *Rotation3::from_euler_angles(0.3, -0.7, 1.1).matrix();
        for (edges, axes) in [
            ([1.0, 1.0, 1.0], Matrix3::identity()),
            ([1.0, 1.2, 0.9], Matrix3::identity()),
            ([1.0, 1.2, 0.9], rotated),
        ] {
            let c = BrickCoefficients::new(
                BrickShape { edges_m: edges },
                Material::new(1000.0, 0.3, 1.0).unwrap(),
            )
            .unwrap();
            // The dense matrix is in the element frame; rotate it to the world frame.
            let k_local = c.linear_stiffness();
            let mut r24 = M24::zeros();
            for n in 0..8 {
                r24.fixed_view_mut::<3, 3>(3 * n, 3 * n).copy_from(&axes);
            }
            let k = r24 * k_local * r24.transpose();
            let op = LinearSprings::new(&c, &axes);
            let u: [V3; 8] = std::array::from_fn(|n| {
                V3::new(
                    (n as f64).sin(),
                    (2.0 * n as f64).cos(),
                    0.3 * n as f64 - 1.0,
                )
            });
            let got = op.apply(&u);
            let mut flat_u = SMatrix::<f64, 24, 1>::zeros();
            for (n, un) in u.iter().enumerate() {
                flat_u.fixed_view_mut::<3, 1>(3 * n, 0).copy_from(un);
            }
            let want = k * flat_u;
            for n in 0..8 {
                for i in 0..3 {
                    assert!(
                        (got[n][i] - want[3 * n + i]).abs() < 1e-9 * k.amax(),
                        "edges {edges:?} corner {n} axis {i}: {} vs {}",
                        got[n][i],
                        want[3 * n + i]
                    );
                }
            }
        }
    }

    /// A lung-like irregular lattice: an ellipsoid with holes, two element classes on
    /// non-cubic bricks, and plane, line and fixed constraints on scattered nodes.
    fn irregular_multigrid(axes: Matrix3<f64>) -> Multigrid {
        let cells = [26, 22, 18];
        let mut active = Vec::new();
        for k in 0..cells[2] {
            for j in 0..cells[1] {
                for i in 0..cells[0] {
                    let r: f64 = [i, j, k]
                        .iter()
                        .zip(&cells)
                        .map(|(&c, &n)| ((c as f64 + 0.5) / n as f64 * 2.0 - 1.0).powi(2))
                        .sum();
                    active.push(r < 1.25 && (i * 7 + j * 3 + k) % 11 != 0);
                }
            }
        }
        let grid = crate::model::VoxelGrid {
            cells,
            cell_size_m: [0.004, 0.005, 0.0045],
            origin_m: V3::new(0.01, -0.02, 0.03),
            axes,
            active,
        };
        let mut mesh = grid.to_mesh(Material::LUNG).unwrap().mesh;
        assert!(
            mesh.element_count() >= PARALLEL_MIN_ELEMENTS,
            "exercise the parallel path"
        );
        let shape = mesh.classes[0].shape;
        mesh.classes.push(
            BrickCoefficients::new(shape, Material::new(2500.0, 0.35, 1.0).unwrap()).unwrap(),
        );
        for (e, class) in mesh.element_class.iter_mut().enumerate() {
            *class = ((e * 7919) % 5 == 0) as u32;
        }
        let lattice = Lattice::infer(&mesh).unwrap();
        let d = V3::new(1.0, 2.0, 0.5).normalize();
        let normal = axes.column(2).into_owned();
        let projector = lattice
            .node
            .iter()
            .map(|l| match l {
                [_, _, 0] => Some(Matrix3::identity() - normal * normal.transpose()),
                [3, _, _] => Some(d * d.transpose()),
                [i, j, 1] if (i + j) % 17 == 0 => Some(Matrix3::zeros()),
                _ => None,
            })
            .collect();
        let mut mg = Multigrid::new(&mesh, &lattice, projector);
        let fine = &mg.levels[0];
        mg.set_shift(0.3 * fine.diag[0].norm() / fine.mass[0]);
        mg
    }

    /// The straightforward product: one element at a time, serially, input projected into a
    /// copy, then shift, output projection and identity on the constrained directions.
    fn reference_apply(level: &Level, x: &[f64]) -> Vec<f64> {
        let mut xs = x.to_vec();
        project_flat(&level.constrained, &mut xs);
        let mut y = vec![0.0; x.len()];
        for (e, corners) in level.elements.iter().enumerate() {
            let m = level.matrix_of[e] as usize;
            let ue =
                corners.map(|n| V3::from_column_slice(&xs[3 * n as usize..3 * n as usize + 3]));
            let ye: Vec<V3> = match level.springs.get(m) {
                Some(op) => op.apply(&ue).to_vec(),
                None => {
                    let flat = SMatrix::<f64, 24, 1>::from_iterator(ue.iter().flatten().copied());
                    let f = level.matrices[m] * flat;
                    (0..8)
                        .map(|c| f.fixed_rows::<3>(3 * c).into_owned())
                        .collect()
                }
            };
            for (&n, f) in corners.iter().zip(&ye) {
                let n = 3 * n as usize;
                y[n..n + 3]
                    .iter_mut()
                    .zip(f.iter())
                    .for_each(|(y, f)| *y += f);
            }
        }
        for (n, m) in level.mass.iter().enumerate() {
            for i in 0..3 {
                y[3 * n + i] += level.shift * m * xs[3 * n + i];
            }
        }
        project_flat(&level.constrained, &mut y);
        for (n, p) in &level.constrained {
            let n = 3 * *n as usize;
            let xn = V3::from_column_slice(&x[n..n + 3]);
            let add = xn - p * xn;
            y[n..n + 3]
                .iter_mut()
                .zip(add.iter())
                .for_each(|(y, a)| *y += a);
        }
        y
    }

    #[test]
    fn batched_products_equal_the_per_element_product() {
        let rotated = *Rotation3::from_euler_angles(0.2, 0.5, -0.3).matrix();
        for axes in [Matrix3::identity(), rotated] {
            let mut mg = irregular_multigrid(axes);
            assert!(!mg.levels[0].constrained.is_empty());
            assert!(mg.levels[0].schedule.is_some());
            assert!(mg.levels[0].row_quad.iter().any(|&r| r));
            for variant in ["chunks", "colours", "dense fine level"] {
                match variant {
                    // The element-colour path, used when the numbering lacks locality.
                    "colours" => mg.levels.iter_mut().for_each(|l| l.schedule = None),
                    // Dense cell products with constrained corners and mixed matrices.
                    "dense fine level" => {
                        mg.levels[0].springs.clear();
                        mg.levels[0].plan();
                    }
                    _ => {}
                }
                for (l, level) in mg.levels.iter().enumerate() {
                    let x: Vec<f64> = (0..3 * level.n_nodes)
                        .map(|i| (0.37 * i as f64).sin() + 0.1)
                        .collect();
                    let want = reference_apply(level, &x);
                    let scale = want.iter().fold(0.0f64, |m, v| m.max(v.abs()));
                    let mut first: Option<Vec<f64>> = None;
                    for threads in [1, 2] {
                        let pool = rayon::ThreadPoolBuilder::new()
                            .num_threads(threads)
                            .build()
                            .unwrap();
                        for simd in [true, false] {
                            let mut y = vec![f64::NAN; x.len()];
                            pool.install(|| level.apply_with(&x, &mut y, simd));
                            let err = y
                                .iter()
                                .zip(&want)
                                .fold(0.0f64, |m, (a, b)| m.max((a - b).abs()));
                            assert!(
                                err <= 1e-12 * scale,
                                "level {l}, {threads} threads, simd {simd}, {variant}: \
                                 error {err:e} of {scale:e}"
                            );
                            if simd {
                                // Same chunks in the same order on any number of threads.
                                match &first {
                                    None => first = Some(y),
                                    Some(f) => assert_eq!(f, &y, "level {l} thread-dependent"),
                                }
                            }
                        }
                    }
                }
            }
        }
    }
}
