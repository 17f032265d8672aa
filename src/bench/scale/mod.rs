//! Run time against error over element sizes (`lungmotion bench --suite scale`): for each
//! case (the CIP chest CT, the full-resolution POPI CT) and each element size from coarse to
//! fine, the model is built and the default 10-phase cycle of a 500 mL breath is run as
//! `lungmotion run` runs it; measured are the build and cycle times, the peak memory of
//! both, the solver's effort, and the error of the end-inhale displacement field against the
//! finest size that completed (mean, p95 and max of |Δu| over the CT's lung voxels, read on
//! the voxel grid both fields share). Each size has a wall-clock budget: a size that exceeds
//! it is stopped through the solver's cancel flag and recorded as such, and finer sizes of
//! that case still run (a finer mesh may converge where a coarser one stalls).
//!
//! The cycle-time exponent is the least-squares slope of log(time) against log(elements)
//! over the sizes that completed; 1 means time per element is constant.
//!
//! Optionally CalculiX solves the CIP end-inhale frame at one size (the reference nobody
//! here wrote), through [`crate::validation::lung_calculix`].

mod report;

use std::path::Path;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use serde::Serialize;

use super::Outcome;
use crate::breathing::{BreathingTrace, LujanBreathing};
use crate::ingest::lung_model::LungModelSettings;
use crate::ingest::pipeline::{ingest_scan, IngestSettings};
use crate::ingest::scan::load_ct;
use crate::math::V3;
use crate::motion::{
    run_motion, run_scene, MotionSettings, WallMotion, PHYSIOLOGICAL_RIB_CAGE_SHARE,
};
use crate::outputs::displacement_field::{FieldGrid, FieldSampler};
use crate::process::{load_average, peak_rss_bytes, process_cpu_s, reset_peak_rss};
use crate::simulation::{QuasiStaticSettings, QuasiStaticSolver};
use crate::validation::lung_calculix::{compare_end_inhale_with_calculix, LungCalculixSettings};
use crate::{Error, Result};

pub use report::TRADE_OFF_PNG;

/// Largest number of lung voxels kept per field for the error (evenly strided beyond it).
const MAX_ERROR_VOXELS: usize = 2_000_000;

/// One CT and the element sizes to run on it.
#[derive(Debug, Clone, Serialize)]
pub struct ScaleCase {
    /// Short name (`CIP`, `POPI`).
    pub name: String,
    /// The CT file or DICOM directory.
    pub ct: std::path::PathBuf,
    /// Element sizes, mm, coarsest first.
    pub element_sizes_mm: Vec<f64>,
}

/// What to run.
#[derive(Debug, Clone, Serialize)]
pub struct ScaleBenchOptions {
    /// The cases.
    pub cases: Vec<ScaleCase>,
    /// Wall-clock budget of each size's cycle, s.
    pub budget_s: f64,
    /// Element size at which CalculiX solves the CIP end-inhale frame (none: skipped).
    pub calculix_element_size_mm: Option<f64>,
}

impl ScaleBenchOptions {
    /// Every size from 16 mm to 2 mm on CIP and on POPI, 10 minutes each, CalculiX at 8 mm;
    /// cases whose data are absent are left out.
    pub fn full() -> Self {
        let sizes = vec![16.0, 12.0, 10.0, 8.0, 6.0, 5.0, 4.0, 3.0, 2.0];
        ScaleBenchOptions {
            cases: cases(&sizes, &sizes),
            budget_s: 600.0,
            calculix_element_size_mm: Some(8.0),
        }
    }

    /// A smoke run of the harness: CIP at 16 and 12 mm, one minute each, no CalculiX.
    pub fn quick() -> Self {
        ScaleBenchOptions {
            cases: cases(&[16.0, 12.0], &[]),
            budget_s: 60.0,
            calculix_element_size_mm: None,
        }
    }
}

fn cases(cip_mm: &[f64], popi_mm: &[f64]) -> Vec<ScaleCase> {
    let mut out = Vec::new();
    if let Some(dir) = crate::datasets::cip_chest_ct64() {
        out.push(ScaleCase {
            name: "CIP".into(),
            ct: dir.join("ct-64.nrrd"),
            element_sizes_mm: cip_mm.to_vec(),
        });
    }
    if let Some(dir) = crate::datasets::popi_chest_ct().filter(|_| !popi_mm.is_empty()) {
        out.push(ScaleCase {
            name: "POPI".into(),
            ct: dir,
            element_sizes_mm: popi_mm.to_vec(),
        });
    }
    out
}

