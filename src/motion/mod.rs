//! Motion: a lung scene driven through a breathing trace, one equilibrium per output frame.
//!
//! Quasi-static by default: each frame is an equilibrium of the elastic lung under the
//! surface pressure that gives the trace's volume (volume driver) or ΔP = ΔV / C
//! (compliance driver). With the volume driver, frames are interpolated in volume from a few
//! key solves whose interpolation error is measured against direct solves (see
//! [`crate::simulation::keyframes`]); every frame's simulated volume is still computed from
//! its own node positions and reported beside the target.

pub mod chest_wall;
pub mod compliance;
pub mod diaphragm;
pub mod dynamic;
pub mod heart_contact;
mod lung_scene;
mod moving_wall;

pub use chest_wall::{move_costal_wall, CostalWallMotion, PHYSIOLOGICAL_RIB_CAGE_SHARE};
pub use compliance::PressureVolumeTable;
pub use heart_contact::{hold_mediastinum_by_contact, MediastinumContact};
pub use lung_scene::{lung_scene, run_scene, run_scene_with_tissue, WallMotion};

use std::time::Instant;

use serde::{Deserialize, Serialize};

use crate::breathing::{BreathingTrace, OutputInstants};
use crate::math::V3;
use crate::model::Material;
use crate::simulation::driver::DrivenState;
use crate::simulation::keyframes::{KeyframeReport, VolumeKeyframes};
use crate::simulation::{BreathingDriver, ImposedMotionShare, QuasiStaticSettings, Scene};
use crate::{Error, Result};

/// The pressure the scene's surface load is built with (λ = 1); frames scale it.
pub const REFERENCE_PRESSURE_PA: f64 = -1.0;

/// How the breathing curve becomes surface pressure.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case", tag = "kind", deny_unknown_fields)]
pub enum DriverKind {
    /// The pressure that makes the simulated volume equal the trace's (default).
    #[default]
    Volume,
    /// ΔP = ΔV / C, the thesis's driver; C from E, ν and the rest volume when not given; or
    /// the pressure read from a pressure–volume table (a non-linear compliance).
    Compliance {
        /// Lung compliance in mL/Pa (≈ 2 mL/Pa for both lungs in vivo).
        compliance_ml_per_pa: Option<f64>,
        /// Instead of one C: rows `[pressure Pa, volume mL]` interpolated piecewise-linearly
        /// ([`compliance`]); not with `compliance_ml_per_pa`.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        pressure_volume: Option<PressureVolumeTable>,
    },
}

impl DriverKind {
    /// The constant compliance driver with compliance `c` mL/Pa (`None`: the elastic one).
    pub fn compliance(c: Option<f64>) -> Self {
        DriverKind::Compliance {
            compliance_ml_per_pa: c,
            pressure_volume: None,
        }
    }

    /// Why this driver cannot run, as (key, reason), if it cannot: a compliance that is not
    /// positive, a pressure–volume table it refuses, or both given.
    pub fn problem(&self) -> Option<(&'static str, String)> {
        let DriverKind::Compliance {
            compliance_ml_per_pa,
            pressure_volume,
        } = self
        else {
            return None;
        };
        if let Some(c) = *compliance_ml_per_pa {
            if !(c.is_finite() && c > 0.0) {
                return Some((
                    "motion.driver.compliance_ml_per_pa",
                    format!("{c} mL/Pa must be positive"),
                ));
            }
            if pressure_volume.is_some() {
                return Some((
                    "motion.driver.pressure_volume",
                    format!(
                        "given with compliance_ml_per_pa = {c}: the pressure comes from one or \
                         the other, give one"
                    ),
                ));
            }
        }
        let reason = pressure_volume.as_ref()?.problem()?;
        Some(("motion.driver.pressure_volume", reason))
    }
}

