//! Explicit velocity-Verlet dynamics (thesis §4.1.3.3) with a time step derived from a bound on
//! the highest eigenfrequency, and blow-up detection.
//!
//! Damping forces use the half-step velocity v(t + h/2), the only velocity available when
//! a(t + h) is computed without an implicit solve.

use serde::Serialize;

use super::scene::Scene;
use crate::math::V3;
use crate::model::element::SPRINGS;
use crate::{Error, Result};

/// The stable time step of a scene and the bounds it came from.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct TimeStepBound {
    /// Upper bound on the highest angular eigenfrequency ω_max (rad/s), from Gershgorin discs of
    /// M⁻¹K with K the small-strain stiffness of springs and corrections (and of linear
    /// contact penalties, n = 1).
    pub omega_max_rad_per_s: f64,
    /// Upper bound on the damping rate of the highest mode (1/s), from Gershgorin discs of M⁻¹C.
    pub damping_rate_per_s: f64,
    /// Largest stable step for that bound: (2/ω)(√(1+ξ²) − ξ), ξ = damping rate / (2ω).
    pub critical_step_s: f64,
    /// Step used: the critical step times the safety factor.
    pub step_s: f64,
}

impl TimeStepBound {
    /// Computes the bound for `scene` and applies `safety` (< 1) to it.
    pub fn new(scene: &Scene, safety: f64) -> Self {
        let mesh = &scene.mesh;
        // Absolute row sums of each class's element stiffness and damping matrices, per DOF.
        let rows: Vec<([f64; 24], [f64; 24])> = mesh
            .classes
            .iter()
            .map(|c| {
                let k = c.linear_stiffness();
                let kr = std::array::from_fn(|r| k.row(r).iter().map(|v| v.abs()).sum());
                // The damping matrix has the spring matrix's pattern with c in place of k.
                let mut cr = [0.0; 24];
                let offs = c.corner_offsets_m();
                for (s, (a, b, _)) in SPRINGS.iter().enumerate() {
                    let n = (offs[*b] - offs[*a]).normalize();
                    for i in 0..3 {
                        let row: f64 = (0..3).map(|j| (n[i] * n[j]).abs()).sum();
                        let v = 2.0 * c.spring_damping_n_s_per_m[s] * row;
                        cr[3 * a + i] += v;
                        cr[3 * b + i] += v;
                    }
                }
                (kr, cr)
            })
            .collect();
        let mut k_sum = vec![[0.0f64; 3]; mesh.node_count()];
        let mut c_sum = vec![[0.0f64; 3]; mesh.node_count()];
        for (corners, &class) in mesh.elements.iter().zip(&mesh.element_class) {
            let (kr, cr) = &rows[class as usize];
            for (k, &node) in corners.iter().enumerate() {
                for i in 0..3 {
                    k_sum[node as usize][i] += kr[3 * k + i];
                    c_sum[node as usize][i] += cr[3 * k + i];
                }
            }
        }
        // A linear penalty (n = 1) is a spring to the obstacle of stiffness k on each tested
        // node; other exponents have no bound independent of the penetration (their tangent
        // n·k·δⁿ⁻¹ grows with it), and their step is the caller's to choose.
        for o in &scene.contact().obstacles {
            if o.law.exponent == 1.0 {
                for &n in &o.nodes {
                    for k in &mut k_sum[n as usize] {
                        *k += o.law.stiffness_n_per_m_pow_n;
                    }
                }
            }
        }
        let mut omega2: f64 = 0.0;
        let mut gamma: f64 = 0.0;
        for n in 0..mesh.node_count() {
            let m = mesh.node_mass_kg[n];
            for i in 0..3 {
                omega2 = omega2.max(k_sum[n][i] / m);
                gamma = gamma.max(c_sum[n][i] / m);
            }
        }
        let omega = omega2.sqrt();
        let xi = gamma / (2.0 * omega);
        let critical = 2.0 / omega * ((1.0 + xi * xi).sqrt() - xi);
        TimeStepBound {
            omega_max_rad_per_s: omega,
            damping_rate_per_s: gamma,
            critical_step_s: critical,
            step_s: critical * safety,
        }
    }
}

