//! The pressurised block solved quasi-statically: timings, scaling with size, and the
//! quasi-static methods compared on one block.

use std::time::Instant;

use super::{QuasiStaticBench, ScalingFit, SolverComparison, BENCH_ELEMENT_EDGE_M};
use crate::bench::{Outcome, TimeStats};
use crate::math::V3;
use crate::model::Material;
use crate::process::{current_rss_bytes, peak_rss_bytes, reset_peak_rss};
use crate::simulation::cases::symmetric_block_under_pressure;
use crate::simulation::{QuasiStaticSettings, QuasiStaticSolver, Scene};
use crate::{Error, Result};

pub(super) fn block_scene(n: usize, pressure_pa: f64) -> Result<(Scene, f64)> {
    let start = Instant::now();
    let scene =
        symmetric_block_under_pressure([n; 3], BENCH_ELEMENT_EDGE_M, Material::LUNG, pressure_pa)?;
    Ok((scene, start.elapsed().as_secs_f64()))
}

/// Set-up plus solve, `runs` times; returns the positions, the report of the median run and
/// the timing statistics (set-up, solve, total).
pub(super) fn time_solves(
    scene: &Scene,
    runs: usize,
) -> Result<(Vec<V3>, crate::simulation::SolveReport, [TimeStats; 3])> {
    let mut samples = Vec::with_capacity(runs);
    let mut last = None;
    for _ in 0..runs {
        let start = Instant::now();
        let mut solver = QuasiStaticSolver::new(scene, QuasiStaticSettings::default())?;
        let setup = start.elapsed().as_secs_f64();
        let (x, rep) = solver.solve(None)?;
        let total = start.elapsed().as_secs_f64();
        samples.push((total, setup, rep.clone()));
        last = Some(x);
    }
    let totals: Vec<f64> = samples.iter().map(|s| s.0).collect();
    let setups: Vec<f64> = samples.iter().map(|s| s.1).collect();
    let solves: Vec<f64> = samples.iter().map(|s| s.0 - s.1).collect();
    let total = TimeStats::new(&totals);
    let median_run = samples
        .iter()
        .min_by(|a, b| {
            (a.0 - total.median_s)
                .abs()
                .total_cmp(&(b.0 - total.median_s).abs())
        })
        .map(|s| s.2.clone())
        .unwrap_or_default();
    let x = last.ok_or_else(|| Error::InvalidModel("no quasi-static run".into()))?;
    Ok((
        x,
        median_run,
        [TimeStats::new(&setups), TimeStats::new(&solves), total],
    ))
}

pub(super) fn quasistatic_block(
    n: usize,
    pressure_pa: f64,
    runs: usize,
) -> Result<QuasiStaticBench> {
    let (scene, scene_build_s) = block_scene(n, pressure_pa)?;
    let rss_before = current_rss_bytes();
    reset_peak_rss();
    let (x, rep, [setup, solve, total]) = time_solves(&scene, runs)?;
    let peak = peak_rss_bytes();
    let mesh = &scene.mesh;
    let v0 = mesh.enclosed_volume_m3(&mesh.rest_positions_m);
    let v1 = mesh.enclosed_volume_m3(&x);
    let max_displacement_m = scene
        .displacements(&x)
        .iter()
        .map(|u| u.norm())
        .fold(0.0, f64::max);
    Ok(QuasiStaticBench {
        cells_per_edge: n,
        elements: mesh.element_count(),
        nodes: mesh.node_count(),
        scene_build_s,
        setup,
        solve,
        total,
        newton_iterations: rep.newton_iterations,
        linear_iterations: rep.linear_iterations,
        residual: rep.residual,
        multigrid_levels: rep.multigrid_levels,
        volume_change: (v1 - v0) / v0,
        linear_volume_change: -pressure_pa / Material::LUNG.bulk_modulus_pa(),
        max_displacement_m,
        peak_extra_rss_bytes_per_element: match (rss_before, peak) {
            (Some(b), Some(p)) => Some(p.saturating_sub(b) as f64 / mesh.element_count() as f64),
            _ => None,
        },
    })
}