/// Settings of a breathing simulation.
#[derive(Debug, Clone, Serialize)]
pub struct MotionSettings {
    /// Volume or compliance driver.
    pub driver: DriverKind,
    /// Which instants get a frame.
    pub instants: OutputInstants,
    /// Largest allowed difference between interpolated and directly solved node positions, mm.
    pub interpolation_tolerance_mm: f64,
    /// Solve every frame directly instead of interpolating from key volumes.
    pub solve_every_frame: bool,
    /// Volume driver tolerance as a fraction of the tidal volume.
    pub volume_tolerance_fraction: f64,
    /// Share of every volume change the moving chest wall makes (0: a rigid wall); needs a
    /// scene whose costal wall moves ([`move_costal_wall`]).
    pub rib_cage_share: f64,
    /// Equilibrium solver settings.
    pub solver: QuasiStaticSettings,
    /// Raised by another thread to stop the run before its next equilibrium solve.
    #[serde(skip)]
    pub cancel: Option<crate::simulation::CancelFlag>,
    /// Told of every equilibrium the solves reach (progress displays and job records).
    #[serde(skip)]
    pub progress: Option<crate::simulation::SolveProgressSink>,
}

/// Relative force residual at which a breathing solve stops. Measured on the CIP lungs
/// (10-phase cycle of 500 mL, end-inhale frame against solves to 1e-8): 0.0006 mm largest
/// node difference at 8 mm and 0.0008 mm at 4 mm, for 20 % and 28 % fewer Krylov
/// iterations than 1e-6 (1e-4 gives 0.007 mm). The tolerance that matters is the
/// interpolation's 0.1 mm.
pub const BREATHING_SOLVER_TOLERANCE: f64 = 1e-5;

impl Default for MotionSettings {
    fn default() -> Self {
        MotionSettings {
            driver: DriverKind::Volume,
            instants: OutputInstants::default(),
            interpolation_tolerance_mm: 0.1,
            solve_every_frame: false,
            volume_tolerance_fraction: 0.005,
            rib_cage_share: 0.0,
            solver: QuasiStaticSettings {
                tolerance: BREATHING_SOLVER_TOLERANCE,
                ..QuasiStaticSettings::default()
            },
            cancel: None,
            progress: None,
        }
    }
}

/// One output frame as `summary.json` lists it.
#[derive(Debug, Clone, Serialize)]
pub struct FrameSummary {
    /// Frame index (0-based, the `frames/<index>` directory).
    pub index: usize,
    /// Time in the trace, s.
    pub time_s: f64,
    /// Breathing phase, percent of the cycle from end-inhale, when phases were asked for.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub phase_percent: Option<f64>,
    /// Volume change from the scan the trace asks for, mL.
    pub target_volume_ml: f64,
    /// Volume change of the simulated lung surface, mL.
    pub simulated_volume_ml: f64,
    /// Surface pressure, Pa (negative inflates).
    pub pressure_pa: f64,
    /// Volume the moving chest wall swept at this frame, mL (0 with a rigid wall).
    pub chest_wall_volume_ml: f64,
    /// Largest node displacement, mm.
    pub max_displacement_mm: f64,
    /// Mean node displacement, mm.
    pub mean_displacement_mm: f64,
    /// Whether the frame was interpolated from key volumes (else solved directly).
    pub interpolated: bool,
    /// Equilibrium solves spent on this frame (0 when interpolated).
    pub solves: usize,
    /// Newton iterations spent on this frame.
    pub newton_iterations: usize,
    /// Krylov iterations spent on this frame.
    pub linear_iterations: usize,
    /// Relative force residual of the frame's solve (of the nearest key when interpolated).
    pub residual: f64,
    /// Wall time to produce the frame's positions, s.
    pub wall_time_s: f64,
}

