//! Stability of the explicit integrator's automatic time step across the parameter ranges of
//! lung tissue, and whether the blow-up detector catches a step that is too large.
//!
//! A small block of elements is clamped on its bottom face, loaded by a pressure on its top
//! face and a sideways body force, each sized to give a modest strain whatever E, ρ and the
//! element size, and damped critically per spring as the thesis does (§4.1.3). Every case
//! must reach equilibrium with `TimeStepBound`'s step, with bounded kinetic energy, and land
//! where a dense Newton solve of the same scene lands. A run at a multiple of the critical step
//! should end in `Error::Diverged`; where it does not, the report says whether the step was
//! below the true limit or the instability went unflagged (saturated oscillation, or a false
//! equilibrium with inverted elements).
//!
//! The true stability limit is measured by bisection on the step, from the spectral radius of
//! the linearised velocity-Verlet map (exact for small motions) and from the production
//! `ExplicitIntegrator::step` (does it settle at the Newton equilibrium?). Their ratio to the
//! Gershgorin bound says how conservative the automatic step is. `run_to_equilibrium` is
//! measured apart: every `check_every` steps it refreshes the accelerations with the full-step
//! velocity, which is not the plain velocity-Verlet map and moves its limit a little.
//!
//! The linearised map is built from the element matrices, not from the kernel: stiffness
//! `BrickCoefficients::linear_stiffness()` (springs and corrections), damping the bare spring
//! dampers, which is what `TimeStepBound` assumes. The kernel's own Jacobians are compared with
//! them, so a kernel that fed its dampers through the corrections again (amplifying them by up
//! to 1/(2 − 4ν)) shows up as a damping mismatch of order one and as a linearised limit that
//! disagrees with the empirical one.

use nalgebra::DMatrix;
use serde::Serialize;

use super::patch::{assemble_linear_stiffness, free_dofs, DenseNewton};
use crate::math::V3;
use crate::model::element::SPRINGS;
use crate::model::{ConstraintSet, HexMesh, Loads, Material, SurfacePressure, VoxelGrid};
use crate::simulation::{
    ExplicitIntegrator, ExplicitSettings, QuasiStaticSettings, QuasiStaticSolver, Scene,
    TimeStepBound,
};
use crate::{Error, Result};

/// What the stability study runs.
#[derive(Debug, Clone, Serialize)]
pub struct StabilityConfig {
    /// Elements of the block along x, y, z; clamped at z = 0.
    pub cells: [usize; 3],
    /// Young's moduli in pascals.
    pub youngs_moduli_pa: Vec<f64>,
    /// Poisson ratios.
    pub poisson_ratios: Vec<f64>,
    /// Element sizes in metres (the longest edge of the element).
    pub element_sizes_m: Vec<f64>,
    /// Element proportions, scaled so that the longest edge is the element size.
    pub element_shapes: Vec<[f64; 3]>,
    /// Densities in kg/m³.
    pub densities_kg_per_m3: Vec<f64>,
    /// Strain scale of the loads: top pressure = strain·E, sideways body force ρ·g with
    /// g = strain·E/(ρ·height).
    pub load_strain: f64,
    /// Fraction of critical damping of every spring.
    pub damping_ratio: f64,
    /// Fraction of the critical step the automatic step uses.
    pub safety: f64,
    /// Step budget of each run to equilibrium.
    pub max_steps: usize,
    /// Multiple of the bound's critical step that should diverge (it cannot where the true
    /// limit is above it).
    pub overstep_factor: f64,
    /// Step budget of the overstep runs and of the empirical bisections (divided by the step
    /// ratio below 1).
    pub divergence_steps: usize,
    /// Bisection iterations for the true critical step (0 skips the measurement).
    pub bisection_iterations: usize,
}

impl StabilityConfig {
    /// The full grid: E 100 Pa – 100 kPa, ν 0.1 – 0.49, elements 1 – 20 mm, cubes and
    /// 1 × 1.2 × 0.9 bricks, ρ 100 – 1050 kg/m³ (a few minutes).
    pub fn full() -> Self {
        StabilityConfig {
            cells: [3, 3, 3],
            youngs_moduli_pa: vec![100.0, 1.0e3, 1.0e4, 1.0e5],
            poisson_ratios: vec![0.1, 0.3, 0.4, 0.45, 0.49],
            element_sizes_m: vec![1e-3, 5e-3, 20e-3],
            element_shapes: vec![[1.0, 1.0, 1.0], [1.0, 1.2, 0.9]],
            densities_kg_per_m3: vec![100.0, 1050.0],
            load_strain: 0.02,
            damping_ratio: 1.0,
            safety: ExplicitSettings::default().safety,
            max_steps: 100_000,
            overstep_factor: 1.5,
            divergence_steps: 20_000,
            bisection_iterations: 14,
        }
    }

    /// The corners of the grid only (extreme E, size, density; cubes), under a minute.
    pub fn quick() -> Self {
        StabilityConfig {
            youngs_moduli_pa: vec![100.0, 1.0e5],
            poisson_ratios: vec![0.1, 0.3, 0.49],
            element_sizes_m: vec![1e-3, 20e-3],
            element_shapes: vec![[1.0, 1.0, 1.0]],
            densities_kg_per_m3: vec![100.0, 1050.0],
            bisection_iterations: 10,
            ..Self::full()
        }
    }
}