pub(super) fn fit_scaling(runs: &[Outcome<QuasiStaticBench>]) -> Option<ScalingFit> {
    let pts: Vec<(f64, f64, usize)> = runs
        .iter()
        .filter_map(Outcome::measured)
        .map(|q| {
            (
                (q.elements as f64).ln(),
                q.total.median_s.ln(),
                q.cells_per_edge,
            )
        })
        .collect();
    if pts.len() < 2 {
        return None;
    }
    let m = pts.len() as f64;
    let (sx, sy) = pts.iter().fold((0.0, 0.0), |(a, b), p| (a + p.0, b + p.1));
    let (mx, my) = (sx / m, sy / m);
    let sxy: f64 = pts.iter().map(|p| (p.0 - mx) * (p.1 - my)).sum();
    let sxx: f64 = pts.iter().map(|p| (p.0 - mx).powi(2)).sum();
    (sxx > 0.0).then(|| ScalingFit {
        exponent: sxy / sxx,
        cells_per_edge: pts.iter().map(|p| p.2).collect(),
    })
}

/// Newton–Krylov with multigrid, with block Jacobi, and damped explicit relaxation on the
/// same pressurised block.
pub(super) fn compare_solvers(cells: usize, pressure_pa: f64) -> Vec<Outcome<SolverComparison>> {
    use crate::simulation::{
        ExplicitIntegrator, ExplicitSettings, PreconditionerKind, QuasiStaticSettings,
        QuasiStaticSolver,
    };
    let newton = |kind: PreconditionerKind, label: &str| -> Result<SolverComparison> {
        let scene = symmetric_block_under_pressure(
            [cells; 3],
            BENCH_ELEMENT_EDGE_M,
            Material::LUNG,
            pressure_pa,
        )?;
        let start = Instant::now();
        let settings = QuasiStaticSettings {
            preconditioner: kind,
            max_linear_iterations: 5000,
            relaxation_max_steps: 0,
            ..QuasiStaticSettings::default()
        };
        let (_, r) = QuasiStaticSolver::new(&scene, settings)?.solve(None)?;
        Ok(SolverComparison {
            method: label.into(),
            elements: scene.mesh.element_count(),
            wall_time_s: start.elapsed().as_secs_f64(),
            iterations: format!(
                "{} Newton / {} Krylov",
                r.newton_iterations, r.linear_iterations
            ),
            residual: r.residual,
        })
    };
    let relaxation = || -> Result<SolverComparison> {
        let mut scene = symmetric_block_under_pressure(
            [cells; 3],
            BENCH_ELEMENT_EDGE_M,
            Material::LUNG,
            pressure_pa,
        )?;
        let start = Instant::now();
        let mut mesh = scene.mesh.clone();
        for c in &mut mesh.classes {
            *c = c.clone().with_damping_ratio(1.0);
        }
        scene =
            crate::simulation::Scene::new(mesh, scene.constraints.clone(), scene.loads.clone())?;
        let mut it = ExplicitIntegrator::new(&scene);
        let r = it.run_to_equilibrium(&ExplicitSettings {
            residual_tolerance: 1e-6,
            kinetic_energy_fraction: 1.0,
            max_steps: 2_000_000,
            ..ExplicitSettings::default()
        })?;
        Ok(SolverComparison {
            method: "explicit velocity Verlet, critical Voigt damping (dynamic relaxation)".into(),
            elements: scene.mesh.element_count(),
            wall_time_s: start.elapsed().as_secs_f64(),
            iterations: format!(
                "{} steps{}",
                r.steps,
                if r.converged { "" } else { " (not converged)" }
            ),
            residual: r.residual,
        })
    };
    vec![
        Outcome::from_result(newton(
            PreconditionerKind::Auto,
            "Newton–Krylov (GMRES), geometric multigrid V-cycle",
        )),
        Outcome::from_result(newton(
            PreconditionerKind::BlockJacobi,
            "Newton–Krylov (GMRES), block Jacobi",
        )),
        Outcome::from_result(relaxation()),
    ]
}