/// What a breathing simulation did, for `summary.json`.
#[derive(Debug, Clone, Serialize)]
pub struct MotionReport {
    /// Settings used.
    pub settings: MotionSettings,
    /// Material of the lung.
    pub material: Material,
    /// Compliance used or implied, mL/Pa.
    pub compliance_ml_per_pa: f64,
    /// How the moving chest wall was scaled to its share of the volume changes.
    pub chest_wall: ImposedMotionShare,
    /// Volume enclosed by the mesh surface at rest, mL.
    pub rest_volume_ml: f64,
    /// Peak-to-peak volume of the requested frames, mL.
    pub tidal_volume_ml: f64,
    /// Volume tolerance of the volume driver, mL.
    pub volume_tolerance_ml: f64,
    /// Key volumes, when frames were interpolated.
    pub keyframes: Option<KeyframeReport>,
    /// Largest |simulated − target| volume over the frames, mL.
    pub max_volume_error_ml: f64,
    /// The frames.
    pub frames: Vec<FrameSummary>,
    /// Wall time of the solves and interpolation, s.
    pub wall_time_s: f64,
}

/// Compliance of a homogeneous linear-elastic lung: C = 3 V₀ (1 − 2ν) / E, in mL/Pa.
pub fn elastic_compliance_ml_per_pa(rest_volume_ml: f64, material: &Material) -> f64 {
    3.0 * rest_volume_ml * (1.0 - 2.0 * material.poisson_ratio) / material.youngs_modulus_pa
}