/// Builds the study's block: clamped bottom, top pressure and sideways body force sized by
/// `load_strain`, springs damped at `damping_ratio` of critical.
pub fn clamped_block(
    cells: [usize; 3],
    edges_m: [f64; 3],
    material: Material,
    damping_ratio: f64,
    load_strain: f64,
) -> Result<Scene> {
    let gm = VoxelGrid::filled_box(cells, edges_m, V3::zeros()).to_mesh(material)?;
    let mut mesh = gm.mesh;
    mesh.classes = mesh
        .classes
        .into_iter()
        .map(|c| c.with_damping_ratio(damping_ratio))
        .collect();
    let top = cells[2] as u32;
    let mut cs = ConstraintSet::new(mesh.node_count());
    for (n, l) in gm.node_lattice.iter().enumerate() {
        if l[2] == 0 {
            cs.fix(n as u32, mesh.rest_positions_m[n])?;
        }
    }
    let top_z = cells[2] as f64 * edges_m[2];
    let on_top = |f: &[u32; 4]| f.iter().all(|&c| gm.node_lattice[c as usize][2] == top);
    let faces: Vec<[u32; 4]> = mesh.external_faces.iter().copied().filter(on_top).collect();
    let e = material.youngs_modulus_pa;
    let g = load_strain * e / (material.density_kg_per_m3 * top_z);
    let loads = Loads {
        gravity_m_per_s2: V3::new(-g, 0.0, 0.0),
        point_forces_n: Vec::new(),
        pressures: vec![SurfacePressure {
            faces,
            pressure_pa: load_strain * e,
            follows_deformation: true,
        }],
    };
    Scene::new(mesh, cs, loads)
}

/// How one explicit run ended.
#[derive(Debug, Clone, Serialize)]
pub struct RunOutcome {
    /// Step used, s.
    pub step_s: f64,
    /// Steps taken (up to the detection when it diverged).
    pub steps: usize,
    /// Whether `run_to_equilibrium` reported equilibrium.
    pub converged: bool,
    /// Final relative force residual (absent when it diverged).
    pub residual: Option<f64>,
    /// Peak kinetic energy over the work of the loads at equilibrium (≤ ½ for a linear damped
    /// system released from rest; absent unless it converged).
    pub peak_kinetic_over_work: Option<f64>,
    /// max |x_explicit − x_Newton| / max |x_Newton − rest| (absent when it diverged).
    pub equilibrium_error: Option<f64>,
    /// The blow-up `run_to_equilibrium` reported, if any.
    pub divergence: Option<Divergence>,
    /// Smallest signed element volume over rest volume at the end (< 0: inverted elements).
    pub min_volume_ratio: Option<f64>,
}

impl RunOutcome {
    /// Converged, finite, with bounded kinetic energy and at the Newton equilibrium.
    pub fn passed(&self) -> bool {
        self.converged
            && self.divergence.is_none()
            && self.equilibrium_error.is_some_and(|e| e < 1e-3)
            && self.peak_kinetic_over_work.is_some_and(|k| k <= 1.0)
    }
}

/// One parameter set: the automatic step and the overstep.
#[derive(Debug, Clone, Serialize)]
pub struct StabilityCase {
    /// Young's modulus, Pa.
    pub youngs_modulus_pa: f64,
    /// Poisson ratio.
    pub poisson_ratio: f64,
    /// Element edges, m.
    pub edges_m: [f64; 3],
    /// Density, kg/m³.
    pub density_kg_per_m3: f64,
    /// `TimeStepBound`'s critical step, s.
    pub critical_step_s: f64,
    /// The thesis's empirical rule, 2 % of the undamped period of the stiffest spring on the
    /// lightest node: 0.02·2π·√(m/k), s.
    pub thesis_step_s: f64,
    /// Largest displacement at the Newton equilibrium over the block height.
    pub max_displacement_over_height: f64,
    /// max |x_production − x_Newton| / max |x_Newton − rest|: the production
    /// `QuasiStaticSolver` against the dense Newton reference.
    pub production_solver_difference: f64,
    /// Run with the automatic step (`safety` × `TimeStepBound`).
    pub automatic: RunOutcome,
    /// Run at `overstep_factor` × `TimeStepBound`'s critical step with `divergence_steps`.
    pub overstep: RunOutcome,
}

/// A detected blow-up.
#[derive(Debug, Clone, Serialize)]
pub struct Divergence {
    /// Step reported by `Error::Diverged`.
    pub step: usize,
    /// Cause reported by `Error::Diverged`.
    pub cause: String,
}

