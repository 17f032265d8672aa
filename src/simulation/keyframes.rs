//! Quasi-static breathing frames without one solve per frame.
//!
//! In quasi-static breathing the lung's shape is a function of its volume alone (an elastic
//! body, no rate effects), so it is solved at a few *key volumes* and every frame is
//! interpolated from them: locally, by the cubic Lagrange polynomial through the four keys
//! nearest its volume. Local, because the response is smooth only piecewise: a node sliding
//! on the chest wall's distance field changes direction where it crosses into another voxel
//! cell of the field, and on the POPI lungs at 8 mm one such node put a kink near +720 mL into
//! a 0–1000 mL ramp. A global polynomial through all keys (Chebyshev–Lobatto, as before)
//! converges only slowly at a kink and spreads its error over the whole range; 65 keys still
//! missed 0.1 mm there.
//!
//! The error is *measured*, not assumed, without extra solves: each key is predicted by the
//! local interpolant of the keys around it with that key left out, and must be matched within
//! the tolerance in mm (leaving it out widens the stencil, so this bounds the error of the
//! interpolant that includes it). Where a key fails, the two intervals beside it are halved
//! by new keys and the new and failing keys are checked again, so keys gather where the
//! response bends and a smooth response costs its first sweep only.
//!
//! Halving stops where it no longer helps: at [`MIN_KEY_STEP_FRACTION`] of the range, or
//! when halving a key's intervals left its miss above [`STALLED_MISS_RATIO`] of what it was
//! (a smooth response's miss falls about 16-fold, a kink's 2-fold). Such a key is not at a
//! bend more keys would resolve but at a jump: below the scanned volume the compressed
//! lung can snap from one equilibrium to another (on the CIP lungs at 8 mm a −500 mL dip
//! kept missing by 2.3 mm near −484 mL with keys 4 mL apart, and halving went on for 94 keys
//! and 5 minutes before it gave up). The intervals beside such a key become *direct*: the
//! keys split into smooth segments there, each interpolated on its own (no stencil reaches
//! across a jump), and a frame whose volume falls inside a direct interval is solved, from
//! the key on the scanned state's side of it. Every frame then meets the tolerance, by
//! interpolation or by its own solve, and the report names each jump: where, which node, by
//! how much.
//!
//! The first sweep is solved in ascending volume from the lowest key and each later key is
//! solved from the key just below it, so all states lie on one gradual-inflation path. The
//! loaded lung can have more than one equilibrium (on the phantom at 6 mm a mediastinal corner
//! node sat 0.67 mm apart at 500 mL when reached in one step instead of 100 mL steps); a
//! state from another branch would read as an interpolation error no number of keys removes.

use serde::Serialize;

use super::driver::{BreathingDriver, DrivenState};
use crate::math::V3;
use crate::{Error, Result};

/// Largest number of key volumes before the interpolation is declared not worth it.
pub const MAX_KEYS: usize = 129;

/// How the first sweep spaces its keys: at least `min_keys`, evenly, and as many more as keep
/// neighbours at most `max_step_ml` apart (a wider range gets more keys, not wider steps).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FirstSweep {
    /// Fewest keys, whatever the range.
    pub min_keys: usize,
    /// Largest step between neighbouring keys, mL.
    pub max_step_ml: f64,
}

impl FirstSweep {
    /// Nodes held on tangent planes and lines (the default scene): 5 keys, at most 125 mL
    /// apart. Measured on 2026-12-05 against 9 keys 62.5 mL apart (the sweep before): the
    /// fields of the CIP and POPI lungs at 4 mm differ by at most 0.02 mm (the 1/64 mm
    /// rounding), the leave-one-out error stays at 0.03–0.05 mm (tolerance 0.1 mm, refined
    /// beyond it), Newton still takes 1–2 steps a key, and the solves take a third less time.
    /// The recording with a vital-capacity manoeuvre (−436 … +1150 mL on the POPI lungs at
    /// 8 mm) gets 14 keys: every solve converged, in 36 Newton iterations against 47 with 27
    /// keys. (Spread over 9 keys, its steps of 198 mL each ran Newton's 40 iterations, 13–60 s,
    /// without converging before the step was halved.)
    pub const PLANES: FirstSweep = FirstSweep {
        min_keys: 5,
        max_step_ml: 125.0,
    };

    /// Nodes sliding on the curved wall's level sets (`sliding = "wall_surface"`): 9 keys, at
    /// most 62.5 mL apart. Their response bends more (a leave-one-out error of 0.08 mm with
    /// 62.5 mL steps on the CIP lungs at 4 mm): with 125 mL steps half the keys missed and were
    /// refined, and the cycle's solves took 6.4 s (26 Newton) against 3.7 s (16).
    pub const CURVED_WALL: FirstSweep = FirstSweep {
        min_keys: 9,
        max_step_ml: 62.5,
    };

    /// Keys of the first sweep over `lo..=hi` mL.
    fn keys(&self, lo: f64, hi: f64) -> usize {
        let steps = ((hi - lo) / self.max_step_ml).ceil();
        if steps.is_finite() {
            self.min_keys.max(steps as usize + 1).min(MAX_KEYS)
        } else {
            self.min_keys
        }
    }
}

/// Keys in one local interpolant.
const STENCIL: usize = 4;