/// Drives `scene` (whose surface pressures add up to [`REFERENCE_PRESSURE_PA`]) through
/// `trace`; `on_frame` receives each frame's summary and node positions in time order.
pub fn run_motion(
    scene: &Scene,
    material: &Material,
    trace: &BreathingTrace,
    settings: &MotionSettings,
    on_frame: &mut dyn FnMut(&FrameSummary, &[V3]) -> Result<()>,
) -> Result<MotionReport> {
    let start = Instant::now();
    trace.validate()?;
    let plan = settings.instants.plan(trace)?;
    let times = plan.times;
    let targets: Vec<f64> = times.iter().map(|&t| trace.volume_at(t)).collect();
    let (lo, hi) = targets
        .iter()
        .fold((f64::MAX, f64::MIN), |(a, b), &v| (a.min(v), b.max(v)));
    let tidal = hi - lo;
    let volume_tolerance_ml = (settings.volume_tolerance_fraction * tidal).max(0.01);
    let rest_volume_ml = scene.mesh.enclosed_volume_m3(&scene.mesh.rest_positions_m) * 1e6;
    if let Some((key, reason)) = settings.driver.problem() {
        return Err(Error::Config {
            settings: "motion settings",
            file: None,
            key: Some(key.into()),
            reason,
        });
    }
    let compliance = match &settings.driver {
        DriverKind::Compliance {
            compliance_ml_per_pa: Some(c),
            ..
        } => *c,
        DriverKind::Compliance {
            pressure_volume: Some(table),
            ..
        } => {
            // Every frame's volume must be in the table: refused before any solve.
            table.pressure_pa(lo)?;
            table.pressure_pa(hi)?;
            table.compliance_at_rest_ml_per_pa()
        }
        _ => elastic_compliance_ml_per_pa(rest_volume_ml, material),
    };
    let mut driver = BreathingDriver::new(
        scene,
        REFERENCE_PRESSURE_PA,
        compliance,
        settings.solver.clone(),
    )?;
    if let Some(flag) = &settings.cancel {
        driver.set_cancel(flag.clone());
    }
    if let Some(sink) = &settings.progress {
        driver.set_progress(sink.clone());
    }
    chest_wall::check_rib_cage_share(settings.rib_cage_share)?;
    if scene.walls_make_volume.is_some() && settings.driver != DriverKind::Volume {
        return Err(Error::settings(
            "motion settings",
            "the compliance driver sets the pressure, but with a sliding diaphragm the walls \
             make the volume: use the volume driver",
        ));
    }
    let chest_wall = driver.share_volume_with_imposed_motion(settings.rib_cage_share)?;
    // With a sliding diaphragm the imposed motions are the rib cage's and the diaphragm's.
    let chest_wall_part = scene.walls_make_volume.unwrap_or(1.0);
    let rest = scene.mesh.rest_positions_m.clone();
    let keyframes = solve_key_volumes(&mut driver, settings, &targets, volume_tolerance_ml)?;
    let mut solver = FrameSolver {
        driver,
        keyframes,
        kind: settings.driver.clone(),
        volume_tolerance_ml,
        compliance_ml_per_pa: compliance,
    };

    let mut frames = Vec::with_capacity(times.len());
    let mut positions = rest.clone();
    let mut max_volume_error: f64 = 0.0;
    for (index, (&time_s, &target)) in times.iter().zip(&targets).enumerate() {
        let t0 = Instant::now();
        let context = |e: Error| match e {
            Error::Cancelled(_) => e,
            e => Error::InvalidModel(format!(
                "frame {index} (t = {time_s:.3} s, target {target:.1} mL): {e}"
            )),
        };
        let solve = solver
            .positions_at(&rest, target, &mut positions)
            .map_err(context)?;
        scene.check_finite(&positions, index).map_err(context)?;
        let simulated = solver.driver.volume_change_ml(&positions);
        if settings.driver == DriverKind::Volume {
            max_volume_error = max_volume_error.max((simulated - target).abs());
        }
        let (max_d, sum_d) = displacement_extent_mm(&positions, &rest);
        let frame = FrameSummary {
            index,
            time_s,
            phase_percent: plan.phase_percent.as_ref().map(|p| p[index]),
            target_volume_ml: target,
            simulated_volume_ml: simulated,
            pressure_pa: solve.pressure_pa,
            chest_wall_volume_ml: solver
                .driver
                .imposed_sweep_ml(solve.pressure_pa / REFERENCE_PRESSURE_PA)
                * chest_wall_part,
            max_displacement_mm: max_d,
            mean_displacement_mm: sum_d / rest.len() as f64,
            interpolated: solve.interpolated,
            solves: solve.solves,
            newton_iterations: solve.newton_iterations,
            linear_iterations: solve.linear_iterations,
            residual: solve.residual,
            wall_time_s: t0.elapsed().as_secs_f64(),
        };
        on_frame(&frame, &positions)?;
        frames.push(frame);
    }
    if settings.driver != DriverKind::Volume {
        max_volume_error = frames
            .iter()
            .map(|f| (f.simulated_volume_ml - f.target_volume_ml).abs())
            .fold(0.0, f64::max);
    }
    Ok(MotionReport {
        settings: settings.clone(),
        material: *material,
        compliance_ml_per_pa: compliance,
        chest_wall,
        rest_volume_ml,
        tidal_volume_ml: tidal,
        volume_tolerance_ml,
        keyframes: solver.keyframes.map(|k| k.report),
        max_volume_error_ml: max_volume_error,
        frames,
        wall_time_s: start.elapsed().as_secs_f64(),
    })
}

/// The key volumes the frames at `targets_ml` are interpolated from: only with the volume
/// driver, more than two frames and interpolation allowed.
fn solve_key_volumes(
    driver: &mut BreathingDriver,
    settings: &MotionSettings,
    targets_ml: &[f64],
    volume_tolerance_ml: f64,
) -> Result<Option<VolumeKeyframes>> {
    Ok(match &settings.driver {
        DriverKind::Volume if !settings.solve_every_frame && targets_ml.len() > 2 => Some(
            VolumeKeyframes::build(
                driver,
                targets_ml,
                settings.interpolation_tolerance_mm,
                volume_tolerance_ml * 0.2,
            )
            .map_err(|e| match e {
                Error::Cancelled(_) | Error::VolumeUnreachable(_) => e,
                e => Error::InvalidModel(format!("solving the key volumes: {e}")),
            })?,
        ),
        _ => None,
    })
}

