//! Dynamic breathing (optional mode): the lung's equations of motion integrated explicitly
//! under the pleural pressure of the bellows law P = V/C + R·dV/dt + I·d²V/dt² applied to
//! the trace's volume, with Voigt dampers on the springs, for users who want inhale/exhale
//! hysteresis.
//!
//! P is the driving (transpulmonary) pressure, positive to inflate; the surface load is −P,
//! applied by scaling the scene's reference pressure. The whole bellows pressure loads the
//! lung surface, as in the thesis: the resistive term R·dV/dt makes the simulated lung lead
//! the trace on inhalation and lag it on exhalation (by about C·R·dV/dt), and the dampers add
//! a tissue-viscous loop; both are reported per frame beside the trace's volume.
//!
//! V' and V'' come from central differences over ±`derivative_half_window_s`: a trace is
//! piecewise linear in time, so its own derivatives would be steps and impulses.
//!
//! C defaults to the scene's secant compliance at the trace's extreme volume (one
//! quasi-static solve), so with R = I = 0 and a slow trace the frames reproduce the
//! quasi-static volume driver at that volume.

use std::time::Instant;

use serde::Serialize;

use super::{displacement_extent_mm, elastic_compliance_ml_per_pa, REFERENCE_PRESSURE_PA};
use crate::breathing::BreathingTrace;
use crate::math::V3;
use crate::simulation::explicit::BlowUpGuard;
use crate::simulation::{
    BreathingDriver, ImposedMotionShare, QuasiStaticSettings, Scene, TimeStepBound,
};
use crate::{Error, Result};

/// Settings of a dynamic breathing run.
#[derive(Debug, Clone, Serialize)]
pub struct DynamicSettings {
    /// Lung compliance C, mL/Pa; `None`: the scene's secant compliance at the trace's
    /// extreme volume.
    pub compliance_ml_per_pa: Option<f64>,
    /// Airway resistance R, Pa·s/mL (physiological ≈ 0.2 Pa·s/mL = 2 cmH₂O·s/L).
    pub resistance_pa_s_per_ml: f64,
    /// Inertance I, Pa·s²/mL (physiological ≈ 0.001 Pa·s²/mL).
    pub inertance_pa_s2_per_ml: f64,
    /// Voigt damper of every spring as a fraction of its critical damping.
    pub voigt_damping_ratio: f64,
    /// Voigt damper of the springs of elements on the lung's surface, if they differ from
    /// the interior's (Boux de Casson's heterogeneous viscosity: a lightly damped skin over a
    /// viscous parenchyma).
    pub surface_damping_ratio: Option<f64>,
    /// The pressure the scene's surface load is built with (λ = 1), Pa.
    pub reference_pressure_pa: f64,
    /// Fraction of the critical explicit time step used, in (0, 1].
    pub time_step_safety: f64,
    /// Half width of the central differences giving V' and V'', s.
    pub derivative_half_window_s: f64,
    /// Steps between blow-up checks.
    pub check_every: usize,
    /// Give up beyond this many steps.
    pub max_steps: usize,
    /// Share of every volume change the moving chest wall makes (0: a rigid wall).
    pub rib_cage_share: f64,
    /// Quasi-static solver for the compliance and the initial equilibrium.
    pub solver: QuasiStaticSettings,
}

impl Default for DynamicSettings {
    fn default() -> Self {
        DynamicSettings {
            compliance_ml_per_pa: None,
            resistance_pa_s_per_ml: 0.0,
            inertance_pa_s2_per_ml: 0.0,
            voigt_damping_ratio: 0.1,
            surface_damping_ratio: None,
            reference_pressure_pa: REFERENCE_PRESSURE_PA,
            time_step_safety: 0.9,
            derivative_half_window_s: 0.05,
            check_every: 50,
            max_steps: 10_000_000,
            rib_cage_share: 0.0,
            solver: QuasiStaticSettings::default(),
        }
    }
}

