//! Internal forces of Baudet elements: springs, Voigt dampers and Lagrange corrections.
//!
//! Cost: one pass over the elements, 16 spring evaluations (one square root and one division
//! each) and a 3 × 3 correction per element; no allocation proportional to the mesh.
//!
//! Layout. Elements are evaluated [`LANES`] at a time in structure-of-arrays form (one SIMD
//! lane per element), so square roots, divisions and the correction run on full vectors; on
//! x86-64 the batch loop is compiled a second time for AVX2 and chosen at run time, since
//! the default target only guarantees SSE2.
//!
//! Parallelism. The element list is cut into contiguous chunks; chunks whose node-index
//! ranges are disjoint get the same colour and run in parallel, each writing through its own
//! sub-slice of the output (no `unsafe`, no atomics). Meshes numbered in lattice order need 2
//! or 3 colours, so an evaluation has 2–3 barriers instead of one per element colour, and each
//! thread walks the mesh in memory order. Meshes without that locality fall back to the
//! mesh's element colouring. The schedule depends only on the mesh, and chunks run in the same
//! order on any number of threads, so results are bit-for-bit independent of the thread count.

use nalgebra::Matrix3;
use rayon::prelude::*;

use super::lanes::{add3, cross3, dot3, normalize3, scale3, sub3, ElementSource, LaneV3, Lanes};
use crate::math::V3;
use crate::model::continuum_correction::DIAGONAL_SIGNS;
use crate::model::element::{BrickCoefficients, CORNER_SIGNS, SPRINGS};
use crate::model::{ContinuumCorrection, HexMesh, HourglassCorrection, VolumetricCorrection};

/// Per-class constants laid out for the force kernel.
#[derive(Debug, Clone)]
pub struct ElementKernel {
    coefficients: BrickCoefficients,
    stiffness: [f64; 16],
    cubic: [f64; 16],
    rest_length: [f64; 16],
    damping: [f64; 16],
    correction_map: Matrix3<f64>,
}

impl ElementKernel {
    /// Packs one coefficient set.
    pub fn new(c: &BrickCoefficients) -> Self {
        ElementKernel {
            coefficients: c.clone(),
            stiffness: SPRINGS.map(|(_, _, k)| c.spring_stiffness(k)),
            cubic: SPRINGS.map(|(_, _, k)| c.spring_cubic_n_per_m3(k)),
            rest_length: SPRINGS.map(|(_, _, k)| c.rest_length_m(k)),
            damping: c.spring_damping_n_s_per_m,
            correction_map: c.correction_map,
        }
    }

    /// Forces in newtons on the 8 corners at positions `x` (and velocities `v` for damping):
    /// [`BrickCoefficients::corner_forces`], the scalar reference of the batched kernel.
    #[inline]
    pub fn forces(&self, x: &[V3; 8], v: Option<&[V3; 8]>) -> [V3; 8] {
        self.coefficients.corner_forces(x, v)
    }
}

pub use super::lanes::LANES;

/// An [`ElementKernel`] replicated across lanes (or gathered, for batches mixing classes).
#[derive(Debug, Clone)]
struct LaneKernel {
    stiffness: [Lanes; 16],
    cubic: [Lanes; 16],
    rest_length: [Lanes; 16],
    damping: [Lanes; 16],
    /// Row-major correction map W.
    correction_map: [Lanes; 9],
    /// 1/(64·V₀): the volume ratio is det(ex, ey, ez) times this.
    inv_64_rest_volume: Lanes,
    /// 1/L_i² per axis (continuum correction: I₁ = Σ|ē_i|²/L_i²).
    inv_edge_squared: [Lanes; 3],
    /// V₀/(4L_i²) per axis (continuum correction: the law's α·F term on axis i).
    volume_over_4_edge_squared: [Lanes; 3],
}

impl LaneKernel {
    fn splat(k: &ElementKernel) -> Self {
        LaneKernel {
            stiffness: k.stiffness.map(Lanes::splat),
            cubic: k.cubic.map(Lanes::splat),
            rest_length: k.rest_length.map(Lanes::splat),
            damping: k.damping.map(Lanes::splat),
            correction_map: std::array::from_fn(|r| Lanes::splat(k.correction_map[(r / 3, r % 3)])),
            inv_64_rest_volume: Lanes::splat(1.0 / (64.0 * k.coefficients.shape.volume_m3())),
            inv_edge_squared: k
                .coefficients
                .shape
                .edges_m
                .map(|l| Lanes::splat(1.0 / (l * l))),
            volume_over_4_edge_squared: k
                .coefficients
                .shape
                .edges_m
                .map(|l| Lanes::splat(k.coefficients.shape.volume_m3() / (4.0 * l * l))),
        }
    }

