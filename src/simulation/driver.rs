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

use serde::Serialize;

use super::quasistatic::{QuasiStaticSettings, QuasiStaticSolver, SolveReport};
use super::scene::Scene;
use crate::math::V3;
use crate::{Error, Result};

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

/// Largest share of the volume change imposed motions may make (at 1 the pressure would
/// do nothing and the load factor would be undetermined).
pub const MAX_IMPOSED_SHARE: f64 = 0.9;

/// How the imposed motions were scaled to make their share of the volume change.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct ImposedMotionShare {
    /// Share of every volume change asked of the imposed motions.
    pub share: f64,
    /// dV/dλ of the surface pressure alone, imposed motions held at rest, mL (for a rigid
    /// wall, the driver's first estimate; 0, not measured, when the walls make the volume).
    pub pressure_slope_ml: f64,
    /// What the imposed motions add to dV/dλ per unit scale, mL: their sweep less the
    /// tissue's recoil elsewhere.
    pub motion_slope_ml: f64,
    /// Volume the imposed motions sweep at λ = 1 and scale 1, mL.
    pub sweep_ml_per_unit: f64,
    /// The solver's imposed-motion scale that makes the share.
    pub scale: f64,
}

/// The rest positions when the unloaded scene holds them (every constraint passes through
/// its node's rest position once imposed displacements are scaled to zero).
fn unloaded_rest(scene: &Scene) -> Option<Vec<V3>> {
    let x = scene.unloaded_positions();
    (x == scene.mesh.rest_positions_m).then_some(x)
}

/// Relative force residual of the two 5 mL probes that set the rib cage's share. They only
/// measure slopes: on the POPI lungs at 6 mm, 1e-3 instead of the breathing solves' 1e-5
/// moved the imposed-motion scale by 4e-5 of itself (the end-inhale share from 0.332550 to
/// 0.332562) and saved a Newton step per probe, 16 % of the solve.
const PROBE_TOLERANCE: f64 = 1e-3;

/// Most times a failed solve's load step is halved before the failure is reported.
pub const MAX_LOAD_BISECTIONS: usize = 4;

/// An equilibrium on the current load path: the predictor extrapolates from these.
#[derive(Debug, Clone)]
struct PathPoint {
    lambda: f64,
    dv_ml: f64,
    positions_m: Vec<V3>,
}

/// Solves a scene's equilibrium at prescribed pressures or volumes, frame after frame.
///
/// Predictor: the last (up to three) equilibria of the current load path give the next
/// solve's load factor (λ as a quadratic in volume) and its starting positions (linear
/// extrapolation in λ), so a Newton solve starts close to its answer and a volume target is
/// usually met by the first solve. Corrector failures halve the load step from the last
/// equilibrium ([`MAX_LOAD_BISECTIONS`] times) before being reported.
pub struct BreathingDriver<'s> {
    scene: &'s Scene,
    solver: QuasiStaticSolver<'s>,
    reference_pressure_pa: f64,
    rest_volume_m3: f64,
    /// Equilibria of the current load path, oldest first, at most three (warm start).
    path: Vec<PathPoint>,
    /// Estimated dV/dλ in mL, refined by every pair of solves.
    slope_ml: f64,
    /// Scratch for the predicted starting positions.
    predicted: Vec<V3>,
    /// Told of every equilibrium reached.
    progress: Option<SolveProgressSink>,
    equilibria: usize,
    /// Volume the imposed displacements sweep at λ = 1 and scale 1, mL (0: none move).
    sweep_ml_per_unit: f64,
    /// dx/dλ at rest for the current imposed-motion scale, when the probes of
    /// [`Self::share_volume_with_imposed_motion`] measured it: the first solve from rest then
    /// starts from the linear response instead of from rest.
    linear_response: Option<Vec<V3>>,
}

/// A flag another thread raises to stop a long computation at its next check.
pub type CancelFlag = std::sync::Arc<std::sync::atomic::AtomicBool>;

/// Where a breathing solve stands after each equilibrium it reaches.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SolveProgress {
    /// Equilibria reached so far by this driver (key volumes, bisection steps, frames).
    pub equilibria: usize,
    /// Lung volume change of the latest equilibrium from the scanned state, mL.
    pub volume_change_ml: f64,
}

/// Receives [`SolveProgress`] on the solving thread (a progress bar, a job record).
#[derive(Clone)]
pub struct SolveProgressSink(pub std::sync::Arc<dyn Fn(SolveProgress) + Send + Sync>);