/// How conservative the bound is, per ν and element shape (the ratio does not depend on E,
/// ρ or size: all three scale time alone).
#[derive(Debug, Clone, Serialize)]
pub struct CriticalStep {
    /// Poisson ratio.
    pub poisson_ratio: f64,
    /// Element proportions.
    pub element_shape: [f64; 3],
    /// Damping ratio of the springs.
    pub damping_ratio: f64,
    /// Largest step with spectral radius ≤ 1 of the linearised velocity-Verlet map, over the
    /// bound's critical step.
    pub linear_ratio: f64,
    /// Largest step at which plain `ExplicitIntegrator::step`s settle at equilibrium, / bound.
    pub empirical_ratio: f64,
    /// Same with `run_to_equilibrium`, whose periodic acceleration refresh shifts the limit.
    pub run_to_equilibrium_ratio: f64,
    /// Same as `linear_ratio` with the dampers removed: isolates the ω_max bound.
    pub undamped_linear_ratio: f64,
    /// max |∂f/∂x + K| / max |K|: kernel Jacobian at rest against `linear_stiffness()`.
    pub kernel_stiffness_mismatch: f64,
    /// max |∂f/∂v + C| / max |C|, C the bare dampers (order one if corrections amplify them).
    pub kernel_damping_mismatch: f64,
}

/// Outcome of the stability study.
#[derive(Debug, Clone, Serialize)]
pub struct StabilityReport {
    /// What was run.
    pub config: StabilityConfig,
    /// Every automatic-step run.
    pub cases: Vec<StabilityCase>,
    /// True critical step over the bound, per ν and shape.
    pub critical_steps: Vec<CriticalStep>,
    /// Whether every automatic run converged, finitely and close to the Newton equilibrium.
    pub all_stable: bool,
    /// Whether every overstepped run was caught as `Error::Diverged`.
    pub all_oversteps_caught: bool,
}

/// Runs the stability study.
pub fn run_stability_study(config: &StabilityConfig) -> Result<StabilityReport> {
    let mut cases = Vec::new();
    let mut critical_steps = Vec::new();
    for &shape in &config.element_shapes {
        for &nu in &config.poisson_ratios {
            for &size in &config.element_sizes_m {
                let longest = shape.iter().cloned().fold(0.0, f64::max);
                let edges = shape.map(|s| s * size / longest);
                for &e in &config.youngs_moduli_pa {
                    for &rho in &config.densities_kg_per_m3 {
                        let material = Material::new(e, nu, rho)?;
                        cases.push(stability_case(config, edges, material)?);
                    }
                }
            }
            if config.bisection_iterations > 0 {
                let material = Material::new(1000.0, nu, 700.0)?;
                let edges = shape.map(|s| s * 0.01);
                critical_steps.push(critical_step(config, edges, material)?);
            }
        }
    }
    let all_stable = cases.iter().all(|c| c.automatic.passed());
    let all_oversteps_caught = cases.iter().all(|c| c.overstep.divergence.is_some());
    Ok(StabilityReport {
        config: config.clone(),
        cases,
        critical_steps,
        all_stable,
        all_oversteps_caught,
    })
}

/// One parameter set: the automatic step checked against a dense Newton equilibrium, plus the
/// overstep run.
pub fn stability_case(
    config: &StabilityConfig,
    edges_m: [f64; 3],
    material: Material,
) -> Result<StabilityCase> {
    let scene = clamped_block(
        config.cells,
        edges_m,
        material,
        config.damping_ratio,
        config.load_strain,
    )?;
    let rest = scene.mesh.rest_positions_m.clone();
    let bound = TimeStepBound::new(&scene, config.safety);
    let (reference, _) = DenseNewton::default().solve(&scene, &rest)?;
    let qs = QuasiStaticSettings {
        tolerance: 1e-10,
        ..Default::default()
    };
    let (production, _) = QuasiStaticSolver::new(&scene, qs)?.solve(None)?;
    let u_ref = max_distance(&reference, &rest);
    let automatic = run_checked(&scene, &reference, bound.step_s, config.max_steps)?;

    let overstep = run_checked(
        &scene,
        &reference,
        config.overstep_factor * bound.critical_step_s,
        config.divergence_steps,
    )?;

    let height = config.cells[2] as f64 * edges_m[2];
    Ok(StabilityCase {
        youngs_modulus_pa: material.youngs_modulus_pa,
        poisson_ratio: material.poisson_ratio,
        edges_m,
        density_kg_per_m3: material.density_kg_per_m3,
        critical_step_s: bound.critical_step_s,
        thesis_step_s: thesis_step(&scene),
        max_displacement_over_height: u_ref / height,
        production_solver_difference: max_distance(&production, &reference) / u_ref,
        automatic,
        overstep,
    })
}

