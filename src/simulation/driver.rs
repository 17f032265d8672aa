//! Driving the lung through a breathing curve with surface pressure.
//!
//! The scene carries one *reference* pressure on the lung surface; each frame solves the
//! quasi-static equilibrium under that pressure scaled by a load factor λ, warm-started from
//! the previous frame, with one preconditioner set up for the whole sequence.
//!
//! * Compliance driver (the thesis's): ΔP = ΔV / C, one solve per frame.
//! * Volume driver (the default, since users hand us a volume curve): the pressure that
//!   makes the simulated volume equal the curve's, found by secant iterations on λ whose
//!   slope dV/dλ carries over from frame to frame (typically 1–3 solves per frame).
//!
//! Sign convention (as [`crate::model::SurfacePressure`]): positive pressure pushes inward,
//! so inhalation is a negative surface pressure.

use nalgebra::Vector3;
use serde::Serialize;

use super::quasistatic::{QuasiStaticSettings, QuasiStaticSolver, SolveReport};
use super::scene::Scene;
use crate::{Error, Result};

type V3 = Vector3<f64>;

/// Most pressure solves the volume driver spends on one frame before giving up.
pub const MAX_VOLUME_SOLVES: usize = 12;

/// An equilibrium of the driven lung.
#[derive(Debug, Clone, Serialize)]
pub struct DrivenState {
    /// Node positions in metres.
    #[serde(skip)]
    pub positions_m: Vec<V3>,
    /// Surface pressure in pascals (negative inflates).
    pub pressure_pa: f64,
    /// Simulated volume change from the rest state, mL.
    pub volume_change_ml: f64,
    /// Equilibrium solves spent on this state.
    pub solves: usize,
    /// Newton iterations over those solves.
    pub newton_iterations: usize,
    /// Krylov iterations over those solves.
    pub linear_iterations: usize,
    /// Relative force residual of the final solve.
    pub residual: f64,
    /// Solver wall time, s.
    pub wall_time_s: f64,
}

/// Solves a scene's equilibrium at prescribed pressures or volumes, frame after frame.
pub struct BreathingDriver<'s> {
    scene: &'s Scene,
    solver: QuasiStaticSolver<'s>,
    reference_pressure_pa: f64,
    rest_volume_m3: f64,
    /// Last solved load factor and its positions (warm start).
    last: Option<(f64, Vec<V3>)>,
    /// Estimated dV/dλ in mL, refined by every pair of solves.
    slope_ml: f64,
}

impl<'s> BreathingDriver<'s> {
    /// Prepares the solver for `scene`, whose surface pressures sum to `reference_pressure_pa`
    /// (the pressure at λ = 1); `compliance_ml_per_pa` seeds the volume driver's first step.
    pub fn new(
        scene: &'s Scene,
        reference_pressure_pa: f64,
        compliance_ml_per_pa: f64,
        settings: QuasiStaticSettings,
    ) -> Result<Self> {
        if !(reference_pressure_pa.is_finite() && reference_pressure_pa != 0.0) {
            return Err(Error::InvalidModel(format!(
                "reference pressure must be finite and non-zero, got {reference_pressure_pa}"
            )));
        }
        if !(compliance_ml_per_pa.is_finite() && compliance_ml_per_pa > 0.0) {
            return Err(Error::InvalidModel(format!(
                "compliance must be positive, got {compliance_ml_per_pa} mL/Pa"
            )));
        }
        let rest_volume_m3 = scene.mesh.enclosed_volume_m3(&scene.mesh.rest_positions_m);
        Ok(BreathingDriver {
            scene,
            solver: QuasiStaticSolver::new(scene, settings)?,
            reference_pressure_pa,
            rest_volume_m3,
            last: None,
            // Inflation (ΔV > 0) needs suction: dV/dλ = −C·P_ref.
            slope_ml: -compliance_ml_per_pa * reference_pressure_pa,
        })
    }

    /// Rest positions of the scene's nodes, metres.
    pub fn rest_positions(&self) -> &[V3] {
        &self.scene.mesh.rest_positions_m
    }

    /// Volume enclosed by the lung surface at rest, mL.
    pub fn rest_volume_ml(&self) -> f64 {
        self.rest_volume_m3 * 1e6
    }

    /// Equilibrium under surface pressure `pressure_pa` (the compliance driver's step).
    pub fn solve_pressure(&mut self, pressure_pa: f64) -> Result<DrivenState> {
        let lambda = pressure_pa / self.reference_pressure_pa;
        let (state, report) = self.solve_factor(lambda)?;
        Ok(self.finish(state, &[report]))
    }

    /// Equilibrium whose volume change from rest is `target_ml` within `tolerance_ml`.
    pub fn solve_volume(&mut self, target_ml: f64, tolerance_ml: f64) -> Result<DrivenState> {
        if !(target_ml.is_finite() && tolerance_ml.is_finite() && tolerance_ml > 0.0) {
            return Err(Error::InvalidInput(format!(
                "volume target {target_ml} mL with tolerance {tolerance_ml} mL"
            )));
        }
        let mut reports = Vec::new();
        let (mut lambda, mut dv) = match &self.last {
            Some((l, x)) => (*l, self.volume_change_ml(x)),
            None => (0.0, 0.0),
        };
        for _ in 0..MAX_VOLUME_SOLVES {
            let error = dv - target_ml;
            if error.abs() <= tolerance_ml && !reports.is_empty() {
                let state = self.last.as_ref().map(|(_, x)| x.clone()).unwrap();
                return Ok(self.finish(state, &reports));
            }
            let next = lambda - error / self.slope_ml;
            let (x, report) = self.solve_factor(next)?;
            reports.push(report);
            let new_dv = self.volume_change_ml(&x);
            // Secant update; the volume grows with suction, so a non-positive slope means the
            // two solves were too close to tell: keep the previous estimate.
            if (next - lambda).abs() > 1e-12 {
                let s = (new_dv - dv) / (next - lambda);
                if s.is_finite() && s * self.slope_ml > 0.0 {
                    self.slope_ml = s;
                }
            }
            lambda = next;
            dv = new_dv;
        }
        if (dv - target_ml).abs() <= tolerance_ml {
            let state = self.last.as_ref().map(|(_, x)| x.clone()).unwrap();
            return Ok(self.finish(state, &reports));
        }
        Err(Error::NotConverged {
            iterations: MAX_VOLUME_SOLVES,
            residual: ((dv - target_ml) / target_ml.abs().max(tolerance_ml)).abs(),
            tolerance: tolerance_ml / target_ml.abs().max(tolerance_ml),
        })
    }

