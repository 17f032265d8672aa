//! Benchmarks behind `lungmotion bench`: force-kernel throughput, memory per element and per
//! node, the quasi-static block solve, and CalculiX on the same block side by side.
//!
//! Every timing is the median of repeated runs with min and max beside it, because the machine
//! is shared and noisy. Ratios (parallel speed-up, CalculiX over ours) come from measurements
//! taken in the same run, interleaved where possible, never from numbers of different runs.
//! Nothing here asserts a speed: the report states the targets and whether they were met.

pub mod ingest;
pub mod motion;
pub mod service;

use std::time::{Instant, SystemTime, UNIX_EPOCH};

use serde::Serialize;

use crate::math::V3;
use crate::model::{HexMesh, Material, VoxelGrid};
use crate::process::{current_rss_bytes, peak_rss_bytes, reset_peak_rss};
use crate::simulation::cases::symmetric_block_under_pressure;
use crate::simulation::{ForceEvaluator, QuasiStaticSettings, QuasiStaticSolver, Scene};
use crate::validation::calculix::{self, CalculixOptions};
use crate::{Error, Result};

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

/// A measured value, or why it is missing.
#[derive(Debug, Clone, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Outcome<T> {
    /// Measured.
    Measured(T),
    /// The measurement ran and failed (the error message).
    Failed(String),
    /// Not run (the reason).
    Skipped(String),
}

impl<T> Outcome<T> {
    fn from_result(r: Result<T>) -> Self {
        match r {
            Ok(v) => Outcome::Measured(v),
            Err(e) => Outcome::Failed(e.to_string()),
        }
    }

    /// The measured value, if any.
    pub fn measured(&self) -> Option<&T> {
        match self {
            Outcome::Measured(v) => Some(v),
            _ => None,
        }
    }
}

/// Median, extremes and count of repeated timings, seconds.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct TimeStats {
    /// Median in seconds.
    pub median_s: f64,
    /// Fastest run in seconds.
    pub min_s: f64,
    /// Slowest run in seconds.
    pub max_s: f64,
    /// Number of runs.
    pub runs: usize,
}

impl TimeStats {
    /// Statistics of `samples` (at least one).
    pub fn new(samples: &[f64]) -> Self {
        let mut s = samples.to_vec();
        s.sort_by(f64::total_cmp);
        let n = s.len();
        let median = if n % 2 == 1 {
            s[n / 2]
        } else {
            0.5 * (s[n / 2 - 1] + s[n / 2])
        };
        TimeStats {
            median_s: median,
            min_s: s[0],
            max_s: s[n - 1],
            runs: n,
        }
    }
}