/// Runs `run_to_equilibrium` at a fixed step and checks the outcome against `reference`.
pub fn run_checked(
    scene: &Scene,
    reference: &[V3],
    step_s: f64,
    max_steps: usize,
) -> Result<RunOutcome> {
    let rest = &scene.mesh.rest_positions_m;
    let settings = ExplicitSettings {
        fixed_step_s: Some(step_s),
        max_steps,
        ..Default::default()
    };
    let mut it = ExplicitIntegrator::new(scene);
    let report = match it.run_to_equilibrium(&settings) {
        Ok(r) => r,
        Err(Error::Diverged { step, cause }) => {
            return Ok(RunOutcome {
                step_s,
                steps: step,
                converged: false,
                residual: None,
                peak_kinetic_over_work: None,
                equilibrium_error: None,
                divergence: Some(Divergence { step, cause }),
                min_volume_ratio: None,
            })
        }
        Err(e) => return Err(e),
    };
    if !report.converged {
        let n = scene.node_count();
        let mut scratch = (vec![V3::zeros(); n], vec![V3::zeros(); n]);
        return Ok(RunOutcome {
            step_s,
            steps: report.steps,
            converged: false,
            residual: Some(
                scene.relative_residual(&it.positions, (&mut scratch.0, &mut scratch.1)),
            ),
            peak_kinetic_over_work: None,
            equilibrium_error: Some(
                max_distance(&it.positions, reference) / max_distance(reference, rest),
            ),
            divergence: None,
            min_volume_ratio: Some(min_volume_ratio(scene, &it.positions)),
        });
    }
    let mut f_ext = vec![V3::zeros(); scene.node_count()];
    scene.external_forces(reference, &mut f_ext);
    let work: f64 = f_ext
        .iter()
        .zip(reference.iter().zip(rest))
        .map(|(f, (x, r))| f.dot(&(x - r)))
        .sum();
    // Replay the same steps by hand to watch the kinetic energy the production loop hides.
    let mut replay = ExplicitIntegrator::new(scene);
    let mut peak_ke: f64 = 0.0;
    for _ in 0..report.steps {
        replay.step(step_s);
        peak_ke = peak_ke.max(replay.kinetic_energy_j());
    }
    Ok(RunOutcome {
        step_s,
        steps: report.steps,
        converged: report.converged,
        residual: Some(report.residual),
        peak_kinetic_over_work: Some(peak_ke / work),
        equilibrium_error: Some(
            max_distance(&it.positions, reference) / max_distance(reference, rest),
        ),
        divergence: None,
        min_volume_ratio: Some(min_volume_ratio(scene, &it.positions)),
    })
}

/// Smallest signed element volume (centre axes ex, ey, ez) over rest volume; < 0 if inverted.
pub fn min_volume_ratio(scene: &Scene, x: &[V3]) -> f64 {
    let mesh = &scene.mesh;
    mesh.elements
        .iter()
        .zip(&mesh.element_class)
        .map(|(corners, &class)| {
            let p = corners.map(|c| x[c as usize]);
            let ex = (p[1] - p[0]) + (p[2] - p[3]) + (p[5] - p[4]) + (p[6] - p[7]);
            let ey = (p[3] - p[0]) + (p[2] - p[1]) + (p[7] - p[4]) + (p[6] - p[5]);
            let ez = (p[4] - p[0]) + (p[5] - p[1]) + (p[6] - p[2]) + (p[7] - p[3]);
            ex.dot(&ey.cross(&ez)) / 64.0 / mesh.classes[class as usize].shape.volume_m3()
        })
        .fold(f64::INFINITY, f64::min)
}

/// Whether plain `ExplicitIntegrator::step`s of `step_s` from rest settle at `reference` (to
/// 1e-6 of the largest displacement) within `max_steps`; the velocity-Verlet map the
/// linearisation models, without `run_to_equilibrium`'s acceleration refresh.
fn plain_steps_settle(scene: &Scene, reference: &[V3], step_s: f64, max_steps: usize) -> bool {
    let tolerance = 1e-6 * max_distance(reference, &scene.mesh.rest_positions_m);
    let mut it = ExplicitIntegrator::new(scene);
    while it.steps < max_steps {
        for _ in 0..50 {
            it.step(step_s);
        }
        // `max_distance` would skip NaNs (f64::max ignores them).
        if !it.positions.iter().all(|p| p.iter().all(|v| v.is_finite())) {
            return false;
        }
        if max_distance(&it.positions, reference) <= tolerance {
            return true;
        }
    }
    false
}

/// 2 % of the undamped period of the stiffest spring acting on the lightest node (§4.1.3).
fn thesis_step(scene: &Scene) -> f64 {
    let k_max = scene
        .mesh
        .classes
        .iter()
        .flat_map(|c| {
            SPRINGS
                .iter()
                .map(move |(_, _, kind)| c.spring_stiffness(*kind))
        })
        .fold(0.0, f64::max);
    let m_min = scene
        .mesh
        .node_mass_kg
        .iter()
        .cloned()
        .fold(f64::INFINITY, f64::min);
    0.02 * 2.0 * std::f64::consts::PI * (m_min / k_max).sqrt()
}

fn max_distance(a: &[V3], b: &[V3]) -> f64 {
    a.iter()
        .zip(b)
        .map(|(p, q)| (p - q).norm())
        .fold(0.0, f64::max)
}