/// Error of one end-inhale field against the case's reference, over lung voxels.
#[derive(Debug, Clone, Serialize)]
pub struct FieldError {
    /// Element size of the reference field, mm.
    pub reference_element_size_mm: f64,
    /// Lung voxels compared.
    pub voxels: usize,
    /// Mean |Δu|, mm.
    pub mean_mm: f64,
    /// 95th percentile of |Δu|, mm.
    pub p95_mm: f64,
    /// Largest |Δu|, mm.
    pub max_mm: f64,
}

/// One element size of one case.
#[derive(Debug, Clone, Serialize)]
pub struct SizePoint {
    /// Element edge, mm.
    pub element_size_mm: f64,
    /// Elements of both lungs (0 when the model could not be built).
    pub elements: usize,
    /// Nodes of both lungs.
    pub nodes: usize,
    /// Segmentation and model, s.
    pub build_s: f64,
    /// The cycle.
    pub cycle: Outcome<CycleRun>,
    /// End-inhale error against the finest completed size.
    pub error: Outcome<FieldError>,
    /// The multigrid on its own operator, apart from any load.
    pub preconditioner: Outcome<PreconditionerCheck>,
}

/// GMRES preconditioned by the multigrid on the operator the multigrid approximates (the
/// projected rest stiffness) from a fixed pseudo-random right-hand side: the preconditioner's
/// quality alone, which the cycle's Krylov count exceeds where the tangent at the deformed
/// state departs from the rest stiffness.
#[derive(Debug, Clone, Serialize)]
pub struct PreconditionerCheck {
    /// Relative residual asked for.
    pub rtol: f64,
    /// GMRES iterations taken.
    pub iterations: usize,
    /// Relative residual reached.
    pub relative_residual: f64,
    /// Wall time of the solver's set-up and the GMRES solve, s.
    pub seconds: f64,
}

/// Residual reduction of the preconditioner check: eight digits.
const PRECONDITIONER_CHECK_RTOL: f64 = 1e-8;

/// One 10-phase cycle.
#[derive(Debug, Clone, Serialize)]
pub struct CycleRun {
    /// Wall time of the cycle (solver set-up, key solves, frames), s.
    pub cycle_s: f64,
    /// CPU time of the cycle (all threads), s.
    pub cpu_s: Option<f64>,
    /// Cycle time per element, µs.
    pub per_element_us: f64,
    /// Peak resident memory of the build and the cycle, bytes.
    pub peak_rss_bytes: Option<u64>,
    /// Key volumes.
    pub keys: usize,
    /// Equilibrium solves.
    pub solves: usize,
    /// Newton iterations.
    pub newton_iterations: usize,
    /// Krylov iterations.
    pub linear_iterations: usize,
    /// Largest node displacement of the end-inhale frame, mm.
    pub end_inhale_max_displacement_mm: f64,
}

/// Power law time ∝ elements^exponent over the completed sizes.
#[derive(Debug, Clone, Serialize)]
pub struct ScalingFit {
    /// Least-squares slope of log(cycle time) against log(elements).
    pub exponent: f64,
    /// Sizes in the fit.
    pub sizes: usize,
    /// Coarsest and finest element size in the fit, mm.
    pub range_mm: [f64; 2],
}

/// Everything measured on one case.
#[derive(Debug, Clone, Serialize)]
pub struct CaseScale {
    /// Case name.
    pub name: String,
    /// CT grid.
    pub ct_dims: [usize; 3],
    /// Per size, coarsest first.
    pub sizes: Vec<SizePoint>,
    /// Cycle-time exponent.
    pub scaling: Option<ScalingFit>,
}

/// CalculiX's end-inhale frame against ours at one size.
#[derive(Debug, Clone, Serialize)]
pub struct CalculixPoint {
    /// Element size, mm.
    pub element_size_mm: f64,
    /// Mean |Δu| over nodes, mm.
    pub mean_mm: f64,
    /// 95th percentile, mm.
    pub p95_mm: f64,
    /// Largest, mm.
    pub max_mm: f64,
    /// Our solve of that frame, s.
    pub ours_s: f64,
    /// CalculiX's solve, s.
    pub calculix_s: f64,
}

