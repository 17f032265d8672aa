//! Quasi-static breathing frames without one solve per frame.
//!
//! In quasi-static breathing the lung's shape is a smooth function of its volume alone (an
//! elastic body, no rate effects), so it is solved at a few *key volumes* and every frame is
//! interpolated from them. Keys are Chebyshev–Lobatto points of the requested volume range
//! and the interpolant is barycentric Lagrange on them, which converges geometrically for a
//! smooth response. Its error is *measured*, not assumed: the points halfway (in angle)
//! between n Lobatto points are exactly the new points of the 2n − 1 Lobatto set, so a sweep
//! of 2n − 1 keys holds both an n-key interpolant (every other key) and n − 1 direct solves
//! to check it against; the sweep is accepted, with all its keys, when that coarser
//! interpolant predicts every check within the tolerance in mm, and is otherwise redone with
//! twice the keys.
//!
//! Each sweep is solved in ascending volume from the lowest key, so all its states lie on one
//! gradual-inflation path. The loaded lung can have more than one equilibrium (on the phantom
//! at 6 mm a mediastinal corner node sat 0.67 mm apart at 500 mL when reached in one step
//! instead of 100 mL steps); keys from a coarse sweep mixed with checks from a fine one read
//! as an interpolation error that no number of keys removed. Checking within one sweep keeps
//! that property without solving the coarse keys twice.

use serde::Serialize;

use super::driver::{BreathingDriver, DrivenState};
use crate::math::V3;
use crate::{Error, Result};

/// Largest number of key volumes before the interpolation is declared not worth it.
pub const MAX_KEYS: usize = 65;

/// Keys of the first sweep: over a 500 mL tidal range its largest volume step is 96 mL, small
/// enough for Newton from the predicted state on the 4 mm CIP lungs, and its every-other-key
/// interpolant (5 keys) already met 0.1 mm on them at 8 mm.
pub const FIRST_SWEEP_KEYS: usize = 9;

/// Solved key volumes and the interpolant over them.
#[derive(Debug, Clone)]
pub struct VolumeKeyframes {
    /// Key volume changes from rest, mL, increasing.
    pub volumes_ml: Vec<f64>,
    /// The solved state at each key.
    pub states: Vec<DrivenState>,
    bary: Vec<f64>,
    /// What building the keys measured.
    pub report: KeyframeReport,
}

/// How the keys were chosen and how well they interpolate.
#[derive(Debug, Clone, Serialize)]
pub struct KeyframeReport {
    /// Number of key volumes solved.
    pub keys: usize,
    /// Largest node-position difference between interpolation and direct solve at the check
    /// volumes, mm (measured with every other key, a bound on the error of all of them).
    pub measured_error_mm: f64,
    /// Tolerance asked for, mm.
    pub tolerance_mm: f64,
    /// Equilibrium solves spent, all keys together.
    pub solves: usize,
    /// Newton iterations spent, all solves together.
    pub newton_iterations: usize,
    /// Krylov iterations spent, all solves together.
    pub linear_iterations: usize,
    /// Solver wall time, s.
    pub solve_time_s: f64,
}

/// `n` Chebyshev–Lobatto points of [lo, hi], increasing.
pub fn chebyshev_lobatto(lo: f64, hi: f64, n: usize) -> Vec<f64> {
    (0..n)
        .map(|j| {
            let theta = std::f64::consts::PI * j as f64 / (n - 1) as f64;
            0.5 * (lo + hi) - 0.5 * (hi - lo) * theta.cos()
        })
        .collect()
}