    /// Lane `l` taken from `kernels[classes[l]]`.
    fn gather(kernels: &[LaneKernel], classes: &[u32; LANES]) -> Self {
        let pick = |get: &dyn Fn(&LaneKernel) -> Lanes| {
            Lanes(std::array::from_fn(|l| {
                get(&kernels[classes[l] as usize]).0[l]
            }))
        };
        LaneKernel {
            stiffness: std::array::from_fn(|s| pick(&|k| k.stiffness[s])),
            cubic: std::array::from_fn(|s| pick(&|k| k.cubic[s])),
            rest_length: std::array::from_fn(|s| pick(&|k| k.rest_length[s])),
            damping: std::array::from_fn(|s| pick(&|k| k.damping[s])),
            correction_map: std::array::from_fn(|r| pick(&|k| k.correction_map[r])),
            inv_64_rest_volume: pick(&|k| k.inv_64_rest_volume),
            inv_edge_squared: std::array::from_fn(|i| pick(&|k| k.inv_edge_squared[i])),
            volume_over_4_edge_squared: std::array::from_fn(|i| {
                pick(&|k| k.volume_over_4_edge_squared[i])
            }),
        }
    }
}

/// [`ElementKernel::forces`] on [`LANES`] elements at once.
///
/// Same operations as the scalar kernel except that the axial resultants are summed per axis
/// before the dot product (Σ_n s_n,i f_n) · e_i, and the direction uses one reciprocal; the
/// results agree to a few ulps of the spring forces.
#[inline(always)]
fn batch_forces<const DAMP: bool>(
    k: &LaneKernel,
    x: &[LaneV3; 8],
    v: &[LaneV3; 8],
    volumetric: Option<&[Option<&VolumetricCorrection>; LANES]>,
    continuum: Option<&[Option<&ContinuumCorrection>; LANES]>,
    hourglass: Option<&[Option<&HourglassCorrection>; LANES]>,
) -> [LaneV3; 8] {
    // With an hourglass correction the springs and corrections see the affine part of the
    // motion (`BrickCoefficients::corner_forces`); `x_all` keeps the whole of it.
    let x_all = x;
    let affine = hourglass.map(|per_lane| affine_lanes(x, per_lane));
    let x = affine.as_ref().unwrap_or(x);
    // Damper forces kept apart from the elastic ones: see `ElementKernel::forces`.
    let mut f = [[Lanes::ZERO; 3]; 8];
    let mut fd = [[Lanes::ZERO; 3]; 8];
    for (s, &(a, b, _)) in SPRINGS.iter().enumerate() {
        let d = sub3(&x[b], &x[a]);
        let len = dot3(&d, &d).sqrt();
        let n = scale3(&d, Lanes::splat(1.0) / len);
        let e = len - k.rest_length[s];
        let fa = scale3(&n, e * (k.stiffness[s] + k.cubic[s] * e * e));
        f[a] = add3(&f[a], &fa);
        f[b] = sub3(&f[b], &fa);
        if DAMP {
            let fv = scale3(&n, k.damping[s] * dot3(&sub3(&v[b], &v[a]), &n));
            fd[a] = add3(&fd[a], &fv);
            fd[b] = sub3(&fd[b], &fv);
        }
    }
    let ex = edge_sum(x, [(1, 0), (2, 3), (5, 4), (6, 7)]);
    let ey = edge_sum(x, [(3, 0), (2, 1), (7, 4), (6, 5)]);
    let e1 = normalize3(&ex);
    let e2 = normalize3(&sub3(&ey, &scale3(&e1, dot3(&ey, &e1))));
    let e3 = cross3(&e1, &e2);
    let axes = [e1, e2, e3];
    // The hourglass correction, lane by lane from the springs' elastic forces (the scalar
    // reference's order; the corrections below act along the linear patterns only).
    let hourglass_forces = hourglass.map(|per_lane| add_hourglass(x_all, &axes, &f, per_lane));
    // a_i = −½ (Σ_n s_n,i f_n) · e_i.
    let mut a = [Lanes::ZERO; 3];
    for (i, axis) in axes.iter().enumerate() {
        let mut g = [Lanes::ZERO; 3];
        for (n, signs) in CORNER_SIGNS.iter().enumerate() {
            g = if signs[i] > 0.0 {
                add3(&g, &f[n])
            } else {
                sub3(&g, &f[n])
            };
        }
        a[i] = Lanes::splat(-0.5) * dot3(&g, axis);
    }
    let w = &k.correction_map;
    let wv: [Lanes; 3] =
        std::array::from_fn(|r| w[3 * r] * a[0] + w[3 * r + 1] * a[1] + w[3 * r + 2] * a[2]);
    let mut wa = [
        scale3(&axes[0], wv[0]),
        scale3(&axes[1], wv[1]),
        scale3(&axes[2], wv[2]),
    ];
    if let Some(laws) = continuum {
        add_continuum(k, x, &ex, &ey, &axes, laws, &mut wa);
    }
    // ±wa₀ ± wa₁ ± wa₂ in the scalar kernel's order; negation is exact, so 2 sums suffice.
    let pp = add3(&wa[0], &wa[1]);
    let pm = sub3(&wa[0], &wa[1]);
    for (n, signs) in CORNER_SIGNS.iter().enumerate() {
        let xy = match (signs[0] > 0.0, signs[1] > 0.0) {
            (true, true) => pp,
            (true, false) => pm,
            (false, true) => pm.map(|c| -c),
            (false, false) => pp.map(|c| -c),
        };
        let corr = if signs[2] > 0.0 {
            add3(&xy, &wa[2])
        } else {
            sub3(&xy, &wa[2])
        };
        f[n] = add3(&f[n], &corr);
        if DAMP {
            f[n] = add3(&f[n], &fd[n]);
        }
    }
    if let Some(vols) = volumetric {
        add_volumetric(k, x, &ex, &ey, vols, &mut f);
    }
    if let Some(h) = hourglass_forces {
        for (fn_, hn) in f.iter_mut().zip(&h) {
            *fn_ = add3(fn_, hn);
        }
    }
    f
}

