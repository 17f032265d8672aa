//! A level's operator product y = A·x: the shift term, the element products scattered chunk
//! by chunk (or colour by colour), and the constraint projections.

use rayon::prelude::*;

use super::batch::{dense_lanes, gather, scatter, Shared, Sink, Window};
use super::level::{Level, FREE};
use super::springs::LaneSprings;
use super::stencil::{Ids, Masked};
use super::NODE_TASK;
use crate::math::V3;
use crate::simulation::forces::PARALLEL_MIN_ELEMENTS;
use crate::simulation::lanes::{ElementSource, LaneV3, Lanes, LANES};
use crate::simulation::linalg::{nodes, nodes_mut};

/// Smallest dense level whose products are worth computing on several cores.
const TWO_PHASE_MIN_CELLS: usize = 512;

/// Cells per task of the two-phase dense product.
const TWO_PHASE_TASK: usize = 128;

/// Whether the CPU has the instructions of the per-cell dense kernel.
fn has_avx2_fma() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma")
    }
    #[cfg(not(target_arch = "x86_64"))]
    false
}

/// The entries of a node-sorted constraint list whose nodes lie in `nodes`.
pub(super) fn constrained_in(
    constrained: &[(u32, nalgebra::Matrix3<f64>)],
    nodes: std::ops::Range<u32>,
) -> &[(u32, nalgebra::Matrix3<f64>)] {
    debug_assert!(constrained.is_sorted_by_key(|c| c.0));
    let lo = constrained.partition_point(|c| c.0 < nodes.start);
    let hi = constrained.partition_point(|c| c.0 < nodes.end);
    &constrained[lo..hi]
}

/// One cell's 24 outputs, handed out corner after corner in the order the kernel asks.
struct CellOutputs<'a> {
    out: &'a mut [f64; 24],
    next: usize,
}

impl Sink for CellOutputs<'_> {
    #[inline(always)]
    fn node(&mut self, _node: u32) -> &mut [f64; 3] {
        let b = 3 * self.next;
        self.next += 1;
        (&mut self.out[b..b + 3]).try_into().expect("3 values")
    }
}

impl Level {
    /// y = A·x on this level.
    pub(super) fn apply(&self, x: &[f64], y: &mut [f64]) {
        self.apply_with(x, y, true);
    }

    /// `apply`, with `simd` = false forcing the portable kernels (to test them on any CPU).
    fn apply_with(&self, x: &[f64], y: &mut [f64], simd: bool) {
        assert_eq!(x.len(), 3 * self.n_nodes);
        assert_eq!(y.len(), 3 * self.n_nodes);
        let parallel =
            rayon::current_num_threads() > 1 && self.elements.len() >= PARALLEL_MIN_ELEMENTS;
        // A stencil over every node sets the whole output (shift term included) by itself.
        let whole = self.stencil.as_ref().is_some_and(|s| s.covers_all());
        if !whole {
            self.init_with_shift(x, y, parallel);
        }
        // The stencil sets its nodes' outputs; the element products then add into the others.
        if let Some(stencil) = &self.stencil {
            stencil.product(
                x,
                &self.constrained,
                &self.mass,
                self.shift,
                y,
                parallel,
                simd,
            );
        }
        // Below the parallel threshold the plan is one chunk in element order, the order the
        // two-phase product keeps (without a plan the order is colour by colour).
        let two_phase = simd
            && self.schedule.is_some()
            && rayon::current_num_threads() > 1
            && self.lane_springs.is_empty()
            && self.stencil.is_none()
            && (TWO_PHASE_MIN_CELLS..PARALLEL_MIN_ELEMENTS).contains(&self.elements.len())
            && has_avx2_fma();
        if whole {
        } else if two_phase {
            self.dense_two_phase(x, y);
        } else {
            self.scatter_all(x, y, parallel, simd);
        }
        // Π y plus the identity on the constrained directions: node range by node range, on
        // every core for long levels (the wall's sliding nodes are a quarter of the CIP
        // lungs' nodes at 4 mm).
        let finish = |(t, y): (usize, &mut [f64])| {
            let lo = (t * NODE_TASK) as u32;
            let hi = lo + (y.len() / 3) as u32;
            let (yn, xn) = (nodes_mut(y), nodes(x));
            for (n, p) in constrained_in(&self.constrained, lo..hi) {
                let (i, n) = ((n - lo) as usize, *n as usize);
                yn[i] = p * yn[i] + (xn[n] - p * xn[n]);
            }
        };
        if parallel {
            y.par_chunks_mut(3 * NODE_TASK).enumerate().for_each(finish);
        } else if !self.constrained.is_empty() {
            finish((0, y));
        }
    }

    /// Sets `y` to the shift term σ·M·(Π x), so the element sums need no zeroed output.
    fn init_with_shift(&self, x: &[f64], y: &mut [f64], parallel: bool) {
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
    }