/// Finds each frame's node positions: interpolated between key volumes when there are
/// some, else solved by the driver.
struct FrameSolver<'s> {
    driver: BreathingDriver<'s>,
    keyframes: Option<VolumeKeyframes>,
    kind: DriverKind,
    volume_tolerance_ml: f64,
    compliance_ml_per_pa: f64,
}

/// How a frame's positions were found.
struct FrameSolve {
    pressure_pa: f64,
    solves: usize,
    newton_iterations: usize,
    linear_iterations: usize,
    residual: f64,
    interpolated: bool,
}

impl FrameSolve {
    /// A frame solved on its own.
    fn solved(s: &DrivenState) -> Self {
        FrameSolve {
            pressure_pa: s.pressure_pa,
            solves: s.solves,
            newton_iterations: s.newton_iterations,
            linear_iterations: s.linear_iterations,
            residual: s.residual,
            interpolated: false,
        }
    }
}

impl FrameSolver<'_> {
    /// Writes the positions of the frame whose volume change is `target` mL into `positions`.
    fn positions_at(
        &mut self,
        rest: &[V3],
        target: f64,
        positions: &mut [V3],
    ) -> Result<FrameSolve> {
        match (&self.keyframes, &self.kind) {
            (Some(keys), _) => {
                if let Some(from) = keys.direct_start(target) {
                    // Across a jump of the shape: solved, continuing from the key on the
                    // scanned state's side, as the breath reaches it.
                    self.driver.warm_start(from);
                    let s = self.driver.solve_volume(target, self.volume_tolerance_ml)?;
                    positions.copy_from_slice(&s.positions_m);
                    return Ok(FrameSolve::solved(&s));
                }
                keys.positions_at(rest, target, positions);
                let nearest = keys
                    .states
                    .iter()
                    .min_by(|a, b| {
                        (a.volume_change_ml - target)
                            .abs()
                            .total_cmp(&(b.volume_change_ml - target).abs())
                    })
                    .expect("keyframes hold at least one state");
                Ok(FrameSolve {
                    pressure_pa: keys.pressure_at(target),
                    solves: 0,
                    newton_iterations: 0,
                    linear_iterations: 0,
                    residual: nearest.residual,
                    interpolated: true,
                })
            }
            (None, kind) => {
                let s = match kind {
                    DriverKind::Volume => {
                        self.driver.solve_volume(target, self.volume_tolerance_ml)
                    }
                    DriverKind::Compliance {
                        pressure_volume: Some(table),
                        ..
                    } => {
                        // The table's distending pressure; the surface pressure is its negative.
                        let p = table.pressure_pa(target)?;
                        self.driver.solve_pressure(-p)
                    }
                    DriverKind::Compliance { .. } => self
                        .driver
                        .solve_pressure(-target / self.compliance_ml_per_pa),
                }?;
                positions.copy_from_slice(&s.positions_m);
                Ok(FrameSolve::solved(&s))
            }
        }
    }
}

