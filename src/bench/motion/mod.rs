//! Breathing-cycle benchmark on the real case: one CT and a tidal breathing curve in, a
//! displacement field per phase out.
//!
//! The case is the CIP chest CT (`ct-64.nrrd`, 64 × 64 × 79 at ≈ 4 mm) taken through the same
//! path as `lungmotion run`: `load_ct`, `ingest_scan` (segmentation and lung model at the
//! element size), `lung_scene`, and a [`FieldSampler`] onto the CT grid. The trace is
//! `LujanBreathing::default().trace(8 s, 25 Hz)`: two 4 s breaths of 500 mL with the CT at
//! end-exhale, and the output instants are the default 10 phases of the first cycle.
//!
//! Three measurements per element size:
//!
//! * **Cycle**: wall time of `run_motion` (solver set-up, key-volume solves, 10 interpolated
//!   frames), median of the repeats with min and max, per phase (total ÷ phases) and per
//!   frame; CPU time (utime + stime of `/proc/self/stat`) beside it, since on a shared
//!   machine CPU ÷ cores is what an idle machine would take; peak memory as `VmHWM` of
//!   `/proc/self/status` after resetting it with `/proc/self/clear_refs` ← 5 just before the
//!   cycles (else it includes earlier phases: stated). A solve that fails is recorded as
//!   a failure with its error text and the benchmark goes on.
//! * **Serving** (interpolated sizes only): the keys are built once more by the same call
//!   `run_motion` makes (`VolumeKeyframes::build` with the same tolerances), then the 10
//!   phases' fields are produced from them (`positions_at` + `sample_mm` on the lung box),
//!   repeated, median → fields per second; separately `positions_at` alone (node states
//!   per second).
//! * **Accuracy**: the same cycle with `solve_every_frame` (one direct volume-driven solve per
//!   frame, volume tolerance 10× tighter than the run's) against the interpolated one, per frame: largest node position difference and
//!   largest voxel displacement difference (mm), and each run's volume error against the
//!   trace (target ≤ 0.5 % of the tidal volume).
//!
//! * **Serving at clinical scale** (issue 13, target 6): the serving pass again on the POPI CT
//!   (512 × 512 × 141, `../shared/data/popi-chest-ct`) at the run's default element size, its
//!   fields on the lung box (about 9.7 M voxels each); skipped in quick mode.
//!
//! Targets (issue 4): whole cycle ≤ 1 s at 8 mm and ≤ 5 s at 4 mm on the 2-core machine;
//! ≥ 200 fields/s served at 8 mm after the solves; interpolation error ≤ 0.1 mm against
//! direct solves. Nothing here asserts a speed: the report states targets and verdicts.

mod report;

use std::time::Instant;

use serde::Serialize;

use super::{Outcome, TimeStats};
use crate::breathing::{BreathingTrace, LujanBreathing};
use crate::datasets::{cip_chest_ct64, popi_chest_ct};
use crate::ingest::lung_model::{LungModelSettings, SlidingMode};
use crate::ingest::pipeline::{ingest_scan, IngestSettings};
use crate::ingest::scan::load_ct;
use crate::math::V3;
use crate::model::Material;
use crate::motion::{
    elastic_compliance_ml_per_pa, run_motion, run_scene, MotionReport, MotionSettings, WallMotion,
    PHYSIOLOGICAL_RIB_CAGE_SHARE, REFERENCE_PRESSURE_PA,
};
use crate::outputs::displacement_field::{FieldGrid, FieldSampler};
use crate::process::{
    current_rss_bytes, load_average, peak_rss_bytes, process_cpu_s, reset_peak_rss,
};
use crate::run::RunConfig;
use crate::simulation::keyframes::VolumeKeyframes;
use crate::simulation::{BreathingDriver, Scene};
use crate::{Error, Result};

/// Target wall time of the whole 10-phase cycle at 8 mm elements, s.
pub const CYCLE_TARGET_8MM_S: f64 = 1.0;
/// Target wall time of the whole 10-phase cycle at 4 mm elements, s.
pub const CYCLE_TARGET_4MM_S: f64 = 5.0;
/// Target rate of displacement fields served from solved keys at 8 mm, per second.
pub const FIELDS_PER_S_TARGET: f64 = 200.0;
/// Target largest interpolation error against direct solves, mm.
pub const INTERPOLATION_TARGET_MM: f64 = 0.1;
/// Target largest volume error per frame, as a fraction of the tidal volume.
pub const VOLUME_ERROR_TARGET_FRACTION: f64 = 0.005;
/// Length of the benchmark trace, s (two 4 s breaths).
pub const TRACE_DURATION_S: f64 = 8.0;
/// Sampling rate of the benchmark trace, Hz.
pub const TRACE_RATE_HZ: f64 = 25.0;