/// A key whose miss is still above this share of its miss before its intervals were halved
/// sits at a jump (a smooth response's miss falls about 16-fold, a kink's 2-fold).
const STALLED_MISS_RATIO: f64 = 0.7;

/// Frames across a stalled key that are solved rather than halving on: about the solves
/// two more rounds of halving beside it would take.
const DIRECT_FRAMES_FOR_A_HALVING: usize = 4;

/// Smallest key step refinement makes, as a fraction of the key range (500 mL: 7.8 mL).
/// A kink from the wall's distance field was met at 15 mL steps on the POPI lungs; a key
/// still missing at this step sits at a jump.
pub const MIN_KEY_STEP_FRACTION: f64 = 1.0 / 64.0;

/// Solved key volumes and the interpolant over them.
#[derive(Debug, Clone)]
pub struct VolumeKeyframes {
    /// Key volume changes from rest, mL, increasing.
    pub volumes_ml: Vec<f64>,
    /// The solved state at each key.
    pub states: Vec<DrivenState>,
    /// What building the keys measured.
    pub report: KeyframeReport,
    /// Per interval between neighbouring keys: solved directly (a jump), not interpolated.
    direct: Vec<bool>,
}

/// How the keys were chosen and how well they interpolate.
#[derive(Debug, Clone, Serialize)]
pub struct KeyframeReport {
    /// Number of key volumes solved.
    pub keys: usize,
    /// Largest node-position difference between a key's direct solve and the local
    /// interpolant of the keys around it without it, mm (a bound on the interpolation error);
    /// `None` when no key could be checked (every interval direct: each frame was solved),
    /// which once read as a perfect 0.0.
    pub measured_error_mm: Option<f64>,
    /// Tolerance asked for, mm.
    pub tolerance_mm: f64,
    /// Rounds of refinement after the first sweep.
    pub refinements: usize,
    /// Smallest distance between two keys, mL (where the response bends most).
    pub smallest_key_step_ml: f64,
    /// Equilibrium solves spent, all keys together.
    pub solves: usize,
    /// Newton iterations spent, all solves together.
    pub newton_iterations: usize,
    /// Krylov iterations spent, all solves together.
    pub linear_iterations: usize,
    /// Solver wall time, s.
    pub solve_time_s: f64,
    /// Volume intervals where the shape jumps: frames there are solved, not interpolated.
    pub direct_intervals: Vec<DirectInterval>,
}

/// A volume interval over which the lung's shape does not follow its volume smoothly.
#[derive(Debug, Clone, Serialize)]
pub struct DirectInterval {
    /// Lower end, mL from the scanned state.
    pub from_ml: f64,
    /// Upper end, mL.
    pub to_ml: f64,
    /// Node that missed its interpolation most.
    pub node: usize,
    /// That node's rest position, LPS mm.
    pub rest_position_mm: [f64; 3],
    /// By how much it missed at the key between the two ends, mm.
    pub error_mm: f64,
}

/// Where a key's leave-one-out check failed worst.
#[derive(Debug, Clone, Copy)]
struct Miss {
    key: usize,
    error_mm: f64,
    volume_ml: f64,
    node: usize,
}

/// The first keys, evenly spaced over `lo..=hi` mL, solved outward from the scanned state:
/// the keys above it ascending and the keys below it descending, each continuing from its
/// neighbour nearer the scanned state, so every key lies on the gradual path a breath takes
/// from the scan (a deep key solved straight from rest, or from the far end of the range,
/// may land on another equilibrium or fail where a gradual path succeeds).
fn first_sweep(
    sweep: FirstSweep,
    lo: f64,
    hi: f64,
    solve: &mut impl FnMut(f64, Option<&DrivenState>) -> Result<DrivenState>,
) -> Result<Vec<DrivenState>> {
    let keys = sweep.keys(lo, hi);
    let volumes: Vec<f64> = (0..keys)
        .map(|j| lo + (hi - lo) * j as f64 / (keys - 1) as f64)
        .collect();
    let nearest = (0..volumes.len())
        .min_by(|&a, &b| volumes[a].abs().total_cmp(&volumes[b].abs()))
        .unwrap_or(0);
    let mut solved: Vec<Option<DrivenState>> = vec![None; volumes.len()];
    solved[nearest] = Some(solve(volumes[nearest], None)?);
    for j in nearest + 1..volumes.len() {
        let state = solve(
            volumes[j],
            (j == nearest + 1)
                .then(|| solved[nearest].as_ref())
                .flatten(),
        )?;
        solved[j] = Some(state);
    }
    for j in (0..nearest).rev() {
        let state = solve(volumes[j], solved[j + 1].as_ref())?;
        solved[j] = Some(state);
    }
    Ok(solved.into_iter().flatten().collect())
}

