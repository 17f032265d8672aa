//! The fine level's product as a 27-point stencil: the assembled operator's row of a node
//! depends only on its cells' class and on which of its eight cells exist, so each node's
//! y = S·(Π x) costs 81 fused multiply–adds of 4 lanes (against 8 × 72 = 576 scalar ones per
//! node element-wise) with no scatter, Π x taken from a projected copy of the input. Nodes
//! whose cells mix classes keep the element-wise product, which then writes only them.
//!
//! The stencil needs node numbers that run along the lattice's x rows (ingest numbers nodes
//! x fastest): the three nodes of a stencil row are then consecutive, and so are the rows of
//! consecutive nodes, so a run of stencil nodes is described by the first node of each of its
//! nine rows. Nodes whose numbering breaks this simply stay element-wise.

use rayon::prelude::*;

use nalgebra::Matrix3;

use super::batch::Sink;
use super::product::constrained_in;
use super::M24;
use crate::model::element::CORNER_SIGNS;
use crate::simulation::lanes::{ElementSource, LANES};
use crate::simulation::linalg::nodes_mut;

/// Nodes per parallel task of the stencil pass (runs are cut at task boundaries).
const TASK_NODES: usize = 2048;

/// Consecutive stencil nodes of one pattern whose rows advance together.
#[derive(Debug, Clone, Copy)]
struct Run {
    /// First node of the run.
    first: u32,
    /// Number of nodes.
    len: u32,
    /// Index into `patterns`.
    pattern: u32,
    /// For each of the nine (dy, dz) rows, the neighbour at dx = −1 of the first node.
    rows: [u32; 9],
}

/// The stencil part of a level's product: which nodes it computes, their runs, and each
/// pattern's row as 81 four-lane columns (3 output components and one unused lane).
pub(super) struct Stencil {
    /// Per node, whether the stencil computes its output.
    pub(super) regular: Vec<bool>,
    /// Per element, whether all its corners are stencil nodes (the element pass skips it).
    pub(super) skip: Vec<bool>,
    /// Whether every node is a stencil node (then no element product is left to do).
    all: bool,
    runs: Vec<Run>,
    /// Per task of [`TASK_NODES`] nodes, its runs in `runs`.
    tasks: Vec<std::ops::Range<usize>>,
    /// Per (class, cells present) met: column 9·r + 3·(dx + 1) + c is the coefficient of
    /// input component c of the neighbour (dx, row r) in the three output components.
    patterns: Vec<[[f64; 4]; 81]>,
    /// Scratch for the projected input Π·x, when a stencil node has a constrained neighbour
    /// (leaving such nodes to the element pass instead covered only half the CIP lungs' nodes
    /// at 4 mm: the wall's sliding nodes and their neighbours are a quarter of the rest).
    projected: Option<std::sync::Mutex<Vec<f64>>>,
}

/// Stencil index of the lattice offset `d` ∈ {−1, 0, 1}³: x fastest.
fn offset_index(d: [i32; 3]) -> usize {
    ((d[0] + 1) + 3 * (d[1] + 1) + 9 * (d[2] + 1)) as usize
}

/// Lattice offset of each cell corner from the cell's first corner.
fn corner_offsets() -> [[i32; 3]; 8] {
    CORNER_SIGNS.map(|s| s.map(|v| i32::from(v > 0.0)))
}

/// The assembled operator's row of a node with the cells of matrix `k` in which it is the
/// corners set in `present`, as four-lane columns (see [`Stencil::patterns`]).
fn columns_of(k: &M24, present: u8) -> [[f64; 4]; 81] {
    let off = corner_offsets();
    let mut s = [[[0.0; 3]; 3]; 27];
    // The node is corner q of one of its cells; that cell couples it to the cell's corner j.
    for (q, oq) in off.iter().enumerate() {
        if present & (1 << q) == 0 {
            continue;
        }
        for (j, oj) in off.iter().enumerate() {
            let d = offset_index(std::array::from_fn(|a| oj[a] - oq[a]));
            for (a, row) in s[d].iter_mut().enumerate() {
                for (b, v) in row.iter_mut().enumerate() {
                    *v += k[(3 * q + a, 3 * j + b)];
                }
            }
        }
    }
    let mut cols = [[0.0; 4]; 81];
    for (i, col) in cols.iter_mut().enumerate() {
        let (r, j) = (i / 9, i % 9);
        let (dx, c) = (j / 3, j % 3);
        let block = &s[dx + 3 * r];
        for (a, v) in col.iter_mut().take(3).enumerate() {
            *v = block[a][c];
        }
    }
    cols
}