/// What to run.
#[derive(Debug, Clone, Serialize)]
pub struct MotionBenchOptions {
    /// 8 mm only, one repeat, few serving repeats: a smoke test of the harness.
    pub quick: bool,
    /// Element sizes whose cycle is timed, mm.
    pub element_sizes_mm: Vec<f64>,
    /// Timed cycles at element sizes ≥ 6 mm (median reported).
    pub repeats: usize,
    /// Timed cycles at finer element sizes, whose solves take much longer.
    pub fine_repeats: usize,
    /// Element sizes whose serving rate and interpolation accuracy are measured, mm.
    pub serve_element_sizes_mm: Vec<f64>,
    /// Timed passes over the 10 phases when serving fields (median reported).
    pub serve_repeats: usize,
    /// Also serve fields on the POPI CT's grid at the run's default element size.
    pub popi_serving: bool,
}

impl Default for MotionBenchOptions {
    fn default() -> Self {
        MotionBenchOptions {
            quick: false,
            element_sizes_mm: vec![8.0, 4.0],
            repeats: 3,
            fine_repeats: 1,
            serve_element_sizes_mm: vec![8.0],
            serve_repeats: 21,
            popi_serving: true,
        }
    }
}

impl MotionBenchOptions {
    /// The smoke-test configuration: 8 mm only, one cycle, a few serving passes.
    pub fn quick() -> Self {
        MotionBenchOptions {
            quick: true,
            element_sizes_mm: vec![8.0],
            repeats: 1,
            fine_repeats: 1,
            serve_element_sizes_mm: vec![8.0],
            serve_repeats: 3,
            popi_serving: false,
        }
    }
}

/// CT loading, segmentation and model building at one element size.
#[derive(Debug, Clone, Serialize)]
pub struct ModelBuild {
    /// CT grid.
    pub ct_dims: [usize; 3],
    /// Elements of both lungs.
    pub elements: usize,
    /// Nodes of both lungs.
    pub nodes: usize,
    /// Lung voxels receiving a displacement.
    pub sampled_voxels: usize,
    /// Reading the CT, s.
    pub load_ct_s: f64,
    /// Lung segmentation, s.
    pub segmentation_s: f64,
    /// Voxel grid, mesh and constraints, s.
    pub model_s: f64,
    /// Breathing scene from the model, s.
    pub scene_s: f64,
    /// Locating the lung voxels in the mesh, s.
    pub field_sampler_s: f64,
    /// All of the above, s.
    pub total_s: f64,
    /// Peak resident memory of the build (reset before it when possible), bytes.
    pub peak_rss_bytes: Option<u64>,
    /// Sliding nodes on tangent planes although the wall surface was asked (0 otherwise).
    pub wall_surface_plane_nodes: usize,
}

/// Timing of the breathing cycle as `run_motion` runs it.
#[derive(Debug, Clone, Serialize)]
pub struct CycleTiming {
    /// Frames of the cycle.
    pub frames: usize,
    /// Wall time of the whole cycle (set-up, key solves, frames).
    pub time: TimeStats,
    /// Median cycle time divided by the frames, s.
    pub per_phase_s: f64,
    /// CPU time per cycle (user + system, all threads), s.
    pub cpu_per_cycle_s: Option<f64>,
    /// Solver set-up alone (`BreathingDriver::new`, timed apart from the cycles), s.
    pub solver_setup_s: f64,
    /// Key volumes solved (0 when every frame was solved).
    pub keys: usize,
    /// Equilibrium solves of the keys (all levels).
    pub key_solves: usize,
    /// Solver wall time of the keys, s (last cycle).
    pub key_solve_time_s: f64,
    /// Interpolation error the keys measured at their check volumes, mm.
    pub key_measured_error_mm: f64,
    /// Wall time of each frame of the last cycle (interpolation only, after the keys), s.
    pub frame_wall_s: Vec<f64>,
    /// Peak-to-peak volume of the frames, mL.
    pub tidal_volume_ml: f64,
    /// Lung volume at rest (the CT), mL.
    pub rest_volume_ml: f64,
    /// Largest |simulated − target| volume over the frames, mL.
    pub max_volume_error_ml: f64,
    /// Resident memory before the cycles, bytes.
    pub rss_before_bytes: Option<u64>,
    /// Peak resident memory during the cycles, bytes.
    pub peak_rss_bytes: Option<u64>,
    /// Whether the peak was reset before the cycles (else it includes the build).
    pub peak_reset: bool,
}