    /// Adds every cell's product into `y`: chunk by chunk (in parallel when `parallel`), or
    /// colour by colour without a chunk plan.
    fn scatter_all(&self, x: &[f64], y: &mut [f64], parallel: bool, simd: bool) {
        match &self.schedule {
            Some(schedule) => schedule.for_each_chunk(y, 3, parallel, |elements, lo, window| {
                let mut sink = Window {
                    lo: lo as u32,
                    out: window,
                };
                let mut batch = elements.start as u32..elements.end as u32;
                match &self.stencil {
                    Some(st) => self.scatter(
                        x,
                        &mut Ids(batch.filter(|&e| !st.skip[e as usize])),
                        &mut Masked {
                            inner: &mut sink,
                            regular: &st.regular,
                            spare: [0.0; 3],
                        },
                        simd,
                    ),
                    None => self.scatter(x, &mut batch, &mut sink, simd),
                }
            }),
            None => {
                let shared = Shared(y.as_mut_ptr(), y.len());
                for colour in &self.colors {
                    let run = |task: &[u32]| match &self.stencil {
                        Some(st) => self.scatter(
                            x,
                            &mut Ids(task.iter().copied().filter(|&e| !st.skip[e as usize])),
                            &mut Masked {
                                inner: &mut { shared },
                                regular: &st.regular,
                                spare: [0.0; 3],
                            },
                            simd,
                        ),
                        None => self.scatter(x, &mut task.iter(), &mut { shared }, simd),
                    };
                    if parallel && colour.len() >= 512 {
                        colour.par_chunks(128).for_each(run);
                    } else {
                        run(colour);
                    }
                }
            }
        }
    }

    /// The dense cells of a level too small for a chunk plan: their products computed on
    /// every core into `cell_products`, then added into `y` on one, cell by cell and corner by
    /// corner, the order of the one-chunk pass, so the sums are the same bits. (Splitting such
    /// a level into chunks changed the order of the sums and cost 8 % more Krylov iterations
    /// on the POPI lungs; on one core its products were a quarter of a 6 mm solve.)
    fn dense_two_phase(&self, x: &[f64], y: &mut [f64]) {
        #[cfg(target_arch = "x86_64")]
        {
            #[target_feature(enable = "avx2,fma")]
            unsafe fn cells(level: &Level, x: &[f64], first: usize, out: &mut [[f64; 24]]) {
                for (i, out) in out.iter_mut().enumerate() {
                    *out = [0.0; 24];
                    let mut sink = CellOutputs { out, next: 0 };
                    // SAFETY: compiled for, and called on, a CPU with AVX2 and FMA.
                    unsafe { level.dense_cell(x, first + i, &mut sink) };
                }
            }
            let mut products = self
                .cell_products
                .lock()
                .unwrap_or_else(std::sync::PoisonError::into_inner);
            products.resize(self.elements.len(), [0.0; 24]);
            products
                .par_chunks_mut(TWO_PHASE_TASK)
                .enumerate()
                .for_each(|(t, out)| {
                    // SAFETY: `two_phase` checked that the CPU has AVX2 and FMA.
                    unsafe { cells(self, x, t * TWO_PHASE_TASK, out) }
                });
            let yn = nodes_mut(y);
            for (corners, product) in self.elements.iter().zip(products.iter()) {
                for (&n, v) in corners.iter().zip(product.chunks_exact(3)) {
                    let o = &mut yn[n as usize];
                    o.x += v[0];
                    o.y += v[1];
                    o.z += v[2];
                }
            }
        }
        #[cfg(not(target_arch = "x86_64"))]
        self.scatter_all(x, y, false, true);
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
}

#[cfg(test)]
pub(super) mod tests {
    use super::super::lattice::Lattice;
    use super::super::level::project_flat;
    use super::super::preconditioner::Multigrid;
    use super::*;
    use crate::model::{BrickCoefficients, HourglassLaw, Material};
    use nalgebra::{Matrix3, Rotation3, SMatrix};

    /// A lung-like irregular lattice: an ellipsoid with holes, two element classes on
    /// non-cubic bricks, and plane, line and fixed constraints on scattered nodes.
    pub(in crate::simulation::multigrid) fn irregular_multigrid(
        axes: Matrix3<f64>,
        hourglass: HourglassLaw,
    ) -> Multigrid {
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
        let mut mesh = grid
            .to_mesh_in_lattice_order(Material::LUNG.with_hourglass(hourglass))
            .unwrap()
            .mesh;
        assert!(
            mesh.element_count() >= PARALLEL_MIN_ELEMENTS,
            "exercise the parallel path"
        );
        let shape = mesh.classes[0].shape;
        mesh.classes.push(
            BrickCoefficients::new(
                shape,
                Material::new(2500.0, 0.35, 1.0)
                    .unwrap()
                    .with_hourglass(hourglass),
            )
            .unwrap(),
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
        let cases = [Matrix3::identity(), rotated]
            .into_iter()
            .flat_map(|a| [HourglassLaw::Springs, HourglassLaw::FullIntegration].map(|h| (a, h)));
        for (axes, hourglass) in cases {
            let mut mg = irregular_multigrid(axes, hourglass);
            // The spring lane kernels carry no hourglass correction: with one, the fine level
            // is multiplied by the classes' dense matrices, which do.
            assert_eq!(
                mg.levels[0].springs.is_empty(),
                hourglass != HourglassLaw::Springs
            );
            assert!(!mg.levels[0].constrained.is_empty());
            // With dense matrices the fine level takes the stencil product where a node's cells
            // share a class, and the element product (writing only the others) elsewhere.
            let coverage = mg.levels[0].stencil.as_ref().map(|s| s.coverage());
            match hourglass {
                HourglassLaw::Springs => assert!(coverage.is_none()),
                _ => assert!(coverage.is_some_and(|c| c > 0.2 && c < 0.9), "{coverage:?}"),
            }
            assert!(mg.levels[0].schedule.is_some());
            assert!(mg.levels[0].row_quad.iter().any(|&r| r));
            // A coarse level takes the two-phase dense product on two threads: the bitwise
            // comparison across thread counts below covers it.
            assert!(mg.levels[1..].iter().any(|l| {
                (TWO_PHASE_MIN_CELLS..PARALLEL_MIN_ELEMENTS).contains(&l.elements.len())
            }));
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
                                "level {l}, {threads} threads, simd {simd}, {variant}, \
                                 {hourglass:?}: error {err:e} of {scale:e}"
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