impl Stencil {
    /// The stencil of a dense fine level (`elements` with `matrix_of` into `matrices`, nodes
    /// with constraint `projector`s), or `None` when no node qualifies.
    pub(super) fn new(
        n_nodes: usize,
        elements: &[[u32; 8]],
        matrix_of: &[u32],
        matrices: &[M24],
        projector: &[Option<Matrix3<f64>>],
    ) -> Option<Stencil> {
        let off = corner_offsets();
        let mut around = vec![[u32::MAX; 8]; n_nodes];
        for (e, corners) in elements.iter().enumerate() {
            for (q, &c) in corners.iter().enumerate() {
                around[c as usize][q] = e as u32;
            }
        }
        let free = |n: u32| projector.get(n as usize).is_none_or(|p| p.is_none());
        let mut touches_constraint = false;
        let mut patterns: Vec<[[f64; 4]; 81]> = Vec::new();
        let mut pattern_of: std::collections::HashMap<(u32, u8), u32> = Default::default();
        // The node's nine row starts and pattern, when the stencil can compute it: its cells
        // share one class, and the neighbours they hold lie along consecutive numbers in each
        // row. A neighbour no cell holds has zero coefficients, so any in-range number serves
        // (a non-finite entry would spoil the Krylov vectors' dot products whatever it touched,
        // and the solver reports a non-finite residual).
        let mut regular = |n: usize| -> Option<([u32; 9], u32)> {
            let cells = around[n];
            let first = cells.iter().find(|&&e| e != u32::MAX)?;
            let class = matrix_of[*first as usize];
            let mut present = 0u8;
            for (q, &e) in cells.iter().enumerate() {
                if e != u32::MAX {
                    if matrix_of[e as usize] != class {
                        return None;
                    }
                    present |= 1 << q;
                }
            }
            let mut nb = [u32::MAX; 27];
            for (q, &e) in cells.iter().enumerate() {
                if e == u32::MAX {
                    continue;
                }
                for (j, &c) in elements[e as usize].iter().enumerate() {
                    let d = offset_index(std::array::from_fn(|a| off[j][a] - off[q][a]));
                    if nb[d] != u32::MAX && nb[d] != c {
                        return None;
                    }
                    nb[d] = c;
                }
            }
            let mut rows = [0u32; 9];
            for (r, start) in rows.iter_mut().enumerate() {
                // Rows without a neighbour read the node's own row, which advances with it.
                let mut base: Option<i64> = None;
                for (dx, &c) in nb[3 * r..3 * r + 3].iter().enumerate() {
                    if c == u32::MAX {
                        continue;
                    }
                    let b = c as i64 - dx as i64;
                    if base.is_some_and(|have| have != b) {
                        return None;
                    }
                    base = Some(b);
                }
                let b = base.unwrap_or(n as i64 - 1);
                if b < 0 || b + 3 > n_nodes as i64 {
                    return None;
                }
                *start = b as u32;
            }
            touches_constraint |= nb.iter().any(|&c| c != u32::MAX && !free(c));
            let pattern = *pattern_of.entry((class, present)).or_insert_with(|| {
                patterns.push(columns_of(&matrices[class as usize], present));
                patterns.len() as u32 - 1
            });
            Some((rows, pattern))
        };
        let mut is_regular = vec![false; n_nodes];
        let mut runs: Vec<Run> = Vec::new();
        for (n, flag) in is_regular.iter_mut().enumerate() {
            let Some((rows, pattern)) = regular(n) else {
                continue;
            };
            *flag = true;
            let n = n as u32;
            if let Some(run) = runs.last_mut() {
                let extends = run.pattern == pattern
                    && run.first + run.len == n
                    && run.first as usize / TASK_NODES == n as usize / TASK_NODES
                    && (0..9).all(|r| run.rows[r] + run.len == rows[r]);
                if extends {
                    run.len += 1;
                    continue;
                }
            }
            runs.push(Run {
                first: n,
                len: 1,
                pattern,
                rows,
            });
        }
        if runs.is_empty() {
            return None;
        }
        let all = is_regular.iter().all(|&r| r);
        let skip = elements
            .iter()
            .map(|cs| cs.iter().all(|&c| is_regular[c as usize]))
            .collect();
        let tasks = (0..n_nodes.div_ceil(TASK_NODES))
            .map(|t| {
                let lo = runs.partition_point(|r| (r.first as usize) < t * TASK_NODES);
                let hi = runs.partition_point(|r| (r.first as usize) < (t + 1) * TASK_NODES);
                lo..hi
            })
            .collect();
        Some(Stencil {
            regular: is_regular,
            skip,
            all,
            runs,
            tasks,
            patterns,
            projected: touches_constraint.then(Default::default),
        })
    }