/// Displacement fields produced from solved keys.
#[derive(Debug, Clone, Serialize)]
pub struct FieldServing {
    /// Time to build the keys once more (the same call `run_motion` makes), s.
    pub key_build_s: f64,
    /// Keys.
    pub keys: usize,
    /// Newton iterations of the final key level's states (the last sweep and the first key).
    pub final_level_newton_iterations: usize,
    /// Krylov (GMRES) iterations of the final key level's states.
    pub final_level_linear_iterations: usize,
    /// Fields per pass (the phases).
    pub fields: usize,
    /// Voxels of each field (the CT grid).
    pub voxels_per_field: usize,
    /// Time of one pass producing every phase's field (positions + sampling on the CT grid).
    pub fields_time: TimeStats,
    /// Fields per second at the median pass.
    pub fields_per_s: f64,
    /// Time of one pass producing every phase's node positions only.
    pub nodes_time: TimeStats,
    /// Node states per second at the median pass.
    pub node_states_per_s: f64,
}

/// One frame interpolated from keys against the same frame solved directly.
#[derive(Debug, Clone, Serialize)]
pub struct FrameAccuracy {
    /// Frame index.
    pub index: usize,
    /// Time in the trace, s.
    pub time_s: f64,
    /// Volume change the trace asks for, mL.
    pub target_volume_ml: f64,
    /// Simulated volume change of the interpolated frame, mL.
    pub interpolated_volume_ml: f64,
    /// Simulated volume change of the directly solved frame, mL.
    pub direct_volume_ml: f64,
    /// Largest node position difference, mm.
    pub node_difference_mm: f64,
    /// Largest voxel displacement difference on the CT grid, mm.
    pub field_difference_mm: f64,
    /// Largest node position difference between the direct frame and the keys evaluated at
    /// the volume the direct solve reached (interpolation alone, without the direct solve's
    /// volume tolerance), mm.
    pub same_volume_node_difference_mm: f64,
    /// Equilibrium solves of the direct frame.
    pub direct_solves: usize,
    /// Newton iterations of the direct frame.
    pub direct_newton_iterations: usize,
    /// Krylov iterations of the direct frame.
    pub direct_linear_iterations: usize,
    /// Wall time of the direct frame, s.
    pub direct_wall_s: f64,
}

/// Interpolated cycle against direct solves of every frame.
#[derive(Debug, Clone, Serialize)]
pub struct InterpolationAccuracy {
    /// Per frame.
    pub frames: Vec<FrameAccuracy>,
    /// Largest node position difference over the frames, mm.
    pub max_node_difference_mm: f64,
    /// Largest voxel displacement difference over the frames, mm.
    pub max_field_difference_mm: f64,
    /// Largest node difference at the direct frames' own volumes, mm.
    pub max_same_volume_node_difference_mm: f64,
    /// Tidal volume, mL.
    pub tidal_volume_ml: f64,
    /// Largest volume error of the interpolated frames, mL.
    pub max_interpolated_volume_error_ml: f64,
    /// Largest volume error of the direct frames, mL.
    pub max_direct_volume_error_ml: f64,
    /// Wall time of the interpolated cycle, s.
    pub interpolated_cycle_s: f64,
    /// Wall time of the direct cycle, s.
    pub direct_cycle_s: f64,
}

/// Largest cost of sliding on the curved wall against tangent planes (issue 14): the cycle's
/// median time at most this many times the tangent planes'.
pub const WALL_SURFACE_COST_TARGET: f64 = 1.3;

/// The same cycle with the sliding nodes on the curved wall (`sliding = "wall_surface"`),
/// timed right after the tangent planes' in the same run.
#[derive(Debug, Clone, Serialize)]
pub struct WallSurfaceCycle {
    /// The cycle.
    pub cycle: CycleTiming,
    /// Its median time over the tangent planes' median.
    pub ratio_to_tangent_planes: f64,
    /// Sliding nodes left on tangent planes at ridges of the wall field.
    pub nodes_on_planes: usize,
}