impl DynamicSettings {
    /// Refuses non-physical or meaningless values.
    pub fn validate(&self) -> Result<()> {
        let bad = |m: String| Err(Error::settings("dynamic breathing settings", m));
        if let Some(c) = self.compliance_ml_per_pa {
            if !(c.is_finite() && c > 0.0) {
                return bad(format!("compliance {c} mL/Pa must be positive"));
            }
        }
        for (name, v) in [
            ("resistance (Pa·s/mL)", self.resistance_pa_s_per_ml),
            ("inertance (Pa·s²/mL)", self.inertance_pa_s2_per_ml),
            ("Voigt damping ratio", self.voigt_damping_ratio),
            (
                "surface damping ratio",
                self.surface_damping_ratio.unwrap_or(0.0),
            ),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                return bad(format!("{name} {v} must be finite and non-negative"));
            }
        }
        let p = self.reference_pressure_pa;
        if !(p.is_finite() && p != 0.0) {
            return bad(format!(
                "reference pressure {p} Pa must be finite and non-zero"
            ));
        }
        let s = self.time_step_safety;
        if !(s.is_finite() && s > 0.0 && s <= 1.0) {
            return bad(format!("time step safety {s} must be in (0, 1]"));
        }
        let w = self.derivative_half_window_s;
        if !(w.is_finite() && w > 0.0) {
            return bad(format!("derivative half window {w} s must be positive"));
        }
        if self.check_every == 0 || self.max_steps == 0 {
            return bad("check_every and max_steps must be positive".into());
        }
        Ok(())
    }
}

/// The bellows law's terms at one instant.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct BellowsState {
    /// Trace volume change from the scan, mL.
    pub volume_ml: f64,
    /// dV/dt, mL/s (positive on inhalation).
    pub flow_ml_per_s: f64,
    /// d²V/dt², mL/s².
    pub flow_rate_ml_per_s2: f64,
    /// P = V/C + R·V' + I·V'', Pa (positive inflates; the surface load is −P).
    pub pressure_pa: f64,
}

/// The bellows law on `trace` at `t_s` (derivatives over ±`half_window_s`).
pub fn bellows_state(
    trace: &BreathingTrace,
    t_s: f64,
    compliance_ml_per_pa: f64,
    resistance_pa_s_per_ml: f64,
    inertance_pa_s2_per_ml: f64,
    half_window_s: f64,
) -> BellowsState {
    let d = half_window_s;
    let (before, v, after) = (
        trace.volume_at(t_s - d),
        trace.volume_at(t_s),
        trace.volume_at(t_s + d),
    );
    let flow = (after - before) / (2.0 * d);
    let flow_rate = (after - 2.0 * v + before) / (d * d);
    BellowsState {
        volume_ml: v,
        flow_ml_per_s: flow,
        flow_rate_ml_per_s2: flow_rate,
        pressure_pa: v / compliance_ml_per_pa
            + resistance_pa_s_per_ml * flow
            + inertance_pa_s2_per_ml * flow_rate,
    }
}

/// One output instant of a dynamic run.
#[derive(Debug, Clone, Serialize)]
pub struct DynamicFrame {
    /// Frame index (0-based, in output order).
    pub index: usize,
    /// Time in the trace, s.
    pub time_s: f64,
    /// The bellows law there (trace volume, flow, driving pressure).
    pub bellows: BellowsState,
    /// Surface pressure applied, Pa (−P; negative inflates).
    pub surface_pressure_pa: f64,
    /// Volume the moving chest wall swept, mL (0 with a rigid wall).
    pub chest_wall_volume_ml: f64,
    /// Volume change of the simulated lung surface, mL.
    pub simulated_volume_ml: f64,
    /// Largest node displacement, mm.
    pub max_displacement_mm: f64,
    /// Mean node displacement, mm.
    pub mean_displacement_mm: f64,
    /// Kinetic energy of the lung, J.
    pub kinetic_energy_j: f64,
    /// Time steps taken since the start of the run.
    pub steps: usize,
}

/// What a dynamic run did.
#[derive(Debug, Clone, Serialize)]
pub struct DynamicReport {
    /// Settings used.
    pub settings: DynamicSettings,
    /// Compliance used, mL/Pa.
    pub compliance_ml_per_pa: f64,
    /// Whether C was measured on the scene (else given).
    pub compliance_calibrated: bool,
    /// How the moving chest wall was scaled to its share of the volume changes.
    pub chest_wall: ImposedMotionShare,
    /// Volume enclosed by the mesh surface at rest, mL.
    pub rest_volume_ml: f64,
    /// Time step bound of the damped scene (the step used is its `step_s`).
    pub time_step: TimeStepBound,
    /// Start of the integration (the trace's first sample), s.
    pub start_time_s: f64,
    /// Bellows pressure of the initial quasi-static equilibrium, Pa.
    pub initial_pressure_pa: f64,
    /// Steps taken.
    pub steps: usize,
    /// Largest |simulated − trace| volume over the frames, mL.
    pub max_volume_difference_ml: f64,
    /// The frames.
    pub frames: Vec<DynamicFrame>,
    /// Wall time of the calibration and initial equilibrium, s.
    pub setup_wall_time_s: f64,
    /// Wall time of the integration, s.
    pub integration_wall_time_s: f64,
}