impl VolumeKeyframes {
    /// Solves key volumes covering the frames' volume changes `frames_ml` until
    /// interpolation reproduces direct solves within `tolerance_mm` (or the frame is solved,
    /// across a jump); each key meets its volume within `volume_tolerance_ml`.
    pub fn build(
        driver: &mut BreathingDriver,
        frames_ml: &[f64],
        tolerance_mm: f64,
        volume_tolerance_ml: f64,
    ) -> Result<Self> {
        let (lo_ml, hi_ml) = frames_ml
            .iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &v| {
                (a.min(v), b.max(v))
            });
        if !(lo_ml.is_finite() && hi_ml.is_finite() && frames_ml.iter().all(|v| v.is_finite())) {
            return Err(Error::Argument {
                what: "key volumes".into(),
                reason: format!(
                    "the frames' volume changes ({} of them, {lo_ml} … {hi_ml} mL) are not a \
                     finite range",
                    frames_ml.len()
                ),
            });
        }
        if !(tolerance_mm.is_finite() && tolerance_mm > 0.0) {
            return Err(Error::Argument {
                what: "interpolation tolerance".into(),
                reason: format!("{tolerance_mm} mm must be positive"),
            });
        }
        // A degenerate range is one key: every frame is the same state.
        let span = (hi_ml - lo_ml).max(2.0 * volume_tolerance_ml);
        let (lo, hi) = (
            0.5 * (lo_ml + hi_ml) - 0.5 * span,
            0.5 * (lo_ml + hi_ml) + 0.5 * span,
        );
        let rest = driver.rest_positions().to_vec();
        let sweep = if driver.slides_on_curved_surfaces() {
            FirstSweep::CURVED_WALL
        } else {
            FirstSweep::PLANES
        };
        Self::refine(
            sweep,
            &rest,
            lo,
            hi,
            frames_ml,
            tolerance_mm,
            |volume_ml, from| {
                if let Some(below) = from {
                    driver.warm_start(below);
                }
                driver.solve_volume(volume_ml, volume_tolerance_ml)
            },
        )
    }

    /// The adaptive key placement over `lo..=hi` mL for frames at `frames_ml`, from a first
    /// sweep spaced by `sweep`, whatever solves the states: `solve(v, from)` returns the
    /// equilibrium at volume change `v`, continuing from the solved state `from` when given,
    /// else from the previous solve.
    pub fn refine(
        sweep: FirstSweep,
        rest: &[V3],
        lo: f64,
        hi: f64,
        frames_ml: &[f64],
        tolerance_mm: f64,
        mut solve: impl FnMut(f64, Option<&DrivenState>) -> Result<DrivenState>,
    ) -> Result<Self> {
        let mut scratch = vec![V3::zeros(); rest.len()];
        let mut states = first_sweep(sweep, lo, hi, &mut solve)?;
        let min_step = (hi - lo) * MIN_KEY_STEP_FRACTION;
        let mut frames: Vec<f64> = frames_ml.to_vec();
        frames.sort_by(f64::total_cmp);
        let frames_within = |a: f64, b: f64| {
            frames.partition_point(|&v| v <= b) - frames.partition_point(|&v| v < a)
        };
        // Per interval (between keys i and i + 1): a jump, solved directly.
        let mut direct = vec![false; states.len() - 1];
        let mut jumps: Vec<DirectInterval> = Vec::new();
        // The end keys of the range and of every smooth segment have no keys beyond them to
        // check them against: the checks of their neighbours cover the intervals beside them.
        let mut checked = vec![false; states.len()];
        // Each key's miss at its last check (NaN before its first).
        let mut last_miss_mm = vec![f64::NAN; states.len()];
        let mut worst_passed: Option<f64> = None;
        let mut refinements = 0;
        loop {
            let volumes: Vec<f64> = states.iter().map(|s| s.volume_change_ml).collect();
            let mut failing = Vec::new();
            let mut worst: Option<Miss> = None;
            for (k, done) in checked.iter_mut().enumerate() {
                let (first, last) = segment(&direct, k);
                if *done || k == first || k == last {
                    *done = true;
                    continue;
                }
                let miss = leave_one_out(&states, &volumes, (first, last), k, rest, &mut scratch);
                tracing::debug!(
                    keys = states.len(),
                    volume_ml = miss.volume_ml,
                    error_mm = miss.error_mm,
                    node = miss.node,
                    "key volume checked against the interpolant of its neighbours"
                );
                let previous = std::mem::replace(&mut last_miss_mm[k], miss.error_mm);
                if miss.error_mm <= tolerance_mm {
                    *done = true;
                    worst_passed =
                        Some(worst_passed.map_or(miss.error_mm, |w| w.max(miss.error_mm)));
                } else {
                    // Halving the intervals beside a key cuts a smooth response's miss about
                    // 16-fold and a kink's 2-fold; a miss that barely moves is a jump.
                    let stalled = miss.error_mm > STALLED_MISS_RATIO * previous;
                    failing.push((miss, stalled));
                    if worst.is_none_or(|w| miss.error_mm > w.error_mm) {
                        worst = Some(miss);
                    }
                }
            }
            let Some(worst) = worst else {
                let mut out = Self::from_states(states, tolerance_mm);
                out.report.measured_error_mm = worst_passed;
                out.report.refinements = refinements;
                out.report.direct_intervals = jumps;
                out.direct = direct;
                return Ok(out);
            };
            // A failing key sits at a jump when its intervals are both down to the smallest
            // step, or when its miss stalled and solving the frames between its neighbours
            // costs no more than halving further would. The worst such key makes its two
            // intervals direct, and the keys are checked again with stencils that stop there,
            // before any key is added (keys near a jump fail only because their stencils
            // reach across it).
            let wide = |i: usize| volumes[i + 1] - volumes[i] > min_step * (1.0 + 1e-9);
            let at_jump = failing
                .iter()
                .filter(|(m, stalled)| {
                    let k = m.key;
                    (!wide(k - 1) && !wide(k))
                        || (*stalled
                            && frames_within(volumes[k - 1], volumes[k + 1])
                                <= DIRECT_FRAMES_FOR_A_HALVING)
                })
                .map(|(m, _)| m)
                .max_by(|a, b| a.error_mm.total_cmp(&b.error_mm));
            if let Some(miss) = at_jump {
                let k = miss.key;
                direct[k - 1] = true;
                direct[k] = true;
                let p = rest[miss.node] * 1e3;
                jumps.push(DirectInterval {
                    from_ml: volumes[k - 1],
                    to_ml: volumes[k + 1],
                    node: miss.node,
                    rest_position_mm: [p.x, p.y, p.z],
                    error_mm: miss.error_mm,
                });
                for (j, done) in checked.iter_mut().enumerate() {
                    let (first, last) = segment(&direct, j);
                    if j - first < STENCIL || last - j < STENCIL {
                        *done = false;
                    }
                }
                continue;
            }
            // Otherwise halve the intervals beside every failing key (interval i lies between
            // keys i and i + 1; failing keys are never segment ends).
            let mut split = vec![false; states.len() - 1];
            for (miss, _) in &failing {
                split[miss.key - 1] |= wide(miss.key - 1);
                split[miss.key] |= wide(miss.key);
            }
            let added = split.iter().filter(|&&s| s).count();
            if states.len() + added > MAX_KEYS {
                return Err(not_smooth(
                    rest,
                    worst,
                    &volumes,
                    states.len(),
                    tolerance_mm,
                ));
            }
            refinements += 1;
            let mut refined = Vec::with_capacity(states.len() + added);
            let mut refined_checked = Vec::with_capacity(states.len() + added);
            let mut refined_miss = Vec::with_capacity(states.len() + added);
            let mut refined_direct = Vec::with_capacity(states.len() + added - 1);
            let mut old = states.into_iter().enumerate().peekable();
            while let Some((i, state)) = old.next() {
                let split_after = split.get(i).copied().unwrap_or(false);
                let solved_mid = match (split_after, old.peek()) {
                    (true, Some((_, next))) => {
                        let mid = 0.5 * (volumes[i] + volumes[i + 1]);
                        // From the neighbour nearer the scanned state, along the breath's path.
                        let from = if volumes[i + 1] <= 0.0 { next } else { &state };
                        Some(solve(mid, Some(from))?)
                    }
                    _ => None,
                };
                refined.push(state);
                refined_checked.push(checked[i]);
                refined_miss.push(last_miss_mm[i]);
                if let Some(mid) = solved_mid {
                    refined.push(mid);
                    refined_checked.push(false);
                    refined_miss.push(f64::NAN);
                    refined_direct.extend([false, false]);
                } else if let Some(&d) = direct.get(i) {
                    refined_direct.push(d);
                }
            }
            states = refined;
            checked = refined_checked;
            last_miss_mm = refined_miss;
            direct = refined_direct;
        }
    }

    /// The direct interval `dv_ml` falls in, if any: the solved key on the scanned state's
    /// side of it, to continue from.
    pub fn direct_start(&self, dv_ml: f64) -> Option<&DrivenState> {
        let i = interval_of(&self.volumes_ml, dv_ml)?;
        self.direct[i].then(|| {
            if self.volumes_ml[i + 1] <= 0.0 {
                &self.states[i + 1]
            } else {
                &self.states[i]
            }
        })
    }

    fn from_states(states: Vec<DrivenState>, tolerance_mm: f64) -> Self {
        let volumes: Vec<f64> = states.iter().map(|s| s.volume_change_ml).collect();
        let smallest_key_step_ml = volumes
            .windows(2)
            .map(|w| w[1] - w[0])
            .fold(f64::INFINITY, f64::min);
        let report = KeyframeReport {
            keys: states.len(),
            measured_error_mm: None,
            tolerance_mm,
            refinements: 0,
            smallest_key_step_ml: if smallest_key_step_ml.is_finite() {
                smallest_key_step_ml
            } else {
                0.0
            },
            solves: states.iter().map(|s| s.solves).sum(),
            newton_iterations: states.iter().map(|s| s.newton_iterations).sum(),
            linear_iterations: states.iter().map(|s| s.linear_iterations).sum(),
            solve_time_s: states.iter().map(|s| s.wall_time_s).sum(),
            direct_intervals: Vec::new(),
        };
        VolumeKeyframes {
            direct: vec![false; volumes.len().saturating_sub(1)],
            volumes_ml: volumes,
            states,
            report,
        }
    }

    /// Interpolation weights of the keys at volume change `dv_ml`: the cubic Lagrange
    /// weights of the four keys nearest it (fewer when there are fewer keys), zero for the
    /// others. Beyond the end keys this extrapolates from the outermost four.
    pub fn weights(&self, dv_ml: f64, out: &mut Vec<f64>) {
        out.clear();
        out.resize(self.volumes_ml.len(), 0.0);
        let mut stencil = [0usize; STENCIL];
        let used = self.stencil(dv_ml, &mut stencil);
        lagrange(&self.volumes_ml, &stencil[..used], dv_ml, |k, w| out[k] = w);
    }

    /// Node positions at volume change `dv_ml`, written into `out`.
    pub fn positions_at(&self, rest_m: &[V3], dv_ml: f64, out: &mut [V3]) {
        let mut stencil = [0usize; STENCIL];
        let used = self.stencil(dv_ml, &mut stencil);
        interpolate(
            &self.states,
            &self.volumes_ml,
            &stencil[..used],
            rest_m,
            dv_ml,
            out,
        );
    }

    /// The keys interpolating at `dv_ml`: the nearest within its smooth segment.
    fn stencil(&self, dv_ml: f64, out: &mut [usize; STENCIL]) -> usize {
        let i = interval_of(&self.volumes_ml, dv_ml).unwrap_or(0);
        let (first, last) = segment(&self.direct, i);
        segment_stencil(&self.volumes_ml, (first, last), None, dv_ml, out)
    }

    /// Surface pressure at volume change `dv_ml`, Pa.
    pub fn pressure_at(&self, dv_ml: f64) -> f64 {
        let mut stencil = [0usize; STENCIL];
        let used = self.stencil(dv_ml, &mut stencil);
        let mut p = 0.0;
        lagrange(&self.volumes_ml, &stencil[..used], dv_ml, |k, w| {
            p += w * self.states[k].pressure_pa
        });
        p
    }
}