/// Everything measured at one element size.
#[derive(Debug, Clone, Serialize)]
pub struct ElementSizeBench {
    /// Element edge, mm.
    pub element_size_mm: f64,
    /// Target cycle time at this size, s, if the issue states one.
    pub cycle_target_s: Option<f64>,
    /// Model build.
    pub build: Outcome<ModelBuild>,
    /// Breathing cycle.
    pub cycle: Outcome<CycleTiming>,
    /// The cycle again, sliding on the curved wall.
    pub wall_surface: Outcome<WallSurfaceCycle>,
    /// Fields served from keys.
    pub serving: Outcome<FieldServing>,
    /// Interpolation against direct solves.
    pub accuracy: Outcome<InterpolationAccuracy>,
}

/// The motion benchmark report.
#[derive(Debug, Clone, Serialize)]
pub struct MotionBenchReport {
    /// Options used.
    pub options: MotionBenchOptions,
    /// Logical cores available.
    pub cores: usize,
    /// 1-, 5- and 15-minute load averages at the start (from /proc/loadavg).
    pub load_average_at_start: Option<[f64; 3]>,
    /// Tidal volume of the trace, mL.
    pub trace_tidal_volume_ml: f64,
    /// Per element size, in the order asked.
    pub sizes: Vec<ElementSizeBench>,
    /// Fields served on the POPI CT's grid (issue 13, target 6).
    pub popi: Outcome<PopiFieldServing>,
}

/// Fields served from solved keys on the POPI CT (512 × 512 × 141) at the run's default
/// element size: the clinical-scale counterpart of [`ElementSizeBench::serving`].
#[derive(Debug, Clone, Serialize)]
pub struct PopiFieldServing {
    /// Element edge, mm.
    pub element_size_mm: f64,
    /// Model build.
    pub build: ModelBuild,
    /// Fields served from keys.
    pub serving: FieldServing,
}

/// Passes over the 10 phases when serving the POPI fields (each pass about 0.3 s).
pub const POPI_SERVE_REPEATS: usize = 7;

/// The lung model and what the cycle needs from it, built as `lungmotion run` builds it.
struct Case {
    scene: Scene,
    sampler: FieldSampler,
    material: Material,
}

/// Runs the motion benchmark; without the shared data every measurement is skipped.
pub fn run_motion_bench(opts: &MotionBenchOptions) -> Result<MotionBenchReport> {
    let cores = rayon::current_num_threads();
    let curve = LujanBreathing::default();
    let trace = curve.trace(TRACE_DURATION_S, TRACE_RATE_HZ)?;
    let load_average_at_start = load_average();
    let Some(dir) = cip_chest_ct64() else {
        let why = "shared data not found (set LUNGMOTION_SHARED_DATA)".to_string();
        let sizes = opts
            .element_sizes_mm
            .iter()
            .map(|&h| ElementSizeBench {
                element_size_mm: h,
                cycle_target_s: cycle_target_s(h),
                build: Outcome::Skipped(why.clone()),
                cycle: Outcome::Skipped(why.clone()),
                wall_surface: Outcome::Skipped(why.clone()),
                serving: Outcome::Skipped(why.clone()),
                accuracy: Outcome::Skipped(why.clone()),
            })
            .collect();
        return Ok(MotionBenchReport {
            options: opts.clone(),
            cores,
            load_average_at_start,
            trace_tidal_volume_ml: curve.tidal_volume_ml,
            sizes,
            popi: Outcome::Skipped(why),
        });
    };
    let ct_path = dir.join("ct-64.nrrd");
    let settings = MotionSettings {
        rib_cage_share: PHYSIOLOGICAL_RIB_CAGE_SHARE,
        ..MotionSettings::default()
    };
    let mut sizes = Vec::with_capacity(opts.element_sizes_mm.len());
    for &h in &opts.element_sizes_mm {
        let mut entry = ElementSizeBench {
            element_size_mm: h,
            cycle_target_s: cycle_target_s(h),
            build: skipped("not run"),
            cycle: skipped("the model could not be built"),
            wall_surface: skipped("the model could not be built"),
            serving: skipped("not asked at this element size"),
            accuracy: skipped("not asked at this element size"),
        };
        let case = match build_case(&ct_path, h, SlidingMode::TangentPlane) {
            Ok((case, build)) => {
                entry.build = Outcome::Measured(build);
                case
            }
            Err(e) => {
                entry.build = Outcome::Failed(e.to_string());
                sizes.push(entry);
                continue;
            }
        };
        let repeats = if h >= 6.0 {
            opts.repeats
        } else {
            opts.fine_repeats
        }
        .max(1);
        entry.cycle = Outcome::from_result(bench_cycle(&case, &trace, &settings, repeats));
        entry.wall_surface = match entry.cycle.measured() {
            Some(planes) => Outcome::from_result(bench_wall_surface(
                &ct_path,
                h,
                &trace,
                &settings,
                repeats,
                planes.time.median_s,
            )),
            None => skipped("the tangent planes' cycle did not run to the end"),
        };
        if opts.serve_element_sizes_mm.contains(&h) {
            if entry.cycle.measured().is_some() {
                match bench_serving(&case, &trace, &settings, opts.serve_repeats.max(1)) {
                    Ok((serving, keys)) => {
                        entry.serving = Outcome::Measured(serving);
                        entry.accuracy =
                            Outcome::from_result(bench_accuracy(&case, &keys, &trace, &settings));
                    }
                    Err(e) => {
                        entry.serving = Outcome::Failed(e.to_string());
                        entry.accuracy = skipped("the keys could not be built");
                    }
                }
            } else {
                let why = "the cycle did not run to the end";
                entry.serving = skipped(why);
                entry.accuracy = skipped(why);
            }
        }
        sizes.push(entry);
    }
    let popi = match (opts.popi_serving, popi_chest_ct()) {
        (false, _) => skipped("not asked (quick mode)"),
        (true, None) => skipped("the POPI CT is not in the shared data"),
        (true, Some(dir)) => Outcome::from_result(bench_popi_serving(&dir, &trace, &settings)),
    };
    Ok(MotionBenchReport {
        options: opts.clone(),
        cores,
        load_average_at_start,
        trace_tidal_volume_ml: curve.tidal_volume_ml,
        sizes,
        popi,
    })
}