    /// Makes `state` the warm start of the next solve, so a sequence can continue from any
    /// solved state (equilibria of the loaded lung are not always unique: a corner element
    /// can settle differently after a large load step than along a gradual inflation).
    pub fn warm_start(&mut self, state: &DrivenState) {
        self.last = Some((
            state.pressure_pa / self.reference_pressure_pa,
            state.positions_m.clone(),
        ));
    }

    /// Volume change from rest of `positions`, mL.
    pub fn volume_change_ml(&self, positions: &[V3]) -> f64 {
        (self.scene.mesh.enclosed_volume_m3(positions) - self.rest_volume_m3) * 1e6
    }

    fn solve_factor(&mut self, lambda: f64) -> Result<(Vec<V3>, SolveReport)> {
        // Unloaded, the rest state is the equilibrium when every constraint passes through
        // it; solving would only chase round-off below the residual's floor.
        if lambda == 0.0 {
            let x = self.scene.initial_positions();
            if x == self.scene.mesh.rest_positions_m {
                self.last = Some((0.0, x.clone()));
                return Ok((x, SolveReport::default()));
            }
        }
        let initial = self.last.as_ref().map(|(_, x)| x.as_slice());
        let (x, report) = self.solver.solve_with_load_factor(initial, lambda)?;
        self.scene.check_finite(&x, report.newton_iterations)?;
        self.last = Some((lambda, x.clone()));
        Ok((x, report))
    }

    fn finish(&self, positions_m: Vec<V3>, reports: &[SolveReport]) -> DrivenState {
        let lambda = self.last.as_ref().map_or(0.0, |(l, _)| *l);
        DrivenState {
            pressure_pa: lambda * self.reference_pressure_pa,
            volume_change_ml: self.volume_change_ml(&positions_m),
            solves: reports.len(),
            newton_iterations: reports.iter().map(|r| r.newton_iterations).sum(),
            linear_iterations: reports.iter().map(|r| r.linear_iterations).sum(),
            residual: reports.last().map_or(0.0, |r| r.residual),
            wall_time_s: reports.iter().map(|r| r.wall_time_s).sum(),
            positions_m,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::Material;
    use crate::validation::cases::symmetric_block_under_pressure;

    fn block() -> Scene {
        symmetric_block_under_pressure([4, 4, 4], 0.01, Material::LUNG, -1.0).unwrap()
    }

    fn linear_compliance_ml_per_pa(scene: &Scene) -> f64 {
        let v0 = scene.mesh.enclosed_volume_m3(&scene.mesh.rest_positions_m) * 1e6;
        v0 / Material::LUNG.bulk_modulus_pa()
    }

    #[test]
    fn volume_driver_meets_its_targets_along_a_breath() {
        let scene = block();
        let c = linear_compliance_ml_per_pa(&scene);
        let mut driver =
            BreathingDriver::new(&scene, -1.0, c, QuasiStaticSettings::default()).unwrap();
        let v0 = driver.rest_volume_ml();
        let mut pressures = Vec::new();
        for frac in [0.02, 0.05, 0.08, 0.05, 0.0, -0.03] {
            let target = frac * v0;
            let tol = 1e-3 * v0;
            let s = driver.solve_volume(target, tol).unwrap();
            assert!(
                (s.volume_change_ml - target).abs() <= tol,
                "{s:?} vs {target}"
            );
            assert!(s.solves >= 1 && s.solves <= 6, "{s:?}");
            pressures.push(s.pressure_pa);
        }
        // More air needs more suction; back at rest the pressure is zero again.
        assert!(pressures[0] < 0.0 && pressures[2] < pressures[1] && pressures[1] < pressures[0]);
        assert!(
            pressures[4].abs() < 0.05 * pressures[2].abs(),
            "{pressures:?}"
        );
        assert!(pressures[5] > 0.0);
    }

    #[test]
    fn compliance_driver_matches_small_strain_theory() {
        let scene = block();
        let c = linear_compliance_ml_per_pa(&scene);
        let mut driver =
            BreathingDriver::new(&scene, -1.0, c, QuasiStaticSettings::default()).unwrap();
        let s = driver.solve_pressure(-0.5).unwrap();
        let linear = 0.5 * c;
        assert!(
            (s.volume_change_ml - linear).abs() < 0.01 * linear,
            "{} vs {linear}",
            s.volume_change_ml
        );
    }

    #[test]
    fn bad_driver_inputs_are_refused() {
        let scene = block();
        assert!(BreathingDriver::new(&scene, 0.0, 1.0, QuasiStaticSettings::default()).is_err());
        assert!(BreathingDriver::new(&scene, -1.0, -1.0, QuasiStaticSettings::default()).is_err());
        let mut d =
            BreathingDriver::new(&scene, -1.0, 1.0, QuasiStaticSettings::default()).unwrap();
        assert!(d.solve_volume(f64::NAN, 1.0).is_err());
    }
}
