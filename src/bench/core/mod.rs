//! The core benchmark (`lungmotion bench --suite core`): force-kernel throughput, memory per
//! element and per node, the quasi-static block solve, and CalculiX on the same block side by
//! side.
//!
//! Every timing is the median of repeated runs with min and max beside it, because the machine
//! is shared and noisy. Ratios (parallel speed-up, CalculiX over ours) come from measurements
//! taken in the same run, interleaved where possible, never from numbers of different runs.
//! Nothing here asserts a speed: the report states the targets and whether they were met.

mod calculix;
mod force;
mod quasistatic;
mod report;

use serde::Serialize;

use super::{cpu_model, simd_level, utc_now, MachineInfo, Outcome, TimeStats};
use crate::model::Material;
use crate::process::peak_rss_bytes;
use crate::{Error, Result};
use calculix::calculix_block;
use force::force_block;
use quasistatic::{compare_solvers, fit_scaling, quasistatic_block};

/// Edge of the cube elements of every benchmark block, metres.
pub const BENCH_ELEMENT_EDGE_M: f64 = 5e-3;
/// Damping ratio (fraction of critical) of the dampers in the with-velocities force runs.
pub const BENCH_DAMPING_RATIO: f64 = 0.1;
/// Random node displacement amplitude, as a fraction of the element edge, so springs are
/// stretched and compressed rather than at rest.
pub const BENCH_PERTURBATION: f64 = 0.05;

/// What to measure and how much.
#[derive(Debug, Clone, Serialize)]
pub struct BenchOptions {
    /// Cells per edge of the cube blocks whose force throughput is measured (n³ elements).
    pub force_block_cells: Vec<usize>,
    /// Timed force evaluations per configuration (after 2 untimed warm-ups).
    pub force_repetitions: usize,
    /// Threads of the parallel measurements; 0 means all available cores.
    pub threads: usize,
    /// Cells per edge of the blocks solved quasi-statically (empty: skip).
    pub quasistatic_block_cells: Vec<usize>,
    /// Quasi-static solves per block size (the median is reported).
    pub quasistatic_runs: usize,
    /// Pressure on the block's outer faces in pascals (negative inflates, as a lung does).
    pub pressure_pa: f64,
    /// Cells per edge of the blocks also solved by CalculiX (empty: skip). 40 takes minutes
    /// and gigabytes with NLGEOM.
    pub calculix_block_cells: Vec<usize>,
    /// Cells per edge of the block on which the quasi-static methods are compared (0: skip).
    pub solver_comparison_cells: usize,
    /// Run CalculiX with a small-strain linear step.
    pub calculix_linear: bool,
    /// Run CalculiX with a geometrically non-linear step (NLGEOM), the same physics class as
    /// ours.
    pub calculix_nlgeom: bool,
}

impl Default for BenchOptions {
    fn default() -> Self {
        BenchOptions {
            force_block_cells: vec![40, 80],
            force_repetitions: 15,
            threads: 0,
            quasistatic_block_cells: vec![20, 30, 40],
            quasistatic_runs: 3,
            pressure_pa: -20.0,
            calculix_block_cells: vec![20, 30],
            solver_comparison_cells: 20,
            calculix_linear: true,
            calculix_nlgeom: true,
        }
    }
}

impl BenchOptions {
    /// A seconds-long run on small blocks, for smoke tests of the harness (numbers meaningless).
    pub fn quick() -> Self {
        BenchOptions {
            force_block_cells: vec![8],
            force_repetitions: 3,
            threads: 0,
            quasistatic_block_cells: vec![4, 6],
            quasistatic_runs: 1,
            pressure_pa: -20.0,
            calculix_block_cells: vec![],
            solver_comparison_cells: 4,
            calculix_linear: true,
            calculix_nlgeom: false,
        }
    }
}

/// Force-evaluation throughput of one block, damping setting and thread count.
#[derive(Debug, Clone, Serialize)]
pub struct ForceThroughput {
    /// Cells per block edge.
    pub cells_per_edge: usize,
    /// Elements in the block.
    pub elements: usize,
    /// Nodes in the block.
    pub nodes: usize,
    /// Whether velocities were passed (dampers evaluated).
    pub with_velocities: bool,
    /// Threads of the rayon pool.
    pub threads: usize,
    /// Wall time per evaluation.
    pub time: TimeStats,
    /// Elements per second at the median time.
    pub elements_per_s: f64,
    /// Elements per second at the fastest time.
    pub elements_per_s_best: f64,
    /// Nanoseconds per element at the median time (wall, not CPU, time).
    pub ns_per_element: f64,
}