/// The POPI case built as `lungmotion run` builds it by default, and its fields served.
fn bench_popi_serving(
    dicom_dir: &std::path::Path,
    trace: &BreathingTrace,
    settings: &MotionSettings,
) -> Result<PopiFieldServing> {
    let element_size_mm = RunConfig::default().element_size_mm;
    let (case, build) = build_case(dicom_dir, element_size_mm, SlidingMode::TangentPlane)?;
    let (serving, _) = bench_serving(&case, trace, settings, POPI_SERVE_REPEATS)?;
    Ok(PopiFieldServing {
        element_size_mm,
        build,
        serving,
    })
}

fn skipped<T>(why: &str) -> Outcome<T> {
    Outcome::Skipped(why.to_string())
}

/// The issue's cycle target at element size `h_mm`, if it states one.
pub fn cycle_target_s(h_mm: f64) -> Option<f64> {
    if (h_mm - 8.0).abs() < 1e-9 {
        Some(CYCLE_TARGET_8MM_S)
    } else if (h_mm - 4.0).abs() < 1e-9 {
        Some(CYCLE_TARGET_4MM_S)
    } else {
        None
    }
}

/// The cycle of [`bench_cycle`] on the model rebuilt with the sliding nodes on the curved wall.
fn bench_wall_surface(
    ct_path: &std::path::Path,
    element_size_mm: f64,
    trace: &BreathingTrace,
    settings: &MotionSettings,
    repeats: usize,
    tangent_planes_median_s: f64,
) -> Result<WallSurfaceCycle> {
    let (case, build) = build_case(ct_path, element_size_mm, SlidingMode::WallSurface)?;
    let cycle = bench_cycle(&case, trace, settings, repeats)?;
    Ok(WallSurfaceCycle {
        ratio_to_tangent_planes: cycle.time.median_s / tangent_planes_median_s,
        cycle,
        nodes_on_planes: build.wall_surface_plane_nodes,
    })
}