/// Integrates `scene` (whose surface pressures add up to `settings.reference_pressure_pa`)
/// through `trace` under the bellows law; `on_frame` receives each requested instant's frame
/// and node positions (metres) in time order. `output_times_s` must be ascending and lie
/// within the trace.
pub fn run_dynamic(
    scene: &Scene,
    trace: &BreathingTrace,
    settings: &DynamicSettings,
    output_times_s: &[f64],
    on_frame: &mut dyn FnMut(&DynamicFrame, &[V3]) -> Result<()>,
) -> Result<DynamicReport> {
    let setup_start = Instant::now();
    settings.validate()?;
    trace.validate()?;
    let t_start = trace.time_s[0];
    let t_end = trace.time_s[trace.time_s.len() - 1];
    check_output_times(output_times_s, t_start, t_end)?;

    if scene.walls_make_volume.is_some() {
        return Err(Error::settings(
            "dynamic settings",
            "the scene's walls make the volume (a sliding diaphragm), but the dynamic bellows \
             drive the lungs with pressure: use the quasi-static motion, or a piston diaphragm",
        ));
    }
    let damped = damped_scene(
        scene,
        settings.voigt_damping_ratio,
        settings.surface_damping_ratio,
    )?;
    let rest = &damped.mesh.rest_positions_m;
    let rest_volume_m3 = damped.mesh.enclosed_volume_m3(rest);
    let p_ref = settings.reference_pressure_pa;

    // The free-solid compliance overestimates a constrained lung's: a cautious first step.
    let seed = damped.mesh.typical_material().map_or(1.0, |m| {
        elastic_compliance_ml_per_pa(rest_volume_m3 * 1e6, &m)
    });
    let mut driver = BreathingDriver::new(&damped, p_ref, seed, settings.solver.clone())?;
    super::chest_wall::check_rib_cage_share(settings.rib_cage_share)?;
    let chest_wall = driver.share_volume_with_imposed_motion(settings.rib_cage_share)?;
    let (compliance, calibrated) = bellows_compliance(&mut driver, trace, settings)?;
    let bellows = |t: f64| {
        bellows_state(
            trace,
            t,
            compliance,
            settings.resistance_pa_s_per_ml,
            settings.inertance_pa_s2_per_ml,
            settings.derivative_half_window_s,
        )
    };

    let initial = bellows(t_start);
    let x = initial_equilibrium(&damped, &mut driver, initial.pressure_pa)?;
    drop(driver);
    let setup_wall_time_s = setup_start.elapsed().as_secs_f64();

    let time_step = explicit_time_step(&damped, settings.time_step_safety)?;
    let h_max = time_step.step_s;

    let start = Instant::now();
    let load_factor = |t: f64| -bellows(t).pressure_pa / p_ref;
    let mut state = ExplicitState::start(&damped, x, t_start, load_factor(t_start));
    state.wall_scale = chest_wall.scale;
    let mut frames = Vec::with_capacity(output_times_s.len());
    let mut max_volume_difference: f64 = 0.0;
    for (index, &t_out) in output_times_s.iter().enumerate() {
        state.advance_to(t_out, h_max, &load_factor, settings)?;
        let mut frame = state.frame(index, t_out, bellows(t_out), rest_volume_m3)?;
        frame.chest_wall_volume_ml =
            load_factor(t_out) * chest_wall.scale * chest_wall.sweep_ml_per_unit;
        max_volume_difference =
            max_volume_difference.max((frame.simulated_volume_ml - frame.bellows.volume_ml).abs());
        on_frame(&frame, &state.x)?;
        frames.push(frame);
    }
    Ok(DynamicReport {
        settings: settings.clone(),
        compliance_ml_per_pa: compliance,
        compliance_calibrated: calibrated,
        chest_wall,
        rest_volume_ml: rest_volume_m3 * 1e6,
        time_step,
        start_time_s: t_start,
        initial_pressure_pa: initial.pressure_pa,
        steps: state.steps,
        max_volume_difference_ml: max_volume_difference,
        frames,
        setup_wall_time_s,
        integration_wall_time_s: start.elapsed().as_secs_f64(),
    })
}