/// The scale benchmark report.
#[derive(Debug, Clone, Serialize)]
pub struct ScaleBenchReport {
    /// Options used.
    pub options: ScaleBenchOptions,
    /// Logical cores.
    pub cores: usize,
    /// Load averages at the start.
    pub load_average_at_start: Option<[f64; 3]>,
    /// Tidal volume of the trace, mL.
    pub tidal_volume_ml: f64,
    /// Per case.
    pub cases: Vec<CaseScale>,
    /// CalculiX on CIP, if asked for.
    pub calculix: Outcome<CalculixPoint>,
}

/// End-inhale field of one size on the lung voxels (strided), for the error.
struct EndInhale {
    element_size_mm: f64,
    u_mm: Vec<[f32; 3]>,
}

/// Runs the suite; writes nothing (see [`ScaleBenchReport::write`]).
pub fn run_scale_bench(opts: &ScaleBenchOptions) -> Result<ScaleBenchReport> {
    if !(opts.budget_s > 0.0 && opts.budget_s.is_finite()) {
        return Err(Error::argument(
            "scale benchmark",
            format!(
                "the budget per size must be positive seconds, got {}",
                opts.budget_s
            ),
        ));
    }
    let curve = LujanBreathing::default();
    let trace = curve.trace(8.0, 25.0)?;
    let load_average_at_start = load_average();
    let mut cases = Vec::new();
    for case in &opts.cases {
        cases.push(run_case(case, &trace, opts.budget_s)?);
    }
    let calculix = match opts.calculix_element_size_mm {
        None => Outcome::Skipped("not asked".into()),
        Some(_) if crate::validation::calculix::ccx_path().is_none() => {
            Outcome::Skipped("CalculiX (ccx) not installed".into())
        }
        Some(h) => Outcome::from_result(calculix_point(h)),
    };
    Ok(ScaleBenchReport {
        options: opts.clone(),
        cores: rayon::current_num_threads(),
        load_average_at_start,
        tidal_volume_ml: curve.tidal_volume_ml,
        cases,
        calculix,
    })
}

fn run_case(case: &ScaleCase, trace: &BreathingTrace, budget_s: f64) -> Result<CaseScale> {
    let scan = load_ct(&case.ct)?;
    let ct_dims = scan.ct.geometry.dims;
    let mut sizes = Vec::new();
    let mut fields: Vec<Option<EndInhale>> = Vec::new();
    for &h in &case.element_sizes_mm {
        crate::process::return_freed_memory();
        let peak_reset = reset_peak_rss();
        eprintln!("lungmotion: scale: {} at {h} mm", case.name);
        let (point, field) = run_size(&scan, h, trace, budget_s, peak_reset);
        sizes.push(point);
        fields.push(field);
    }
    // The reference is the finest size that completed.
    let reference = fields
        .iter()
        .flatten()
        .min_by(|a, b| a.element_size_mm.total_cmp(&b.element_size_mm));
    for (point, field) in sizes.iter_mut().zip(&fields) {
        point.error = match (reference, field) {
            (None, _) => Outcome::Skipped("no size completed".into()),
            (Some(_), None) => Outcome::Skipped("the cycle did not complete".into()),
            (Some(r), Some(f)) if std::ptr::eq(r, f) => {
                Outcome::Skipped("the reference (finest completed size)".into())
            }
            (Some(r), Some(f)) => Outcome::Measured(field_error(f, r)),
        };
    }
    let scaling = scaling_fit(&sizes);
    Ok(CaseScale {
        name: case.name.clone(),
        ct_dims,
        sizes,
        scaling,
    })
}