/// Bisects the true critical step of one block, linearised and empirical, damped and not.
pub fn critical_step(
    config: &StabilityConfig,
    edges_m: [f64; 3],
    material: Material,
) -> Result<CriticalStep> {
    let scene = clamped_block(
        config.cells,
        edges_m,
        material,
        config.damping_ratio,
        config.load_strain,
    )?;
    let bound = TimeStepBound::new(&scene, 1.0).critical_step_s;
    let lin = LinearVerlet::new(&scene)?;
    let (kernel_stiffness_mismatch, kernel_damping_mismatch) = lin.kernel_mismatch(&scene);
    let linear_ratio = bisect(config.bisection_iterations, |r| {
        Ok(lin.spectral_radius(r * bound)? <= 1.0 + 1e-9)
    })?;
    let (reference, _) = DenseNewton::default().solve(&scene, &scene.mesh.rest_positions_m)?;
    // Small steps need proportionally more of them to settle.
    let budget = |r: f64| (config.divergence_steps as f64 / r.min(1.0)).ceil() as usize;
    let empirical_ratio = bisect(config.bisection_iterations, |r| {
        Ok(plain_steps_settle(&scene, &reference, r * bound, budget(r)))
    })?;
    let run_to_equilibrium_ratio = bisect(config.bisection_iterations, |r| {
        let run = run_checked(&scene, &reference, r * bound, budget(r))?;
        Ok(run.converged && run.equilibrium_error.is_some_and(|e| e < 1e-3))
    })?;
    let undamped = clamped_block(config.cells, edges_m, material, 0.0, config.load_strain)?;
    let bound0 = TimeStepBound::new(&undamped, 1.0).critical_step_s;
    let lin0 = LinearVerlet::new(&undamped)?;
    let undamped_linear_ratio = bisect(config.bisection_iterations, |r| {
        Ok(lin0.spectral_radius(r * bound0)? <= 1.0 + 1e-9)
    })?;
    Ok(CriticalStep {
        poisson_ratio: material.poisson_ratio,
        element_shape: edges_m.map(|e| e / edges_m[0]),
        damping_ratio: config.damping_ratio,
        linear_ratio,
        empirical_ratio,
        run_to_equilibrium_ratio,
        undamped_linear_ratio,
        kernel_stiffness_mismatch,
        kernel_damping_mismatch,
    })
}

/// Largest ratio r in [1/8, 8] with `stable(r)` (0 if none), assuming stability is monotone
/// in r.
fn bisect(iterations: usize, mut stable: impl FnMut(f64) -> Result<bool>) -> Result<f64> {
    let (mut lo, mut hi) = (1.0 / 8.0, 8.0);
    if !stable(lo)? {
        return Ok(0.0);
    }
    if stable(hi)? {
        return Ok(hi);
    }
    for _ in 0..iterations {
        let mid = (lo * hi).sqrt();
        if stable(mid)? {
            lo = mid;
        } else {
            hi = mid;
        }
    }
    Ok(lo)
}

/// Global damping matrix (3n × 3n, force = −C·v) of the bare spring dampers at rest, each
/// acting along its spring; the elements must be aligned with the world axes, as
/// `assemble_linear_stiffness` checks.
fn assemble_spring_damping(mesh: &HexMesh) -> DMatrix<f64> {
    let n = mesh.node_count();
    let mut c = DMatrix::zeros(3 * n, 3 * n);
    for (corners, &class) in mesh.elements.iter().zip(&mesh.element_class) {
        let coeffs = &mesh.classes[class as usize];
        let offsets = coeffs.corner_offsets_m();
        for (s, &(a, b, _)) in SPRINGS.iter().enumerate() {
            let d = (offsets[b] - offsets[a]).normalize();
            let (na, nb) = (corners[a] as usize, corners[b] as usize);
            for i in 0..3 {
                for j in 0..3 {
                    let v = coeffs.spring_damping_n_s_per_m[s] * d[i] * d[j];
                    c[(3 * na + i, 3 * na + j)] += v;
                    c[(3 * nb + i, 3 * nb + j)] += v;
                    c[(3 * na + i, 3 * nb + j)] -= v;
                    c[(3 * nb + i, 3 * na + j)] -= v;
                }
            }
        }
    }
    c
}

/// The production velocity-Verlet step linearised about rest, on the free DOFs.
///
/// The integrator evaluates damping with the half-step velocity, so the state is
/// (x, w = v(t − h/2)): a = A·x + B·w with A = −M⁻¹·K and B = −M⁻¹·C, then
/// x' = x + h·(w + h·a) and w' = w + h·a. K and C come from the element matrices (see the
/// module doc), with the pressure's follower stiffness left out (2 % of E against E).
struct LinearVerlet {
    dofs: Vec<usize>,
    k: DMatrix<f64>,
    c: DMatrix<f64>,
    a: DMatrix<f64>,
    b: DMatrix<f64>,
}

impl LinearVerlet {
    fn new(scene: &Scene) -> Result<Self> {
        let dofs = free_dofs(scene, &scene.mesh.rest_positions_m)?;
        let k_full = assemble_linear_stiffness(&scene.mesh)?;
        let c_full = assemble_spring_damping(&scene.mesh);
        let m = dofs.len();
        let k = DMatrix::from_fn(m, m, |r, q| k_full[(dofs[r], dofs[q])]);
        let c = DMatrix::from_fn(m, m, |r, q| c_full[(dofs[r], dofs[q])]);
        let inv_mass = |r: usize| 1.0 / scene.mesh.node_mass_kg[dofs[r] / 3];
        let a = DMatrix::from_fn(m, m, |r, q| -k[(r, q)] * inv_mass(r));
        let b = DMatrix::from_fn(m, m, |r, q| -c[(r, q)] * inv_mass(r));
        Ok(LinearVerlet { dofs, k, c, a, b })
    }