/// `scene` with a Voigt damper of `damping_ratio` on every spring, or of `surface_ratio` on
/// those of elements with a face on the lung's surface. The dampers live in the element
/// classes the force kernels are packed from: one rebuilt scene for the whole run, with a
/// surface copy of every class when the two ratios differ.
fn damped_scene(scene: &Scene, damping_ratio: f64, surface_ratio: Option<f64>) -> Result<Scene> {
    let mut mesh = scene.mesh.clone();
    let interior: Vec<_> = mesh
        .classes
        .iter()
        .map(|c| c.clone().with_damping_ratio(damping_ratio))
        .collect();
    match surface_ratio {
        Some(surface) if surface != damping_ratio => {
            let n = mesh.classes.len() as u32;
            let skin: Vec<_> = mesh
                .classes
                .iter()
                .map(|c| c.clone().with_damping_ratio(surface))
                .collect();
            for (e, on_surface) in surface_elements(&mesh).into_iter().enumerate() {
                if on_surface {
                    mesh.element_class[e] += n;
                }
            }
            mesh.classes = interior.into_iter().chain(skin).collect();
        }
        _ => mesh.classes = interior,
    }
    let mut damped = Scene::new(mesh, scene.constraints.clone(), scene.loads.clone())?
        .with_contact(scene.contact().clone())?;
    damped.one_sided = scene.one_sided.clone();
    Ok(damped)
}

/// Whether each element has a face on the mesh's external surface.
fn surface_elements(mesh: &crate::model::HexMesh) -> Vec<bool> {
    use crate::model::mesh::HEX_FACES;
    let key = |f: [u32; 4]| {
        let mut k = f;
        k.sort_unstable();
        k
    };
    let external: std::collections::HashSet<[u32; 4]> =
        mesh.external_faces.iter().map(|&f| key(f)).collect();
    mesh.elements
        .iter()
        .map(|corners| {
            HEX_FACES
                .iter()
                .any(|face| external.contains(&key(face.map(|c| corners[c]))))
        })
        .collect()
}

/// The bellows law's compliance, mL/Pa, and whether it was calibrated: the given one, else
/// the scene's secant compliance at the trace's extreme volume (one quasi-static solve).
fn bellows_compliance(
    driver: &mut BreathingDriver,
    trace: &BreathingTrace,
    settings: &DynamicSettings,
) -> Result<(f64, bool)> {
    let (compliance, calibrated) = match settings.compliance_ml_per_pa {
        Some(c) => (c, false),
        None => {
            let extreme = trace.volume_change_ml.iter().copied().fold(0.0f64, |m, v| {
                if v.abs() > m.abs() {
                    v
                } else {
                    m
                }
            });
            if extreme.abs() < 1e-9 {
                return Err(Error::settings(
                    "dynamic breathing settings",
                    "the trace never leaves the scanned volume, so the \
                     compliance cannot be calibrated; give compliance_ml_per_pa",
                ));
            }
            let s = driver
                .solve_volume(extreme, 1e-3 * extreme.abs())
                .map_err(|e| {
                    Error::InvalidModel(format!(
                        "calibrating the compliance at {extreme:.1} mL: {e}"
                    ))
                })?;
            // Surface pressure −P inflates by ΔV: C = ΔV / P.
            (extreme / -s.pressure_pa, true)
        }
    };
    if !(compliance.is_finite() && compliance > 0.0) {
        return Err(Error::InvalidModel(format!(
            "dynamic breathing: compliance {compliance} mL/Pa is not positive"
        )));
    }
    Ok((compliance, calibrated))
}

/// Node positions of the quasi-static equilibrium under the bellows pressure at the start
/// (the rest state when that pressure is zero).
fn initial_equilibrium(
    damped: &Scene,
    driver: &mut BreathingDriver,
    initial_pressure_pa: f64,
) -> Result<Vec<V3>> {
    Ok(if initial_pressure_pa == 0.0 {
        // Unloaded, a moving wall is at rest too.
        damped.unloaded_positions()
    } else {
        driver
            .solve_pressure(-initial_pressure_pa)
            .map_err(|e| {
                Error::InvalidModel(format!(
                    "initial equilibrium at {initial_pressure_pa:.2} Pa: {e}"
                ))
            })?
            .positions_m
    })
}