/// `x` with, in each lane whose class has an hourglass correction, its hourglass components
/// removed ([`crate::model::hourglass::affine_part`]).
#[inline(always)]
fn affine_lanes(x: &[LaneV3; 8], per_lane: &[Option<&HourglassCorrection>; LANES]) -> [LaneV3; 8] {
    let mut out = *x;
    for (l, h) in per_lane.iter().enumerate() {
        if h.is_none() {
            continue;
        }
        let xl: [V3; 8] =
            std::array::from_fn(|n| V3::new(x[n][0].0[l], x[n][1].0[l], x[n][2].0[l]));
        let a = crate::model::hourglass::affine_part(&xl);
        for n in 0..8 {
            for i in 0..3 {
                out[n][i].0[l] = a[n][i];
            }
        }
    }
    out
}

/// The hourglass correction's corner forces of each lane whose class has one
/// ([`HourglassCorrection::corner_forces`], evaluated per lane); zero in the others.
#[inline(always)]
fn add_hourglass(
    x: &[LaneV3; 8],
    axes: &[LaneV3; 3],
    f: &[LaneV3; 8],
    per_lane: &[Option<&HourglassCorrection>; LANES],
) -> [LaneV3; 8] {
    let mut out = [[Lanes::ZERO; 3]; 8];
    for (l, h) in per_lane.iter().enumerate() {
        let Some(h) = h else { continue };
        let pick = |v: &LaneV3| V3::new(v[0].0[l], v[1].0[l], v[2].0[l]);
        let xl: [V3; 8] = std::array::from_fn(|n| pick(&x[n]));
        let fl: [V3; 8] = std::array::from_fn(|n| pick(&f[n]));
        let al: [V3; 3] = std::array::from_fn(|i| pick(&axes[i]));
        let c = h.corner_forces(&xl, &al, &fl);
        for n in 0..8 {
            for i in 0..3 {
                out[n][i].0[l] = c[n][i];
            }
        }
    }
    out
}

