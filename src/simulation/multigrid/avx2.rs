//! AVX2 forms of the batch gather and scatter (node triples ↔ lane vectors by shuffles).

use super::batch::{Sink, ROW_LINES};
use crate::simulation::lanes::{LaneV3, Lanes, LANES};
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

/// See `batch::gather`. Not itself marked AVX2, so that it can be forced inline into its
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
    for &(a, b) in &ROW_LINES {
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
    for &(a, b) in &ROW_LINES {
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

/// See `batch::scatter`; same order of additions. Inlined like `gather`.
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
unsafe fn add_lanes<S: Sink>(sink: &mut S, nodes: &[u32; LANES], count: usize, v: [__m256d; 3]) {
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