    /// Central-difference Jacobians of the force kernel at rest against −K and −C, each as
    /// max |J + M| / max |M| (see `CriticalStep`).
    fn kernel_mismatch(&self, scene: &Scene) -> (f64, f64) {
        let rest = &scene.mesh.rest_positions_m;
        let n = scene.node_count();
        let size = scene
            .mesh
            .classes
            .iter()
            .flat_map(|c| c.shape.edges_m)
            .fold(0.0, f64::max);
        let h = 1e-7 * size;
        // Velocity scale giving damping forces of the same order as the elastic ones.
        let vh = h * TimeStepBound::new(scene, 1.0).omega_max_rad_per_s;
        let zero = vec![V3::zeros(); n];
        let (mut fp, mut fm) = (zero.clone(), zero.clone());
        let (mut x, mut v) = (rest.clone(), zero.clone());
        let (mut dk, mut dc) = (0.0f64, 0.0f64);
        for (col, &q) in self.dofs.iter().enumerate() {
            x[q / 3][q % 3] += h;
            scene.internal_forces(&x, Some(&zero), &mut fp);
            x[q / 3][q % 3] -= 2.0 * h;
            scene.internal_forces(&x, Some(&zero), &mut fm);
            x[q / 3][q % 3] += h;
            for (row, &r) in self.dofs.iter().enumerate() {
                let j = (fp[r / 3][r % 3] - fm[r / 3][r % 3]) / (2.0 * h);
                dk = dk.max((j + self.k[(row, col)]).abs());
            }
            v[q / 3][q % 3] = vh;
            scene.internal_forces(rest, Some(&v), &mut fp);
            v[q / 3][q % 3] = -vh;
            scene.internal_forces(rest, Some(&v), &mut fm);
            v[q / 3][q % 3] = 0.0;
            for (row, &r) in self.dofs.iter().enumerate() {
                let j = (fp[r / 3][r % 3] - fm[r / 3][r % 3]) / (2.0 * vh);
                dc = dc.max((j + self.c[(row, col)]).abs());
            }
        }
        let scale = |m: &DMatrix<f64>| m.amax().max(f64::MIN_POSITIVE);
        (dk / scale(&self.k), dc / scale(&self.c))
    }

    fn spectral_radius(&self, h: f64) -> Result<f64> {
        let m = self.a.nrows();
        let id = DMatrix::<f64>::identity(m, m);
        let ha = &self.a * h;
        let hb = &self.b * h;
        let mut map = DMatrix::zeros(2 * m, 2 * m);
        map.view_mut((0, 0), (m, m)).copy_from(&(&id + &ha * h));
        map.view_mut((0, m), (m, m)).copy_from(&((&id + &hb) * h));
        map.view_mut((m, 0), (m, m)).copy_from(&ha);
        map.view_mut((m, m), (m, m)).copy_from(&(&id + &hb));
        let eig = map
            .try_schur(1e-12, 10_000)
            .ok_or_else(|| Error::External("Schur decomposition did not converge".into()))?
            .complex_eigenvalues();
        Ok(eig.iter().map(|z| z.norm()).fold(0.0, f64::max))
    }
}

fn opt_max(v: impl Iterator<Item = Option<f64>>) -> String {
    let vals: Vec<f64> = v.flatten().collect();
    if vals.is_empty() {
        "–".into()
    } else {
        format!(
            "{:.1e}",
            vals.iter().cloned().fold(f64::NEG_INFINITY, f64::max)
        )
    }
}

/// How an overstep run ended, in the words of the report's table.
fn overstep_kind(run: &RunOutcome) -> &'static str {
    if run.divergence.is_some() {
        "diverged"
    } else if run.passed() {
        "at equilibrium"
    } else if run.converged {
        "converged elsewhere"
    } else {
        "not converged"
    }
}