/// Settings of the explicit integrator.
#[derive(Debug, Clone, Serialize)]
pub struct ExplicitSettings {
    /// Fraction of the critical step to use (automatic step), in (0, 1].
    pub safety: f64,
    /// Fixed step in seconds, overriding the automatic one (for stability studies).
    pub fixed_step_s: Option<f64>,
    /// Give up after this many steps.
    pub max_steps: usize,
    /// Equilibrium when the relative force residual is below this…
    pub residual_tolerance: f64,
    /// …and the kinetic energy is below this fraction of the peak kinetic energy seen.
    pub kinetic_energy_fraction: f64,
    /// Steps between equilibrium and blow-up checks.
    pub check_every: usize,
    /// Raised by another thread to stop at the next check with [`Error::Cancelled`].
    #[serde(skip)]
    pub cancel: Option<super::CancelFlag>,
    /// Ends the message of an inverted element (see [`BlowUpGuard::with_inversion_hint`]).
    #[serde(skip)]
    pub inversion_hint: Option<&'static str>,
    /// Give up (not converged) when the best residual has not fallen by a tenth within this
    /// many steps: a relaxation that stagnates would otherwise run to `max_steps` (minutes).
    pub stall_steps: Option<usize>,
}

impl Default for ExplicitSettings {
    fn default() -> Self {
        ExplicitSettings {
            safety: 0.9,
            fixed_step_s: None,
            max_steps: 1_000_000,
            residual_tolerance: 1e-6,
            kinetic_energy_fraction: 1e-10,
            check_every: 50,
            cancel: None,
            inversion_hint: None,
            stall_steps: None,
        }
    }
}

/// Outcome of an explicit run.
#[derive(Debug, Clone, Serialize)]
pub struct ExplicitReport {
    /// Steps taken.
    pub steps: usize,
    /// Step used, seconds.
    pub step_s: f64,
    /// Simulated time, seconds.
    pub time_s: f64,
    /// Relative force residual at the end.
    pub residual: f64,
    /// Kinetic energy at the end, joules.
    pub kinetic_energy_j: f64,
    /// Whether equilibrium was reached.
    pub converged: bool,
}

/// Velocity-Verlet integrator state: positions, velocities, accelerations, no allocation per step.
pub struct ExplicitIntegrator<'s> {
    scene: &'s Scene,
    /// Node positions in metres.
    pub positions: Vec<V3>,
    /// Node velocities in m/s.
    pub velocities: Vec<V3>,
    accelerations: Vec<V3>,
    force: Vec<V3>,
    scratch: Vec<V3>,
    inv_mass: Vec<f64>,
    /// Simulated time in seconds.
    pub time_s: f64,
    /// Steps taken so far.
    pub steps: usize,
}

impl<'s> ExplicitIntegrator<'s> {
    /// Starts at rest in the constrained rest configuration.
    pub fn new(scene: &'s Scene) -> Self {
        let n = scene.node_count();
        let mut it = ExplicitIntegrator {
            scene,
            positions: scene.initial_positions(),
            velocities: vec![V3::zeros(); n],
            accelerations: vec![V3::zeros(); n],
            force: vec![V3::zeros(); n],
            scratch: vec![V3::zeros(); n],
            inv_mass: scene.mesh.node_mass_kg.iter().map(|m| 1.0 / m).collect(),
            time_s: 0.0,
            steps: 0,
        };
        it.update_accelerations(false);
        it
    }