impl std::fmt::Debug for SolveProgressSink {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str("SolveProgressSink")
    }
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
        let mut path = Vec::with_capacity(3);
        // The unloaded rest state is the path's first equilibrium when every constraint
        // passes through it: the first solve's end point then extrapolates the second's start.
        if let Some(rest) = unloaded_rest(scene) {
            path.push(PathPoint {
                lambda: 0.0,
                dv_ml: 0.0,
                positions_m: rest,
            });
        }
        Ok(BreathingDriver {
            scene,
            solver: QuasiStaticSolver::new(scene, settings)?,
            reference_pressure_pa,
            rest_volume_m3,
            path,
            // Inflation (ΔV > 0) needs suction: dV/dλ = −C·P_ref.
            slope_ml: -compliance_ml_per_pa * reference_pressure_pa,
            predicted: Vec::new(),
            progress: None,
            equilibria: 0,
            sweep_ml_per_unit: scene.imposed_sweep_ml(|_| true),
            linear_response: None,
        })
    }

    /// Whether some nodes slide on curved surfaces (level sets of a distance field) rather
    /// than on planes and lines.
    pub fn slides_on_curved_surfaces(&self) -> bool {
        !self.scene.constraints.fields.is_empty()
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
        let mut reports = Vec::new();
        let state = self.solve_factor(lambda, &mut reports)?;
        Ok(self.finish(state, &reports))
    }

    /// Equilibrium whose volume change from rest is `target_ml` within `tolerance_ml`.
    pub fn solve_volume(&mut self, target_ml: f64, tolerance_ml: f64) -> Result<DrivenState> {
        if !(target_ml.is_finite() && tolerance_ml.is_finite() && tolerance_ml > 0.0) {
            return Err(Error::Argument {
                what: "volume target".into(),
                reason: format!(
                    "{target_ml} mL with tolerance {tolerance_ml} mL (both must be finite, the \
                     tolerance positive)"
                ),
            });
        }
        let mut reports = Vec::new();
        let mut dv = self.path.last().map_or(0.0, |p| p.dv_ml);
        for _ in 0..MAX_VOLUME_SOLVES {
            if (dv - target_ml).abs() <= tolerance_ml && !reports.is_empty() {
                let state = self.path.last().map(|p| p.positions_m.clone()).unwrap();
                return Ok(self.finish(state, &reports));
            }
            let next = self.predict_lambda(target_ml);
            self.solve_factor(next, &mut reports)
                .map_err(|e| self.unreachable(target_ml, e))?;
            dv = self.path.last().map_or(0.0, |p| p.dv_ml);
        }
        if (dv - target_ml).abs() <= tolerance_ml {
            let state = self.path.last().map(|p| p.positions_m.clone()).unwrap();
            return Ok(self.finish(state, &reports));
        }
        Err(Error::NotConverged {
            iterations: MAX_VOLUME_SOLVES,
            residual: ((dv - target_ml) / target_ml.abs().max(tolerance_ml)).abs(),
            tolerance: tolerance_ml / target_ml.abs().max(tolerance_ml),
        })
    }

    /// Turns a solve failure on the way to `target_ml` into [`Error::VolumeUnreachable`], naming
    /// the most compressed element of the last equilibrium reached (where the mesh gives way).
    fn unreachable(&self, target_ml: f64, e: Error) -> Error {
        let (Error::NotConverged { .. } | Error::Diverged { .. }) = e else {
            return e;
        };
        let Some(last) = self.path.last() else {
            return e;
        };
        let Some((element, volume_ratio)) = self
            .scene
            .most_compressed_element(&last.positions_m, f64::INFINITY)
        else {
            return e;
        };
        let rest = &self.scene.mesh.rest_positions_m;
        let centre = self.scene.mesh.elements[element]
            .iter()
            .map(|&n| rest[n as usize])
            .sum::<V3>()
            * (1e3 / 8.0);
        let remedy = if target_ml < last.dv_ml && last.dv_ml <= 0.0 {
            "Below the scanned volume the lungs are compressed and the linear springs soften until \
             the mesh buckles where the rising diaphragm squeezes tissue against the walls or the \
             fixed hilum: a larger element size reaches further (the CIP lungs at 8 mm to about \
             -400 mL, at 12 mm to about -580 mL), or keep the trace above the reached volume."
        } else {
            "A larger element size, or a trace that stays within the reached volume, may help; \
             the element named is where the mesh is most strained."
        };
        Error::VolumeUnreachable(Box::new(crate::error::UnreachableVolume {
            target_ml,
            reached_ml: last.dv_ml,
            element,
            centre_lps_mm: [centre.x, centre.y, centre.z],
            volume_ratio,
            group: None,
            cause: e.to_string(),
            remedy: remedy.to_string(),
        }))
    }

    /// Makes `state` the warm start of the next solve, so a sequence can continue from any
    /// solved state (equilibria of the loaded lung are not always unique: a corner element
    /// can settle differently after a large load step than along a gradual inflation).
    /// The predictor forgets the path it was on.
    pub fn warm_start(&mut self, state: &DrivenState) {
        self.path.clear();
        self.path.push(PathPoint {
            lambda: state.pressure_pa / self.reference_pressure_pa,
            dv_ml: state.volume_change_ml,
            positions_m: state.positions_m.clone(),
        });
    }

    /// Volume change from rest of `positions`, mL.
    pub fn volume_change_ml(&self, positions: &[V3]) -> f64 {
        (self.scene.mesh.enclosed_volume_m3(positions) - self.rest_volume_m3) * 1e6
    }

    /// Load factor expected to give volume change `target_ml`: λ(V) through the path's last
    /// three equilibria (the P–V curve bends as the lung stiffens), kept within half a linear
    /// step of the secant prediction, whose slope carries over between frames.
    fn predict_lambda(&self, target_ml: f64) -> f64 {
        let (l1, v1) = self.path.last().map_or((0.0, 0.0), |p| (p.lambda, p.dv_ml));
        let linear = l1 + (target_ml - v1) / self.slope_ml;
        if self.path.len() < 3 {
            return linear;
        }
        let pts = &self.path[self.path.len() - 3..];
        let mut quadratic = 0.0;
        for (j, pj) in pts.iter().enumerate() {
            let mut w = 1.0;
            for (k, pk) in pts.iter().enumerate() {
                if k != j {
                    w *= (target_ml - pk.dv_ml) / (pj.dv_ml - pk.dv_ml);
                }
            }
            quadratic += w * pj.lambda;
        }
        if quadratic.is_finite() && (quadratic - linear).abs() <= 0.5 * (linear - l1).abs() {
            quadratic
        } else {
            linear
        }
    }

    /// Scales the scene's imposed displacements (a moving chest wall) so that they make
    /// `share` of every volume change and the surface pressure the rest: measures the lung's
    /// pressure slope dV/dλ with the imposed motions held at rest (one small solve from rest,
    /// in the linear range) and the volume they sweep per unit of load, and sets the solver's
    /// imposed-motion scale from the two. `share` 0 holds them at rest.
    pub fn share_volume_with_imposed_motion(&mut self, share: f64) -> Result<ImposedMotionShare> {
        if !(share.is_finite() && (0.0..MAX_IMPOSED_SHARE).contains(&share)) {
            return Err(Error::Argument {
                what: "share of the volume change from imposed motion".into(),
                reason: format!("{share} must lie in [0, {MAX_IMPOSED_SHARE})"),
            });
        }
        let sweep_ml = self.sweep_ml_per_unit;
        if self.scene.walls_make_volume.is_some() {
            return self.let_walls_make_volume(share);
        }
        if share == 0.0 {
            self.set_imposed_motion_scale(0.0);
            return Ok(ImposedMotionShare {
                share,
                pressure_slope_ml: self.slope_ml,
                motion_slope_ml: 0.0,
                sweep_ml_per_unit: sweep_ml,
                scale: 0.0,
            });
        }
        if sweep_ml == 0.0 {
            return Err(Error::InvalidModel(format!(
                "a share of {share} of the volume change from imposed motion was asked, but no \
                 constraint of this scene moves"
            )));
        }
        // Two small solves from rest, in the linear range, give V(λ, s) = λ·(a + s·b): a the
        // pressure's slope with the imposed motions held, b what they add per unit scale
        // (less than their geometric sweep S: the tissue they pull recoils elsewhere, the
        // base rising as the costal wall moves out). The share is the sweep over the total,
        // s·S / (a + s·b), so s = share·a / (S − share·b).
        let (pressure_slope_ml, held) = self.linear_slope_ml(0.0)?;
        let guess = share / (1.0 - share) * pressure_slope_ml / sweep_ml;
        let (with_motion_ml, moved) = self.linear_slope_ml(guess)?;
        let motion_slope_ml = (with_motion_ml - pressure_slope_ml) / guess;
        let scale = share * pressure_slope_ml / (sweep_ml - share * motion_slope_ml);
        if !(scale.is_finite() && scale > 0.0) {
            return Err(Error::InvalidModel(format!(
                "imposed motion cannot make {share} of the volume change: the lungs change by \
                 {pressure_slope_ml:.3} mL per unit load, the moving constraints sweep \
                 {sweep_ml:.3} mL per unit and add {motion_slope_ml:.3} mL"
            )));
        }
        self.set_imposed_motion_scale(scale);
        self.slope_ml = pressure_slope_ml + scale * motion_slope_ml;
        // Both probes are linear in λ and in the scale, so is their response: the first
        // solve from rest starts from it (one Newton step fewer than from rest).
        let t = scale / guess;
        self.linear_response = Some(
            held.iter()
                .zip(&moved)
                .map(|(h, m)| h + (m - h) * t)
                .collect(),
        );
        Ok(ImposedMotionShare {
            share,
            pressure_slope_ml,
            motion_slope_ml,
            sweep_ml_per_unit: sweep_ml,
            scale,
        })
    }

    /// The walls enclose the lung and make every volume change (their split, `share` from
    /// the rib cage, is in the scene's constraints): scales them to sweep the driver's
    /// compliance volume at λ = 1, so the pressure reported stays ΔV / C, and the pressure
    /// only adds what sliding along the walls changes.
    fn let_walls_make_volume(&mut self, share: f64) -> Result<ImposedMotionShare> {
        let sweep_ml = self.sweep_ml_per_unit;
        if !(sweep_ml.is_finite() && sweep_ml > 0.0) {
            return Err(Error::InvalidModel(format!(
                "the scene's walls make the volume, but they sweep {sweep_ml} mL per unit of \
                 motion: they must enlarge the lungs"
            )));
        }
        let scale = self.slope_ml / sweep_ml;
        self.set_imposed_motion_scale(scale);
        Ok(ImposedMotionShare {
            share,
            pressure_slope_ml: 0.0,
            motion_slope_ml: sweep_ml,
            sweep_ml_per_unit: sweep_ml,
            scale,
        })
    }

    /// dV/dλ from rest, in the linear range, with the imposed motions at `scale` (one small
    /// solve; the load path returns to rest): how much volume the pressure and the moving
    /// constraints make per unit of load, for callers that split a breath between walls.
    pub fn linear_volume_slope_ml(&mut self, scale: f64) -> Result<f64> {
        let kept = self.solver.imposed_motion_scale();
        let slope = self.linear_slope_ml(scale).map(|(slope, _)| slope);
        self.set_imposed_motion_scale(kept);
        slope
    }

    /// dV/dλ from rest with the imposed motions at `scale`, by one solve of about 5 mL (linear,
    /// yet far above the solver's round-off), and dx/dλ there; leaves the path at rest.
    fn linear_slope_ml(&mut self, scale: f64) -> Result<(f64, Vec<V3>)> {
        self.set_imposed_motion_scale(scale);
        let probe = 5.0 / self.slope_ml.abs();
        let mut reports = Vec::new();
        let kept = self.solver.tolerance();
        self.solver.set_tolerance(kept.max(PROBE_TOLERANCE));
        let x = self.solve_factor(probe, &mut reports);
        self.solver.set_tolerance(kept);
        let x = x?;
        let slope = self.volume_change_ml(&x) / probe;
        let rest = &self.scene.mesh.rest_positions_m;
        let response = x.iter().zip(rest).map(|(x, r)| (x - r) / probe).collect();
        self.set_imposed_motion_scale(scale);
        Ok((slope, response))
    }

    /// Sets the solver's imposed-motion scale; the load path solved so far is forgotten (it
    /// belonged to the other scale) back to the unloaded rest state.
    fn set_imposed_motion_scale(&mut self, scale: f64) {
        self.solver.set_imposed_motion_scale(scale);
        self.path.clear();
        self.linear_response = None;
        if let Some(rest) = unloaded_rest(self.scene) {
            self.path.push(PathPoint {
                lambda: 0.0,
                dv_ml: 0.0,
                positions_m: rest,
            });
        }
    }

    /// Volume swept by the imposed motions at `lambda`, mL (first order).
    pub fn imposed_sweep_ml(&self, lambda: f64) -> f64 {
        lambda * self.solver.imposed_motion_scale() * self.sweep_ml_per_unit
    }

    /// Stops the solve under way and every later one with [`Error::Cancelled`] once `flag` is
    /// raised (the solver holds the flag and checks it inside its iterations).
    pub fn set_cancel(&mut self, flag: CancelFlag) {
        self.solver.set_cancel(flag);
    }

    /// Tells `sink` of every equilibrium reached from now on.
    pub fn set_progress(&mut self, sink: SolveProgressSink) {
        self.progress = Some(sink);
    }

    /// Solves at load factor `lambda` from the predicted positions, halving the step from the
    /// last equilibrium when the corrector fails; every equilibrium reached joins the path.
    fn solve_factor(&mut self, lambda: f64, reports: &mut Vec<SolveReport>) -> Result<Vec<V3>> {
        if self.solver.cancel_raised() {
            return Err(Error::Cancelled(
                "stopped between equilibrium solves".into(),
            ));
        }
        // Unloaded, the rest state is the equilibrium when every constraint passes through
        // it; solving would only chase round-off below the residual's floor.
        if lambda == 0.0 {
            if let Some(x) = unloaded_rest(self.scene) {
                self.push_equilibrium(0.0, x.clone());
                reports.push(SolveReport::default());
                return Ok(x);
            }
        }
        let mut pending = vec![lambda];
        while let Some(&target) = pending.last() {
            let start = self.predict_positions(target);
            let last_resort = pending.len() > MAX_LOAD_BISECTIONS;
            let initial = start.then_some(self.predicted.as_slice());
            match self
                .solver
                .solve_load_factor_from(initial, target, last_resort)
            {
                Ok((x, report)) => {
                    self.scene.check_finite(&x, report.newton_iterations)?;
                    reports.push(report);
                    pending.pop();
                    if pending.is_empty() {
                        self.push_equilibrium(target, x.clone());
                        return Ok(x);
                    }
                    self.push_equilibrium(target, x);
                }
                Err(e @ (Error::NotConverged { .. } | Error::Diverged { .. })) => {
                    if last_resort {
                        return Err(e);
                    }
                    let from = self.path.last().map_or(0.0, |p| p.lambda);
                    tracing::debug!(from, target, "halving the load step: {e}");
                    pending.push(0.5 * (from + target));
                }
                Err(e) => return Err(e),
            }
        }
        unreachable!("the loop returns once the last pending load factor is solved")
    }

    /// Writes the predicted starting positions for load factor `lambda` into `self.predicted`;
    /// false when no equilibrium is known (start from rest).
    fn predict_positions(&mut self, lambda: f64) -> bool {
        let Some(p1) = self.path.last() else {
            return false;
        };
        self.predicted.clear();
        self.predicted.extend_from_slice(&p1.positions_m);
        if let (Some(du), [rest]) = (&self.linear_response, self.path.as_slice()) {
            if rest.lambda == 0.0 {
                for (x, du) in self.predicted.iter_mut().zip(du) {
                    *x += du * lambda;
                }
                return true;
            }
        }
        if self.path.len() == 3 {
            // Lagrange extrapolation in λ through the last three equilibria (the CIP 8 mm
            // cycle: 131 Krylov iterations against 136 for the linear one).
            let pts = &self.path[..];
            let mut w = [1.0; 3];
            for (j, wj) in w.iter_mut().enumerate() {
                for (k, pk) in pts.iter().enumerate() {
                    if k != j {
                        *wj *= (lambda - pk.lambda) / (pts[j].lambda - pk.lambda);
                    }
                }
            }
            // Far extrapolation or two nearly equal load factors (secant iterates) make the
            // weights large and the prediction worse than the linear one.
            if w.iter().all(|v| v.is_finite() && v.abs() <= 8.0) {
                for (i, x) in self.predicted.iter_mut().enumerate() {
                    *x = pts[0].positions_m[i] * w[0]
                        + pts[1].positions_m[i] * w[1]
                        + pts[2].positions_m[i] * w[2];
                }
                return true;
            }
        }
        if let [.., p0, p1] = self.path.as_slice() {
            let dl = p1.lambda - p0.lambda;
            if dl.abs() > 1e-12 * p1.lambda.abs().max(1e-300) {
                let t = (lambda - p1.lambda) / dl;
                for (x, x0) in self.predicted.iter_mut().zip(&p0.positions_m) {
                    *x += (*x - x0) * t;
                }
            }
        }
        true
    }

    /// Appends an equilibrium to the path and refines the slope dV/dλ from the last two.
    fn push_equilibrium(&mut self, lambda: f64, positions_m: Vec<V3>) {
        let dv_ml = self.volume_change_ml(&positions_m);
        self.equilibria += 1;
        if let Some(sink) = &self.progress {
            (sink.0)(SolveProgress {
                equilibria: self.equilibria,
                volume_change_ml: dv_ml,
            });
        }
        if let Some(p) = self.path.last() {
            // The volume grows with suction, so a slope of the wrong sign means the two solves
            // were too close to tell: keep the previous estimate.
            if (lambda - p.lambda).abs() > 1e-12 {
                let s = (dv_ml - p.dv_ml) / (lambda - p.lambda);
                if s.is_finite() && s * self.slope_ml > 0.0 {
                    self.slope_ml = s;
                }
            }
            // Two equilibria at (nearly) one volume make the quadratic meaningless.
            if (dv_ml - p.dv_ml).abs() < 1e-9 {
                self.path.pop();
            }
        }
        if self.path.len() == 3 {
            self.path.remove(0);
        }
        self.path.push(PathPoint {
            lambda,
            dv_ml,
            positions_m,
        });
    }

    fn finish(&self, positions_m: Vec<V3>, reports: &[SolveReport]) -> DrivenState {
        let lambda = self.path.last().map_or(0.0, |p| p.lambda);
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
    use crate::simulation::cases::symmetric_block_under_pressure;

    fn block() -> Scene {
        symmetric_block_under_pressure([4, 4, 4], 0.01, Material::LUNG, -1.0).unwrap()
    }

    fn linear_compliance_ml_per_pa(scene: &Scene) -> f64 {
        let v0 = scene.mesh.enclosed_volume_m3(&scene.mesh.rest_positions_m) * 1e6;
        v0 / Material::LUNG.bulk_modulus_pa()
    }

    #[test]
    fn the_first_solve_after_the_share_probes_starts_from_their_linear_response() {
        // The block's free +x face moves outward as a wall would, 1 mm per unit load.
        let block = block();
        let xmax = block
            .mesh
            .rest_positions_m
            .iter()
            .map(|p| p.x)
            .fold(f64::MIN, f64::max);
        let mut constraints = block.constraints.clone();
        for (n, p) in block.mesh.rest_positions_m.iter().enumerate() {
            if p.x == xmax && constraints.get(n as u32).is_none() {
                let wall = crate::model::NodeConstraint::Plane {
                    point_m: p + V3::x() * 1e-3,
                    normal: V3::x(),
                };
                constraints.set(n as u32, wall).unwrap();
            }
        }
        let scene = Scene::new(block.mesh.clone(), constraints, block.loads.clone()).unwrap();
        let c = linear_compliance_ml_per_pa(&scene);
        let v0 = scene.mesh.enclosed_volume_m3(&scene.mesh.rest_positions_m) * 1e6;
        let first_key = |from_response: bool| {
            let mut driver =
                BreathingDriver::new(&scene, -1.0, c, QuasiStaticSettings::default()).unwrap();
            driver.share_volume_with_imposed_motion(0.3).unwrap();
            assert!(driver.linear_response.is_some());
            if !from_response {
                driver.linear_response = None;
            }
            driver.solve_volume(0.06 * v0, 1e-3 * v0).unwrap()
        };
        let (predicted, from_rest) = (first_key(true), first_key(false));
        assert!(
            predicted.newton_iterations < from_rest.newton_iterations,
            "{predicted:?} against {from_rest:?}"
        );
        // The same equilibrium, within the solver's tolerance.
        let largest = |x: &[V3]| {
            x.iter()
                .zip(&scene.mesh.rest_positions_m)
                .map(|(x, r)| (x - r).norm())
                .fold(0.0, f64::max)
        };
        let apart = largest(&predicted.positions_m)
            .max(largest(&from_rest.positions_m))
            .max(1e-12);
        let diff = predicted
            .positions_m
            .iter()
            .zip(&from_rest.positions_m)
            .map(|(a, b)| (a - b).norm())
            .fold(0.0, f64::max);
        assert!(diff <= 1e-4 * apart, "{diff:e} m of {apart:e} m");
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
    fn a_volume_the_solves_cannot_reach_is_named_with_the_most_compressed_element() {
        let scene = block();
        let c = linear_compliance_ml_per_pa(&scene);
        // One Newton iteration and no fallback: every solve beyond the first small step fails.
        let settings = QuasiStaticSettings {
            max_newton_iterations: 1,
            relaxation_max_steps: 0,
            ..QuasiStaticSettings::default()
        };
        let mut driver = BreathingDriver::new(&scene, -1.0, c, settings).unwrap();
        let v0 = driver.rest_volume_ml();
        let target = -0.3 * v0;
        match driver.solve_volume(target, 1e-3 * v0) {
            Err(Error::VolumeUnreachable(u)) => {
                let crate::error::UnreachableVolume {
                    target_ml,
                    reached_ml,
                    element,
                    centre_lps_mm,
                    volume_ratio,
                    group,
                    cause,
                    remedy,
                } = *u;
                assert_eq!(target_ml, target);
                assert!(reached_ml <= 0.0 && reached_ml > target, "{reached_ml}");
                assert!(element < scene.mesh.element_count());
                assert!(volume_ratio > 0.0 && volume_ratio <= 1.0, "{volume_ratio}");
                assert!(centre_lps_mm.iter().all(|c| c.is_finite()));
                assert!(group.is_none(), "the solver does not know the anatomy");
                assert!(cause.contains("did not converge"), "{cause}");
                assert!(remedy.contains("larger element size"), "{remedy}");
            }
            other => panic!("expected VolumeUnreachable, got {other:?}"),
        }
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
    fn a_load_step_newton_cannot_take_is_halved_until_it_can() {
        let scene = block();
        let c = linear_compliance_ml_per_pa(&scene);
        let v0 = scene.mesh.enclosed_volume_m3(&scene.mesh.rest_positions_m) * 1e6;
        let pressure = -0.3 * v0 / c;
        let short = QuasiStaticSettings {
            max_newton_iterations: 2,
            relaxation_max_steps: 0,
            ..QuasiStaticSettings::default()
        };
        // In one step the load is too large for two Newton iterations...
        let mut solver = QuasiStaticSolver::new(&scene, short.clone()).unwrap();
        assert!(solver
            .solve_with_load_factor(None, pressure / -1.0)
            .is_err());
        // ...in halved steps from the last equilibrium it is not, and it lands where a
        // patient solver does.
        let mut driver = BreathingDriver::new(&scene, -1.0, c, short).unwrap();
        let s = driver.solve_pressure(pressure).unwrap();
        assert!(s.solves >= 2, "{s:?}");
        assert!(s.residual <= 1e-6, "{s:?}");
        let mut patient =
            BreathingDriver::new(&scene, -1.0, c, QuasiStaticSettings::default()).unwrap();
        let p = patient.solve_pressure(pressure).unwrap();
        assert_eq!(p.solves, 1, "{p:?}");
        let diff = s
            .positions_m
            .iter()
            .zip(&p.positions_m)
            .map(|(a, b)| (a - b).norm())
            .fold(0.0, f64::max);
        let moved = p
            .positions_m
            .iter()
            .zip(&scene.mesh.rest_positions_m)
            .map(|(a, b)| (a - b).norm())
            .fold(0.0, f64::max);
        assert!(diff < 1e-4 * moved, "{diff} m apart, {moved} m moved");
    }

    #[test]
    fn predicted_keys_along_an_inflation_need_one_solve_each() {
        let scene = block();
        let c = linear_compliance_ml_per_pa(&scene);
        let v0 = scene.mesh.enclosed_volume_m3(&scene.mesh.rest_positions_m) * 1e6;
        let mut driver =
            BreathingDriver::new(&scene, -1.0, c, QuasiStaticSettings::default()).unwrap();
        let tol = 1e-4 * v0;
        let mut solves = Vec::new();
        for k in 1..=8 {
            let target = 0.02 * k as f64 * v0;
            let s = driver.solve_volume(target, tol).unwrap();
            assert!((s.volume_change_ml - target).abs() <= tol, "{s:?}");
            solves.push(s.solves);
        }
        // The first steps learn the P–V slope and curvature; after them the quadratic
        // prediction of the load factor meets each volume in one solve.
        assert!(solves[3..].iter().all(|&n| n == 1), "{solves:?}");
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