/// Adds the continuum correction's per-axis vectors c_i (corner n gets Σ_i s_n,i c_i, the
/// Lagrange correction's pattern) to `wa`: [`crate::model::continuum_correction`], whose
/// `corner_axis_forces_n` is the scalar reference. Lanes whose class has no law get nothing.
#[inline(always)]
fn add_continuum(
    k: &LaneKernel,
    x: &[LaneV3; 8],
    ex: &LaneV3,
    ey: &LaneV3,
    axes: &[LaneV3; 3],
    laws: &[Option<&ContinuumCorrection>; LANES],
    wa: &mut [LaneV3; 3],
) {
    let ez = edge_sum(x, [(4, 0), (5, 1), (6, 2), (7, 3)]);
    let quarter = Lanes::splat(0.25);
    // Mean edge vectors ē_i = F̄·L_i·ê_i: the springs' lengths under the homogeneous F̄.
    let m = [
        scale3(ex, quarter),
        scale3(ey, quarter),
        scale3(&ez, quarter),
    ];
    // Tension over length of a spring of index `s` stretched to `v`.
    let tension_per_length = |s: usize, v: &LaneV3| {
        let len = dot3(v, v).sqrt();
        let e = len - k.rest_length[s];
        e * (k.stiffness[s] + k.cubic[s] * e * e) / len
    };
    let four = Lanes::splat(4.0);
    let mut r: [LaneV3; 3] = std::array::from_fn(|i| {
        // Springs 0, 4, 8 are the first edge along x, y, z; the other three of each axis are
        // identical under a homogeneous deformation.
        scale3(&m[i], four * tension_per_length(4 * i, &m[i]))
    });
    for (d, sigma) in DIAGONAL_SIGNS.iter().enumerate() {
        let mut v = m[2];
        v = if sigma[0] > 0.0 {
            add3(&v, &m[0])
        } else {
            sub3(&v, &m[0])
        };
        v = if sigma[1] > 0.0 {
            add3(&v, &m[1])
        } else {
            sub3(&v, &m[1])
        };
        let t = scale3(&v, tension_per_length(12 + d, &v));
        for (i, ri) in r.iter_mut().enumerate() {
            *ri = if sigma[i] > 0.0 {
                add3(ri, &t)
            } else {
                sub3(ri, &t)
            };
        }
    }
    // The Lagrange correction's magnitudes under F̄: w = W·a, a_i = ê_i·R_i.
    let a: [Lanes; 3] = std::array::from_fn(|i| dot3(&axes[i], &r[i]));
    let w = &k.correction_map;
    let wh: [Lanes; 3] =
        std::array::from_fn(|r| w[3 * r] * a[0] + w[3 * r + 1] * a[1] + w[3 * r + 2] * a[2]);
    // The law at F̄ = [ē_i/L_i]: P = α·F̄ + γ·cof F̄.
    let cof = [
        cross3(&m[1], &m[2]),
        cross3(&m[2], &m[0]),
        cross3(&m[0], &m[1]),
    ];
    let i1 = dot3(&m[0], &m[0]) * k.inv_edge_squared[0]
        + dot3(&m[1], &m[1]) * k.inv_edge_squared[1]
        + dot3(&m[2], &m[2]) * k.inv_edge_squared[2];
    let j = dot3(ex, &cross3(ey, &ez)) * k.inv_64_rest_volume;
    let mut alpha = Lanes::ZERO;
    let mut gamma_quarter = Lanes::ZERO;
    let mut on = Lanes::ZERO;
    for (l, law) in laws.iter().enumerate() {
        if let Some(law) = law {
            let (a, g) = law.piola_coefficients_pa(i1.0[l], j.0[l]);
            alpha.0[l] = a;
            gamma_quarter.0[l] = 0.25 * g;
            on.0[l] = 1.0;
        }
    }
    for i in 0..3 {
        // c_i = R_i/4 − w_i·ê_i − V₀·P·ê_i/(4L_i), and V₀·P·ê_i/(4L_i) =
        // α·V₀/(4L_i²)·ē_i + (γ/4)·ē_j × ē_k.
        let law = add3(
            &scale3(&m[i], alpha * k.volume_over_4_edge_squared[i]),
            &scale3(&cof[i], gamma_quarter),
        );
        let own = sub3(&scale3(&r[i], quarter), &scale3(&axes[i], wh[i]));
        wa[i] = add3(&wa[i], &scale3(&sub3(&own, &law), on));
    }
}

/// Σ (x[hi] − x[lo]) over the four parallel edges `pairs`: four times the element's mean
/// edge vector along one axis.
#[inline(always)]
fn edge_sum(x: &[LaneV3; 8], pairs: [(usize, usize); 4]) -> LaneV3 {
    let [a, b, c, d] = pairs.map(|(hi, lo)| sub3(&x[hi], &x[lo]));
    add3(&add3(&add3(&a, &b), &c), &d)
}