/// The interval between neighbouring keys that holds `dv_ml` (the end intervals hold the
/// volumes beyond them); `None` with fewer than two keys.
fn interval_of(volumes: &[f64], dv_ml: f64) -> Option<usize> {
    let intervals = volumes.len().checked_sub(1).filter(|&n| n > 0)?;
    Some(
        volumes
            .partition_point(|&v| v <= dv_ml)
            .saturating_sub(1)
            .min(intervals - 1),
    )
}

/// First and last key of the smooth segment holding key `at`, or the interval from key
/// `at` to the next (segments end where an interval is direct).
fn segment(direct: &[bool], at: usize) -> (usize, usize) {
    let first = direct[..at].iter().rposition(|&d| d).map_or(0, |b| b + 1);
    let last = direct[at..]
        .iter()
        .position(|&d| d)
        .map_or(direct.len(), |b| at + b);
    (first, last)
}

/// [`local_stencil`] within the keys `first..=last` of a smooth segment.
fn segment_stencil(
    volumes: &[f64],
    (first, last): (usize, usize),
    skip: Option<usize>,
    dv_ml: f64,
    out: &mut [usize; STENCIL],
) -> usize {
    let used = local_stencil(&volumes[first..=last], skip.map(|k| k - first), dv_ml, out);
    out[..used].iter_mut().for_each(|k| *k += first);
    used
}