/// The stable explicit time step of the damped scene; refuses one that is not positive.
fn explicit_time_step(damped: &Scene, safety: f64) -> Result<TimeStepBound> {
    let time_step = TimeStepBound::new(damped, safety);
    let h_max = time_step.step_s;
    if !(h_max.is_finite() && h_max > 0.0) {
        return Err(Error::InvalidModel(format!(
            "dynamic breathing: time step {h_max} s is not positive"
        )));
    }
    Ok(time_step)
}

/// The explicit integration's state: node positions, velocities and accelerations at `t_s`,
/// with the scratch buffers of the force evaluation.
struct ExplicitState<'s> {
    scene: &'s Scene,
    x: Vec<V3>,
    v: Vec<V3>,
    a: Vec<V3>,
    force: Vec<V3>,
    external: Vec<V3>,
    inv_mass: Vec<f64>,
    guard: BlowUpGuard,
    /// Imposed displacements (a moving chest wall) follow the load factor times this.
    wall_scale: f64,
    t_s: f64,
    /// Time steps taken since the start of the run.
    steps: usize,
}

impl<'s> ExplicitState<'s> {
    /// At rest in positions `x` at `t_s`, accelerated by the loads scaled by `load_factor`.
    fn start(scene: &'s Scene, x: Vec<V3>, t_s: f64, load_factor: f64) -> Self {
        let n = scene.node_count();
        let mut state = ExplicitState {
            scene,
            x,
            v: vec![V3::zeros(); n],
            a: vec![V3::zeros(); n],
            force: vec![V3::zeros(); n],
            external: vec![V3::zeros(); n],
            inv_mass: scene.mesh.node_mass_kg.iter().map(|m| 1.0 / m).collect(),
            guard: BlowUpGuard::new(&scene.mesh.rest_positions_m),
            wall_scale: 1.0,
            t_s,
            steps: 0,
        };
        state.update_accelerations(load_factor);
        state
    }

    /// Velocity-Verlet steps of at most `h_max` up to `t_out`, the loads scaled by
    /// `load_factor(t)`; steps land exactly on `t_out`: the last one is shortened.
    fn advance_to(
        &mut self,
        t_out: f64,
        h_max: f64,
        load_factor: &impl Fn(f64) -> f64,
        settings: &DynamicSettings,
    ) -> Result<()> {
        let constraints = &self.scene.constraints;
        let rest = &self.scene.mesh.rest_positions_m;
        // A moving wall: one copy of the constraints per output frame, moved on every step.
        let mut moved = constraints
            .imposes_motion(rest)
            .then(|| constraints.clone());
        while t_out - self.t_s > 1e-9 * h_max {
            let t = self.t_s;
            let h = h_max.min(t_out - t);
            for ((xi, vi), ai) in self.x.iter_mut().zip(self.v.iter_mut()).zip(&self.a) {
                *vi += ai * (0.5 * h);
                *xi += *vi * h;
            }
            self.t_s = if t_out - (t + h) <= 1e-9 * h_max {
                t_out
            } else {
                t + h
            };
            match moved.as_mut() {
                Some(m) => {
                    let factor = load_factor(self.t_s) * self.wall_scale;
                    constraints.write_at_load_factor(rest, factor, m);
                    m.project_positions(&mut self.x);
                }
                None => constraints.project_positions(&mut self.x),
            }
            constraints.project_field(&self.x, &mut self.v);
            self.scene.one_sided.enforce(&mut self.x, &mut self.v);
            self.update_accelerations(load_factor(self.t_s));
            for (vi, ai) in self.v.iter_mut().zip(&self.a) {
                *vi += ai * (0.5 * h);
            }
            constraints.project_field(&self.x, &mut self.v);
            self.steps += 1;
            let steps = self.steps;
            if steps.is_multiple_of(settings.check_every) {
                let ke = kinetic_energy_j(self.scene, &self.v);
                self.guard.check(self.scene, &self.x, ke, steps)?;
            }
            if steps >= settings.max_steps {
                return Err(Error::settings(
                    "dynamic breathing settings",
                    format!(
                        "{steps} steps of {h_max:.3e} s reached the limit before \
                     t = {t_out} s"
                    ),
                ));
            }
        }
        Ok(())
    }