/// Parallel speed-up of one block and damping setting, from interleaved measurements.
#[derive(Debug, Clone, Serialize)]
pub struct ParallelSpeedup {
    /// Cells per block edge.
    pub cells_per_edge: usize,
    /// Whether velocities were passed.
    pub with_velocities: bool,
    /// Threads of the parallel pool.
    pub threads: usize,
    /// Median one-thread time over median parallel time.
    pub speedup: f64,
    /// Fastest one-thread time over fastest parallel time (least disturbed by other load).
    pub speedup_best: f64,
    /// Speed-up over thread count.
    pub efficiency: f64,
}

/// Memory of one block, counted from the data structures' capacities.
#[derive(Debug, Clone, Serialize)]
pub struct MemoryUsage {
    /// Cells per block edge.
    pub cells_per_edge: usize,
    /// Elements.
    pub elements: usize,
    /// Nodes.
    pub nodes: usize,
    /// Element arrays of the mesh (corners, class, colour lists), bytes per element.
    pub mesh_bytes_per_element: f64,
    /// Node arrays of the mesh (rest position, mass), bytes per node.
    pub mesh_bytes_per_node: f64,
    /// External-face list, bytes per external face.
    pub surface_bytes_per_face: f64,
    /// Whole mesh (all arrays and classes), bytes per element.
    pub mesh_total_bytes_per_element: f64,
    /// Explicit-dynamics state (positions, velocities, forces), bytes per node.
    pub state_bytes_per_node: f64,
    /// Force evaluator (packed kernels and parallel schedule), bytes in total.
    pub force_evaluator_bytes: usize,
    /// Mesh + state + evaluator, bytes per element.
    pub total_bytes_per_element: f64,
    /// Time to build the mesh (grid to `HexMesh`, including its checks), seconds.
    pub mesh_build_s: f64,
}

/// One quasi-static block size.
#[derive(Debug, Clone, Serialize)]
pub struct QuasiStaticBench {
    /// Cells per block edge.
    pub cells_per_edge: usize,
    /// Elements.
    pub elements: usize,
    /// Nodes.
    pub nodes: usize,
    /// Scene construction (mesh, constraints, loads), seconds, once.
    pub scene_build_s: f64,
    /// Solver set-up (preconditioner), per run.
    pub setup: TimeStats,
    /// Solve alone, per run.
    pub solve: TimeStats,
    /// Set-up plus solve, per run: the time compared with CalculiX and the target.
    pub total: TimeStats,
    /// Newton iterations of the median run.
    pub newton_iterations: usize,
    /// Krylov iterations of the median run.
    pub linear_iterations: usize,
    /// Relative force residual reached.
    pub residual: f64,
    /// Multigrid levels.
    pub multigrid_levels: usize,
    /// Volume change ΔV/V of the block.
    pub volume_change: f64,
    /// Volume change of linear elasticity, −p/K.
    pub linear_volume_change: f64,
    /// Largest displacement, metres.
    pub max_displacement_m: f64,
    /// Peak resident memory during the solves minus resident memory before, bytes per element.
    pub peak_extra_rss_bytes_per_element: Option<f64>,
}

/// Fit t ∝ elementsᵏ of the quasi-static total time.
#[derive(Debug, Clone, Serialize)]
pub struct ScalingFit {
    /// Fitted exponent k (1 is linear scaling).
    pub exponent: f64,
    /// Block sizes (cells per edge) fitted.
    pub cells_per_edge: Vec<usize>,
}

/// CalculiX and ours on one block and analysis type.
#[derive(Debug, Clone, Serialize)]
pub struct CalculixComparison {
    /// Cells per block edge.
    pub cells_per_edge: usize,
    /// Elements.
    pub elements: usize,
    /// CalculiX analysis: "linear" or "nlgeom"; elements are C3D8 (full integration).
    pub analysis: String,
    /// CalculiX wall time (deck read, assembly, solve, output), seconds, one run.
    pub calculix_wall_s: f64,
    /// Threads CalculiX was given (OMP_NUM_THREADS).
    pub calculix_threads: usize,
    /// Our set-up plus solve, median, seconds (measured just before CalculiX).
    pub ours_wall_s: f64,
    /// Our scene construction, seconds (not in `ours_wall_s`; CalculiX's deck read is in its time).
    pub ours_scene_build_s: f64,
    /// CalculiX time over ours.
    pub speedup: f64,
    /// CalculiX time over ours including our scene construction.
    pub speedup_with_scene_build: f64,
    /// max |u_ours − u_ccx| / max |u_ccx|.
    pub max_displacement_difference_rel: f64,
    /// RMS |u_ours − u_ccx| / RMS |u_ccx|.
    pub rms_displacement_difference_rel: f64,
    /// Largest CalculiX displacement, metres.
    pub calculix_max_displacement_m: f64,
}