fn run_size(
    scan: &crate::ingest::scan::LoadedScan,
    h: f64,
    trace: &BreathingTrace,
    budget_s: f64,
    peak_reset: bool,
) -> (SizePoint, Option<EndInhale>) {
    let mut point = SizePoint {
        element_size_mm: h,
        elements: 0,
        nodes: 0,
        build_s: 0.0,
        cycle: Outcome::Skipped("the model could not be built".into()),
        error: Outcome::Skipped("not measured".into()),
        preconditioner: Outcome::Skipped("the model could not be built".into()),
    };
    let t = Instant::now();
    let model_settings = LungModelSettings {
        element_size_mm: h,
        ..LungModelSettings::default()
    };
    let material = model_settings.material;
    let built = ingest_scan(
        scan,
        &IngestSettings {
            model: model_settings,
            ..IngestSettings::default()
        },
    )
    .and_then(|outcome| {
        // As `lungmotion run` builds it by default (the chest wall makes a third of each breath).
        let scene = run_scene(&outcome.model, &WallMotion::default())?;
        let sampler = FieldSampler::new(
            &outcome.segmentation.lungs,
            &scene.mesh,
            &outcome.model.element_lung,
            FieldGrid::LungBox,
        )?;
        Ok((outcome.segmentation.lungs, scene, sampler))
    });
    point.build_s = t.elapsed().as_secs_f64();
    let (lungs, scene, sampler) = match built {
        Ok(b) => b,
        Err(e) => {
            point.cycle = Outcome::Failed(format!("building the model: {e}"));
            return (point, None);
        }
    };
    point.elements = scene.mesh.elements.len();
    point.nodes = scene.node_count();

    let cancel: crate::simulation::CancelFlag = Arc::new(AtomicBool::new(false));
    let settings = MotionSettings {
        cancel: Some(cancel.clone()),
        rib_cage_share: PHYSIOLOGICAL_RIB_CAGE_SHARE,
        ..MotionSettings::default()
    };
    let done = Arc::new(AtomicBool::new(false));
    let watchdog = {
        let (cancel, done) = (cancel.clone(), done.clone());
        std::thread::spawn(move || {
            let deadline = Instant::now() + Duration::from_secs_f64(budget_s);
            while !done.load(Ordering::Relaxed) {
                if Instant::now() >= deadline {
                    cancel.store(true, Ordering::Relaxed);
                    return;
                }
                std::thread::sleep(Duration::from_millis(100));
            }
        })
    };
    let cpu_before = process_cpu_s();
    let t = Instant::now();
    let mut end_inhale: (f64, Vec<V3>) = (f64::MIN, Vec::new());
    let result = run_motion(&scene, &material, trace, &settings, &mut |f, x| {
        if f.target_volume_ml > end_inhale.0 {
            end_inhale = (f.target_volume_ml, x.to_vec());
        }
        Ok(())
    });
    let cycle_s = t.elapsed().as_secs_f64();
    done.store(true, Ordering::Relaxed);
    let _ = watchdog.join();
    // After the cycle, so its set-up counts in neither the cycle's time nor its memory.
    point.preconditioner = preconditioner_check(&scene);
    let report = match result {
        Ok(r) => r,
        Err(e) if cancel.load(Ordering::Relaxed) => {
            point.cycle = Outcome::Failed(format!(
                "stopped by the {budget_s:.0} s budget after {cycle_s:.1} s ({e})"
            ));
            return (point, None);
        }
        Err(e) => {
            point.cycle = Outcome::Failed(format!("failed after {cycle_s:.1} s: {e}"));
            return (point, None);
        }
    };
    let keys = report.keyframes.as_ref();
    let frames = &report.frames;
    point.cycle = Outcome::Measured(CycleRun {
        cycle_s,
        cpu_s: cpu_before.zip(process_cpu_s()).map(|(b, a)| a - b),
        per_element_us: cycle_s / point.elements.max(1) as f64 * 1e6,
        peak_rss_bytes: peak_reset.then(peak_rss_bytes).flatten(),
        keys: keys.map_or(0, |k| k.keys),
        solves: keys.map_or_else(|| frames.iter().map(|f| f.solves).sum(), |k| k.solves),
        newton_iterations: keys.map_or_else(
            || frames.iter().map(|f| f.newton_iterations).sum(),
            |k| k.newton_iterations,
        ),
        linear_iterations: keys.map_or_else(
            || frames.iter().map(|f| f.linear_iterations).sum(),
            |k| k.linear_iterations,
        ),
        end_inhale_max_displacement_mm: frames
            .iter()
            .map(|f| f.max_displacement_mm)
            .fold(0.0, f64::max),
    });
    let field = lung_voxel_field(&lungs, &sampler, &scene.mesh, &end_inhale.1);
    (
        point,
        Some(EndInhale {
            element_size_mm: h,
            u_mm: field,
        }),
    )
}