    /// Starts at rest from given positions (constrained nodes are moved onto their constraints).
    pub fn from_positions(scene: &'s Scene, positions_m: &[V3]) -> Result<Self> {
        if positions_m.len() != scene.node_count() {
            return Err(Error::InvalidModel(format!(
                "{} positions for {} nodes",
                positions_m.len(),
                scene.node_count()
            )));
        }
        scene.check_finite(positions_m, 0)?;
        let mut it = Self::new(scene);
        it.positions.copy_from_slice(positions_m);
        scene.constraints.project_positions(&mut it.positions);
        it.update_accelerations(false);
        Ok(it)
    }

    fn update_accelerations(&mut self, with_velocities: bool) {
        let vel = with_velocities.then_some(&self.velocities[..]);
        self.scene
            .total_forces_at(&self.positions, vel, self.time_s, &mut self.force);
        self.scene
            .constraints
            .project_field(&self.positions, &mut self.force);
        for ((a, f), im) in self
            .accelerations
            .iter_mut()
            .zip(&self.force)
            .zip(&self.inv_mass)
        {
            *a = f * *im;
        }
    }

    /// Advances one velocity-Verlet step of `h` seconds.
    pub fn step(&mut self, h: f64) {
        for ((x, v), a) in self
            .positions
            .iter_mut()
            .zip(self.velocities.iter_mut())
            .zip(&self.accelerations)
        {
            *v += a * (0.5 * h);
            *x += *v * h;
        }
        self.scene
            .constraints
            .project_positions(&mut self.positions);
        self.scene
            .constraints
            .project_field(&self.positions, &mut self.velocities);
        self.scene
            .one_sided
            .enforce(&mut self.positions, &mut self.velocities);
        // Moving obstacles are where they are at the end of the step.
        self.time_s += h;
        self.update_accelerations(true);
        for (v, a) in self.velocities.iter_mut().zip(&self.accelerations) {
            *v += a * (0.5 * h);
        }
        self.scene
            .constraints
            .project_field(&self.positions, &mut self.velocities);
        self.steps += 1;
    }

    /// Kinetic energy in joules.
    pub fn kinetic_energy_j(&self) -> f64 {
        self.velocities
            .iter()
            .zip(&self.scene.mesh.node_mass_kg)
            .map(|(v, m)| 0.5 * m * v.norm_squared())
            .sum()
    }

    /// Runs to equilibrium (or `max_steps`); detects blow-up.
    pub fn run_to_equilibrium(&mut self, settings: &ExplicitSettings) -> Result<ExplicitReport> {
        let h = match settings.fixed_step_s {
            Some(h) => h,
            None => TimeStepBound::new(self.scene, settings.safety).step_s,
        };
        if !(h.is_finite() && h > 0.0) {
            return Err(Error::InvalidModel(format!(
                "time step {h} s is not positive"
            )));
        }
        let mut guard = BlowUpGuard::new(&self.scene.mesh.rest_positions_m);
        if let Some(hint) = settings.inversion_hint {
            guard = guard.with_inversion_hint(hint);
        }
        let mut peak_ke: f64 = 0.0;
        let check = settings.check_every.max(1);
        let mut residual = f64::INFINITY;
        let mut ke = 0.0;
        // The best residual, and the step since which it has not fallen by a tenth.
        let (mut best, mut best_since) = (f64::INFINITY, self.steps);
        while self.steps < settings.max_steps {
            for _ in 0..check {
                self.step(h);
            }
            ke = self.kinetic_energy_j();
            peak_ke = peak_ke.max(ke);
            guard.check(self.scene, &self.positions, ke, self.steps)?;
            if settings
                .cancel
                .as_ref()
                .is_some_and(|c| c.load(std::sync::atomic::Ordering::Relaxed))
            {
                return Err(Error::Cancelled(
                    "stopped during explicit relaxation".into(),
                ));
            }
            let (a, b) = (&mut self.force, &mut self.scratch);
            residual = self
                .scene
                .relative_residual_at(&self.positions, self.time_s, (a, b));
            if residual < 0.9 * best {
                (best, best_since) = (residual, self.steps);
            }
            if residual <= settings.residual_tolerance
                && ke <= settings.kinetic_energy_fraction * peak_ke.max(f64::MIN_POSITIVE)
            {
                self.update_accelerations(true);
                return Ok(ExplicitReport {
                    steps: self.steps,
                    step_s: h,
                    time_s: self.time_s,
                    residual,
                    kinetic_energy_j: ke,
                    converged: true,
                });
            }
            self.update_accelerations(true);
            if settings
                .stall_steps
                .is_some_and(|n| self.steps - best_since > n)
            {
                break;
            }
        }
        Ok(ExplicitReport {
            steps: self.steps,
            step_s: h,
            time_s: self.time_s,
            residual,
            kinetic_energy_j: ke,
            converged: false,
        })
    }
}

