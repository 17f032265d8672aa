//! Lane batches of elements: gathering their corners from a node vector into SIMD lanes,
//! the dense 24 × 24 product on lanes, and scattering the results into the output.

use crate::simulation::lanes::{LaneV3, Lanes, LANES};

/// Where element products are added: one chunk's node window of the output, or (fallback)
/// the whole output shared by the elements of one colour.
pub(super) trait Sink {
    /// The three output values of `node`.
    fn node(&mut self, node: u32) -> &mut [f64; 3];
}

/// A chunk's own window `out[3·lo..]` of the output.
pub(super) struct Window<'a> {
    pub(super) lo: u32,
    pub(super) out: &'a mut [f64],
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
pub(super) struct Shared(pub(super) *mut f64, pub(super) usize);
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
pub(super) fn gather<const AVX2: bool>(
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
                super::avx2::gather_row(x, corners, u);
            } else {
                super::avx2::gather(x, corners, u);
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
pub(super) fn scatter<const AVX2: bool, S: Sink>(
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
                super::avx2::scatter_row(f, corners, sink);
            } else {
                super::avx2::scatter(f, corners, count, sink);
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
pub(super) fn dense_lanes(k: impl Fn(usize) -> Lanes, u: &[LaneV3; 8], f: &mut [LaneV3; 8]) {
    for (r, fr) in f.as_flattened_mut().iter_mut().enumerate() {
        let mut acc = Lanes::ZERO;
        for (j, uj) in u.as_flattened().iter().enumerate() {
            acc = acc + k(24 * j + r) * *uj;
        }
        *fr = acc;
    }
}

/// Corner pairs (a, b) joined by the element's x edges: corner b of an element is corner a
/// of the next element along its row.
pub(super) const ROW_LINES: [(usize, usize); 4] = [(0, 1), (3, 2), (4, 5), (7, 6)];