/// One target of the issue and where it stands.
#[derive(Debug, Clone, Serialize)]
pub struct TargetCheck {
    /// What is required.
    pub target: String,
    /// What was measured (or why not).
    pub measured: String,
    /// Met, not met, or not measured.
    pub met: Option<bool>,
}

/// Everything measured by [`run_bench`].
#[derive(Debug, Clone, Serialize)]
pub struct BenchReport {
    /// The options of the run.
    pub options: BenchOptions,
    /// The machine.
    pub machine: MachineInfo,
    /// Material of every block.
    pub material: Material,
    /// Element edge, metres.
    pub element_edge_m: f64,
    /// Force throughput, every block × velocities × thread count.
    pub force: Vec<ForceThroughput>,
    /// Parallel speed-ups from the same runs.
    pub speedups: Vec<ParallelSpeedup>,
    /// Memory of the force-benchmark blocks.
    pub memory: Vec<MemoryUsage>,
    /// Quasi-static block solves.
    pub quasistatic: Vec<Outcome<QuasiStaticBench>>,
    /// Scaling of the quasi-static time with element count.
    pub quasistatic_scaling: Option<ScalingFit>,
    /// Quasi-static methods compared on one block (how the default was chosen).
    pub solver_comparison: Vec<Outcome<SolverComparison>>,
    /// CalculiX side by side.
    pub calculix: Vec<Outcome<CalculixComparison>>,
    /// Peak resident memory of the process (VmHWM) at the end, bytes.
    pub peak_rss_bytes: Option<u64>,
    /// The targets.
    pub targets: Vec<TargetCheck>,
}

/// One quasi-static method on the comparison block.
#[derive(Debug, Clone, Serialize)]
pub struct SolverComparison {
    /// What was run.
    pub method: String,
    /// Elements of the block.
    pub elements: usize,
    /// Wall time including set-up, seconds.
    pub wall_time_s: f64,
    /// Newton/Krylov iterations ("n / m") or explicit steps.
    pub iterations: String,
    /// Relative force residual reached.
    pub residual: f64,
}

/// Runs every benchmark of `options` and collects the report.
///
/// Failures of the quasi-static solver or of CalculiX are recorded in the report rather than
/// returned, so one missing piece does not hide the other measurements.
pub fn run_bench(options: &BenchOptions) -> Result<BenchReport> {
    if options.force_repetitions == 0 || options.quasistatic_runs == 0 {
        return Err(Error::InvalidModel(
            "benchmark repetitions must be at least 1".into(),
        ));
    }
    let cores = std::thread::available_parallelism().map_or(1, |n| n.get());
    let threads = if options.threads == 0 {
        cores
    } else {
        options.threads
    };
    let machine = MachineInfo {
        cores,
        cpu_model: cpu_model(),
        simd: simd_level().into(),
        date_utc: utc_now(),
        threads,
        lungmotion_version: env!("CARGO_PKG_VERSION").into(),
    };
    let mut force = Vec::new();
    let mut speedups = Vec::new();
    let mut memory = Vec::new();
    for &n in &options.force_block_cells {
        let (f, s, m) = force_block(n, threads, options.force_repetitions)?;
        force.extend(f);
        speedups.extend(s);
        memory.push(m);
    }
    let mut quasistatic = Vec::new();
    for &n in &options.quasistatic_block_cells {
        quasistatic.push(Outcome::from_result(quasistatic_block(
            n,
            options.pressure_pa,
            options.quasistatic_runs,
        )));
    }
    let quasistatic_scaling = fit_scaling(&quasistatic);
    let solver_comparison = match options.solver_comparison_cells {
        0 => Vec::new(),
        n => compare_solvers(n, options.pressure_pa),
    };
    let mut calculix_runs = Vec::new();
    let analyses: Vec<bool> = [
        (false, options.calculix_linear),
        (true, options.calculix_nlgeom),
    ]
    .iter()
    .filter(|(_, on)| *on)
    .map(|(nl, _)| *nl)
    .collect();
    for &n in &options.calculix_block_cells {
        for &nlgeom in &analyses {
            calculix_runs.push(calculix_block(
                n,
                options.pressure_pa,
                nlgeom,
                threads,
                options.quasistatic_runs,
            ));
        }
    }
    let mut report = BenchReport {
        options: options.clone(),
        machine,
        material: Material::LUNG,
        element_edge_m: BENCH_ELEMENT_EDGE_M,
        force,
        speedups,
        memory,
        quasistatic,
        quasistatic_scaling,
        solver_comparison,
        calculix: calculix_runs,
        peak_rss_bytes: peak_rss_bytes(),
        targets: Vec::new(),
    };
    report.targets = targets(&report);
    Ok(report)
}