/// [`PreconditionerCheck`] on `scene` with the solver's default settings.
fn preconditioner_check(scene: &crate::simulation::Scene) -> Outcome<PreconditionerCheck> {
    let t = Instant::now();
    let mut solver = match QuasiStaticSolver::new(scene, QuasiStaticSettings::default()) {
        Ok(s) => s,
        Err(e) => return Outcome::Failed(format!("solver set-up: {e}")),
    };
    match solver.preconditioner_iterations(PRECONDITIONER_CHECK_RTOL) {
        Some((iterations, relative_residual)) => Outcome::Measured(PreconditionerCheck {
            rtol: PRECONDITIONER_CHECK_RTOL,
            iterations,
            relative_residual,
            seconds: t.elapsed().as_secs_f64(),
        }),
        None => Outcome::Skipped("block Jacobi (the mesh is not on a lattice)".into()),
    }
}

/// The field on the CT's lung voxels (every `stride`-th beyond [`MAX_ERROR_VOXELS`]), in the
/// CT's voxel order: the same voxels for every element size of a case, since the
/// segmentation does not depend on the element size.
fn lung_voxel_field(
    lungs: &crate::volume::Volume<u8>,
    sampler: &FieldSampler,
    mesh: &crate::model::HexMesh,
    positions_m: &[V3],
) -> Vec<[f32; 3]> {
    let dims = sampler.geometry().dims;
    let mut grid = vec![[0.0f32; 3]; dims[0] * dims[1] * dims[2]];
    sampler.sample_mm(mesh, positions_m, &mut grid);
    let start = sampler.start();
    let voxels = lungs.voxels();
    let stride = sampler.sampled_voxels().div_ceil(MAX_ERROR_VOXELS).max(1);
    let mut out = Vec::with_capacity(sampler.sampled_voxels() / stride + 1);
    let mut seen = 0usize;
    for k in 0..dims[2] {
        for j in 0..dims[1] {
            for i in 0..dims[0] {
                if voxels[[start[2] + k, start[1] + j, start[0] + i]] == 0 {
                    continue;
                }
                if seen.is_multiple_of(stride) {
                    out.push(grid[(k * dims[1] + j) * dims[0] + i]);
                }
                seen += 1;
            }
        }
    }
    out
}