fn build_case(
    ct_path: &std::path::Path,
    element_size_mm: f64,
    sliding: SlidingMode,
) -> Result<(Case, ModelBuild)> {
    let peak_reset = reset_peak_rss();
    let start = Instant::now();
    let scan = load_ct(ct_path)?;
    let load_ct_s = start.elapsed().as_secs_f64();
    let model_settings = LungModelSettings {
        element_size_mm,
        sliding,
        ..LungModelSettings::default()
    };
    let material = model_settings.material;
    let outcome = ingest_scan(
        &scan,
        &IngestSettings {
            model: model_settings,
            ..IngestSettings::default()
        },
    )?;
    let timing = |k: &str| {
        outcome
            .summary
            .timings_s
            .get(k)
            .copied()
            .unwrap_or(f64::NAN)
    };
    let t = Instant::now();
    // As `lungmotion run` builds it by default: the chest wall makes a third of each breath.
    let scene = run_scene(&outcome.model, &WallMotion::default())?;
    let scene_s = t.elapsed().as_secs_f64();
    let t = Instant::now();
    // As `lungmotion run` writes them by default.
    let sampler = FieldSampler::new(
        &outcome.segmentation.lungs,
        &scene.mesh,
        &outcome.model.element_lung,
        FieldGrid::LungBox,
    )?;
    let field_sampler_s = t.elapsed().as_secs_f64();
    let build = ModelBuild {
        ct_dims: scan.ct.geometry.dims,
        elements: scene.mesh.elements.len(),
        nodes: scene.node_count(),
        sampled_voxels: sampler.sampled_voxels(),
        load_ct_s,
        segmentation_s: timing("segmentation"),
        model_s: timing("model"),
        scene_s,
        field_sampler_s,
        total_s: start.elapsed().as_secs_f64(),
        peak_rss_bytes: peak_reset.then(peak_rss_bytes).flatten(),
        wall_surface_plane_nodes: outcome.model.report.wall_surface_plane_nodes,
    };
    let case = Case {
        scene,
        sampler,
        material,
    };
    Ok((case, build))
}

fn bench_cycle(
    case: &Case,
    trace: &BreathingTrace,
    settings: &MotionSettings,
    repeats: usize,
) -> Result<CycleTiming> {
    let rest_volume_ml = case
        .scene
        .mesh
        .enclosed_volume_m3(&case.scene.mesh.rest_positions_m)
        * 1e6;
    let compliance = elastic_compliance_ml_per_pa(rest_volume_ml, &case.material);
    let t = Instant::now();
    drop(BreathingDriver::new(
        &case.scene,
        REFERENCE_PRESSURE_PA,
        compliance,
        settings.solver.clone(),
    )?);
    let solver_setup_s = t.elapsed().as_secs_f64();

    let rss_before = current_rss_bytes();
    let peak_reset = reset_peak_rss();
    let cpu_before = process_cpu_s();
    let mut times = Vec::with_capacity(repeats);
    let mut last: Option<MotionReport> = None;
    for _ in 0..repeats {
        drop(last.take());
        let t = Instant::now();
        let report = run_motion(&case.scene, &case.material, trace, settings, &mut |_, _| {
            Ok(())
        })?;
        times.push(t.elapsed().as_secs_f64());
        last = Some(report);
    }
    let peak = peak_rss_bytes();
    let cpu_per_cycle_s = cpu_before
        .zip(process_cpu_s())
        .map(|(b, a)| (a - b) / repeats as f64);
    let report = last.ok_or_else(|| Error::argument("motion benchmark", "no cycle ran"))?;
    let time = TimeStats::new(&times);
    let frames = report.frames.len();
    let keys = report.keyframes.as_ref();
    Ok(CycleTiming {
        frames,
        time,
        per_phase_s: time.median_s / frames.max(1) as f64,
        cpu_per_cycle_s,
        solver_setup_s,
        keys: keys.map_or(0, |k| k.keys),
        key_solves: keys.map_or(0, |k| k.solves),
        key_solve_time_s: keys.map_or(0.0, |k| k.solve_time_s),
        key_measured_error_mm: keys.and_then(|k| k.measured_error_mm).unwrap_or(f64::NAN),
        frame_wall_s: report.frames.iter().map(|f| f.wall_time_s).collect(),
        tidal_volume_ml: report.tidal_volume_ml,
        rest_volume_ml: report.rest_volume_ml,
        max_volume_error_ml: report.max_volume_error_ml,
        rss_before_bytes: rss_before,
        peak_rss_bytes: peak,
        peak_reset,
    })
}

/// The frames' target volumes and the volume tolerance `run_motion` derives from them.
fn frame_targets(trace: &BreathingTrace, settings: &MotionSettings) -> Result<(Vec<f64>, f64)> {
    let targets: Vec<f64> = settings
        .instants
        .times(trace)?
        .iter()
        .map(|&t| trace.volume_at(t))
        .collect();
    let (lo, hi) = targets
        .iter()
        .fold((f64::MAX, f64::MIN), |(a, b), &v| (a.min(v), b.max(v)));
    let tolerance = (settings.volume_tolerance_fraction * (hi - lo)).max(0.01);
    Ok((targets, tolerance))
}