/// Largest and summed node displacement from `rest`, mm.
fn displacement_extent_mm(positions: &[V3], rest: &[V3]) -> (f64, f64) {
    positions
        .iter()
        .zip(rest)
        .map(|(x, r)| (x - r).norm() * 1e3)
        .fold((0.0f64, 0.0), |(m, s), d| (m.max(d), s + d))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::breathing::LujanBreathing;
    use crate::simulation::cases::symmetric_block_under_pressure;

    fn block() -> (Scene, f64) {
        let scene = symmetric_block_under_pressure([4, 4, 4], 0.01, Material::LUNG, -1.0).unwrap();
        let v0 = scene.mesh.enclosed_volume_m3(&scene.mesh.rest_positions_m) * 1e6;
        (scene, v0)
    }

    #[test]
    fn volume_driven_frames_follow_the_curve_interpolated_or_solved() {
        let (scene, v0) = block();
        let curve = LujanBreathing {
            tidal_volume_ml: 0.08 * v0,
            ..LujanBreathing::default()
        };
        let trace = curve.trace(8.0, 25.0).unwrap();
        let mut seen = 0;
        let settings = MotionSettings::default();
        let interp = run_motion(&scene, &Material::LUNG, &trace, &settings, &mut |f, x| {
            assert_eq!(f.index, seen);
            assert_eq!(x.len(), scene.node_count());
            seen += 1;
            Ok(())
        })
        .unwrap();
        assert_eq!(interp.frames.len(), 10);
        let tidal = interp.tidal_volume_ml;
        assert!(
            interp.max_volume_error_ml <= 0.005 * tidal,
            "{}",
            interp.max_volume_error_ml
        );
        let direct = run_motion(
            &scene,
            &Material::LUNG,
            &trace,
            &MotionSettings {
                solve_every_frame: true,
                ..MotionSettings::default()
            },
            &mut |_, _| Ok(()),
        )
        .unwrap();
        for (a, b) in interp.frames.iter().zip(&direct.frames) {
            assert!(a.interpolated && !b.interpolated);
            assert!((a.max_displacement_mm - b.max_displacement_mm).abs() < 0.1);
            assert!((a.simulated_volume_ml - b.simulated_volume_ml).abs() <= 0.01 * tidal);
        }
        // End-inhale (phase 0) is the largest displacement and the strongest suction.
        let f0 = &interp.frames[0];
        assert!(interp
            .frames
            .iter()
            .all(|f| f.max_displacement_mm <= f0.max_displacement_mm + 1e-9));
        assert!(f0.pressure_pa < 0.0);
    }

    #[test]
    fn compliance_driver_uses_the_elastic_compliance() {
        let (scene, v0) = block();
        let c = elastic_compliance_ml_per_pa(v0, &Material::LUNG);
        assert!((c - v0 / Material::LUNG.bulk_modulus_pa()).abs() < 1e-12 * c);
        let trace = BreathingTrace::new(vec![0.0, 1.0], vec![0.0, 0.01 * v0]).unwrap();
        let settings = MotionSettings {
            driver: DriverKind::compliance(None),
            instants: OutputInstants::EverySample,
            ..MotionSettings::default()
        };
        let r = run_motion(&scene, &Material::LUNG, &trace, &settings, &mut |_, _| {
            Ok(())
        })
        .unwrap();
        let f = &r.frames[1];
        assert!((f.pressure_pa + 0.01 * v0 / c).abs() < 1e-9);
        // Small strain: the compliance driver meets the volume to within a few percent.
        assert!(
            (f.simulated_volume_ml - 0.01 * v0).abs() < 0.03 * 0.01 * v0,
            "{f:?}"
        );
    }

    /// The compliance driver through `table` (or the constant `c`) on a small breath.
    fn run_compliance(
        scene: &Scene,
        trace: &BreathingTrace,
        c: Option<f64>,
        table: Option<PressureVolumeTable>,
    ) -> Result<(MotionReport, Vec<Vec<V3>>)> {
        let settings = MotionSettings {
            driver: DriverKind::Compliance {
                compliance_ml_per_pa: c,
                pressure_volume: table,
            },
            instants: OutputInstants::EverySample,
            ..MotionSettings::default()
        };
        let mut fields = Vec::new();
        let r = run_motion(scene, &Material::LUNG, trace, &settings, &mut |_, x| {
            fields.push(x.to_vec());
            Ok(())
        })?;
        Ok((r, fields))
    }

    fn breath(v0: f64) -> BreathingTrace {
        let v = [0.0, 0.01, 0.02, 0.03, 0.015, 0.0].map(|f| f * v0);
        BreathingTrace::new((0..v.len()).map(|i| i as f64).collect(), v.to_vec()).unwrap()
    }

    #[test]
    fn a_pressure_volume_table_of_one_compliance_gives_that_compliance_s_fields() {
        let (scene, v0) = block();
        let c = elastic_compliance_ml_per_pa(v0, &Material::LUNG);
        let trace = breath(v0);
        let (by_c, x_c) = run_compliance(&scene, &trace, Some(c), None).unwrap();
        // Three collinear rows through [0, 0] with slope C: the same line.
        let p = 0.05 * v0 / c;
        let table = PressureVolumeTable(vec![
            [-p, -c * p],
            [0.0, 0.0],
            [0.3 * p, 0.3 * c * p],
            [p, c * p],
        ]);
        let (by_table, x_t) = run_compliance(&scene, &trace, None, Some(table)).unwrap();
        assert!((by_table.compliance_ml_per_pa - c).abs() < 1e-12 * c);
        for (a, b) in by_c.frames.iter().zip(&by_table.frames) {
            // Closed form: ΔP = −ΔV / C, to round-off of the interpolation.
            assert!((a.pressure_pa + a.target_volume_ml / c).abs() < 1e-12 * p.max(1.0));
            assert!(
                (a.pressure_pa - b.pressure_pa).abs() < 1e-9 * p,
                "{a:?} {b:?}"
            );
        }
        let diff = x_c
            .iter()
            .flatten()
            .zip(x_t.iter().flatten())
            .map(|(a, b)| (a - b).norm())
            .fold(0.0, f64::max);
        let moved = x_c
            .iter()
            .flat_map(|x| x.iter().zip(&scene.mesh.rest_positions_m))
            .map(|(a, r)| (a - r).norm())
            .fold(0.0, f64::max);
        assert!(
            moved > 0.0 && diff <= 1e-6 * moved,
            "{diff:e} m of {moved:e} m"
        );
    }

    #[test]
    fn a_convex_pressure_volume_table_asks_more_pressure_for_the_larger_volumes() {
        let (scene, v0) = block();
        let c = elastic_compliance_ml_per_pa(v0, &Material::LUNG);
        let trace = breath(v0);
        let (linear, _) = run_compliance(&scene, &trace, Some(c), None).unwrap();
        // Compliance C up to 1 % of V₀, C/2 to 2 %, C/4 beyond: a lung that stiffens.
        let v1 = 0.01 * v0;
        let (p1, p2) = (v1 / c, v1 / c + 2.0 * v1 / c);
        let table = PressureVolumeTable(vec![
            [0.0, 0.0],
            [p1, v1],
            [p2, 2.0 * v1],
            [p2 + 4.0 * v1 / c, 3.0 * v1],
        ]);
        let (stiff, _) = run_compliance(&scene, &trace, None, Some(table)).unwrap();
        for (a, b) in linear.frames.iter().zip(&stiff.frames) {
            let v = a.target_volume_ml / v1;
            // Expected: ΔV/C up to 1 %, then 2/C and 4/C per unit above each knee.
            let expected = if v <= 1.0 {
                v
            } else if v <= 2.0 {
                1.0 + 2.0 * (v - 1.0)
            } else {
                3.0 + 4.0 * (v - 2.0)
            } * v1
                / c;
            assert!(
                (b.pressure_pa + expected).abs() < 1e-9 * p2,
                "{b:?} vs {expected}"
            );
            if v > 1.0 + 1e-9 {
                // Measurably more suction than the linear driver, and more volume for it.
                assert!(
                    b.pressure_pa < a.pressure_pa - 0.2 * a.pressure_pa.abs(),
                    "{a:?} {b:?}"
                );
                assert!(
                    b.simulated_volume_ml > a.simulated_volume_ml + 0.1 * v1,
                    "{a:?} {b:?}"
                );
            } else {
                assert!((a.pressure_pa - b.pressure_pa).abs() < 1e-9 * p1);
            }
        }
    }

    #[test]
    fn the_compliance_driver_refuses_a_bad_table_or_a_trace_beyond_it_before_solving() {
        let (scene, v0) = block();
        let trace = breath(v0);
        let key = |r: Result<(MotionReport, Vec<Vec<V3>>)>| match r {
            Err(Error::Config { key, reason, .. }) => (key.unwrap_or_default(), reason),
            other => panic!(
                "expected a refused setting, got {:?}",
                other.map(|r| r.0.frames.len())
            ),
        };
        let short = PressureVolumeTable(vec![[0.0, 0.0], [10.0, 0.02 * v0]]);
        let (k, why) = key(run_compliance(&scene, &trace, None, Some(short)));
        assert_eq!(k, "motion.driver.pressure_volume");
        assert!(
            why.contains("outside the table") && why.contains("extend it"),
            "{why}"
        );
        let falling = PressureVolumeTable(vec![[0.0, 0.0], [10.0, 5.0], [20.0, 4.0]]);
        let (k, why) = key(run_compliance(&scene, &trace, None, Some(falling)));
        assert_eq!(k, "motion.driver.pressure_volume");
        assert!(why.contains("volume must rise with pressure"), "{why}");
        let both = PressureVolumeTable(vec![[0.0, 0.0], [10.0, 0.05 * v0]]);
        let (k, why) = key(run_compliance(&scene, &trace, Some(2.0), Some(both)));
        assert_eq!(k, "motion.driver.pressure_volume");
        assert!(why.contains("give one"), "{why}");
        let (k, why) = key(run_compliance(&scene, &trace, Some(-2.0), None));
        assert_eq!(k, "motion.driver.compliance_ml_per_pa");
        assert!(why.contains("-2 mL/Pa"), "{why}");
    }

    #[test]
    fn a_raised_cancel_flag_stops_the_solves_as_a_cancellation() {
        let (scene, v0) = block();
        let trace = BreathingTrace::new(vec![0.0, 1.0, 2.0], vec![0.0, 0.01 * v0, 0.0]).unwrap();
        let flag = crate::simulation::CancelFlag::default();
        let settings = MotionSettings {
            instants: OutputInstants::EverySample,
            solve_every_frame: true,
            cancel: Some(flag.clone()),
            ..MotionSettings::default()
        };
        let mut frames = 0;
        let r = run_motion(&scene, &Material::LUNG, &trace, &settings, &mut |_, _| {
            frames += 1;
            // Raised from the frame callback, as another thread would between two solves.
            flag.store(true, std::sync::atomic::Ordering::SeqCst);
            Ok(())
        });
        assert!(matches!(r, Err(Error::Cancelled(_))), "{r:?}");
        assert_eq!(
            frames, 1,
            "the rest state needs no solve; the next one is refused"
        );
    }

    #[test]
    fn every_equilibrium_reached_is_reported_to_the_progress_sink() {
        let (scene, v0) = block();
        let trace = BreathingTrace::new(vec![0.0, 1.0, 2.0], vec![0.0, 0.01 * v0, 0.0]).unwrap();
        let seen = std::sync::Arc::new(std::sync::Mutex::new(Vec::new()));
        let sink = {
            let seen = seen.clone();
            crate::simulation::SolveProgressSink(std::sync::Arc::new(move |p| {
                seen.lock().unwrap().push(p)
            }))
        };
        let settings = MotionSettings {
            instants: OutputInstants::EverySample,
            solve_every_frame: true,
            progress: Some(sink),
            ..MotionSettings::default()
        };
        run_motion(&scene, &Material::LUNG, &trace, &settings, &mut |_, _| {
            Ok(())
        })
        .unwrap();
        let seen = seen.lock().unwrap();
        assert!(!seen.is_empty());
        for (i, p) in seen.iter().enumerate() {
            assert_eq!(p.equilibria, i + 1, "{seen:?}");
        }
        let peak = seen.iter().map(|p| p.volume_change_ml).fold(0.0, f64::max);
        let want_ml = 0.01 * v0;
        // Within the volume driver's tolerance; key volumes may reach a little beyond.
        assert!(
            peak > 0.99 * want_ml && peak < 1.05 * want_ml,
            "{peak} vs {want_ml}"
        );
    }
}