fn field_error(field: &EndInhale, reference: &EndInhale) -> FieldError {
    let mut d: Vec<f64> = field
        .u_mm
        .iter()
        .zip(&reference.u_mm)
        .map(|(a, b)| {
            let v = [a[0] - b[0], a[1] - b[1], a[2] - b[2]];
            f64::from(v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt()
        })
        .collect();
    d.sort_by(f64::total_cmp);
    let n = d.len();
    FieldError {
        reference_element_size_mm: reference.element_size_mm,
        voxels: n,
        mean_mm: d.iter().sum::<f64>() / n.max(1) as f64,
        p95_mm: d
            .get((n * 95 / 100).min(n.saturating_sub(1)))
            .copied()
            .unwrap_or(0.0),
        max_mm: d.last().copied().unwrap_or(0.0),
    }
}

/// Least-squares slope of log(cycle time) against log(elements) over completed sizes.
fn scaling_fit(sizes: &[SizePoint]) -> Option<ScalingFit> {
    let pts: Vec<(f64, f64, f64)> = sizes
        .iter()
        .filter_map(|s| {
            s.cycle
                .measured()
                .map(|c| ((s.elements as f64).ln(), c.cycle_s.ln(), s.element_size_mm))
        })
        .collect();
    if pts.len() < 2 {
        return None;
    }
    let n = pts.len() as f64;
    let (mx, my) = (
        pts.iter().map(|p| p.0).sum::<f64>() / n,
        pts.iter().map(|p| p.1).sum::<f64>() / n,
    );
    let sxy: f64 = pts.iter().map(|p| (p.0 - mx) * (p.1 - my)).sum();
    let sxx: f64 = pts.iter().map(|p| (p.0 - mx).powi(2)).sum();
    let sizes_mm = pts.iter().map(|p| p.2);
    Some(ScalingFit {
        exponent: sxy / sxx,
        sizes: pts.len(),
        range_mm: [
            sizes_mm.clone().fold(f64::MIN, f64::max),
            sizes_mm.fold(f64::MAX, f64::min),
        ],
    })
}

fn calculix_point(h: f64) -> Result<CalculixPoint> {
    // The run's default material, CalculiX following the same law (St Venant–Kirchhoff for
    // the springs alone, NEO HOOKE for the neo-Hookean correction).
    let settings = LungCalculixSettings {
        element_size_mm: h,
        material: crate::model::Material::default(),
        ..LungCalculixSettings::default()
    };
    let r = compare_end_inhale_with_calculix(&settings)?;
    let first = r
        .calculix
        .first()
        .ok_or_else(|| Error::argument("scale benchmark", "CalculiX returned no solve"))?;
    Ok(CalculixPoint {
        element_size_mm: h,
        mean_mm: first.ours_vs_calculix.mean_mm,
        p95_mm: first.ours_vs_calculix.p95_mm,
        max_mm: first.ours_vs_calculix.max_mm,
        ours_s: r.ours.pressure_solve_wall_time_s,
        calculix_s: first.wall_time_s,
    })
}

impl ScaleBenchReport {
    /// Writes the time–error plot as [`TRADE_OFF_PNG`] into `dir`.
    pub fn write_plot(&self, dir: &Path) -> Result<()> {
        report::write_plot(self, dir)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn point(h: f64, elements: usize, cycle_s: f64) -> SizePoint {
        SizePoint {
            element_size_mm: h,
            elements,
            nodes: elements,
            build_s: 0.0,
            cycle: Outcome::Measured(CycleRun {
                cycle_s,
                cpu_s: None,
                per_element_us: 0.0,
                peak_rss_bytes: None,
                keys: 0,
                solves: 0,
                newton_iterations: 0,
                linear_iterations: 0,
                end_inhale_max_displacement_mm: 0.0,
            }),
            error: Outcome::Skipped(String::new()),
            preconditioner: Outcome::Skipped(String::new()),
        }
    }

    #[test]
    fn the_exponent_of_a_power_law_is_recovered_and_failed_sizes_are_left_out() {
        let mut sizes = vec![
            point(16.0, 1000, 0.5 * 1000f64.powf(1.3)),
            point(8.0, 8000, 0.5 * 8000f64.powf(1.3)),
            point(4.0, 64000, 0.5 * 64000f64.powf(1.3)),
        ];
        let mut failed = point(2.0, 512_000, 1.0);
        failed.cycle = Outcome::Failed("budget".into());
        sizes.push(failed);
        let fit = scaling_fit(&sizes).unwrap();
        assert!((fit.exponent - 1.3).abs() < 1e-9, "{}", fit.exponent);
        assert_eq!((fit.sizes, fit.range_mm), (3, [16.0, 4.0]));
        assert!(scaling_fit(&sizes[..1]).is_none());
    }

    #[test]
    fn field_error_statistics_over_voxels() {
        let reference = EndInhale {
            element_size_mm: 2.0,
            u_mm: vec![[0.0; 3]; 100],
        };
        let field = EndInhale {
            element_size_mm: 8.0,
            u_mm: (0..100)
                .map(|i| [0.0, 3.0 * i as f32 / 5.0, 4.0 * i as f32 / 5.0])
                .collect(),
        };
        let e = field_error(&field, &reference);
        assert_eq!((e.voxels, e.reference_element_size_mm), (100, 2.0));
        let close = |a: f64, b: f64| (a - b).abs() < 1e-4;
        assert!(
            close(e.mean_mm, 49.5) && close(e.max_mm, 99.0) && close(e.p95_mm, 95.0),
            "{e:?}"
        );
    }

    #[test]
    fn a_bad_budget_is_refused_by_value() {
        let mut o = ScaleBenchOptions::quick();
        o.budget_s = -1.0;
        let e = run_scale_bench(&o).unwrap_err().to_string();
        assert!(e.contains("got -1"), "{e}");
    }
}