    /// The output frame at `time_s` of the current state (checked for blow-up) under `bellows`.
    fn frame(
        &mut self,
        index: usize,
        time_s: f64,
        bellows: BellowsState,
        rest_volume_m3: f64,
    ) -> Result<DynamicFrame> {
        let scene = self.scene;
        let ke = kinetic_energy_j(scene, &self.v);
        self.guard.check(scene, &self.x, ke, self.steps)?;
        let simulated = (scene.mesh.enclosed_volume_m3(&self.x) - rest_volume_m3) * 1e6;
        let (max_d, sum_d) = displacement_extent_mm(&self.x, &scene.mesh.rest_positions_m);
        Ok(DynamicFrame {
            index,
            time_s,
            bellows,
            surface_pressure_pa: -bellows.pressure_pa,
            chest_wall_volume_ml: 0.0,
            simulated_volume_ml: simulated,
            max_displacement_mm: max_d,
            mean_displacement_mm: sum_d / scene.node_count() as f64,
            kinetic_energy_j: ke,
            steps: self.steps,
        })
    }

    /// Accelerations at the current positions and velocities.
    fn update_accelerations(&mut self, load_factor: f64) {
        accelerations(
            self.scene,
            &self.x,
            &self.v,
            (load_factor, self.t_s),
            &self.inv_mass,
            (&mut self.force, &mut self.external),
            &mut self.a,
        );
    }
}

fn check_output_times(times: &[f64], t_start: f64, t_end: f64) -> Result<()> {
    if times.is_empty() {
        return Err(Error::settings(
            "output instants",
            "dynamic breathing: no output time requested",
        ));
    }
    for (i, &t) in times.iter().enumerate() {
        if !(t.is_finite() && t >= t_start && t <= t_end) {
            return Err(Error::settings(
                "output instants",
                format!(
                    "dynamic breathing: output time {t} s (index {i}) is outside the trace \
                 ({t_start} … {t_end} s)"
                ),
            ));
        }
        if i > 0 && t < times[i - 1] {
            return Err(Error::settings(
                "output instants",
                format!(
                    "dynamic breathing: output times must ascend; {t} s (index {i}) follows {} s",
                    times[i - 1]
                ),
            ));
        }
    }
    Ok(())
}

/// Accelerations of the free motion under internal forces (dampers read `v`), contact with the
/// obstacles where they are at `t_s` and the scene's loads scaled by `load_factor`;
/// `scratch` holds the force and external-load buffers.
fn accelerations(
    scene: &Scene,
    x: &[V3],
    v: &[V3],
    (load_factor, t_s): (f64, f64),
    inv_mass: &[f64],
    scratch: (&mut [V3], &mut [V3]),
    a: &mut [V3],
) {
    let (force, external) = scratch;
    scene.internal_forces(x, Some(v), force);
    scene.add_contact_forces(x, Some(v), t_s, force);
    scene.external_forces(x, external);
    for (f, e) in force.iter_mut().zip(external.iter()) {
        *f += e * load_factor;
    }
    scene.constraints.project_field(x, force);
    for ((ai, f), im) in a.iter_mut().zip(force.iter()).zip(inv_mass) {
        *ai = f * *im;
    }
}

fn kinetic_energy_j(scene: &Scene, v: &[V3]) -> f64 {
    v.iter()
        .zip(&scene.mesh.node_mass_kg)
        .map(|(v, m)| 0.5 * m * v.norm_squared())
        .sum()
}

impl DynamicFrame {
    /// The frame as `summary.json` lists quasi-static frames: the target is the trace's
    /// volume, the pressure the surface pressure; no solver iterations (residual undefined).
    pub fn as_frame_summary(&self) -> super::FrameSummary {
        super::FrameSummary {
            index: self.index,
            time_s: self.time_s,
            phase_percent: None,
            target_volume_ml: self.bellows.volume_ml,
            simulated_volume_ml: self.simulated_volume_ml,
            pressure_pa: self.surface_pressure_pa,
            chest_wall_volume_ml: self.chest_wall_volume_ml,
            max_displacement_mm: self.max_displacement_mm,
            mean_displacement_mm: self.mean_displacement_mm,
            interpolated: false,
            solves: 0,
            newton_iterations: 0,
            linear_iterations: 0,
            residual: f64::NAN,
            wall_time_s: 0.0,
        }
    }
}