/// Adds the volumetric correction −(p(J)/64)·(s_x·ey×ez + s_y·ez×ex + s_z·ex×ey) of
/// [`BrickCoefficients::corner_forces`]; lanes whose class has no volumetric law get p = 0.
#[inline(always)]
fn add_volumetric(
    k: &LaneKernel,
    x: &[LaneV3; 8],
    ex: &LaneV3,
    ey: &LaneV3,
    vols: &[Option<&VolumetricCorrection>; LANES],
    f: &mut [LaneV3; 8],
) {
    let ez = edge_sum(x, [(4, 0), (5, 1), (6, 2), (7, 3)]);
    let c = [cross3(ey, &ez), cross3(&ez, ex), cross3(ex, ey)];
    let j = dot3(ex, &c[0]) * k.inv_64_rest_volume;
    let scale = Lanes(std::array::from_fn(|l| {
        vols[l].map_or(0.0, |v| -v.pressure_pa(j.0[l]) / 64.0)
    }));
    for (n, signs) in CORNER_SIGNS.iter().enumerate() {
        let mut g = [Lanes::ZERO; 3];
        for (i, ci) in c.iter().enumerate() {
            g = if signs[i] > 0.0 {
                add3(&g, ci)
            } else {
                sub3(&g, ci)
            };
        }
        f[n] = add3(&f[n], &scale3(&g, scale));
    }
}

/// Where element forces are added: a node-index window of the output owned by one chunk, or
/// (fallback) the whole output shared by elements of one colour.
trait Sink {
    fn add(&mut self, node: u32, f: V3);
}

/// A chunk's own window `out[lo..]` of the output.
struct Window<'a> {
    lo: u32,
    out: &'a mut [V3],
}

impl Sink for Window<'_> {
    #[inline(always)]
    fn add(&mut self, node: u32, f: V3) {
        // A node outside the window (a mesh other than the one the schedule was built for)
        // wraps or overruns and panics on the bounds check instead of racing.
        self.out[node.wrapping_sub(self.lo) as usize] += f;
    }
}

#[derive(Clone, Copy)]
struct SharedOut(*mut V3, usize);
// SAFETY: elements of one colour share no node, so concurrent writers touch disjoint nodes.
unsafe impl Send for SharedOut {}
unsafe impl Sync for SharedOut {}

impl Sink for SharedOut {
    #[inline(always)]
    fn add(&mut self, node: u32, f: V3) {
        let c = node as usize;
        assert!(c < self.1, "node {c} beyond the output's {} nodes", self.1);
        // SAFETY: `c` is in bounds and no other thread writes node `c` while this colour is
        // processed (the mesh colouring guarantees it).
        unsafe { *self.0.add(c) += f };
    }
}

/// What one evaluation reads.
struct Inputs<'a> {
    mesh: &'a HexMesh,
    x: &'a [V3],
    v: Option<&'a [V3]>,
    lane_kernels: &'a [LaneKernel],
    /// Each class's volumetric correction; `None` for every class: the term is skipped.
    volumetric: Option<&'a [Option<VolumetricCorrection>]>,
    /// Each class's continuum correction; `None` for every class: the term is skipped.
    continuum: Option<&'a [Option<ContinuumCorrection>]>,
    /// Each class's hourglass correction; `None` for every class: the term is skipped.
    hourglass: Option<&'a [Option<HourglassCorrection>]>,
}

/// Evaluates the elements yielded by `elements` (indices into the mesh) into `sink`.
#[inline(always)]
fn run_elements<const DAMP: bool, E: ElementSource, S: Sink>(
    inp: &Inputs<'_>,
    elements: &mut E,
    sink: &mut S,
) {
    let mesh = inp.mesh;
    let x = inp.x;
    let v = inp.v.unwrap_or(x);
    let mut xs = [[Lanes::ZERO; 3]; 8];
    let mut vs = [[Lanes::ZERO; 3]; 8];
    let mut mixed: Option<LaneKernel> = None;
    let mut ids = [0u32; LANES];
    while let Some(count) = elements.next_batch(&mut ids) {
        let corners: [&[u32; 8]; LANES] = ids.map(|e| &mesh.elements[e as usize]);
        let classes = ids.map(|e| mesh.element_class[e as usize]);
        for (l, cs) in corners.iter().enumerate() {
            for (n, &c) in cs.iter().enumerate() {
                let p = &x[c as usize];
                for i in 0..3 {
                    xs[n][i].0[l] = p[i];
                }
                if DAMP {
                    let q = &v[c as usize];
                    for i in 0..3 {
                        vs[n][i].0[l] = q[i];
                    }
                }
            }
        }
        let kernel = if classes.iter().all(|&c| c == classes[0]) {
            &inp.lane_kernels[classes[0] as usize]
        } else {
            &*mixed.insert(LaneKernel::gather(inp.lane_kernels, &classes))
        };
        let vols = inp
            .volumetric
            .map(|per_class| std::array::from_fn(|l| per_class[classes[l] as usize].as_ref()));
        let laws = inp
            .continuum
            .map(|per_class| std::array::from_fn(|l| per_class[classes[l] as usize].as_ref()));
        let hourglass = inp
            .hourglass
            .map(|per_class| std::array::from_fn(|l| per_class[classes[l] as usize].as_ref()));
        let f = batch_forces::<DAMP>(
            kernel,
            &xs,
            &vs,
            vols.as_ref(),
            laws.as_ref(),
            hourglass.as_ref(),
        );
        for (l, cs) in corners.iter().enumerate().take(count) {
            for (n, &c) in cs.iter().enumerate() {
                sink.add(c, V3::new(f[n][0].0[l], f[n][1].0[l], f[n][2].0[l]));
            }
        }
    }
}