fn bench_serving(
    case: &Case,
    trace: &BreathingTrace,
    settings: &MotionSettings,
    repeats: usize,
) -> Result<(FieldServing, VolumeKeyframes)> {
    let (targets, volume_tolerance_ml) = frame_targets(trace, settings)?;
    let scene = &case.scene;
    let rest_volume_ml = scene.mesh.enclosed_volume_m3(&scene.mesh.rest_positions_m) * 1e6;
    let t = Instant::now();
    let mut driver = BreathingDriver::new(
        scene,
        REFERENCE_PRESSURE_PA,
        elastic_compliance_ml_per_pa(rest_volume_ml, &case.material),
        settings.solver.clone(),
    )?;
    // The chest wall scaled as `run_motion` scales it.
    driver.share_volume_with_imposed_motion(settings.rib_cage_share)?;
    // The same tolerances as `run_motion`, so these are the keys the cycle served from.
    let keys = VolumeKeyframes::build(
        &mut driver,
        &targets,
        settings.interpolation_tolerance_mm,
        volume_tolerance_ml * 0.2,
    )?;
    let key_build_s = t.elapsed().as_secs_f64();
    let rest = &scene.mesh.rest_positions_m;
    let mut positions = rest.clone();
    let mut field_mm = vec![[0.0f32; 3]; case.sampler.geometry().voxel_count()];
    let mut field_times = Vec::with_capacity(repeats);
    let mut node_times = Vec::with_capacity(repeats);
    // One untimed pass so first-touch page faults of the field buffer are not timed.
    for &v in &targets {
        keys.positions_at(rest, v, &mut positions);
        case.sampler
            .sample_mm(&scene.mesh, &positions, &mut field_mm);
    }
    let mut checksum = 0.0f64;
    for _ in 0..repeats {
        let t = Instant::now();
        for &v in &targets {
            keys.positions_at(rest, v, &mut positions);
        }
        node_times.push(t.elapsed().as_secs_f64());
        checksum += positions[0].x;
        let t = Instant::now();
        for &v in &targets {
            keys.positions_at(rest, v, &mut positions);
            case.sampler
                .sample_mm(&scene.mesh, &positions, &mut field_mm);
        }
        field_times.push(t.elapsed().as_secs_f64());
        checksum += f64::from(field_mm[field_mm.len() / 2][0]);
    }
    if !checksum.is_finite() {
        return Err(Error::InvalidModel(
            "served positions or fields are not finite".into(),
        ));
    }
    let fields_time = TimeStats::new(&field_times);
    let nodes_time = TimeStats::new(&node_times);
    let n = targets.len() as f64;
    let serving = FieldServing {
        key_build_s,
        keys: keys.report.keys,
        final_level_newton_iterations: keys.states.iter().map(|s| s.newton_iterations).sum(),
        final_level_linear_iterations: keys.states.iter().map(|s| s.linear_iterations).sum(),
        fields: targets.len(),
        voxels_per_field: field_mm.len(),
        fields_time,
        fields_per_s: n / fields_time.median_s,
        nodes_time,
        node_states_per_s: n / nodes_time.median_s,
    };
    Ok((serving, keys))
}