/// Detects numerical blow-up: non-finite values, sustained exponential growth of kinetic
/// energy, or nodes flung far beyond the mesh.
#[derive(Debug, Clone)]
pub struct BlowUpGuard {
    extent_m: f64,
    last_ke: f64,
    growth_streak: usize,
    growth_since: usize,
    /// Ends the message of an inverted element: what makes it likely in this use.
    inversion_hint: &'static str,
}

impl BlowUpGuard {
    /// A guard for a mesh whose rest positions are given.
    pub fn new(rest: &[V3]) -> Self {
        let (mut lo, mut hi) = (V3::repeat(f64::INFINITY), V3::repeat(f64::NEG_INFINITY));
        for p in rest {
            lo = lo.inf(p);
            hi = hi.sup(p);
        }
        BlowUpGuard {
            extent_m: (hi - lo).norm().max(f64::MIN_POSITIVE),
            last_ke: 0.0,
            growth_streak: 0,
            growth_since: 0,
            inversion_hint: "time step above the stability limit, or a load too large for the mesh",
        }
    }

    /// The same guard, whose message for an inverted element ends with `hint` (the explicit
    /// relaxation inside a static solve runs at a stable step: there the load is the cause).
    pub fn with_inversion_hint(mut self, hint: &'static str) -> Self {
        self.inversion_hint = hint;
        self
    }

    /// Returns an error naming the step and the cause if the state has blown up.
    pub fn check(&mut self, scene: &Scene, x: &[V3], ke: f64, step: usize) -> Result<()> {
        scene.check_finite(x, step)?;
        scene.check_not_inverted(x, step, self.inversion_hint)?;
        if !ke.is_finite() {
            return Err(Error::Diverged {
                step,
                cause: "kinetic energy is not finite".into(),
            });
        }
        let rest = &scene.mesh.rest_positions_m;
        if let Some((n, d)) = x
            .iter()
            .zip(rest)
            .map(|(p, r)| (p - r).norm())
            .enumerate()
            .find(|(_, d)| *d > 100.0 * self.extent_m)
        {
            return Err(Error::Diverged {
                step,
                cause: format!(
                    "node {n} moved {d:.3e} m, over 100 times the mesh size ({:.3e} m)",
                    self.extent_m
                ),
            });
        }
        // Ten consecutive checks each at least doubling the kinetic energy: the signature of
        // an unstable mode, which physical loading never produces while damped.
        if ke > 2.0 * self.last_ke && self.last_ke > 0.0 {
            if self.growth_streak == 0 {
                self.growth_since = step;
            }
            self.growth_streak += 1;
        } else {
            self.growth_streak = 0;
        }
        let first = self.last_ke;
        self.last_ke = ke;
        if self.growth_streak >= 10 {
            return Err(Error::Diverged {
                step,
                cause: format!(
                    "kinetic energy grew exponentially since step {} (now {ke:.3e} J, previous \
                     check {first:.3e} J): time step above the stability limit?",
                    self.growth_since
                ),
            });
        }
        Ok(())
    }
}