impl StabilityReport {
    /// Markdown: the automatic step's outcomes over the grid, and the measured critical steps.
    pub fn to_markdown(&self) -> String {
        use crate::markdown::Table;
        let c = &self.config;
        let mut s = String::new();
        s.push_str("## Explicit integrator: automatic time step and blow-up detection\n\n");
        s.push_str(&format!(
            "Block of {}×{}×{} elements clamped at z = 0, top pressure {:.0} %·E (follower) and \
             a sideways body force giving the same strain scale, springs at {} × critical \
             damping (the thesis's regime). Grid: E {:?} Pa, ν {:?}, element size {:?} m, \
             shapes {:?}, ρ {:?} kg/m³: {} runs. *Automatic*: step = {} × `TimeStepBound`'s \
             critical step. A run passes when `run_to_equilibrium` reports equilibrium \
             (residual ≤ 1e-6), peak kinetic energy ≤ the loads' work and the positions agree \
             with a dense Newton solve to 1e-3 of the largest displacement. *Overstep*: {} × \
             `TimeStepBound`'s critical step, {} steps at most, which should end in \
             `Error::Diverged`; otherwise it stays at the equilibrium (the step is below the \
             true limit), converges elsewhere (a false equilibrium, smallest element volume \
             given) or runs out of steps. E, ρ and size only rescale time (loads scale with \
             E), so within a (shape, ν) row every run takes the same number of steps.\n\n",
            c.cells[0],
            c.cells[1],
            c.cells[2],
            100.0 * c.load_strain,
            c.damping_ratio,
            c.youngs_moduli_pa,
            c.poisson_ratios,
            c.element_sizes_m,
            c.element_shapes,
            c.densities_kg_per_m3,
            self.cases.len(),
            c.safety,
            c.overstep_factor,
            c.divergence_steps
        ));
        let mut table = Table::new([
            "shape",
            "ν",
            "runs",
            "automatic passed",
            "automatic diverged (earliest step)",
            "automatic failed unflagged",
            "steps (max)",
            "worst equilibrium error (passed runs)",
            "worst KE / work",
            "overstep / linearised limit",
            "overstep outcomes",
        ]);
        for &shape in &c.element_shapes {
            let same_shape = |edges: [f64; 3]| {
                (edges[1] / edges[0] - shape[1] / shape[0]).abs() < 1e-9
                    && (edges[2] / edges[0] - shape[2] / shape[0]).abs() < 1e-9
            };
            for &nu in &c.poisson_ratios {
                let group: Vec<&StabilityCase> = self
                    .cases
                    .iter()
                    .filter(|k| k.poisson_ratio == nu && same_shape(k.edges_m))
                    .collect();
                let diverged: Vec<usize> = group
                    .iter()
                    .filter_map(|k| k.automatic.divergence.as_ref().map(|d| d.step))
                    .collect();
                let passed_error = |r: &RunOutcome| r.equilibrium_error.filter(|_| r.passed());
                let limit = self
                    .critical_steps
                    .iter()
                    .find(|k| k.poisson_ratio == nu && same_shape(k.element_shape))
                    .map_or("–".to_string(), |k| {
                        format!("{:.3}", c.overstep_factor / k.linear_ratio)
                    });
                let mut outcomes = Vec::new();
                for kind in [
                    "diverged",
                    "at equilibrium",
                    "converged elsewhere",
                    "not converged",
                ] {
                    let runs: Vec<&RunOutcome> = group
                        .iter()
                        .map(|k| &k.overstep)
                        .filter(|r| overstep_kind(r) == kind)
                        .collect();
                    if runs.is_empty() {
                        continue;
                    }
                    let volume = runs
                        .iter()
                        .filter_map(|r| r.min_volume_ratio)
                        .fold(f64::INFINITY, f64::min);
                    outcomes.push(if kind == "converged elsewhere" {
                        format!("{} {kind} (volume ≥ {volume:.2})", runs.len())
                    } else {
                        format!("{} {kind}", runs.len())
                    });
                }
                table.row([
                    format!("{shape:?}"),
                    nu.to_string(),
                    group.len().to_string(),
                    group
                        .iter()
                        .filter(|k| k.automatic.passed())
                        .count()
                        .to_string(),
                    if diverged.is_empty() {
                        "0".to_string()
                    } else {
                        format!(
                            "{} ({})",
                            diverged.len(),
                            diverged.iter().min().unwrap_or(&0)
                        )
                    },
                    group
                        .iter()
                        .filter(|k| !k.automatic.passed() && k.automatic.divergence.is_none())
                        .count()
                        .to_string(),
                    group
                        .iter()
                        .map(|k| k.automatic.steps)
                        .max()
                        .unwrap_or(0)
                        .to_string(),
                    opt_max(group.iter().map(|k| passed_error(&k.automatic))),
                    opt_max(group.iter().map(|k| k.automatic.peak_kinetic_over_work)),
                    limit,
                    outcomes.join(", "),
                ]);
            }
        }
        table.write_to(&mut s);
        let range = |f: &dyn Fn(&StabilityCase) -> f64| {
            let v: Vec<f64> = self.cases.iter().map(f).collect();
            (
                v.iter().cloned().fold(f64::INFINITY, f64::min),
                v.iter().cloned().fold(f64::NEG_INFINITY, f64::max),
            )
        };
        let (a, b) = range(&|k| k.automatic.step_s);
        s.push_str(&format!("\nAutomatic step: {a:.2e} – {b:.2e} s. "));
        let (a, b) = range(&|k| k.automatic.step_s / k.thesis_step_s);
        s.push_str(&format!(
            "Automatic step over the thesis's rule (2 % of the stiffest spring's undamped \
             period on the lightest node): {a:.2} – {b:.2}. "
        ));
        let (a, b) = range(&|k| k.max_displacement_over_height);
        s.push_str(&format!(
            "Largest displacement / height at equilibrium: {a:.4} – {b:.4}. "
        ));
        let (_, b) = range(&|k| k.production_solver_difference);
        s.push_str(&format!(
            "The production `QuasiStaticSolver` lands within {b:.1e} (relative to the largest \
             displacement) of the dense Newton reference.\n"
        ));
        if let Some(k) = self
            .cases
            .iter()
            .find(|k| !k.automatic.passed() && k.automatic.divergence.is_none())
        {
            s.push_str(&format!(
                "\nExample unflagged failure (ν = {}): `run_to_equilibrium` returned Ok after \
                 {} steps, converged {}, residual {:.2}, positions off the equilibrium by \
                 {:.2} × the static displacement, smallest element volume {:.2} × rest.\n",
                k.poisson_ratio,
                k.automatic.steps,
                k.automatic.converged,
                k.automatic.residual.unwrap_or(f64::NAN),
                k.automatic.equilibrium_error.unwrap_or(f64::NAN),
                k.automatic.min_volume_ratio.unwrap_or(f64::NAN)
            ));
        }
        if let Some(d) = self
            .cases
            .iter()
            .find_map(|k| k.automatic.divergence.as_ref())
        {
            s.push_str(&format!(
                "\nExample automatic-step blow-up: `Error::Diverged {{ step: {}, cause: \"{}\" }}`.\n",
                d.step, d.cause
            ));
        }
        if let Some(d) = self
            .cases
            .iter()
            .find_map(|k| k.overstep.divergence.as_ref())
        {
            s.push_str(&format!(
                "\nExample overstep detection: `Error::Diverged {{ step: {}, cause: \"{}\" }}`.\n",
                d.step, d.cause
            ));
        }
        for (kind, why) in [
            (
                "converged elsewhere",
                "the unstable mode turned elements inside out and the run settled in that \
                 false equilibrium, which neither `BlowUpGuard` nor the convergence test \
                 rejects",
            ),
            (
                "not converged",
                "a bounded instability: the oscillation saturates instead of growing \
                 exponentially, so `BlowUpGuard` does not flag it and the run ends Ok at its \
                 step budget",
            ),
        ] {
            if let Some(k) = self
                .cases
                .iter()
                .find(|k| overstep_kind(&k.overstep) == kind)
            {
                s.push_str(&format!(
                    "\nExample overstep {kind} (ν = {}): {} steps, residual {:.1e}, positions \
                     off the equilibrium by {:.2} × the static displacement, smallest element \
                     volume {:.2} × rest: {why}.\n",
                    k.poisson_ratio,
                    k.overstep.steps,
                    k.overstep.residual.unwrap_or(f64::NAN),
                    k.overstep.equilibrium_error.unwrap_or(f64::NAN),
                    k.overstep.min_volume_ratio.unwrap_or(f64::NAN)
                ));
            }
        }
        if !self.critical_steps.is_empty() {
            s.push_str(
                "\n### True critical step over the bounds\n\n\
                 Bisection on the step (E = 1 kPa, ρ = 700 kg/m³, 10 mm; the ratios do not \
                 depend on them). *Linearised*: spectral radius of the velocity-Verlet map \
                 linearised at rest (damping on the half-step velocity, as the integrator \
                 does) ≤ 1; the map is built from `linear_stiffness()` and the bare spring \
                 dampers, and the last two columns compare the force kernel's Jacobians at \
                 rest with them (max abs(J + K) / max abs(K), same for C). *Empirical*: plain \
                 `ExplicitIntegrator::step`s settle at the Newton equilibrium. \
                 *`run_to_equilibrium`*: it converges there (it refreshes the accelerations \
                 with the full-step velocity at every check, which shifts its limit). \
                 *Undamped*: linearised, dampers removed (bound recomputed). A ratio below 1 \
                 means the bound is not a bound; above the overstep factor, the overstep \
                 cannot diverge.\n\n",
            );
            let mut table = Table::new([
                "shape",
                "ν",
                "ζ",
                "linearised / `TimeStepBound`",
                "empirical / `TimeStepBound`",
                "`run_to_equilibrium` / `TimeStepBound`",
                "undamped linearised / `TimeStepBound`",
                "kernel vs K",
                "kernel vs C",
            ]);
            for k in &self.critical_steps {
                table.row([
                    format!(
                        "{:?}",
                        k.element_shape.map(|v| (v * 1000.0).round() / 1000.0)
                    ),
                    k.poisson_ratio.to_string(),
                    k.damping_ratio.to_string(),
                    format!("{:.3}", k.linear_ratio),
                    format!("{:.3}", k.empirical_ratio),
                    format!("{:.3}", k.run_to_equilibrium_ratio),
                    format!("{:.3}", k.undamped_linear_ratio),
                    format!("{:.0e}", k.kernel_stiffness_mismatch),
                    format!("{:.0e}", k.kernel_damping_mismatch),
                ]);
            }
            table.write_to(&mut s);
        }
        s.push_str(&format!(
            "\nEvery automatic run stable and at equilibrium: **{}**. Every overstep caught: \
             **{}**.\n",
            if self.all_stable { "yes" } else { "NO" },
            if self.all_oversteps_caught {
                "yes"
            } else {
                "NO"
            }
        ));
        s
    }
}