/// Runs [`run_elements`] with the widest vector instructions the CPU offers.
fn dispatch<E: ElementSource, S: Sink>(inp: &Inputs<'_>, elements: &mut E, sink: &mut S) {
    #[cfg(target_arch = "x86_64")]
    {
        #[target_feature(enable = "avx2")]
        unsafe fn avx2<const DAMP: bool, E: ElementSource, S: Sink>(
            inp: &Inputs<'_>,
            elements: &mut E,
            sink: &mut S,
        ) {
            run_elements::<DAMP, E, S>(inp, elements, sink)
        }
        if std::arch::is_x86_feature_detected!("avx2") {
            // SAFETY: the CPU supports AVX2 (checked just above).
            unsafe {
                match inp.v {
                    Some(_) => avx2::<true, E, S>(inp, elements, sink),
                    None => avx2::<false, E, S>(inp, elements, sink),
                }
            }
            return;
        }
    }
    match inp.v {
        Some(_) => run_elements::<true, E, S>(inp, elements, sink),
        None => run_elements::<false, E, S>(inp, elements, sink),
    }
}

/// A run of consecutive elements and the node-index window `[node_lo, node_hi)` they touch.
#[derive(Debug, Clone)]
struct Chunk {
    first_element: u32,
    end_element: u32,
    node_lo: u32,
    node_hi: u32,
}

/// Chunk lengths tried, largest first (multiples of [`LANES`] so only a chunk's tail pads).
const CHUNK_LENGTHS: [u32; 7] = [16384, 8192, 4096, 2048, 1024, 512, 256];
/// More colours than this and the mesh's own element colouring is no worse.
const MAX_CHUNK_COLOURS: usize = 8;
/// Chunks wanted in every colour, so that up to this many threads stay busy.
const CHUNKS_PER_COLOUR: usize = 8;
/// Below this many elements an evaluation runs on one thread (spawn cost dominates).
pub const PARALLEL_MIN_ELEMENTS: usize = 4096;
/// Elements per parallel task in the element-colour fallback.
const FALLBACK_TASK: usize = 256;
/// Nodes per parallel task when zeroing the output.
const ZERO_TASK: usize = 16384;

/// A race-free parallel scatter plan for element loops: the element list cut into contiguous
/// chunks, coloured so that the chunks of one colour touch disjoint node-index windows.
///
/// Each chunk writes through its own sub-slice of the output, so no `unsafe` and no atomics
/// are needed, a pass has one barrier per colour (2–3 for lattice-numbered meshes instead of
/// 8 element colours), and each thread walks its elements in memory order. Chunks run in the
/// same order whatever the thread count, so sums are bit-for-bit reproducible. Any element
/// operator that scatters into nodes (forces, matrix-free products) can use it.
#[derive(Debug, Clone)]
pub struct ChunkSchedule {
    colours: Vec<Vec<Chunk>>,
    node_count: usize,
}

impl ChunkSchedule {
    /// Plans `elements` (corner node indices < `node_count`); `None` when the numbering has so
    /// little locality that chunks would serialise the work (then colour single elements).
    pub fn new(elements: &[[u32; 8]], node_count: usize) -> Option<Self> {
        let n = elements.len();
        let plan = |colours| ChunkSchedule {
            colours,
            node_count,
        };
        if n < PARALLEL_MIN_ELEMENTS {
            return Some(plan(colour_chunks(elements, (n as u32).max(1))));
        }
        // Largest chunks that still give every colour enough chunks: fewest barriers and the
        // longest runs in memory order.
        let mut best: Option<(usize, Vec<Vec<Chunk>>)> = None;
        for len in CHUNK_LENGTHS {
            let colours = colour_chunks(elements, len);
            let fewest = colours.iter().map(Vec::len).min().unwrap_or(0);
            if colours.len() > MAX_CHUNK_COLOURS {
                continue;
            }
            if fewest >= CHUNKS_PER_COLOUR {
                return Some(plan(colours));
            }
            if best.as_ref().is_none_or(|(f, _)| fewest > *f) {
                best = Some((fewest, colours));
            }
        }
        match best {
            Some((fewest, colours)) if fewest >= 2 => Some(plan(colours)),
            _ => None,
        }
    }