    /// Fraction of the nodes the stencil computes.
    pub(super) fn coverage(&self) -> f64 {
        let n: u32 = self.runs.iter().map(|r| r.len).sum();
        n as f64 / self.regular.len().max(1) as f64
    }

    /// Whether the stencil computes every node (no element product is left to do).
    pub(super) fn covers_all(&self) -> bool {
        self.all
    }

    /// Sets `y` = (σ·M + S)·(Π x) on the stencil nodes, Π projecting the `constrained` nodes,
    /// M the lumped `mass` and σ the `shift` (on every core when `parallel`; `simd` = false
    /// forces the portable kernel).
    #[allow(clippy::too_many_arguments)]
    pub(super) fn product(
        &self,
        x: &[f64],
        constrained: &[(u32, Matrix3<f64>)],
        mass: &[f64],
        shift: f64,
        y: &mut [f64],
        parallel: bool,
        simd: bool,
    ) {
        assert_eq!(x.len(), 3 * self.regular.len());
        assert_eq!(y.len(), x.len());
        assert_eq!(mass.len(), self.regular.len());
        let mut guard = self.projected.as_ref().map(|m| {
            let mut p = m.lock().unwrap_or_else(std::sync::PoisonError::into_inner);
            p.resize(x.len(), 0.0);
            let copy = |(t, (p, x)): (usize, (&mut [f64], &[f64]))| {
                p.copy_from_slice(x);
                let lo = (t * TASK_NODES) as u32;
                let pn = nodes_mut(p);
                for (n, proj) in constrained_in(constrained, lo..lo + pn.len() as u32) {
                    let i = (n - lo) as usize;
                    pn[i] = proj * pn[i];
                }
            };
            if parallel {
                p.par_chunks_mut(3 * TASK_NODES)
                    .zip(x.par_chunks(3 * TASK_NODES))
                    .enumerate()
                    .for_each(copy);
            } else {
                copy((0, (&mut p[..], x)));
            }
            p
        });
        let x: &[f64] = guard.as_deref_mut().map_or(x, |p| &p[..]);
        let simd = simd && has_avx2_fma();
        let task = |(t, y): (usize, &mut [f64])| {
            let lo = t * TASK_NODES;
            for run in &self.runs[self.tasks[t].clone()] {
                let cols = &self.patterns[run.pattern as usize];
                let (first, end) = (run.first as usize, (run.first + run.len) as usize);
                let out = &mut y[3 * (first - lo)..3 * (end - lo)];
                // Every node a run reads (up to dx = +1 of its last node) is a mesh node.
                let last =
                    run.rows.iter().max().copied().unwrap_or(0) as usize + run.len as usize + 1;
                assert!(3 * last + 3 <= x.len(), "stencil run beyond the input");
                let (xs, ms) = (&x[3 * first..3 * end], &mass[first..end]);
                #[cfg(target_arch = "x86_64")]
                if simd {
                    // SAFETY: the CPU has AVX2 and FMA (checked above); the run's reads are in
                    // bounds (asserted just above) and `out` holds its 3·len outputs.
                    unsafe { run_avx2(cols, x, &run.rows, out) };
                    shifted(out, xs, ms, shift);
                    continue;
                }
                run_portable(cols, x, &run.rows, out);
                shifted(out, xs, ms, shift);
            }
        };
        if parallel {
            y.par_chunks_mut(3 * TASK_NODES).enumerate().for_each(task);
        } else {
            y.chunks_mut(3 * TASK_NODES).enumerate().for_each(task);
        }
    }
}

/// Adds the shift term σ·m·x to a run's outputs (`x` and `m`: the run's own nodes).
#[inline(always)]
fn shifted(out: &mut [f64], x: &[f64], m: &[f64], shift: f64) {
    if shift > 0.0 {
        for ((o, x), m) in out.chunks_exact_mut(3).zip(x.chunks_exact(3)).zip(m) {
            let s = shift * m;
            o[0] += s * x[0];
            o[1] += s * x[1];
            o[2] += s * x[2];
        }
    }
}

/// Whether the CPU has the instructions of the AVX2 kernel.
fn has_avx2_fma() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma")
    }
    #[cfg(not(target_arch = "x86_64"))]
    false
}