/// Where and when the benchmark ran.
#[derive(Debug, Clone, Serialize)]
pub struct MachineInfo {
    /// Logical cores available to the process.
    pub cores: usize,
    /// CPU model from /proc/cpuinfo.
    pub cpu_model: String,
    /// Widest vector instructions the force kernel uses.
    pub simd: String,
    /// UTC date and time of the run (ISO 8601).
    pub date_utc: String,
    /// Threads of the parallel measurements.
    pub threads: usize,
    /// Crate version.
    pub lungmotion_version: String,
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

fn block_mesh(n: usize) -> Result<HexMesh> {
    Ok(
        VoxelGrid::filled_box([n; 3], [BENCH_ELEMENT_EDGE_M; 3], V3::zeros())
            .to_mesh(Material::LUNG)?
            .mesh,
    )
}

/// xorshift64*: reproducible positions without a dependency.
fn pseudo_random(state: &mut u64) -> f64 {
    *state ^= *state >> 12;
    *state ^= *state << 25;
    *state ^= *state >> 27;
    (state.wrapping_mul(0x2545_f491_4f6c_dd1d) >> 11) as f64 / (1u64 << 53) as f64 - 0.5
}

fn pool(threads: usize) -> Result<rayon::ThreadPool> {
    rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .map_err(|e| Error::External(format!("cannot start {threads} threads: {e}")))
}

type ForceBlock = (Vec<ForceThroughput>, Vec<ParallelSpeedup>, MemoryUsage);

fn force_block(n: usize, threads: usize, reps: usize) -> Result<ForceBlock> {
    let start = Instant::now();
    let mut mesh = block_mesh(n)?;
    let mesh_build_s = start.elapsed().as_secs_f64();
    let plain = ForceEvaluator::new(&mesh);
    let undamped = mesh.classes.clone();
    mesh.classes = undamped
        .iter()
        .map(|c| c.clone().with_damping_ratio(BENCH_DAMPING_RATIO))
        .collect();
    let damped = ForceEvaluator::new(&mesh);
    mesh.classes = undamped;
    let mut seed = 0x9e37_79b9_7f4a_7c15u64 ^ n as u64;
    let amp = BENCH_PERTURBATION * BENCH_ELEMENT_EDGE_M;
    let mut rnd3 = |scale: f64| {
        V3::new(
            pseudo_random(&mut seed),
            pseudo_random(&mut seed),
            pseudo_random(&mut seed),
        ) * scale
    };
    let x: Vec<V3> = mesh
        .rest_positions_m
        .iter()
        .map(|p| p + rnd3(2.0 * amp))
        .collect();
    let v: Vec<V3> = x.iter().map(|_| rnd3(0.02)).collect();
    let mut out = vec![V3::zeros(); mesh.node_count()];
    let one = pool(1)?;
    let many = pool(threads)?;
    let mut results = Vec::new();
    let mut speedups = Vec::new();
    for with_velocities in [false, true] {
        let (eval, vel) = if with_velocities {
            (&damped, Some(&v[..]))
        } else {
            (&plain, None)
        };
        let mut run = |p: &rayon::ThreadPool| {
            p.install(|| {
                let t = Instant::now();
                eval.internal_forces(&mesh, &x, vel, &mut out);
                t.elapsed().as_secs_f64()
            })
        };
        for _ in 0..2 {
            run(&one);
            run(&many);
        }
        // Interleaved so that load from other processes hits both thread counts alike.
        let mut t1 = Vec::with_capacity(reps);
        let mut tn = Vec::with_capacity(reps);
        for _ in 0..reps {
            t1.push(run(&one));
            tn.push(run(&many));
        }
        let s1 = TimeStats::new(&t1);
        let sn = TimeStats::new(&tn);
        for (t, s) in [(1, s1), (threads, sn)] {
            let e = mesh.element_count() as f64;
            results.push(ForceThroughput {
                cells_per_edge: n,
                elements: mesh.element_count(),
                nodes: mesh.node_count(),
                with_velocities,
                threads: t,
                time: s,
                elements_per_s: e / s.median_s,
                elements_per_s_best: e / s.min_s,
                ns_per_element: s.median_s / e * 1e9,
            });
        }
        let speedup = s1.median_s / sn.median_s;
        speedups.push(ParallelSpeedup {
            cells_per_edge: n,
            with_velocities,
            threads,
            speedup,
            speedup_best: s1.min_s / sn.min_s,
            efficiency: speedup / threads as f64,
        });
    }
    let memory = memory_usage(n, &mesh, &damped, mesh_build_s);
    Ok((results, speedups, memory))
}

fn vec_bytes<T>(v: &Vec<T>) -> usize {
    v.capacity() * std::mem::size_of::<T>()
}

fn memory_usage(n: usize, mesh: &HexMesh, eval: &ForceEvaluator, mesh_build_s: f64) -> MemoryUsage {
    let e = mesh.element_count() as f64;
    let nodes = mesh.node_count() as f64;
    let colours: usize = mesh.colors.iter().map(vec_bytes).sum::<usize>() + vec_bytes(&mesh.colors);
    let element_bytes = vec_bytes(&mesh.elements) + vec_bytes(&mesh.element_class) + colours;
    let node_bytes = vec_bytes(&mesh.rest_positions_m) + vec_bytes(&mesh.node_mass_kg);
    let face_bytes = vec_bytes(&mesh.external_faces);
    let class_bytes = vec_bytes(&mesh.classes);
    let mesh_total = element_bytes + node_bytes + face_bytes + class_bytes;
    let state_per_node = 3.0 * std::mem::size_of::<V3>() as f64;
    let eval_bytes = eval.heap_bytes() + std::mem::size_of::<ForceEvaluator>();
    MemoryUsage {
        cells_per_edge: n,
        elements: mesh.element_count(),
        nodes: mesh.node_count(),
        mesh_bytes_per_element: element_bytes as f64 / e,
        mesh_bytes_per_node: node_bytes as f64 / nodes,
        surface_bytes_per_face: face_bytes as f64 / mesh.external_faces.len().max(1) as f64,
        mesh_total_bytes_per_element: mesh_total as f64 / e,
        state_bytes_per_node: state_per_node,
        force_evaluator_bytes: eval_bytes,
        total_bytes_per_element: (mesh_total as f64 + state_per_node * nodes + eval_bytes as f64)
            / e,
        mesh_build_s,
    }
}

fn block_scene(n: usize, pressure_pa: f64) -> Result<(Scene, f64)> {
    let start = Instant::now();
    let scene =
        symmetric_block_under_pressure([n; 3], BENCH_ELEMENT_EDGE_M, Material::LUNG, pressure_pa)?;
    Ok((scene, start.elapsed().as_secs_f64()))
}

/// Set-up plus solve, `runs` times; returns the positions, the report of the median run and
/// the timing statistics (set-up, solve, total).
fn time_solves(
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

fn quasistatic_block(n: usize, pressure_pa: f64, runs: usize) -> Result<QuasiStaticBench> {
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

fn fit_scaling(runs: &[Outcome<QuasiStaticBench>]) -> Option<ScalingFit> {
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

fn calculix_block(
    n: usize,
    pressure_pa: f64,
    nlgeom: bool,
    threads: usize,
    runs: usize,
) -> Outcome<CalculixComparison> {
    let analysis = if nlgeom { "nlgeom" } else { "linear" };
    if let Err(e) = calculix::require_ccx() {
        return Outcome::Skipped(format!("calculix: not available ({e})"));
    }
    let run = || -> Result<CalculixComparison> {
        let (scene, scene_build_s) = block_scene(n, pressure_pa)?;
        let (x, _, [_, _, total]) = time_solves(&scene, runs)?;
        let ours = scene.displacements(&x);
        let options = CalculixOptions {
            threads,
            ..if nlgeom {
                CalculixOptions::default()
            } else {
                CalculixOptions::linear()
            }
        };
        let ccx = calculix::solve(&scene, &options)?;
        let theirs = &ccx.displacements_m;
        let max_ccx = theirs.iter().map(|u| u.norm()).fold(0.0, f64::max);
        let max_diff = ours
            .iter()
            .zip(theirs)
            .map(|(a, b)| (a - b).norm())
            .fold(0.0, f64::max);
        let rms = |it: &mut dyn Iterator<Item = f64>| {
            let (s, c) = it.fold((0.0, 0usize), |(s, c), v| (s + v * v, c + 1));
            (s / c.max(1) as f64).sqrt()
        };
        let rms_diff = rms(&mut ours.iter().zip(theirs).map(|(a, b)| (a - b).norm()));
        let rms_ccx = rms(&mut theirs.iter().map(|u| u.norm()));
        Ok(CalculixComparison {
            cells_per_edge: n,
            elements: scene.mesh.element_count(),
            analysis: analysis.into(),
            calculix_wall_s: ccx.wall_time_s,
            calculix_threads: threads,
            ours_wall_s: total.median_s,
            ours_scene_build_s: scene_build_s,
            speedup: ccx.wall_time_s / total.median_s,
            speedup_with_scene_build: ccx.wall_time_s / (total.median_s + scene_build_s),
            max_displacement_difference_rel: max_diff / max_ccx,
            rms_displacement_difference_rel: rms_diff / rms_ccx,
            calculix_max_displacement_m: max_ccx,
        })
    };
    Outcome::from_result(run())
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

impl BenchReport {
    /// The report as a markdown document (tables of every measurement).
    pub fn to_markdown(&self) -> String {
        use std::fmt::Write as _;
        let mut s = String::new();
        let m = &self.machine;
        let _ = writeln!(s, "# lungmotion benchmark\n");
        let _ = writeln!(
            s,
            "{} · CPU: {} · {} cores · {} threads in parallel runs · SIMD: {} · lungmotion {}\n",
            m.date_utc, m.cpu_model, m.cores, m.threads, m.simd, m.lungmotion_version
        );
        let _ = writeln!(
            s,
            "Blocks of {:.0} mm cubes, lung material E = {} Pa, ν = {}, ρ = {} kg/m³. \
             Times are medians with [min – max] over the runs; ratios come from the same run.\n",
            self.element_edge_m * 1e3,
            self.material.youngs_modulus_pa,
            self.material.poisson_ratio,
            self.material.density_kg_per_m3
        );
        let _ = writeln!(s, "## Targets\n");
        let _ = writeln!(s, "| Target | Measured | Met |\n|---|---|---|");
        for t in &self.targets {
            let met = match t.met {
                Some(true) => "yes",
                Some(false) => "**no**",
                None => "not measured",
            };
            let _ = writeln!(s, "| {} | {} | {} |", t.target, t.measured, met);
        }
        let _ = writeln!(s, "\n## Force evaluation\n");
        let _ = writeln!(
            s,
            "Nodes displaced randomly by up to ±{:.0} % of the edge; with velocities: dampers \
             at {} of critical. Wall time per evaluation of all elements.\n",
            BENCH_PERTURBATION * 100.0,
            BENCH_DAMPING_RATIO
        );
        let _ = writeln!(
            s,
            "| Block | Elements | Velocities | Threads | Median ms [min – max] | M elements/s (best) | ns/element |\n|---|---|---|---|---|---|---|"
        );
        for f in &self.force {
            let _ = writeln!(
                s,
                "| {n}³ | {} | {} | {} | {:.2} [{:.2} – {:.2}] | {:.2} ({:.2}) | {:.1} |",
                f.elements,
                if f.with_velocities { "yes" } else { "no" },
                f.threads,
                f.time.median_s * 1e3,
                f.time.min_s * 1e3,
                f.time.max_s * 1e3,
                f.elements_per_s / 1e6,
                f.elements_per_s_best / 1e6,
                f.ns_per_element,
                n = f.cells_per_edge
            );
        }
        let _ = writeln!(
            s,
            "\n| Block | Velocities | Threads | Parallel speed-up (medians) | Efficiency | Speed-up (best runs) |\n|---|---|---|---|---|---|"
        );
        for p in &self.speedups {
            let _ = writeln!(
                s,
                "| {}³ | {} | {} | {:.2}× | {:.0} % | {:.2}× |",
                p.cells_per_edge,
                if p.with_velocities { "yes" } else { "no" },
                p.threads,
                p.speedup,
                p.efficiency * 100.0,
                p.speedup_best
            );
        }
        let _ = writeln!(s, "\n## Memory\n");
        let _ = writeln!(
            s,
            "Counted from vector capacities. Mesh per element: corners, class, colour lists; per \
             node: rest position, mass. State: positions, velocities, forces.\n"
        );
        let _ = writeln!(
            s,
            "| Block | Elements | Nodes | Mesh B/element | Mesh B/node | Mesh total B/element | State B/node | Evaluator B | Total B/element | Mesh build s |\n|---|---|---|---|---|---|---|---|---|---|"
        );
        for mu in &self.memory {
            let _ = writeln!(
                s,
                "| {}³ | {} | {} | {:.1} | {:.1} | {:.1} | {:.0} | {} | {:.1} | {:.3} |",
                mu.cells_per_edge,
                mu.elements,
                mu.nodes,
                mu.mesh_bytes_per_element,
                mu.mesh_bytes_per_node,
                mu.mesh_total_bytes_per_element,
                mu.state_bytes_per_node,
                mu.force_evaluator_bytes,
                mu.total_bytes_per_element,
                mu.mesh_build_s
            );
        }
        if let Some(p) = self.peak_rss_bytes {
            let _ = writeln!(
                s,
                "\nProcess peak resident memory (VmHWM) at the end: {:.1} MB.",
                p as f64 / 1e6
            );
        }
        let _ = writeln!(s, "\n## Quasi-static block\n");
        let _ = writeln!(
            s,
            "One octant of a cube block: symmetry planes x = 0, y = 0, z = 0 (nodes slide in \
             the plane; on two planes, along their line; the corner is fixed), follower \
             pressure {} Pa on the three outer faces. `QuasiStaticSolver` with default settings \
             (relative force residual 1e-6). Total = solver set-up + solve; the scene \
             construction is listed apart.\n",
            self.options.pressure_pa
        );
        let _ = writeln!(
            s,
            "| Block | Elements | Total s [min – max] | Set-up s | Solve s | Newton | Krylov | Residual | MG levels | ΔV/V (linear −p/K) | Peak extra RSS B/element | Scene build s |\n|---|---|---|---|---|---|---|---|---|---|---|---|"
        );
        for (o, &n) in self
            .quasistatic
            .iter()
            .zip(&self.options.quasistatic_block_cells)
        {
            match o {
                Outcome::Measured(q) => {
                    let _ = writeln!(
                        s,
                        "| {}³ | {} | {:.3} [{:.3} – {:.3}] | {:.3} | {:.3} | {} | {} | {:.1e} | {} | {:.4} ({:.4}) | {} | {:.3} |",
                        q.cells_per_edge,
                        q.elements,
                        q.total.median_s,
                        q.total.min_s,
                        q.total.max_s,
                        q.setup.median_s,
                        q.solve.median_s,
                        q.newton_iterations,
                        q.linear_iterations,
                        q.residual,
                        q.multigrid_levels,
                        q.volume_change,
                        q.linear_volume_change,
                        q.peak_extra_rss_bytes_per_element
                            .map_or("–".into(), |b| format!("{b:.0}")),
                        q.scene_build_s
                    );
                }
                Outcome::Failed(e) | Outcome::Skipped(e) => {
                    let _ = writeln!(s, "| {n}³ | – | {} | | | | | | | | | |", one_line(e));
                }
            }
        }
        if let Some(f) = &self.quasistatic_scaling {
            let _ = writeln!(
                s,
                "\nTime ∝ elements^{:.2} (least-squares fit over blocks {:?}).",
                f.exponent, f.cells_per_edge
            );
        }
        if !self.solver_comparison.is_empty() {
            let _ = writeln!(s, "\n## Choosing the quasi-static method\n");
            let _ = writeln!(
                s,
                "Same block and load, each method to relative residual 1e-6 (one run each, \
                 set-up included). The solver's default is multigrid on lattice meshes; on \
                 tiny blocks its set-up can cost more than it saves.\n"
            );
            let _ = writeln!(s, "| Method | Elements | Wall s | Iterations | Residual |");
            let _ = writeln!(s, "|---|---|---|---|---|");
            for c in &self.solver_comparison {
                match c {
                    Outcome::Measured(c) => {
                        let _ = writeln!(
                            s,
                            "| {} | {} | {:.3} | {} | {:.1e} |",
                            c.method, c.elements, c.wall_time_s, c.iterations, c.residual
                        );
                    }
                    Outcome::Failed(e) | Outcome::Skipped(e) => {
                        let _ = writeln!(s, "| – | – | – | – | {e} |");
                    }
                }
            }
        }
        let _ = writeln!(s, "\n## CalculiX side by side\n");
        let _ = writeln!(
            s,
            "Same scene written as a C3D8 deck (full integration); ours is set-up + solve \
             (median), measured just before CalculiX. Displacement differences are relative to \
             CalculiX's.\n"
        );
        if self.calculix.is_empty() {
            let _ = writeln!(s, "Not run.");
        } else {
            let _ = writeln!(
                s,
                "| Block | Elements | CalculiX analysis | CalculiX s | Ours s | Ratio | Ratio incl. our scene build | max Δu / max u | RMS Δu / RMS u |\n|---|---|---|---|---|---|---|---|---|"
            );
            for o in &self.calculix {
                match o {
                    Outcome::Measured(c) => {
                        let _ = writeln!(
                            s,
                            "| {}³ | {} | {} ({} threads) | {:.2} | {:.3} | {:.1}× | {:.1}× | {:.2e} | {:.2e} |",
                            c.cells_per_edge,
                            c.elements,
                            c.analysis,
                            c.calculix_threads,
                            c.calculix_wall_s,
                            c.ours_wall_s,
                            c.speedup,
                            c.speedup_with_scene_build,
                            c.max_displacement_difference_rel,
                            c.rms_displacement_difference_rel
                        );
                    }
                    Outcome::Failed(e) | Outcome::Skipped(e) => {
                        let _ = writeln!(s, "| | | {} | | | | | | |", one_line(e));
                    }
                }
            }
        }
        s
    }
}

/// First line of an error message, table-safe.
fn one_line(e: &str) -> String {
    e.lines().next().unwrap_or("").replace('|', "/")
}

fn cpu_model() -> String {
    std::fs::read_to_string("/proc/cpuinfo")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("model name"))
                .and_then(|l| l.split(':').nth(1))
                .map(|m| m.trim().to_string())
        })
        .unwrap_or_else(|| "unknown".into())
}

fn simd_level() -> &'static str {
    #[cfg(target_arch = "x86_64")]
    {
        if std::arch::is_x86_feature_detected!("avx2") {
            return "avx2 (4 × f64)";
        }
        "sse2 (2 × f64)"
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        "portable"
    }
}

/// Current UTC time as ISO 8601, from the system clock (no date crate needed).
fn utc_now() -> String {
    let secs = SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| d.as_secs()) as i64;
    let (days, rem) = (secs.div_euclid(86_400), secs.rem_euclid(86_400));
    // Howard Hinnant's civil-from-days.
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z - era * 146_097;
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let day = doy - (153 * mp + 2) / 5 + 1;
    let month = if mp < 10 { mp + 3 } else { mp - 9 };
    let year = yoe + era * 400 + (month <= 2) as i64;
    format!(
        "{year:04}-{month:02}-{day:02}T{:02}:{:02}:{:02}Z",
        rem / 3600,
        rem % 3600 / 60,
        rem % 60
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn median_of_even_and_odd_counts() {
        let s = TimeStats::new(&[3.0, 1.0, 2.0]);
        assert_eq!((s.median_s, s.min_s, s.max_s, s.runs), (2.0, 1.0, 3.0, 3));
        assert_eq!(TimeStats::new(&[4.0, 1.0, 2.0, 3.0]).median_s, 2.5);
    }

    #[test]
    fn date_is_iso_8601() {
        let d = utc_now();
        assert_eq!(d.len(), 20, "{d}");
        assert!(d.starts_with("20") && d.ends_with('Z'), "{d}");
    }

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

/// Newton–Krylov with multigrid, with block Jacobi, and damped explicit relaxation on the
/// same pressurised block.
fn compare_solvers(cells: usize, pressure_pa: f64) -> Vec<Outcome<SolverComparison>> {
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