    /// Colour passes (barriers) per parallel sweep.
    pub fn colour_count(&self) -> usize {
        self.colours.len()
    }

    /// Bytes held on the heap.
    pub fn heap_bytes(&self) -> usize {
        self.colours
            .iter()
            .map(|v| v.capacity() * std::mem::size_of::<Chunk>())
            .sum::<usize>()
            + self.colours.capacity() * std::mem::size_of::<Vec<Chunk>>()
    }

    /// Calls `f(elements, node_lo, window)` for every chunk, colour by colour; the chunks of a
    /// colour run in parallel on the current rayon pool when `parallel`.
    ///
    /// `out` holds `per_node` values per node; `window` is
    /// `out[per_node·node_lo .. per_node·node_hi]`, so node `c` of the chunk's elements is at
    /// `window[per_node·(c − node_lo) ..]`. An index outside the window panics on the bounds
    /// check (an element list other than the planned one) instead of racing.
    pub fn for_each_chunk<T, F>(&self, out: &mut [T], per_node: usize, parallel: bool, f: F)
    where
        T: Send,
        F: Fn(std::ops::Range<usize>, usize, &mut [T]) + Sync,
    {
        assert_eq!(
            out.len(),
            per_node * self.node_count,
            "output must hold {per_node} values for each of the {} planned nodes",
            self.node_count
        );
        for colour in &self.colours {
            let windows = split_windows(colour, out, per_node);
            let run = |(chunk, window): (&Chunk, &mut [T])| {
                f(
                    chunk.first_element as usize..chunk.end_element as usize,
                    chunk.node_lo as usize,
                    window,
                )
            };
            if parallel {
                windows.into_par_iter().for_each(run);
            } else {
                windows.into_iter().for_each(run);
            }
        }
    }
}

/// Cuts the elements into chunks of `len` and colours them greedily so that chunks of one
/// colour have disjoint node windows.
fn colour_chunks(elements: &[[u32; 8]], len: u32) -> Vec<Vec<Chunk>> {
    let n = elements.len() as u32;
    let mut colours: Vec<Vec<Chunk>> = Vec::new();
    let mut start = 0;
    while start < n {
        let end = n.min(start.saturating_add(len));
        let (lo, hi) = elements[start as usize..end as usize]
            .iter()
            .flatten()
            .fold((u32::MAX, 0), |(lo, hi), &c| (lo.min(c), hi.max(c + 1)));
        let chunk = Chunk {
            first_element: start,
            end_element: end,
            node_lo: lo,
            node_hi: hi,
        };
        let free = colours.iter().position(|col| {
            col.iter()
                .all(|o| o.node_hi <= chunk.node_lo || chunk.node_hi <= o.node_lo)
        });
        match free {
            Some(c) => colours[c].push(chunk),
            None => colours.push(vec![chunk]),
        }
        start = end;
    }
    for col in &mut colours {
        col.sort_by_key(|c| c.node_lo);
    }
    colours
}

/// Splits `out` into the disjoint node windows of one colour's chunks (sorted by window).
fn split_windows<'c, 'o, T>(
    colour: &'c [Chunk],
    out: &'o mut [T],
    per_node: usize,
) -> Vec<(&'c Chunk, &'o mut [T])> {
    let mut windows = Vec::with_capacity(colour.len());
    let mut rest = out;
    let mut offset = 0usize;
    for chunk in colour {
        let (lo, hi) = (
            per_node * chunk.node_lo as usize,
            per_node * chunk.node_hi as usize,
        );
        let tail = std::mem::take(&mut rest);
        let (_, tail) = tail.split_at_mut(lo - offset);
        let (window, tail) = tail.split_at_mut(hi - lo);
        windows.push((chunk, window));
        rest = tail;
        offset = hi;
    }
    windows
}

/// Evaluates internal forces over a whole mesh.
#[derive(Debug, Clone)]
pub struct ForceEvaluator {
    kernels: Vec<ElementKernel>,
    lane_kernels: Vec<LaneKernel>,
    /// Per class; empty when no class has a volumetric law.
    volumetric: Vec<Option<VolumetricCorrection>>,
    /// Per class; empty when no class has a continuum correction.
    continuum: Vec<Option<ContinuumCorrection>>,
    /// Per class; empty when no class has an hourglass correction.
    hourglass: Vec<Option<HourglassCorrection>>,
    /// `None`: the mesh numbering has no chunk locality; use the mesh's element colours.
    schedule: Option<ChunkSchedule>,
    element_count: usize,
    node_count: usize,
}