/// One run's outputs `out` (3 per node) = S·x, node by node.
fn run_portable(cols: &[[f64; 4]; 81], x: &[f64], rows: &[u32; 9], out: &mut [f64]) {
    for (t, y) in out.chunks_exact_mut(3).enumerate() {
        let mut acc = [0.0; 3];
        for (r, &start) in rows.iter().enumerate() {
            let w = &x[3 * (start as usize + t)..3 * (start as usize + t) + 9];
            for (j, &xj) in w.iter().enumerate() {
                let col = &cols[9 * r + j];
                for a in 0..3 {
                    acc[a] += col[a] * xj;
                }
            }
        }
        y.copy_from_slice(&acc);
    }
}

/// [`run_portable`] with fused multiply–adds, two nodes at a time sharing the column loads,
/// three accumulators per node (one per dx) so the additions do not wait on each other.
///
/// # Safety
/// The CPU must support AVX2 and FMA; `x` must hold every node of the run's rows up to
/// dx = +1 of its last node.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn run_avx2(cols: &[[f64; 4]; 81], x: &[f64], rows: &[u32; 9], out: &mut [f64]) {
    use std::arch::x86_64::*;
    let len = out.len() / 3;
    let xp = x.as_ptr();
    let add_out = |out: &mut [f64], acc: [__m256d; 3]| {
        let mut v = [0.0; 4];
        // SAFETY: `v` holds 4 f64; the caller's contract gives AVX.
        unsafe {
            _mm256_storeu_pd(
                v.as_mut_ptr(),
                _mm256_add_pd(_mm256_add_pd(acc[0], acc[1]), acc[2]),
            )
        };
        out.copy_from_slice(&v[..3]);
    };
    let mut t = 0;
    // SAFETY (both loops): reads stay within x by the caller's contract, columns are 4 f64.
    unsafe {
        while t + 2 <= len {
            let mut a = [_mm256_setzero_pd(); 3];
            let mut b = [_mm256_setzero_pd(); 3];
            for (r, &start) in rows.iter().enumerate() {
                let w = xp.add(3 * (start as usize + t));
                for (dx, (a, b)) in a.iter_mut().zip(&mut b).enumerate() {
                    for c in 0..3 {
                        let j = 3 * dx + c;
                        let col = _mm256_loadu_pd(cols[9 * r + j].as_ptr());
                        *a = _mm256_fmadd_pd(col, _mm256_broadcast_sd(&*w.add(j)), *a);
                        *b = _mm256_fmadd_pd(col, _mm256_broadcast_sd(&*w.add(j + 3)), *b);
                    }
                }
            }
            add_out(&mut out[3 * t..3 * t + 3], a);
            add_out(&mut out[3 * t + 3..3 * t + 6], b);
            t += 2;
        }
        if t < len {
            let mut a = [_mm256_setzero_pd(); 3];
            for (r, &start) in rows.iter().enumerate() {
                let w = xp.add(3 * (start as usize + t));
                for (dx, a) in a.iter_mut().enumerate() {
                    for c in 0..3 {
                        let j = 3 * dx + c;
                        let col = _mm256_loadu_pd(cols[9 * r + j].as_ptr());
                        *a = _mm256_fmadd_pd(col, _mm256_broadcast_sd(&*w.add(j)), *a);
                    }
                }
            }
            add_out(&mut out[3 * t..3 * t + 3], a);
        }
    }
}

/// Element ids from an iterator, [`LANES`] at a time (the element pass's non-skipped cells).
pub(super) struct Ids<I>(pub(super) I);

impl<I: Iterator<Item = u32>> ElementSource for Ids<I> {
    #[inline(always)]
    fn next_batch(&mut self, ids: &mut [u32; LANES]) -> Option<usize> {
        let mut count = 0;
        while count < LANES {
            match self.0.next() {
                Some(e) => {
                    ids[count] = e;
                    count += 1;
                }
                None => break,
            }
        }
        if count == 0 {
            return None;
        }
        let last = ids[count - 1];
        ids[count..].fill(last);
        Some(count)
    }
}

/// A sink that drops the stencil nodes' contributions (the stencil pass computes them whole).
pub(super) struct Masked<'a, S> {
    pub(super) inner: &'a mut S,
    pub(super) regular: &'a [bool],
    pub(super) spare: [f64; 3],
}

impl<S: Sink> Sink for Masked<'_, S> {
    #[inline(always)]
    fn node(&mut self, node: u32) -> &mut [f64; 3] {
        if self.regular[node as usize] {
            &mut self.spare
        } else {
            self.inner.node(node)
        }
    }
}