fn bench_accuracy(
    case: &Case,
    keys: &VolumeKeyframes,
    trace: &BreathingTrace,
    settings: &MotionSettings,
) -> Result<InterpolationAccuracy> {
    let scene = &case.scene;
    let mut interpolated: Vec<Vec<V3>> = Vec::new();
    let interp = run_motion(scene, &case.material, trace, settings, &mut |_, x| {
        interpolated.push(x.to_vec());
        Ok(())
    })?;
    let voxels = case.sampler.geometry().voxel_count();
    let mut field_a = vec![[0.0f32; 3]; voxels];
    let mut field_b = vec![[0.0f32; 3]; voxels];
    let rest = &scene.mesh.rest_positions_m;
    let mut at_direct_volume = rest.clone();
    let mut differences: Vec<[f64; 3]> = Vec::with_capacity(interpolated.len());
    // The direct solves meet their volumes 10× tighter than the run's 0.5 % of tidal: a
    // direct solve that stops 2.5 mL short is a different state, and the difference would be
    // the volume driver's tolerance rather than the interpolation error being measured.
    let direct_settings = MotionSettings {
        solve_every_frame: true,
        volume_tolerance_fraction: 0.1 * settings.volume_tolerance_fraction,
        ..settings.clone()
    };
    let direct = run_motion(
        scene,
        &case.material,
        trace,
        &direct_settings,
        &mut |f, x| {
            let a = interpolated.get(f.index).ok_or_else(|| {
                Error::InvalidModel(format!("direct frame {} has no interpolated twin", f.index))
            })?;
            let node = a
                .iter()
                .zip(x)
                .map(|(p, q)| (p - q).norm())
                .fold(0.0, f64::max)
                * 1e3;
            case.sampler.sample_mm(&scene.mesh, a, &mut field_a);
            case.sampler.sample_mm(&scene.mesh, x, &mut field_b);
            let field = field_a
                .iter()
                .zip(&field_b)
                .map(|(p, q)| {
                    let d = [p[0] - q[0], p[1] - q[1], p[2] - q[2]];
                    f64::from(d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt()
                })
                .fold(0.0, f64::max);
            // The direct solve meets its volume only within the driver's tolerance: the keys
            // evaluated at the volume it reached isolate the interpolation error itself.
            keys.positions_at(rest, f.simulated_volume_ml, &mut at_direct_volume);
            let same_volume = at_direct_volume
                .iter()
                .zip(x)
                .map(|(p, q)| (p - q).norm())
                .fold(0.0, f64::max)
                * 1e3;
            differences.push([node, field, same_volume]);
            Ok(())
        },
    )?;
    let frames: Vec<FrameAccuracy> = interp
        .frames
        .iter()
        .zip(&direct.frames)
        .zip(&differences)
        .map(|((a, b), &[node, field, same_volume])| FrameAccuracy {
            index: a.index,
            time_s: a.time_s,
            target_volume_ml: a.target_volume_ml,
            interpolated_volume_ml: a.simulated_volume_ml,
            direct_volume_ml: b.simulated_volume_ml,
            node_difference_mm: node,
            field_difference_mm: field,
            same_volume_node_difference_mm: same_volume,
            direct_solves: b.solves,
            direct_newton_iterations: b.newton_iterations,
            direct_linear_iterations: b.linear_iterations,
            direct_wall_s: b.wall_time_s,
        })
        .collect();
    let max_of = |f: &dyn Fn(&FrameAccuracy) -> f64| frames.iter().map(f).fold(0.0, f64::max);
    Ok(InterpolationAccuracy {
        max_node_difference_mm: max_of(&|f| f.node_difference_mm),
        max_field_difference_mm: max_of(&|f| f.field_difference_mm),
        max_same_volume_node_difference_mm: max_of(&|f| f.same_volume_node_difference_mm),
        max_interpolated_volume_error_ml: max_of(&|f| {
            (f.interpolated_volume_ml - f.target_volume_ml).abs()
        }),
        max_direct_volume_error_ml: max_of(&|f| (f.direct_volume_ml - f.target_volume_ml).abs()),
        tidal_volume_ml: interp.tidal_volume_ml,
        interpolated_cycle_s: interp.wall_time_s,
        direct_cycle_s: direct.wall_time_s,
        frames,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cycle_targets_follow_the_issue() {
        assert_eq!(cycle_target_s(8.0), Some(CYCLE_TARGET_8MM_S));
        assert_eq!(cycle_target_s(4.0), Some(CYCLE_TARGET_4MM_S));
        assert_eq!(cycle_target_s(6.0), None);
    }

    #[test]
    fn a_failed_cycle_is_reported_as_a_failure_with_its_text() {
        let entry = ElementSizeBench {
            element_size_mm: 4.0,
            cycle_target_s: cycle_target_s(4.0),
            build: Outcome::Skipped("not run".into()),
            cycle: Outcome::Failed("solving the key volumes: did not converge".into()),
            wall_surface: Outcome::Failed("element 5430 is inverted".into()),
            serving: Outcome::Skipped("the cycle did not run to the end".into()),
            accuracy: Outcome::Skipped("the cycle did not run to the end".into()),
        };
        let mut md = String::new();
        entry.write_markdown(&mut md);
        assert!(
            md.contains("**Cycle FAILED**: solving the key volumes: did not converge"),
            "{md}"
        );
        assert!(
            md.contains("**Curved-wall cycle FAILED**: element 5430 is inverted"),
            "{md}"
        );
        let json = serde_json::to_string(&entry).unwrap();
        assert!(json.contains("\"failed\""), "{json}");
    }
}