impl ForceEvaluator {
    /// Packs the kernels of every class of `mesh` and plans the parallel schedule.
    pub fn new(mesh: &HexMesh) -> Self {
        let kernels: Vec<ElementKernel> = mesh.classes.iter().map(ElementKernel::new).collect();
        let volumetric: Vec<Option<VolumetricCorrection>> =
            mesh.classes.iter().map(|c| c.volumetric.clone()).collect();
        let continuum: Vec<Option<ContinuumCorrection>> =
            mesh.classes.iter().map(|c| c.continuum).collect();
        let hourglass: Vec<Option<HourglassCorrection>> =
            mesh.classes.iter().map(|c| c.hourglass.clone()).collect();
        ForceEvaluator {
            hourglass: if hourglass.iter().any(Option::is_some) {
                hourglass
            } else {
                Vec::new()
            },
            continuum: if continuum.iter().any(Option::is_some) {
                continuum
            } else {
                Vec::new()
            },
            volumetric: if volumetric.iter().any(Option::is_some) {
                volumetric
            } else {
                Vec::new()
            },
            lane_kernels: kernels.iter().map(LaneKernel::splat).collect(),
            kernels,
            schedule: ChunkSchedule::new(&mesh.elements, mesh.node_count()),
            element_count: mesh.element_count(),
            node_count: mesh.node_count(),
        }
    }

    /// The scalar kernel of each element class.
    pub fn kernels(&self) -> &[ElementKernel] {
        &self.kernels
    }

    /// Number of barriers (colour passes) per evaluation on more than one thread.
    pub fn colour_passes(&self, mesh: &HexMesh) -> usize {
        match &self.schedule {
            Some(s) => s.colour_count(),
            None => mesh.colors.len(),
        }
    }

    /// Bytes held by the evaluator (kernels and schedule), excluding the mesh.
    pub fn heap_bytes(&self) -> usize {
        self.kernels.capacity() * std::mem::size_of::<ElementKernel>()
            + self.lane_kernels.capacity() * std::mem::size_of::<LaneKernel>()
            + self.schedule.as_ref().map_or(0, ChunkSchedule::heap_bytes)
    }

    /// Overwrites `out` with the internal (spring + damper + correction) force on every node.
    ///
    /// `mesh` must be the mesh the evaluator was built for. Runs on the current rayon pool;
    /// the result does not depend on the number of threads.
    pub fn internal_forces(&self, mesh: &HexMesh, x: &[V3], v: Option<&[V3]>, out: &mut [V3]) {
        assert_eq!(x.len(), mesh.node_count());
        assert_eq!(out.len(), mesh.node_count());
        if let Some(v) = v {
            assert_eq!(v.len(), mesh.node_count());
        }
        assert!(
            mesh.element_count() == self.element_count && mesh.node_count() == self.node_count,
            "ForceEvaluator built for {} elements and {} nodes, called with {} and {}",
            self.element_count,
            self.node_count,
            mesh.element_count(),
            mesh.node_count()
        );
        let inp = Inputs {
            mesh,
            x,
            v,
            lane_kernels: &self.lane_kernels,
            volumetric: (!self.volumetric.is_empty()).then_some(&self.volumetric[..]),
            continuum: (!self.continuum.is_empty()).then_some(&self.continuum[..]),
            hourglass: (!self.hourglass.is_empty()).then_some(&self.hourglass[..]),
        };
        let parallel =
            rayon::current_num_threads() > 1 && mesh.element_count() >= PARALLEL_MIN_ELEMENTS;
        if parallel {
            out.par_chunks_mut(ZERO_TASK)
                .for_each(|c| c.fill(V3::zeros()));
        } else {
            out.fill(V3::zeros());
        }
        match &self.schedule {
            Some(schedule) => {
                schedule.for_each_chunk(out, 1, parallel, |elements, node_lo, window| {
                    let mut sink = Window {
                        lo: node_lo as u32,
                        out: window,
                    };
                    dispatch(
                        &inp,
                        &mut (elements.start as u32..elements.end as u32),
                        &mut sink,
                    );
                });
            }
            None => {
                let shared = SharedOut(out.as_mut_ptr(), out.len());
                for colour in &mesh.colors {
                    let run = |task: &[u32]| {
                        let mut sink = shared;
                        dispatch(&inp, &mut task.iter(), &mut sink);
                    };
                    if parallel && colour.len() >= PARALLEL_MIN_ELEMENTS {
                        colour.par_chunks(FALLBACK_TASK).for_each(run);
                    } else {
                        run(colour);
                    }
                }
            }
        }
    }
}