/// The (up to) [`STENCIL`] keys nearest `dv_ml` in `volumes` (increasing), `skip` left out,
/// written to `out` in increasing order; returns how many.
fn local_stencil(
    volumes: &[f64],
    skip: Option<usize>,
    dv_ml: f64,
    out: &mut [usize; STENCIL],
) -> usize {
    // The keys without `skip`, counted by rank r: key r, or r + 1 from `skip` on. Ranked,
    // not collected, because frames are interpolated in the hot path.
    let skipped = |r: usize| usize::from(skip.is_some_and(|k| r >= k));
    let keys = volumes.len() - usize::from(skip.is_some());
    let n = keys.min(STENCIL);
    // The first key above dv, then a window of n keys centred on the interval it closes.
    let first_above = volumes.partition_point(|&v| v <= dv_ml);
    let above = first_above - usize::from(skip.is_some_and(|k| k < first_above));
    let start = above.saturating_sub(n / 2).min(keys - n);
    for (i, slot) in out[..n].iter_mut().enumerate() {
        *slot = start + i + skipped(start + i);
    }
    n
}

/// Calls `weight(k, w)` with the Lagrange weight of each key `k` of `stencil` at `dv_ml`.
fn lagrange(volumes: &[f64], stencil: &[usize], dv_ml: f64, mut weight: impl FnMut(usize, f64)) {
    for &j in stencil {
        let w = stencil
            .iter()
            .filter(|&&k| k != j)
            .map(|&k| (dv_ml - volumes[k]) / (volumes[j] - volumes[k]))
            .product::<f64>();
        weight(j, w);
    }
}

/// Positions at `dv_ml` interpolated from the keys of `stencil`, into `out`.
fn interpolate(
    states: &[DrivenState],
    volumes: &[f64],
    stencil: &[usize],
    rest_m: &[V3],
    dv_ml: f64,
    out: &mut [V3],
) {
    out.copy_from_slice(rest_m);
    lagrange(volumes, stencil, dv_ml, |k, wk| {
        for ((o, x), r) in out.iter_mut().zip(&states[k].positions_m).zip(rest_m) {
            *o += (x - r) * wk;
        }
    });
}

/// How far key `k`'s solved positions are from the local interpolant of the other keys.
fn leave_one_out(
    states: &[DrivenState],
    volumes: &[f64],
    segment: (usize, usize),
    k: usize,
    rest_m: &[V3],
    scratch: &mut [V3],
) -> Miss {
    let mut stencil = [0usize; STENCIL];
    let used = segment_stencil(volumes, segment, Some(k), volumes[k], &mut stencil);
    interpolate(
        states,
        volumes,
        &stencil[..used],
        rest_m,
        volumes[k],
        scratch,
    );
    let (node, error_m) = scratch
        .iter()
        .zip(&states[k].positions_m)
        .map(|(a, b)| (a - b).norm())
        .enumerate()
        .fold((0, 0.0), |m, (i, e)| if e > m.1 { (i, e) } else { m });
    Miss {
        key: k,
        error_mm: error_m * 1e3,
        volume_ml: volumes[k],
        node,
    }
}