impl VolumeKeyframes {
    /// Solves key volumes covering `lo_ml..=hi_ml` until interpolation reproduces direct
    /// solves within `tolerance_mm`; each key meets its volume within `volume_tolerance_ml`.
    pub fn build(
        driver: &mut BreathingDriver,
        lo_ml: f64,
        hi_ml: f64,
        tolerance_mm: f64,
        volume_tolerance_ml: f64,
    ) -> Result<Self> {
        if !(lo_ml.is_finite() && hi_ml.is_finite() && lo_ml <= hi_ml) {
            return Err(Error::Argument {
                what: "key volume range".into(),
                reason: format!("{lo_ml} … {hi_ml} mL is not an ordered finite range"),
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
        let mut scratch = vec![V3::zeros(); rest.len()];
        let mut spent = Spent::default();
        let first = driver.solve_volume(lo, volume_tolerance_ml)?;
        spent.add(&first);
        let mut n = FIRST_SWEEP_KEYS;
        loop {
            // One ascending sweep from the lowest key, each solve starting from the states
            // just below it, so that every key lies on the same gradual-inflation path.
            driver.warm_start(&first);
            let mut states = Vec::with_capacity(n);
            states.push(first.clone());
            for &v in &chebyshev_lobatto(lo, hi, n)[1..] {
                let state = driver.solve_volume(v, volume_tolerance_ml)?;
                spent.add(&state);
                states.push(state);
            }
            // Every other key is the Lobatto set of (n + 1) / 2 points; the keys between
            // them are direct solves that its interpolant must reproduce.
            let coarse = Self::from_states(states.iter().step_by(2).cloned().collect(), 0.0);
            let mut error_mm: f64 = 0.0;
            for check in states.iter().skip(1).step_by(2) {
                coarse.positions_at(&rest, check.volume_change_ml, &mut scratch);
                let e = scratch
                    .iter()
                    .zip(&check.positions_m)
                    .map(|(a, b)| (a - b).norm())
                    .fold(0.0, f64::max);
                error_mm = error_mm.max(e * 1e3);
            }
            if error_mm <= tolerance_mm {
                let mut out = Self::from_states(states, tolerance_mm);
                out.report.measured_error_mm = error_mm;
                out.report.solves = spent.solves;
                out.report.newton_iterations = spent.newton_iterations;
                out.report.linear_iterations = spent.linear_iterations;
                out.report.solve_time_s = spent.solve_time_s;
                return Ok(out);
            }
            if n >= MAX_KEYS {
                return Err(Error::NotConverged {
                    iterations: n,
                    residual: error_mm,
                    tolerance: tolerance_mm,
                });
            }
            n = 2 * n - 1;
        }
    }

    fn from_states(states: Vec<DrivenState>, tolerance_mm: f64) -> Self {
        let n = states.len();
        // Barycentric weights of Chebyshev–Lobatto points; the keys sit at their solved
        // volumes (within the volume tolerance of the ideal points), so use the general formula.
        let volumes: Vec<f64> = states.iter().map(|s| s.volume_change_ml).collect();
        let bary = (0..n)
            .map(|j| {
                1.0 / (0..n)
                    .filter(|&k| k != j)
                    .map(|k| volumes[j] - volumes[k])
                    .product::<f64>()
            })
            .collect();
        let report = KeyframeReport {
            keys: n,
            measured_error_mm: f64::NAN,
            tolerance_mm,
            solves: states.iter().map(|s| s.solves).sum(),
            newton_iterations: states.iter().map(|s| s.newton_iterations).sum(),
            linear_iterations: states.iter().map(|s| s.linear_iterations).sum(),
            solve_time_s: states.iter().map(|s| s.wall_time_s).sum(),
        };
        VolumeKeyframes {
            volumes_ml: volumes,
            states,
            bary,
            report,
        }
    }

    /// Lagrange weights of the keys at volume change `dv_ml` (extrapolation beyond the keys
    /// is allowed but grows less accurate with distance).
    pub fn weights(&self, dv_ml: f64, out: &mut Vec<f64>) {
        out.clear();
        if let Some(j) = self.volumes_ml.iter().position(|&v| v == dv_ml) {
            out.extend((0..self.volumes_ml.len()).map(|k| f64::from(u8::from(k == j))));
            return;
        }
        let terms = self
            .volumes_ml
            .iter()
            .zip(&self.bary)
            .map(|(v, w)| w / (dv_ml - v));
        out.extend(terms);
        let sum: f64 = out.iter().sum();
        for w in out.iter_mut() {
            *w /= sum;
        }
    }

    /// Node positions at volume change `dv_ml`, written into `out`.
    pub fn positions_at(&self, rest_m: &[V3], dv_ml: f64, out: &mut [V3]) {
        let mut w = Vec::with_capacity(self.states.len());
        self.weights(dv_ml, &mut w);
        out.copy_from_slice(rest_m);
        for (state, &wk) in self.states.iter().zip(&w) {
            for ((o, x), r) in out.iter_mut().zip(&state.positions_m).zip(rest_m) {
                *o += (x - r) * wk;
            }
        }
    }

    /// Surface pressure at volume change `dv_ml`, Pa.
    pub fn pressure_at(&self, dv_ml: f64) -> f64 {
        let mut w = Vec::with_capacity(self.states.len());
        self.weights(dv_ml, &mut w);
        self.states
            .iter()
            .zip(&w)
            .map(|(s, wk)| s.pressure_pa * wk)
            .sum()
    }
}

/// Solver work summed over the states of a build.
#[derive(Default)]
struct Spent {
    solves: usize,
    newton_iterations: usize,
    linear_iterations: usize,
    solve_time_s: f64,
}

impl Spent {
    fn add(&mut self, s: &DrivenState) {
        self.solves += s.solves;
        self.newton_iterations += s.newton_iterations;
        self.linear_iterations += s.linear_iterations;
        self.solve_time_s += s.wall_time_s;
    }
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
        let keys = VolumeKeyframes::build(&mut driver, lo, hi, 0.01, tol_ml).unwrap();
        assert!(keys.report.measured_error_mm <= 0.01, "{:?}", keys.report);
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

    #[test]
    fn lobatto_points_nest_when_doubled() {
        let coarse = chebyshev_lobatto(-1.0, 3.0, 5);
        let fine = chebyshev_lobatto(-1.0, 3.0, 9);
        for (j, c) in coarse.iter().enumerate() {
            assert!((fine[2 * j] - c).abs() < 1e-12);
        }
        assert_eq!(coarse[0], -1.0);
        assert!((coarse[4] - 3.0).abs() < 1e-12);
    }
}