fn targets(r: &BenchReport) -> Vec<TargetCheck> {
    let mut t = Vec::new();
    let parallel: Vec<&ForceThroughput> = r
        .force
        .iter()
        .filter(|f| f.threads == r.machine.threads)
        .collect();
    let worst = parallel
        .iter()
        .min_by(|a, b| a.elements_per_s.total_cmp(&b.elements_per_s));
    t.push(match worst {
        Some(w) => TargetCheck {
            target: format!(
                "force evaluation ≥ 5 M elements/s on {} threads (aim 10 M)",
                r.machine.threads
            ),
            measured: format!(
                "worst case {:.1} M/s ({}³ block, {} velocities); best {:.1} M/s",
                w.elements_per_s / 1e6,
                w.cells_per_edge,
                if w.with_velocities { "with" } else { "without" },
                parallel
                    .iter()
                    .map(|f| f.elements_per_s)
                    .fold(0.0, f64::max)
                    / 1e6
            ),
            met: Some(w.elements_per_s >= 5e6),
        },
        None => TargetCheck {
            target: "force evaluation ≥ 5 M elements/s".into(),
            measured: "not measured".into(),
            met: None,
        },
    });
    let qs64 = r
        .quasistatic
        .iter()
        .filter_map(Outcome::measured)
        .find(|q| q.elements == 64_000);
    t.push(TargetCheck {
        target: "quasi-static 40³ = 64 000-element block to residual 1e-6 in ≤ 1 s".into(),
        measured: match qs64 {
            Some(q) => format!(
                "{:.3} s median set-up + solve ({:.3} s solve alone), residual {:.1e}",
                q.total.median_s, q.solve.median_s, q.residual
            ),
            None => match r.quasistatic.iter().find_map(|o| match o {
                Outcome::Failed(e) => Some(e.clone()),
                _ => None,
            }) {
                Some(e) => format!("failed: {e}"),
                None => "40³ not run".into(),
            },
        },
        met: qs64.map(|q| q.total.median_s <= 1.0 && q.residual <= 1e-6),
    });
    let ccx64 = r
        .calculix
        .iter()
        .filter_map(Outcome::measured)
        .filter(|c| c.elements == 64_000)
        .min_by(|a, b| a.speedup.total_cmp(&b.speedup));
    let measured_ratios: Vec<String> = r
        .calculix
        .iter()
        .filter_map(Outcome::measured)
        .map(|c| format!("{}³ {}: {:.1}×", c.cells_per_edge, c.analysis, c.speedup))
        .collect();
    t.push(TargetCheck {
        target: "≥ 25× faster than CalculiX on the same 64 000-element block and load".into(),
        measured: match ccx64 {
            Some(c) => format!("{:.1}× ({})", c.speedup, c.analysis),
            None if measured_ratios.is_empty() => "CalculiX not run".into(),
            None => format!(
                "64 000 not run side by side; smaller blocks: {}",
                measured_ratios.join(", ")
            ),
        },
        met: ccx64.map(|c| c.speedup >= 25.0),
    });
    t
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn quick_bench_produces_a_complete_report() {
        let report = run_bench(&BenchOptions::quick()).unwrap();
        // 1 block × 2 velocity settings × 2 thread counts.
        assert_eq!(report.force.len(), 4);
        assert_eq!(report.memory.len(), 1);
        let mu = &report.memory[0];
        // Corners (32 B) and class (4 B) at least; positions (24 B) and mass (8 B) per node.
        assert!(mu.mesh_bytes_per_element >= 36.0, "{mu:?}");
        assert!(mu.mesh_bytes_per_node >= 32.0, "{mu:?}");
        assert_eq!(report.quasistatic.len(), 2);
        assert_eq!(report.targets.len(), 3);
        let md = report.to_markdown();
        for section in [
            "## Targets",
            "## Force evaluation",
            "## Memory",
            "## Quasi-static",
        ] {
            assert!(md.contains(section), "missing {section}");
        }
        serde_json::to_string(&report).unwrap();
    }
}