impl DynamicReport {
    /// The run in the quasi-static report's shape (frames converted, no key volumes); the
    /// volume error is the dynamic lag behind the trace, not a solver tolerance.
    pub fn as_motion_report(
        &self,
        settings: &super::MotionSettings,
        material: &crate::model::Material,
    ) -> super::MotionReport {
        let frames: Vec<super::FrameSummary> = self
            .frames
            .iter()
            .map(DynamicFrame::as_frame_summary)
            .collect();
        let (lo, hi) = frames.iter().fold((f64::MAX, f64::MIN), |(a, b), f| {
            (a.min(f.target_volume_ml), b.max(f.target_volume_ml))
        });
        super::MotionReport {
            settings: settings.clone(),
            material: *material,
            compliance_ml_per_pa: self.compliance_ml_per_pa,
            chest_wall: self.chest_wall,
            rest_volume_ml: self.rest_volume_ml,
            tidal_volume_ml: hi - lo,
            volume_tolerance_ml: f64::NAN,
            keyframes: None,
            max_volume_error_ml: self.max_volume_difference_ml,
            frames,
            wall_time_s: self.setup_wall_time_s + self.integration_wall_time_s,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bellows_law_differentiates_a_sampled_parabola() {
        // V = 100 t² mL sampled at 100 Hz: V' = 200 t, V'' = 200.
        let times: Vec<f64> = (0..=200).map(|i| i as f64 * 0.01).collect();
        let volumes = times.iter().map(|t| 100.0 * t * t).collect();
        let trace = BreathingTrace::new(times, volumes).unwrap();
        let (c, r, i) = (5.0, 0.2, 0.01);
        let b = bellows_state(&trace, 1.0, c, r, i, 0.05);
        assert!((b.volume_ml - 100.0).abs() < 1e-9);
        assert!((b.flow_ml_per_s - 200.0).abs() < 1e-6, "{b:?}");
        assert!((b.flow_rate_ml_per_s2 - 200.0).abs() < 1e-6, "{b:?}");
        assert!((b.pressure_pa - (100.0 / c + r * 200.0 + i * 200.0)).abs() < 1e-6);
    }

    #[test]
    fn bad_settings_and_times_are_refused() {
        let s = DynamicSettings {
            resistance_pa_s_per_ml: -1.0,
            ..Default::default()
        };
        assert!(s.validate().is_err());
        let s = DynamicSettings {
            time_step_safety: 1.5,
            ..Default::default()
        };
        assert!(s.validate().is_err());
        assert!(DynamicSettings::default().validate().is_ok());
        assert!(check_output_times(&[0.0, 1.0], 0.0, 2.0).is_ok());
        assert!(check_output_times(&[1.0, 0.5], 0.0, 2.0).is_err());
        assert!(check_output_times(&[3.0], 0.0, 2.0).is_err());
        assert!(check_output_times(&[], 0.0, 2.0).is_err());
    }

    #[test]
    fn surface_elements_get_their_own_damping_and_the_interior_keeps_the_ratio() {
        use crate::model::{ConstraintSet, Loads, Material, VoxelGrid};
        let grid = VoxelGrid::filled_box([3, 3, 3], [0.01; 3], V3::zeros());
        let mesh = grid.to_mesh(Material::LUNG).unwrap().mesh;
        let on_surface = surface_elements(&mesh);
        // Of a 3 × 3 × 3 block only the centre has no face outside.
        assert_eq!(on_surface.iter().filter(|&&s| !s).count(), 1);
        assert!(!on_surface[13]);
        let n = mesh.node_count();
        let scene = Scene::new(mesh, ConstraintSet::new(n), Loads::default()).unwrap();
        let uniform = damped_scene(&scene, 0.1, None).unwrap();
        assert_eq!(uniform.mesh.classes.len(), 1);
        let skin = damped_scene(&scene, 0.1, Some(0.01)).unwrap();
        assert_eq!(skin.mesh.classes.len(), 2);
        let damping = |e: usize| {
            skin.mesh.classes[skin.mesh.element_class[e] as usize].spring_damping_n_s_per_m[0]
        };
        let interior = uniform.mesh.classes[0].spring_damping_n_s_per_m[0];
        assert!(interior > 0.0);
        assert!((damping(13) - interior).abs() < 1e-15);
        assert!((damping(0) - 0.1 * interior).abs() < 1e-12 * interior);
    }
}