/// The refusal when keys keep missing: where, by how much, and what it means.
fn not_smooth(
    rest_m: &[V3],
    worst: Miss,
    volumes: &[f64],
    keys: usize,
    tolerance_mm: f64,
) -> Error {
    let k = worst.key;
    let step = (volumes[k] - volumes[k - 1]).min(volumes[k + 1] - volumes[k]);
    let p = rest_m[worst.node] * 1e3;
    Error::InvalidModel(format!(
        "the lung's shape does not follow its volume smoothly near {:.1} mL: with {keys} key \
         volumes, {:.2} mL apart there, node {} (rest position {:.1}, {:.1}, {:.1} mm) is still \
         {:.3} mm from the interpolation of its neighbours (tolerance {tolerance_mm} mm). Its \
         equilibrium jumps or bends there (a node crossing a cell of the chest wall's distance \
         field, or two equilibria); raise interpolation_tolerance_mm or set \
         solve_every_frame = true",
        worst.volume_ml, step, worst.node, p.x, p.y, p.z, worst.error_mm
    ))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::Material;
    use crate::simulation::cases::symmetric_block_under_pressure;
    use crate::simulation::QuasiStaticSettings;

    #[test]
    fn interpolated_frames_match_direct_solves_within_the_measured_error() {
        let scene = symmetric_block_under_pressure([4, 4, 4], 0.01, Material::LUNG, -1.0).unwrap();
        let v0 = scene.mesh.enclosed_volume_m3(&scene.mesh.rest_positions_m) * 1e6;
        let c = v0 / Material::LUNG.bulk_modulus_pa();
        let settings = QuasiStaticSettings::default();
        let mut driver = BreathingDriver::new(&scene, -1.0, c, settings.clone()).unwrap();
        let (lo, hi) = (-0.02 * v0, 0.12 * v0);
        let tol_ml = 1e-4 * v0;
        let keys = VolumeKeyframes::build(&mut driver, &[lo, hi], 0.01, tol_ml).unwrap();
        assert!(
            keys.report.measured_error_mm.is_some_and(|e| e <= 0.01),
            "{:?}",
            keys.report
        );
        assert!(keys.report.keys >= 5, "{:?}", keys.report);
        // Fresh direct solves at volumes that are not keys.
        let mut direct = BreathingDriver::new(&scene, -1.0, c, settings).unwrap();
        let rest = scene.mesh.rest_positions_m.clone();
        let mut x = vec![V3::zeros(); rest.len()];
        for frac in [0.013, 0.047, 0.101] {
            let s = direct.solve_volume(frac * v0, tol_ml).unwrap();
            keys.positions_at(&rest, s.volume_change_ml, &mut x);
            let err_mm = x
                .iter()
                .zip(&s.positions_m)
                .map(|(a, b)| (a - b).norm())
                .fold(0.0, f64::max)
                * 1e3;
            assert!(err_mm < 0.01, "frac {frac}: {err_mm} mm");
            assert!(
                (keys.pressure_at(s.volume_change_ml) - s.pressure_pa).abs()
                    < 1e-3 * s.pressure_pa.abs()
            );
        }
        // A key reproduces itself exactly.
        keys.positions_at(&rest, keys.volumes_ml[2], &mut x);
        assert_eq!(x, keys.states[2].positions_m);
    }

    /// A state whose node 0 moves by `x_mm(v)` along x and node 1 stays at rest.
    fn synthetic(volume_ml: f64, x_mm: impl Fn(f64) -> f64) -> DrivenState {
        DrivenState {
            positions_m: vec![
                V3::new(x_mm(volume_ml) * 1e-3, 0.0, 0.0),
                V3::new(0.0, 0.0, 0.1),
            ],
            pressure_pa: -volume_ml / 3.0,
            volume_change_ml: volume_ml,
            solves: 1,
            newton_iterations: 2,
            linear_iterations: 10,
            residual: 1e-7,
            wall_time_s: 0.0,
        }
    }

    fn rest() -> Vec<V3> {
        vec![V3::zeros(), V3::new(0.0, 0.0, 0.1)]
    }

    #[test]
    fn keys_gather_at_a_kink_and_the_interpolant_meets_the_tolerance_everywhere() {
        // A smooth stretch plus a node that starts sliding at 713 mL (slope change 0.02
        // mm/mL), as a wall node crossing a cell of the distance field does.
        let x_mm = |v: f64| 0.03 * v + 2e-6 * v * v + 0.02 * (v - 713.0).max(0.0);
        let keys = VolumeKeyframes::refine(
            FirstSweep::PLANES,
            &rest(),
            0.0,
            1000.0,
            &[],
            0.1,
            |v, _| Ok(synthetic(v, x_mm)),
        )
        .unwrap();
        let r = &keys.report;
        assert!(r.refinements > 0 && r.keys < 40, "{r:?}");
        assert!(r.measured_error_mm.is_some_and(|e| e <= 0.1), "{r:?}");
        // The refinement went to the kink: the closest keys sit beside it, the far end of
        // the range kept the first sweep's spacing.
        let v = &keys.volumes_ml;
        let closest = (1..v.len())
            .min_by(|&a, &b| (v[a] - v[a - 1]).total_cmp(&(v[b] - v[b - 1])))
            .unwrap();
        assert!((v[closest] - 713.0).abs() < 50.0, "{v:?}");
        let first_sweep_below_300 = (300.0 / FirstSweep::PLANES.max_step_ml).ceil() as usize;
        assert!(
            v.iter().filter(|&&x| x < 300.0).count() <= first_sweep_below_300,
            "{v:?}"
        );
        let mut x = rest();
        let worst = (0..=2000)
            .map(|i| {
                let v = i as f64 * 0.5;
                keys.positions_at(&rest(), v, &mut x);
                (x[0].x * 1e3 - x_mm(v)).abs()
            })
            .fold(0.0, f64::max);
        assert!(worst <= 0.1, "worst interpolation error {worst} mm");
        assert!((keys.pressure_at(300.0) + 100.0).abs() < 1e-9);
    }

    #[test]
    fn keys_are_solved_outward_from_the_scanned_state_each_from_its_neighbour_nearer_it() {
        // A kink below the scan forces a refinement there too.
        let x_mm = |v: f64| 0.03 * v + 0.02 * (-250.0 - v).max(0.0);
        let mut calls: Vec<(f64, Option<f64>)> = Vec::new();
        let keys = VolumeKeyframes::refine(
            FirstSweep::PLANES,
            &rest(),
            -400.0,
            100.0,
            &[],
            0.1,
            |v, from| {
                calls.push((v, from.map(|s| s.volume_change_ml)));
                Ok(synthetic(v, x_mm))
            },
        )
        .unwrap();
        // The first sweep: -400 + 125 j; the key nearest the scan (-25) first, from wherever
        // the driver is (the rest state), then up from it, then down from it.
        assert_eq!(FirstSweep::PLANES.min_keys, 5);
        let sweep: Vec<f64> = calls.iter().take(5).map(|c| c.0).collect();
        assert_eq!(sweep, [-25.0, 100.0, -150.0, -275.0, -400.0]);
        assert_eq!(calls[0].1, None);
        assert_eq!(calls[1].1, Some(-25.0));
        assert_eq!(calls[2].1, Some(-25.0));
        assert_eq!(calls[3].1, Some(-150.0));
        // Refinement keys below the scan continue from the key above them.
        let refined = &calls[5..];
        assert!(!refined.is_empty());
        for &(v, from) in refined {
            let from = from.expect("a refinement key starts from a solved neighbour");
            if v < 0.0 {
                assert!(from > v, "key {v} started from {from}");
            }
        }
        assert!(keys.report.measured_error_mm.is_some_and(|e| e <= 0.1));
    }

    #[test]
    fn stencils_are_the_four_keys_around_a_volume_without_the_one_left_out() {
        // The reference: the kept keys listed, then the window around the first one above.
        let reference = |volumes: &[f64], skip: Option<usize>, dv: f64| -> Vec<usize> {
            let keys: Vec<usize> = (0..volumes.len()).filter(|&k| Some(k) != skip).collect();
            let n = keys.len().min(STENCIL);
            let above = keys.partition_point(|&k| volumes[k] <= dv);
            let start = above.saturating_sub(n / 2).min(keys.len() - n);
            keys[start..start + n].to_vec()
        };
        for len in 2..9 {
            let volumes: Vec<f64> = (0..len).map(|k| (k * k) as f64).collect();
            for skip in std::iter::once(None).chain((0..len).map(Some)) {
                if len == 2 && skip.is_some() {
                    continue;
                }
                for dv in [-1.0, 0.0, 0.5, 3.0, 4.0, 20.0, 100.0] {
                    let mut got = [0; STENCIL];
                    let n = local_stencil(&volumes, skip, dv, &mut got);
                    assert_eq!(
                        got[..n],
                        reference(&volumes, skip, dv),
                        "{len} {skip:?} {dv}"
                    );
                }
            }
        }
    }

    #[test]
    fn a_wide_range_gets_more_first_sweep_keys_not_wider_steps() {
        let planes = FirstSweep::PLANES;
        assert_eq!(planes.keys(0.0, 500.0), planes.min_keys);
        assert_eq!(planes.keys(-100.0, 100.0), planes.min_keys);
        // The recording with a vital-capacity manoeuvre: −436 … +1150 mL.
        let n = planes.keys(-436.0, 1150.0);
        assert_eq!(n, 14);
        assert!(1586.0 / (n - 1) as f64 <= planes.max_step_ml);
        let mut solved = Vec::new();
        VolumeKeyframes::refine(
            FirstSweep::PLANES,
            &rest(),
            -436.0,
            1150.0,
            &[],
            0.1,
            |v, _| {
                solved.push(v);
                Ok(synthetic(v, |v| 0.03 * v))
            },
        )
        .unwrap();
        solved.sort_by(f64::total_cmp);
        assert_eq!(solved.len(), n);
        assert!(solved
            .windows(2)
            .all(|w| w[1] - w[0] <= planes.max_step_ml + 1e-9));
        assert_eq!(planes.keys(f64::NAN, 1.0), planes.min_keys);
        // The curved wall keeps the finer sweep: 9 keys over a 500 mL breath, 62.5 mL apart.
        assert_eq!(FirstSweep::CURVED_WALL.keys(0.0, 500.0), 9);
        assert_eq!(FirstSweep::CURVED_WALL.keys(-436.0, 1150.0), 27);
    }

    #[test]
    fn a_smooth_response_takes_the_first_sweep_only() {
        let keys =
            VolumeKeyframes::refine(FirstSweep::PLANES, &rest(), 0.0, 500.0, &[], 0.1, |v, _| {
                Ok(synthetic(v, |v| 0.05 * v - 1e-5 * v * v))
            })
            .unwrap();
        assert_eq!(
            (keys.report.keys, keys.report.refinements),
            (FirstSweep::PLANES.min_keys, 0)
        );
        assert!(
            keys.report.measured_error_mm.is_some_and(|e| e < 1e-9),
            "{:?}",
            keys.report
        );
    }

    #[test]
    fn a_jump_becomes_a_direct_interval_and_the_rest_is_interpolated_within_the_tolerance() {
        // Two equilibria: node 0 snaps 1 mm at 480 mL. No number of keys interpolates that.
        let x_mm = |v: f64| 0.03 * v + if v > 480.0 { 1.0 } else { 0.0 };
        // Many frames (a long recording): narrowing the jump down is cheaper than solving them.
        let frames: Vec<f64> = (0..=2000).map(|i| i as f64 * 0.5).collect();
        let mut solves = 0;
        let keys = VolumeKeyframes::refine(
            FirstSweep::PLANES,
            &rest(),
            0.0,
            1000.0,
            &frames,
            0.1,
            |v, _| {
                solves += 1;
                Ok(synthetic(v, x_mm))
            },
        )
        .unwrap();
        let jumps = &keys.report.direct_intervals;
        assert_eq!(jumps.len(), 1, "{jumps:?}");
        let jump = &jumps[0];
        assert!(jump.from_ml < 480.0 && jump.to_ml > 480.0, "{jump:?}");
        assert!(
            jump.to_ml - jump.from_ml <= 2.0 * 1000.0 / 64.0 + 1e-9,
            "{jump:?}"
        );
        assert_eq!(jump.node, 0);
        assert!(jump.error_mm > 0.1, "{jump:?}");
        assert!(keys.report.keys < 40, "{:?}", keys.report);
        // Outside the jump every volume interpolates within the tolerance; inside it the
        // frame is solved from the key just below it (above the scan, the side the breath
        // comes from).
        let mut x = rest();
        for i in 0..=2000 {
            let v = i as f64 * 0.5;
            match keys.direct_start(v) {
                Some(from) => {
                    assert!(v >= jump.from_ml && v <= jump.to_ml, "{v}");
                    let f = from.volume_change_ml;
                    assert!(
                        f >= jump.from_ml && f <= v && v - f <= 1000.0 / 64.0,
                        "{v}: {f}"
                    );
                }
                None => {
                    keys.positions_at(&rest(), v, &mut x);
                    let e = (x[0].x * 1e3 - x_mm(v)).abs();
                    assert!(e <= 0.1, "{v} mL: {e} mm");
                }
            }
        }
        // Ten frames: the jump is left wide as soon as halving stops helping, for fewer
        // solves, and no more than a few frames fall inside it (none, when the first
        // sweep's keys already sit closer than the frames).
        let ten: Vec<f64> = (0..10).map(|i| i as f64 * 111.0).collect();
        let mut few_solves = 0;
        let wide = VolumeKeyframes::refine(
            FirstSweep::PLANES,
            &rest(),
            0.0,
            999.0,
            &ten,
            0.1,
            |v, _| {
                few_solves += 1;
                Ok(synthetic(v, x_mm))
            },
        )
        .unwrap();
        let jump = &wide.report.direct_intervals[0];
        assert!(jump.from_ml < 480.0 && jump.to_ml > 480.0, "{jump:?}");
        let inside = ten
            .iter()
            .filter(|&&v| wide.direct_start(v).is_some())
            .count();
        assert!(inside <= DIRECT_FRAMES_FOR_A_HALVING, "{inside}");
        assert!(few_solves < solves, "{few_solves} vs {solves}");
    }

    #[test]
    fn below_the_scan_a_jump_is_solved_from_the_key_nearer_the_scan() {
        let x_mm = |v: f64| 0.03 * v + if v < -300.0 { -2.0 } else { 0.0 };
        let frames: Vec<f64> = (0..=600).map(|i| i as f64 - 500.0).collect();
        let keys = VolumeKeyframes::refine(
            FirstSweep::PLANES,
            &rest(),
            -500.0,
            100.0,
            &frames,
            0.1,
            |v, _| Ok(synthetic(v, x_mm)),
        )
        .unwrap();
        let jump = &keys.report.direct_intervals[0];
        assert!(jump.from_ml < -300.0 && jump.to_ml > -300.0, "{jump:?}");
        let from = keys.direct_start(-300.0).expect("inside the jump");
        let f = from.volume_change_ml;
        assert!(
            f >= -300.0 && f <= jump.to_ml && f + 300.0 <= 600.0 / 64.0,
            "{f}"
        );
        assert!(keys.direct_start(-450.0).is_none() && keys.direct_start(0.0).is_none());
    }
}
