//! Quasi-static equilibrium: positions where internal and external forces balance on every
//! free direction, found without simulating inertia.
//!
//! Newton–Krylov: each Newton step solves J·δ = r by restarted GMRES, with J·v taken as a
//! finite difference of the exact nonlinear forces (springs, corrections, follower pressure)
//! and a geometric-multigrid V-cycle on the small-strain stiffness as preconditioner
//! (block Jacobi when the mesh is not a voxel lattice). The preconditioner is built once per
//! scene and reused across solves, so a breathing sequence pays the set-up once.
//! Large loads can be applied in increments; each Newton step is backtracked until the
//! residual decreases.

use std::time::Instant;

use nalgebra::Matrix3;
use serde::Serialize;

use super::linalg::{self, flat, nodes, nodes_mut};
use super::multigrid::{project_flat, sparse, Lattice, Multigrid};
use super::scene::Scene;
use crate::math::V3;
use crate::model::one_sided::ActiveSetChange;
use crate::model::{ConstraintSet, NodeConstraint, OneSidedPlanes};
use crate::{Error, Result};

/// Settings of the quasi-static solver.
#[derive(Debug, Clone, Serialize)]
pub struct QuasiStaticSettings {
    /// Stop when ‖free part of total force‖ / max(‖external‖, ‖internal‖) is below this.
    pub tolerance: f64,
    /// Loads (forces, pressures, gravity and imposed displacements) are applied in this many
    /// equal increments, each solved to equilibrium; more steps help very large deformations.
    pub load_steps: usize,
    /// Newton iterations allowed per load step.
    pub max_newton_iterations: usize,
    /// Krylov iterations allowed per Newton iteration.
    pub max_linear_iterations: usize,
    /// Which preconditioner to build.
    pub preconditioner: PreconditionerKind,
    /// Chebyshev smoothing degree of the multigrid V-cycle (fine-level products per
    /// half-cycle): lower is cheaper per Krylov iteration, weaker per iteration.
    pub smoothing_degree: usize,
    /// If Newton and pseudo-time steps fail (non-conservative corrections near a mechanism can
    /// trap them), continue with critically damped explicit relaxation for at most this many
    /// steps; 0 disables the fallback.
    pub relaxation_max_steps: usize,
    /// Raised by another thread to stop the solve at its next Newton, Krylov or relaxation
    /// check (a cancelled job must stop within a second, not at the end of a long solve).
    #[serde(skip)]
    pub cancel: Option<super::CancelFlag>,
}

/// Preconditioner of the Krylov solves.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
pub enum PreconditionerKind {
    /// Multigrid when the mesh lies on one voxel lattice (bodies touching on it, such as the
    /// two lungs, stay apart on every level), else block Jacobi.
    Auto,
    /// Block Jacobi (3 × 3 nodal blocks) always: for comparison.
    BlockJacobi,
}

impl Default for QuasiStaticSettings {
    fn default() -> Self {
        QuasiStaticSettings {
            tolerance: 1e-6,
            load_steps: 1,
            max_newton_iterations: 40,
            max_linear_iterations: 300,
            preconditioner: PreconditionerKind::Auto,
            smoothing_degree: 4,
            relaxation_max_steps: 2_000_000,
            cancel: None,
        }
    }
}

/// What a quasi-static solve did.
#[derive(Debug, Clone, Serialize, Default)]
pub struct SolveReport {
    /// Newton iterations, all load steps together.
    pub newton_iterations: usize,
    /// Krylov iterations, all Newton iterations together.
    pub linear_iterations: usize,
    /// Final relative force residual.
    pub residual: f64,
    /// Load increments used.
    pub load_steps: usize,
    /// Newton steps taken as pseudo-time steps (σ > 0) because plain Newton could not
    /// reduce the residual: non-zero flags a mechanism or a very large load.
    pub pseudo_time_steps: usize,
    /// Explicit relaxation steps taken by the fallback (0 when Newton converged).
    pub relaxation_steps: usize,
    /// Multigrid levels (1 = block Jacobi or a single dense level).
    pub multigrid_levels: usize,
    /// Preconditioner set-up time in seconds (paid once per solver).
    pub setup_time_s: f64,
    /// Wall time of this solve in seconds (set-up excluded).
    pub wall_time_s: f64,
    /// Newton solves repeated because one-sided contacts were released or engaged
    /// ([`crate::model::OneSidedPlanes`]; 0 without them or when the set held).
    pub contact_rounds: usize,
    /// Contacts released (the plane would have pulled) over those rounds.
    pub contacts_released: usize,
    /// Contacts engaged (a free node crossed its plane) over those rounds.
    pub contacts_engaged: usize,
}

enum Preconditioner {
    Multigrid(Box<Multigrid>),
    BlockJacobi {
        diag: Vec<Matrix3<f64>>,
        inverse: Vec<Matrix3<f64>>,
        projector: Vec<Option<Matrix3<f64>>>,
    },
}

/// Quasi-static solver bound to one scene; reusable across solves (e.g. breathing frames).
pub struct QuasiStaticSolver<'s> {
    scene: &'s Scene,
    settings: QuasiStaticSettings,
    /// Constraint projectors at rest of the scene's constraints (without the contacts).
    projector: Vec<Option<Matrix3<f64>>>,
    /// The voxel lattice the multigrid is built on, if the mesh lies on one.
    lattice: Option<Lattice>,
    constrained: Vec<(u32, Matrix3<f64>)>,
    /// Nodes on curved surfaces, whose free directions the Krylov operator takes where the
    /// node is (the preconditioner keeps those at rest).
    curved: Vec<CurvedNode>,
    preconditioner: Preconditioner,
    /// Current pseudo-transient shift σ of the preconditioner.
    shift: f64,
    /// Typical stiffness-to-mass ratio (median diagonal), the scale of σ.
    shift_scale: f64,
    /// Imposed displacements are applied at λ times this (1: in step with the loads).
    imposed_motion_scale: f64,
    /// Moving obstacles are held where they are at this time, s.
    contact_time_s: f64,
    /// Which of the scene's one-sided contacts touch (held on their plane); kept from one
    /// solve to the next, as the positions are.
    contact_active: Vec<bool>,
    /// Length of `constrained` without the touching one-sided contacts, which follow.
    base_constrained: usize,
    setup_time_s: f64,
    /// GMRES's basis, reused by every linear solve.
    krylov: linalg::KrylovWorkspace,
}

impl<'s> QuasiStaticSolver<'s> {
    /// Prepares the solver and its preconditioner for `scene`.
    pub fn new(scene: &'s Scene, settings: QuasiStaticSettings) -> Result<Self> {
        if !(settings.tolerance > 0.0 && settings.tolerance.is_finite()) {
            return Err(Error::InvalidModel(format!(
                "solver tolerance must be positive, got {}",
                settings.tolerance
            )));
        }
        let start = Instant::now();
        let rest = &scene.mesh.rest_positions_m;
        let projector = projectors(&scene.constraints, rest);
        let lattice = match settings.preconditioner {
            PreconditionerKind::Auto => Lattice::infer(&scene.mesh),
            PreconditionerKind::BlockJacobi => None,
        };
        // Every one-sided contact touches at rest (it rests on its plane).
        let contact_active = vec![true; scene.one_sided.len()];
        let preconditioner = build_preconditioner(
            scene,
            &settings,
            lattice.as_ref(),
            with_contact_projectors(&projector, &scene.one_sided, &contact_active),
        );
        let mut constrained = sparse(&projector);
        let base_constrained = constrained.len();
        push_contact_projectors(&scene.one_sided, &contact_active, &mut constrained);
        let curved = constrained
            .iter()
            .enumerate()
            .filter_map(|(slot, (node, _))| match scene.constraints.get(*node) {
                Some(NodeConstraint::Surface { field, .. }) => Some(CurvedNode {
                    slot,
                    node: *node,
                    field: *field,
                    normal: V3::zeros(),
                }),
                _ => None,
            })
            .collect();
        Ok(QuasiStaticSolver {
            scene,
            settings,
            constrained,
            curved,
            shift_scale: shift_scale(scene),
            shift: 0.0,
            imposed_motion_scale: 1.0,
            contact_time_s: 0.0,
            contact_active,
            base_constrained,
            projector,
            lattice,
            preconditioner,
            setup_time_s: start.elapsed().as_secs_f64(),
            krylov: linalg::KrylovWorkspace::default(),
        })
    }
}

/// The preconditioner of `scene` with constraint projectors `projector`: multigrid on a
/// voxel `lattice`, block Jacobi otherwise.
fn build_preconditioner(
    scene: &Scene,
    settings: &QuasiStaticSettings,
    lattice: Option<&Lattice>,
    projector: Vec<Option<Matrix3<f64>>>,
) -> Preconditioner {
    match lattice {
        Some(lattice) => {
            let mut mg = Multigrid::new(&scene.mesh, lattice, projector);
            mg.set_smoothing_degree(settings.smoothing_degree.max(1));
            if tracing::enabled!(tracing::Level::DEBUG) {
                for (l, c) in mg.profile(9).iter().enumerate() {
                    tracing::debug!(
                        "multigrid level {l}: {} nodes, {} cells, {} distinct cell \
                             matrices, {:.0} % of nodes by stencil, {:.3} ms a product",
                        c.nodes,
                        c.cells,
                        c.distinct_matrices,
                        100.0 * c.stencil_fraction,
                        c.product_ms
                    );
                }
            }
            Preconditioner::Multigrid(Box::new(mg))
        }
        None => {
            let diag = stiffness_diagonal(scene);
            let inverse = invert_blocks(&diag, &scene.mesh.node_mass_kg, 0.0, &projector);
            Preconditioner::BlockJacobi {
                diag,
                inverse,
                projector,
            }
        }
    }
}

impl<'s> QuasiStaticSolver<'s> {
    /// The multigrid hierarchy's per-level sizes and product costs (empty for block Jacobi).
    pub fn preconditioner_profile(&self, repeats: usize) -> Vec<super::multigrid::LevelCost> {
        match &self.preconditioner {
            Preconditioner::Multigrid(mg) => mg.profile(repeats),
            Preconditioner::BlockJacobi { .. } => Vec::new(),
        }
    }

    /// GMRES iterations the preconditioner needs on its own operator (the projected rest
    /// stiffness) to cut the residual of a fixed pseudo-random right-hand side by `rtol`, and
    /// the residual reached; None for block Jacobi. Flat as elements shrink when the
    /// multigrid hierarchy is sound: a rise in a solve's Krylov count beyond it comes from
    /// the tangent at the deformed state departing from the rest stiffness.
    pub fn preconditioner_iterations(&mut self, rtol: f64) -> Option<(usize, f64)> {
        let Preconditioner::Multigrid(mg) = &mut self.preconditioner else {
            return None;
        };
        let n = 3 * self.scene.node_count();
        // xorshift64: the same right-hand side at every element size and on every run.
        let mut state = 0x9E37_79B9_7F4A_7C15u64;
        let mut b: Vec<f64> = (0..n)
            .map(|_| {
                state ^= state << 13;
                state ^= state >> 7;
                state ^= state << 17;
                state as f64 / u64::MAX as f64 - 0.5
            })
            .collect();
        project_flat(&self.constrained, &mut b);
        let mut x = vec![0.0; n];
        let mg = std::cell::RefCell::new(mg);
        Some(linalg::gmres(
            &mut |v, out| mg.borrow().apply_operator(v, out),
            &mut |r, z| mg.borrow_mut().apply(r, z),
            &|| false,
            &b,
            &mut x,
            GMRES_RESTART,
            rtol,
            PRECONDITIONER_CHECK_MAX_ITERATIONS,
            &mut self.krylov,
        ))
    }

    /// Solves for equilibrium starting from `initial` (or the rest configuration) and returns
    /// node positions in metres.
    pub fn solve(&mut self, initial: Option<&[V3]>) -> Result<(Vec<V3>, SolveReport)> {
        self.solve_with_load_factor(initial, 1.0)
    }

    /// Solves for equilibrium under the scene's loads and imposed displacements multiplied by
    /// `load_factor`: a breathing sequence scales one reference pressure per frame, reusing
    /// the preconditioner and warm-starting from the previous frame's positions.
    pub fn solve_with_load_factor(
        &mut self,
        initial: Option<&[V3]>,
        load_factor: f64,
    ) -> Result<(Vec<V3>, SolveReport)> {
        self.solve_load_factor_from(initial, load_factor, true)
    }

    /// As [`Self::solve_with_load_factor`], with the explicit-relaxation fallback only when
    /// `allow_relaxation`: a caller that can retry with a smaller load step (the breathing
    /// driver) gets Newton's failure back at once instead of a long relaxation.
    pub fn solve_load_factor_from(
        &mut self,
        initial: Option<&[V3]>,
        load_factor: f64,
        allow_relaxation: bool,
    ) -> Result<(Vec<V3>, SolveReport)> {
        // A solve makes thousands of parallel calls of a fraction of a millisecond each (the
        // V-cycle's products and sweeps). Called from outside the thread pool, every one of
        // them is injected into the pool while this thread sleeps; from inside, the calling
        // thread takes part and the others steal, without that hand-over.
        if rayon::current_thread_index().is_none() && rayon::current_num_threads() > 1 {
            return rayon::scope(|_| self.solve_in_pool(initial, load_factor, allow_relaxation));
        }
        self.solve_in_pool(initial, load_factor, allow_relaxation)
    }

    /// [`Self::solve_load_factor_from`], on whatever thread calls it.
    fn solve_in_pool(
        &mut self,
        initial: Option<&[V3]>,
        load_factor: f64,
        allow_relaxation: bool,
    ) -> Result<(Vec<V3>, SolveReport)> {
        if !load_factor.is_finite() {
            return Err(Error::InvalidModel(format!(
                "load factor must be finite, got {load_factor}"
            )));
        }
        let start = Instant::now();
        let scene = self.scene;
        let n = scene.node_count();
        let mut x: Vec<V3> = match initial {
            Some(x0) if x0.len() == n => x0.to_vec(),
            Some(x0) => {
                return Err(Error::InvalidModel(format!(
                    "initial state has {} nodes, the mesh {n}",
                    x0.len()
                )))
            }
            None => scene.mesh.rest_positions_m.clone(),
        };
        scene.check_finite(&x, 0)?;
        let steps = self.settings.load_steps.max(1);
        let mut report = SolveReport {
            load_steps: steps,
            multigrid_levels: match &self.preconditioner {
                Preconditioner::Multigrid(mg) => mg.level_count(),
                Preconditioner::BlockJacobi { .. } => 1,
            },
            setup_time_s: self.setup_time_s,
            ..SolveReport::default()
        };
        let mut work = Work::new(n);
        for step in 1..=steps {
            let lambda = load_factor * step as f64 / steps as f64;
            let base = scene.constraints.at_load_factor(
                &scene.mesh.rest_positions_m,
                lambda * self.imposed_motion_scale,
            );
            let tol = if step == steps {
                self.settings.tolerance
            } else {
                self.settings.tolerance.max(1e-4)
            };
            // A caller that would otherwise relax retries a smaller load step instead: for it, a
            // Newton solve whose Krylov solves cannot converge gives up early.
            let may_bisect = !allow_relaxation;
            let mut rounds = 0;
            loop {
                let constraints = self.with_touching_contacts(&base)?;
                constraints.project_positions(&mut x);
                match self.newton(
                    &constraints,
                    lambda,
                    tol,
                    may_bisect,
                    &mut x,
                    &mut work,
                    &mut report,
                ) {
                    Err(Error::NotConverged { .. })
                        if allow_relaxation && self.settings.relaxation_max_steps > 0 =>
                    {
                        self.relax(&constraints, lambda, tol, &mut x, &mut report)?;
                    }
                    other => other?,
                }
                if scene.one_sided.is_empty() {
                    break;
                }
                let change = self.update_contacts(lambda, &x, &mut work);
                if !change.changed() {
                    break;
                }
                rounds += 1;
                report.contact_rounds += 1;
                report.contacts_released += change.released;
                report.contacts_engaged += change.engaged;
                tracing::debug!(step, rounds, ?change, "one-sided contacts changed");
                if rounds >= MAX_CONTACT_ROUNDS {
                    return Err(contact_unsettled(change, rounds));
                }
            }
        }
        // An equilibrium with an inverted element is not one the tissue can reach.
        scene.check_not_inverted(
            &x,
            report.newton_iterations,
            "the mesh gave way under this load step",
        )?;
        report.wall_time_s = start.elapsed().as_secs_f64();
        Ok((x, report))
    }

    /// Newton iterations to `tol`; when a plain Newton step cannot reduce the residual
    /// (a mechanism such as the element's twist modes, or a very large load), switches to
    /// pseudo-transient continuation: solves (σ·M + J)·δ = r, an implicit pseudo-time step,
    /// and lets σ shrink with the residual (switched evolution relaxation), which returns
    /// to plain Newton near the solution. With `may_bisect` (the caller retries a smaller
    /// load step on failure) a solve whose Krylov solves reach their limit
    /// [`BISECT_AFTER_CAPPED_KRYLOV`] times stops there.
    #[allow(clippy::too_many_arguments)]
    fn newton(
        &mut self,
        constraints: &ConstraintSet,
        lambda: f64,
        tol: f64,
        may_bisect: bool,
        x: &mut [V3],
        w: &mut Work,
        report: &mut SolveReport,
    ) -> Result<()> {
        let scene = self.scene;
        let increment = LoadIncrement {
            constraints,
            lambda,
            h_scale: shortest_edge_m(scene),
            contact_time_s: self.contact_time_s,
        };
        let t_c = self.contact_time_s;
        let mut sigma = 0.0;
        let mut res = residual(scene, constraints, lambda, t_c, x, w);
        let mut stalled = 0;
        let mut capped_krylov = 0;
        for it in 0..self.settings.max_newton_iterations {
            self.check_cancelled()?;
            if !res.is_finite() {
                return Err(Error::Diverged {
                    step: report.newton_iterations,
                    cause: "force residual is not finite".into(),
                });
            }
            if res <= tol {
                report.residual = res;
                return Ok(());
            }
            self.follow_curved_constraints(constraints, x);
            let base = NewtonBase {
                b: flat(&w.r).to_vec(),
                x: x.to_vec(),
                f: w.f.clone(),
                residual: res,
                eta: linear_tolerance(sigma, tol, res),
            };
            let (accepted, taken) = self.newton_step(&increment, &base, &mut sigma, x, w, report);
            report.newton_iterations += 1;
            self.check_cancelled()?;
            tracing::debug!(
                it,
                res,
                new_res = accepted.unwrap_or(f64::NAN),
                alpha = taken.0,
                sigma,
                eta = base.eta,
                gmres = taken.1,
                gmres_res = taken.2,
                "newton"
            );
            let Some(new_res) = accepted else {
                x.copy_from_slice(&base.x);
                w.f = base.f;
                res = residual(scene, constraints, lambda, t_c, x, w);
                report.residual = res;
                return Err(Error::NotConverged {
                    iterations: it + 1,
                    residual: res,
                    tolerance: tol,
                });
            };
            if sigma > 0.0 {
                report.pseudo_time_steps += 1;
                // Switched evolution relaxation (the pseudo-time step grows as the residual
                // falls), at least doubling per accepted step so a slow decrease cannot stall it.
                sigma *= (new_res / res).min(0.5);
                if sigma < self.shift_scale * 1e-8 {
                    sigma = 0.0;
                }
            }
            // Krylov iterations that cannot reduce the linear residual at all, while Newton
            // creeps, mean a singular tangent (a limit point: the mesh buckles under this
            // load). More iterations only burn minutes; the caller bisects or reports.
            let krylov_stuck = taken.1 >= self.settings.max_linear_iterations && taken.2 > 0.9;
            stalled = if krylov_stuck && new_res > 0.99 * res {
                stalled + 1
            } else {
                0
            };
            capped_krylov += usize::from(taken.1 >= self.settings.max_linear_iterations);
            if may_bisect && new_res > tol && capped_krylov >= BISECT_AFTER_CAPPED_KRYLOV {
                tracing::debug!(
                    it,
                    capped_krylov,
                    "newton: the caller bisects the load step"
                );
                report.residual = new_res;
                return Err(Error::NotConverged {
                    iterations: it + 1,
                    residual: new_res,
                    tolerance: tol,
                });
            }
            res = new_res;
            if stalled >= STALLED_NEWTON_LIMIT {
                report.residual = res;
                return Err(Error::NotConverged {
                    iterations: it + 1,
                    residual: res,
                    tolerance: tol,
                });
            }
        }
        report.residual = res;
        if res <= tol {
            Ok(())
        } else {
            Err(Error::NotConverged {
                iterations: self.settings.max_newton_iterations,
                residual: res,
                tolerance: tol,
            })
        }
    }

    /// The constraint set `base` plus the touching one-sided contacts' planes.
    fn with_touching_contacts<'c>(
        &self,
        base: &'c ConstraintSet,
    ) -> Result<std::borrow::Cow<'c, ConstraintSet>> {
        let planes = &self.scene.one_sided;
        if planes.is_empty() {
            return Ok(std::borrow::Cow::Borrowed(base));
        }
        let mut set = base.clone();
        for i in OneSidedPlanes::touching(&self.contact_active) {
            set.set(planes.nodes()[i], planes.constraint(i))?;
        }
        Ok(std::borrow::Cow::Owned(set))
    }

    /// One round of the one-sided contacts' active set at the equilibrium `x`: a held node
    /// pulled off its plane by more than 1 % of the mean pressing force (or a negligible
    /// force) is released, a free one more than a thousandth of the shortest edge across its
    /// plane is held; the Krylov operator's projectors follow.
    fn update_contacts(&mut self, lambda: f64, x: &[V3], w: &mut Work) -> ActiveSetChange {
        let scene = self.scene;
        total_force(scene, lambda, self.contact_time_s, x, &mut w.f, &mut w.ext);
        let planes = &scene.one_sided;
        let pull_tolerance = (CONTACT_PULL_FRACTION
            * planes.mean_pressing_force_n(&w.f, &self.contact_active))
        .max(force_floor_n(scene));
        let change = planes.update_active(
            x,
            &w.f,
            &mut self.contact_active,
            pull_tolerance,
            CONTACT_PENETRATION_FRACTION * shortest_edge_m(scene),
        );
        if change.changed() {
            self.constrained.truncate(self.base_constrained);
            push_contact_projectors(planes, &self.contact_active, &mut self.constrained);
            // The preconditioner holds the touching nodes too: with the whole face free in it,
            // GMRES took 4.8× the iterations on the CIP lungs at 6 mm.
            let start = Instant::now();
            self.preconditioner = build_preconditioner(
                scene,
                &self.settings,
                self.lattice.as_ref(),
                with_contact_projectors(&self.projector, planes, &self.contact_active),
            );
            let sigma = std::mem::take(&mut self.shift);
            self.set_shift(sigma);
            self.setup_time_s += start.elapsed().as_secs_f64();
        }
        change
    }

    /// Which one-sided contacts touch (held on their plane), in the scene's order.
    pub fn touching_contacts(&self) -> &[bool] {
        &self.contact_active
    }

    /// Takes the free directions of nodes on curved surfaces at their positions `x`: the
    /// residual is projected on the tangent plane where the node is, and a Newton step along
    /// the rest tangent would leave the surface at first order once the node has slid.
    fn follow_curved_constraints(&mut self, constraints: &ConstraintSet, x: &[V3]) {
        for c in &mut self.curved {
            let normal = constraints.fields[c.field as usize].spline_normal(x[c.node as usize]);
            c.normal = normal;
            self.constrained[c.slot].1 = Matrix3::identity() - normal * normal.transpose();
        }
    }

    /// One Newton iteration from `base`: plain Newton first (σ = 0), then pseudo-time steps
    /// with growing σ if needed. Returns the accepted residual (none if every attempt failed)
    /// and the step taken (α, GMRES iterations, GMRES residual); `x` and `w` hold the last
    /// trial state.
    fn newton_step(
        &mut self,
        increment: &LoadIncrement,
        base: &NewtonBase,
        sigma: &mut f64,
        x: &mut [V3],
        w: &mut Work,
        report: &mut SolveReport,
    ) -> (Option<f64>, (f64, usize, f64)) {
        let mut accepted = None;
        let mut taken = (0.0, 0usize, 0.0);
        for attempt in 0..12 {
            self.set_shift(*sigma);
            let (delta, lin, lin_res) = self.linear_solve(
                increment, *sigma, &base.x, &base.f, &base.b, base.eta, report,
            );
            if let Some((alpha, new_res)) =
                line_search(self.scene, increment, base, *sigma, &delta, x, w)
            {
                accepted = Some(new_res);
                taken = (alpha, lin, lin_res);
                break;
            }
            *sigma = if *sigma == 0.0 {
                self.shift_scale * 1e-2
            } else {
                *sigma * 10.0
            };
            report.pseudo_time_steps += usize::from(attempt == 0);
        }
        (accepted, taken)
    }

    /// Fallback: damped explicit dynamics from `x` to equilibrium. Runs on a copy of the scene
    /// whose springs carry critical Voigt damping and whose loads and imposed displacements
    /// are scaled by λ, so the caller's scene is untouched.
    fn relax(
        &mut self,
        constraints: &ConstraintSet,
        lambda: f64,
        tol: f64,
        x: &mut [V3],
        report: &mut SolveReport,
    ) -> Result<()> {
        let mut mesh = self.scene.mesh.clone();
        for c in &mut mesh.classes {
            *c = c.clone().with_damping_ratio(1.0);
        }
        let mut loads = self.scene.loads.clone();
        loads.gravity_m_per_s2 *= lambda;
        loads
            .point_forces_n
            .iter_mut()
            .for_each(|(_, f)| *f *= lambda);
        loads
            .pressures
            .iter_mut()
            .for_each(|p| p.pressure_pa *= lambda);
        let damped = Scene::new(mesh, constraints.clone(), loads)?
            .with_contact(self.scene.contact().frozen_at(self.contact_time_s))?;
        let mut integrator = super::explicit::ExplicitIntegrator::from_positions(&damped, x)?;
        let outcome = integrator.run_to_equilibrium(&super::explicit::ExplicitSettings {
            residual_tolerance: tol,
            kinetic_energy_fraction: 1.0,
            max_steps: self.settings.relaxation_max_steps,
            cancel: self.settings.cancel.clone(),
            stall_steps: Some(RELAXATION_STALL_STEPS),
            inversion_hint: Some(
                "the mesh gave way under this load step (in the damped relaxation fallback)",
            ),
            ..Default::default()
        })?;
        report.relaxation_steps += outcome.steps;
        x.copy_from_slice(&integrator.positions);
        report.residual = outcome.residual;
        if outcome.converged {
            Ok(())
        } else {
            Err(Error::NotConverged {
                iterations: report.newton_iterations + outcome.steps,
                residual: outcome.residual,
                tolerance: tol,
            })
        }
    }

    /// Sets the relative force residual later solves stop at.
    pub fn set_tolerance(&mut self, tolerance: f64) {
        self.settings.tolerance = tolerance;
    }

    /// The relative force residual solves stop at.
    pub fn tolerance(&self) -> f64 {
        self.settings.tolerance
    }

    /// Applies the scene's imposed displacements (a moving chest wall, prescribed motions) at
    /// `scale` times the load factor in later solves: 0 holds every moving constraint at
    /// rest, 1 (the default) moves it in step with the loads.
    pub fn set_imposed_motion_scale(&mut self, scale: f64) {
        self.imposed_motion_scale = scale;
    }

    /// The factor set by [`QuasiStaticSolver::set_imposed_motion_scale`].
    pub fn imposed_motion_scale(&self) -> f64 {
        self.imposed_motion_scale
    }

    /// Holds moving obstacles where they are at `t_s` in later solves (0 by default).
    pub fn set_contact_time(&mut self, t_s: f64) {
        self.contact_time_s = t_s;
    }

    /// Stops every later solve, and the one under way at its next check, once `flag` is raised.
    pub fn set_cancel(&mut self, flag: super::CancelFlag) {
        self.settings.cancel = Some(flag);
    }

    /// Whether the cancel flag given by [`QuasiStaticSolver::set_cancel`] (or the settings) is
    /// raised.
    pub fn cancel_raised(&self) -> bool {
        is_raised(&self.settings.cancel)
    }

    fn check_cancelled(&self) -> Result<()> {
        if self.cancel_raised() {
            return Err(Error::Cancelled(
                "stopped during an equilibrium solve".into(),
            ));
        }
        Ok(())
    }

    fn set_shift(&mut self, sigma: f64) {
        if sigma == self.shift {
            return;
        }
        self.shift = sigma;
        match &mut self.preconditioner {
            Preconditioner::Multigrid(mg) => mg.set_shift(sigma),
            Preconditioner::BlockJacobi {
                diag,
                inverse,
                projector,
            } => {
                let mass = &self.scene.mesh.node_mass_kg;
                *inverse = invert_blocks(diag, mass, sigma, projector);
            }
        }
    }

    /// GMRES on (σ·M + J)·δ = b, J by finite differences of the exact forces at `x_base`.
    #[allow(clippy::too_many_arguments)]
    fn linear_solve(
        &mut self,
        increment: &LoadIncrement,
        sigma: f64,
        x_base: &[V3],
        f_base: &[V3],
        b: &[f64],
        eta: f64,
        report: &mut SolveReport,
    ) -> (Vec<f64>, usize, f64) {
        let (lambda, t_c, h_scale) = (
            increment.lambda,
            increment.contact_time_s,
            increment.h_scale,
        );
        let scene = self.scene;
        let mass = &scene.mesh.node_mass_kg;
        let constrained = &self.constrained;
        let curved = &self.curved;
        let fields = &scene.constraints.fields;
        let eps = 1e-7 * h_scale;
        let n = x_base.len();
        let (mut xp, mut fp, mut ext) = (
            vec![V3::zeros(); n],
            vec![V3::zeros(); n],
            vec![V3::zeros(); n],
        );
        let mut apply = |v: &[f64], out: &mut [f64]| {
            // (σ·M − d(total force)/dx)·v, projected; identity on constrained directions.
            let vmax = v.iter().fold(0.0f64, |m, a| m.max(a.abs()));
            if vmax == 0.0 {
                out.iter_mut().for_each(|o| *o = 0.0);
                return;
            }
            let hstep = eps / vmax;
            let vn = nodes(v);
            // Perturb along Π·v only: the operator is Π·(σM + J)·Π + (I − Π).
            for ((p, b), d) in xp.iter_mut().zip(x_base).zip(vn) {
                *p = b + d * hstep;
            }
            for (nd, pm) in constrained {
                let nd = *nd as usize;
                xp[nd] = x_base[nd] + pm * vn[nd] * hstep;
            }
            total_force(scene, lambda, t_c, &xp, &mut fp, &mut ext);
            let on = nodes_mut(out);
            for ((((o, a), b), d), m) in on.iter_mut().zip(&fp).zip(f_base).zip(vn).zip(mass) {
                *o = (b - a) / hstep + d * (sigma * m);
            }
            for (nd, pm) in constrained {
                let nd = *nd as usize;
                // The shift was added on Π·v only.
                on[nd] -= (vn[nd] - pm * vn[nd]) * (sigma * mass[nd]);
            }
            project_flat(constrained, out);
            let on = nodes_mut(out);
            // A node held on a curved surface by a normal force f·n feels, as it slides by
            // δ, that force turned by the normal's change: (f·n)·dn, a stiffness of (f·n)·κ.
            // Under a breath's pressure it is a third of the tissue's own at the staircase
            // corners; without it Newton converges only linearly.
            for c in curved {
                let nd = c.node as usize;
                let turned = fields[c.field as usize].spline_normal(xp[nd]) - c.normal;
                on[nd] += turned * (f_base[nd].dot(&c.normal) / hstep);
            }
            for (nd, p) in constrained {
                let nd = *nd as usize;
                on[nd] += vn[nd] - p * vn[nd];
            }
        };
        let preconditioner = &mut self.preconditioner;
        let mut precondition = |r: &[f64], z: &mut [f64]| match preconditioner {
            Preconditioner::Multigrid(mg) => mg.apply(r, z),
            Preconditioner::BlockJacobi { inverse, .. } => {
                let (rn, zn) = (nodes(r), nodes_mut(z));
                for ((z, r), d) in zn.iter_mut().zip(rn).zip(inverse.iter()) {
                    *z = d * r;
                }
            }
        };
        let mut delta = vec![0.0; b.len()];
        let cancel = &self.settings.cancel;
        let (lin, lin_res) = linalg::gmres(
            &mut apply,
            &mut precondition,
            &|| is_raised(cancel),
            b,
            &mut delta,
            GMRES_RESTART,
            eta,
            self.settings.max_linear_iterations,
            &mut self.krylov,
        );
        report.linear_iterations += lin;
        (delta, lin, lin_res)
    }
}

/// Krylov vectors GMRES keeps before it restarts, in the Newton steps and in the
/// preconditioner check alike.
const GMRES_RESTART: usize = 40;

/// Iterations after which [`QuasiStaticSolver::preconditioner_iterations`] gives up (a sound
/// hierarchy needs about one per digit).
const PRECONDITIONER_CHECK_MAX_ITERATIONS: usize = 200;

/// Newton solves of one load step repeated for a changing contact set, after which the
/// solve gives up: on the lungs' mediastinal face the set settles in 1–3 rounds.
const MAX_CONTACT_ROUNDS: usize = 12;

/// A touching node is released when pulled off its plane by more than this fraction of the
/// mean force pressing the touching nodes on theirs: smaller pulls are the solver's
/// tolerance, and releasing them would make nodes chatter between rounds.
const CONTACT_PULL_FRACTION: f64 = 1e-2;

/// A free node is held again when across its plane by more than this fraction of the
/// shortest element edge (6 µm at 6 mm).
const CONTACT_PENETRATION_FRACTION: f64 = 1e-3;

/// `base` with the touching one-sided contacts' tangent projectors.
fn with_contact_projectors(
    base: &[Option<Matrix3<f64>>],
    planes: &OneSidedPlanes,
    active: &[bool],
) -> Vec<Option<Matrix3<f64>>> {
    let mut p = base.to_vec();
    let mut touching = Vec::new();
    push_contact_projectors(planes, active, &mut touching);
    for (node, pm) in touching {
        p[node as usize] = Some(pm);
    }
    p
}

/// Appends the touching one-sided contacts' tangent projectors to `constrained`.
fn push_contact_projectors(
    planes: &OneSidedPlanes,
    active: &[bool],
    constrained: &mut Vec<(u32, Matrix3<f64>)>,
) {
    for i in OneSidedPlanes::touching(active) {
        let n = planes.normal(i);
        constrained.push((planes.nodes()[i], Matrix3::identity() - n * n.transpose()));
    }
}

/// The error of a load step whose contact set still changed after `rounds` Newton solves.
fn contact_unsettled(change: ActiveSetChange, rounds: usize) -> Error {
    Error::InvalidModel(format!(
        "the one-sided contacts did not settle: after {rounds} Newton solves at equilibrium \
         the last round still released {} and engaged {} nodes; a larger element size, or \
         sliding instead of contact at the mediastinum, avoids this",
        change.released, change.engaged
    ))
}

/// Explicit relaxation steps without a tenth's fall of the residual after which the fallback
/// gives up: the fallback is for mechanisms Newton cannot cross, not for a buckling mesh.
const RELAXATION_STALL_STEPS: usize = 50_000;

/// Krylov solves stopped by their iteration limit after which a solve that may bisect its
/// load step gives up: from a warm start inside Newton's basin they converge in 10–80
/// iterations; on the POPI lungs a load step outside it made them hit the 300 limit (5–12 s
/// each) for 40 Newton iterations.
const BISECT_AFTER_CAPPED_KRYLOV: usize = 2;

/// Consecutive Newton iterations with a stuck Krylov solve and under 1 % residual decrease
/// after which a solve is declared stalled.
const STALLED_NEWTON_LIMIT: usize = 3;

fn is_raised(flag: &Option<super::CancelFlag>) -> bool {
    flag.as_ref()
        .is_some_and(|c| c.load(std::sync::atomic::Ordering::Relaxed))
}

/// One load increment's equilibrium problem: its constraints, load factor λ, the length
/// scale of the finite-difference Jacobian (the shortest element edge) and the time at which
/// moving obstacles are held.
struct LoadIncrement<'c> {
    constraints: &'c ConstraintSet,
    lambda: f64,
    h_scale: f64,
    contact_time_s: f64,
}

/// The state a Newton iteration starts from (restored when no step is accepted), with the
/// right-hand side and tolerance of its linear solve.
struct NewtonBase {
    /// Free part of the total force at `x`, flattened: the right-hand side.
    b: Vec<f64>,
    x: Vec<V3>,
    /// Total force at `x`.
    f: Vec<V3>,
    /// Relative residual at `x`.
    residual: f64,
    /// Relative tolerance η of the linear solve.
    eta: f64,
}

/// The shortest element edge of the scene, m.
fn shortest_edge_m(scene: &Scene) -> f64 {
    scene
        .mesh
        .classes
        .iter()
        .map(|c| {
            c.shape
                .edges_m
                .iter()
                .cloned()
                .fold(f64::INFINITY, f64::min)
        })
        .fold(f64::INFINITY, f64::min)
}

/// Relative tolerance η of the Krylov solve of a Newton step at residual `res`.
fn linear_tolerance(sigma: f64, tol: f64, res: f64) -> f64 {
    // Inexact Newton: the step cuts the residual by about the linear tolerance η (the
    // lung's forces are nearly linear over one warm-started step), so ask for what
    // reaches `tol` (half of it, for margin), but never below 1e-2, where each digit of
    // GMRES costs more than another Newton step. On the CIP 8 mm cycle this took
    // 124 Krylov iterations against 136 for η = √(tol/res) ∈ [1e-3, 0.1].
    if sigma > 0.0 {
        0.1
    } else {
        (0.5 * tol / res).clamp(1e-2, 0.1)
    }
}

/// Moves `x` along `delta` from `base.x`: Newton backtracks until the residual falls;
/// pseudo-time takes the step if it does not blow the residual up (non-monotone, as
/// pseudo-transient methods are). Returns the step length α and the new residual, if
/// accepted; `x` and `w` hold the last trial either way.
fn line_search(
    scene: &Scene,
    increment: &LoadIncrement,
    base: &NewtonBase,
    sigma: f64,
    delta: &[f64],
    x: &mut [V3],
    w: &mut Work,
) -> Option<(f64, f64)> {
    let LoadIncrement {
        constraints,
        lambda,
        contact_time_s,
        ..
    } = *increment;
    let res = base.residual;
    let dn = nodes(delta);
    let (mut alpha, trials) = if sigma == 0.0 { (1.0, 8) } else { (1.0, 1) };
    for _ in 0..trials {
        for ((xi, b), d) in x.iter_mut().zip(&base.x).zip(dn) {
            *xi = b + d * alpha;
        }
        constraints.project_positions(x);
        let new_res = residual(scene, constraints, lambda, contact_time_s, x, w);
        let ok = new_res.is_finite()
            && if sigma == 0.0 {
                new_res < res
            } else {
                new_res < 2.0 * res
            };
        if ok {
            return Some((alpha, new_res));
        }
        alpha *= 0.5;
    }
    None
}

/// A node sliding on a curved surface, as the Krylov operator sees it.
struct CurvedNode {
    /// Its entry in the solver's `constrained` list.
    slot: usize,
    /// The node.
    node: u32,
    /// Its surface, in the constraint set's fields.
    field: u32,
    /// The surface's unit normal where the node is at the current Newton iterate.
    normal: V3,
}

/// Scratch buffers of a solve.
struct Work {
    f: Vec<V3>,
    ext: Vec<V3>,
    r: Vec<V3>,
}

impl Work {
    fn new(n: usize) -> Self {
        Work {
            f: vec![V3::zeros(); n],
            ext: vec![V3::zeros(); n],
            r: vec![V3::zeros(); n],
        }
    }
}

/// f = internal + contact (obstacles held where they are at `t_c`) + λ·external at x; `ext`
/// receives the unscaled external force. Contact is not scaled: it is a reaction, and counts
/// with the internal forces in the residual's scale.
fn total_force(
    scene: &Scene,
    lambda: f64,
    t_c: f64,
    x: &[V3],
    f: &mut [V3],
    ext: &mut [V3],
) -> (f64, f64) {
    scene.internal_forces(x, None, f);
    scene.add_contact_forces(x, None, t_c, f);
    scene.external_forces(x, ext);
    let mut ni = 0.0;
    let mut ne = 0.0;
    for (f, e) in f.iter_mut().zip(ext.iter()) {
        ni += f.norm_squared();
        ne += e.norm_squared() * lambda * lambda;
        *f += e * lambda;
    }
    (ni.sqrt(), ne.sqrt())
}

/// Relative residual at x; leaves the total force in `w.f` and its free part in `w.r`.
fn residual(
    scene: &Scene,
    constraints: &ConstraintSet,
    lambda: f64,
    t_c: f64,
    x: &[V3],
    w: &mut Work,
) -> f64 {
    let (ni, ne) = total_force(scene, lambda, t_c, x, &mut w.f, &mut w.ext);
    w.r.copy_from_slice(&w.f);
    constraints.project_field(x, &mut w.r);
    let scale = ni.max(ne).max(force_floor_n(scene));
    super::scene::norm(&w.r) / scale
}

/// A force too small to matter: an element strained by 1e-6 (the floor is then 1e-12 strain
/// at the default tolerance). Without it the residual of an
/// unloaded scene (a breathing frame at the scanned volume) would be round-off over round-off.
fn force_floor_n(scene: &Scene) -> f64 {
    scene
        .mesh
        .classes
        .iter()
        .map(|c| {
            let h = c
                .shape
                .edges_m
                .iter()
                .cloned()
                .fold(f64::INFINITY, f64::min);
            1e-6 * c.material.youngs_modulus_pa * h * h
        })
        .fold(f64::INFINITY, f64::min)
        .min(1.0)
}

/// Constraint projector of each node at the rest configuration (None = free).
fn projectors(cs: &ConstraintSet, rest: &[V3]) -> Vec<Option<Matrix3<f64>>> {
    let mut p = vec![None; rest.len()];
    for (node, c) in &cs.entries {
        let n = *node as usize;
        p[n] = Some(cs.free_projector(c, rest[n]));
    }
    p
}

fn stiffness_diagonal(scene: &Scene) -> Vec<Matrix3<f64>> {
    let mesh = &scene.mesh;
    let ks: Vec<_> = mesh.classes.iter().map(|c| c.linear_stiffness()).collect();
    let mut d = vec![Matrix3::zeros(); mesh.node_count()];
    for (corners, &class) in mesh.elements.iter().zip(&mesh.element_class) {
        let k = &ks[class as usize];
        for (c, &n) in corners.iter().enumerate() {
            d[n as usize] += k.fixed_view::<3, 3>(3 * c, 3 * c).into_owned();
        }
    }
    d
}

/// Median over nodes of trace(K_nn) / (3·m_n): the squared frequency scale of σ.
fn shift_scale(scene: &Scene) -> f64 {
    let d = stiffness_diagonal(scene);
    let mut r: Vec<f64> = d
        .iter()
        .zip(&scene.mesh.node_mass_kg)
        .map(|(k, m)| k.trace() / (3.0 * m))
        .collect();
    r.sort_by(f64::total_cmp);
    r.get(r.len() / 2)
        .copied()
        .unwrap_or(1.0)
        .max(f64::MIN_POSITIVE)
}

fn invert_blocks(
    diag: &[Matrix3<f64>],
    mass: &[f64],
    sigma: f64,
    projector: &[Option<Matrix3<f64>>],
) -> Vec<Matrix3<f64>> {
    diag.iter()
        .zip(mass)
        .zip(projector)
        .map(|((d, m), p)| {
            let d = d + Matrix3::identity() * (sigma * m);
            let d = match p {
                Some(p) => p * d * p + (Matrix3::identity() - p),
                None => d,
            };
            d.try_inverse().unwrap_or_else(Matrix3::identity)
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use std::sync::Arc;

    use nalgebra::Vector3;

    use super::*;
    use crate::model::contact::{Contact, HuntCrossley, Obstacle, ObstacleMotion};
    use crate::model::{Loads, Material, SignedDistanceField, VoxelGrid};

    const EDGE_M: f64 = 0.005;

    /// A soft block (E = 10 kPa) of `cells` cubes of 5 mm, bottom face on z = 0, with its
    /// lattice coordinates.
    fn block(cells: [usize; 3]) -> (crate::model::HexMesh, Vec<[u32; 3]>) {
        let material = Material::new(10e3, 0.3, 1000.0).unwrap();
        let gm = VoxelGrid::filled_box(cells, [EDGE_M; 3], Vector3::zeros())
            .to_mesh(material)
            .unwrap();
        (gm.mesh, gm.node_lattice)
    }

    /// The 20 × 20 × 10 mm block ([`block`], 4 × 4 × 2 cubes) with its top face held.
    fn block_held_by_its_top() -> (crate::model::HexMesh, Vec<[u32; 3]>, ConstraintSet) {
        let cells = [4, 4, 2];
        let (mesh, lattice) = block(cells);
        let mut cs = ConstraintSet::new(mesh.node_count());
        for (i, l) in lattice.iter().enumerate() {
            if l[2] == cells[2] as u32 {
                cs.fix(i as u32, mesh.rest_positions_m[i]).unwrap();
            }
        }
        (mesh, lattice, cs)
    }

    /// A node of the block carries about E·h = 50 N/m; a penalty a hundred times stiffer
    /// lets an obstacle in by about a hundredth of how far it pushes.
    const PENALTY_N_PER_M: f64 = 100.0 * 10e3 * EDGE_M;

    #[test]
    fn contact_keeps_nodes_outside_a_sphere_pushed_into_a_held_block() {
        // 20 × 20 × 10 mm, top face held; a sphere of radius 15 mm under the middle of the
        // bottom face rises 3 mm into it (a moving obstacle, held at t = 1 s for the solve).
        let (mesh, lattice, cs) = block_held_by_its_top();
        let (r, centre) = (0.015, Vector3::new(0.01, 0.01, -0.015));
        let push_m = 0.003;
        let field = SignedDistanceField::from_fn(
            Vector3::new(-0.01, -0.01, -0.04),
            Vector3::new(0.03, 0.03, 0.015),
            0.0025,
            |p| (p - centre).norm() - r,
        )
        .unwrap();
        for exponent in [1.0, 1.5] {
            // Same stiffness at 0.1 mm penetration for both exponents.
            let k = PENALTY_N_PER_M * 1e-4_f64.powf(1.0 - exponent);
            let contact = Contact {
                obstacles: vec![Obstacle {
                    field: Arc::new(field.clone()),
                    motion: ObstacleMotion::Translated {
                        times_s: vec![0.0, 1.0],
                        offsets_m: vec![Vector3::zeros(), Vector3::new(0.0, 0.0, push_m)],
                    },
                    law: HuntCrossley::new(k, exponent, 0.5).unwrap(),
                    nodes: mesh.surface_nodes(),
                }],
            };
            let scene = Scene::new(mesh.clone(), cs.clone(), Loads::default())
                .unwrap()
                .with_contact(contact)
                .unwrap();
            let mut solver =
                QuasiStaticSolver::new(&scene, QuasiStaticSettings::default()).unwrap();
            solver.set_contact_time(1.0);
            let (x, report) = solver.solve(None).unwrap();
            assert!(report.residual <= 1e-6, "n = {exponent}: {report:?}");
            let deepest = scene.contact().deepest(&x, 1.0).unwrap();
            println!(
                "sphere pushed 3 mm into the block, n = {exponent}: deepest node {:.4} mm; \
                 {} Newton, {} Krylov iterations, {} pseudo-time, {} relaxation steps",
                deepest.depth_m * 1e3,
                report.newton_iterations,
                report.linear_iterations,
                report.pseudo_time_steps,
                report.relaxation_steps
            );
            // Without contact the bottom's middle node would sit `push_m` inside.
            let rest_depth = scene
                .contact()
                .deepest(&mesh.rest_positions_m, 1.0)
                .unwrap();
            assert!((rest_depth.depth_m - push_m).abs() < 1e-4, "{rest_depth:?}");
            assert!(
                deepest.depth_m < 0.05 * push_m,
                "n = {exponent}: {deepest:?} ({report:?})"
            );
            // The block gave way instead: its bottom's middle rose by about the push.
            let mid = lattice.iter().position(|l| *l == [2, 2, 0]).unwrap();
            let rise = x[mid].z - mesh.rest_positions_m[mid].z;
            assert!(
                rise > 0.9 * push_m && rise < push_m,
                "n = {exponent}: rise {rise}"
            );
            // At rest (t = 0) the sphere only touches: nothing moves.
            let mut at_rest =
                QuasiStaticSolver::new(&scene, QuasiStaticSettings::default()).unwrap();
            let (x0, _) = at_rest.solve(None).unwrap();
            let moved = x0
                .iter()
                .zip(&mesh.rest_positions_m)
                .map(|(a, b)| (a - b).norm())
                .fold(0.0, f64::max);
            assert!(moved < 1e-9, "{moved}");
        }
    }

    /// The block's bottom face (z = 0) in one-sided contact with a floor below it.
    fn on_floor(mesh: &crate::model::HexMesh, lattice: &[[u32; 3]]) -> OneSidedPlanes {
        let planes = lattice
            .iter()
            .enumerate()
            .filter(|(_, l)| l[2] == 0)
            .map(|(i, _)| (i as u32, mesh.rest_positions_m[i], -Vector3::z()))
            .collect();
        OneSidedPlanes::new(mesh.node_count(), planes).unwrap()
    }

    fn gravity(g_z: f64) -> Loads {
        Loads {
            gravity_m_per_s2: Vector3::new(0.0, 0.0, g_z),
            ..Loads::default()
        }
    }

    #[test]
    fn one_sided_contact_holds_a_block_pressed_onto_it_and_frees_one_pulled_off() {
        // 20 × 20 × 10 mm hung by its top face, its bottom face resting on a floor; its own
        // weight (1 % strain) pushes it onto the floor, then (reversed) lifts it off.
        let (mesh, lattice, cs) = block_held_by_its_top();
        let floor = on_floor(&mesh, &lattice);
        let tolerance_m = CONTACT_PENETRATION_FRACTION * EDGE_M;
        for g_z in [-9.81, 9.81] {
            let free = Scene::new(mesh.clone(), cs.clone(), gravity(g_z)).unwrap();
            let mut scene = free.clone();
            scene.one_sided = floor.clone();
            let (x_free, _) = QuasiStaticSolver::new(&free, QuasiStaticSettings::default())
                .unwrap()
                .solve(None)
                .unwrap();
            let mut solver =
                QuasiStaticSolver::new(&scene, QuasiStaticSettings::default()).unwrap();
            let (x, report) = solver.solve(None).unwrap();
            assert!(report.residual <= 1e-6, "{report:?}");
            let free_state = floor.state(&x_free, 1e-7);
            let state = floor.state(&x, 1e-7);
            println!(
                "gravity {g_z} m/s²: without contact {free_state:?}; with it {state:?}, {report:?}"
            );
            assert!(state.max_penetration_m <= tolerance_m, "{state:?}");
            if g_z < 0.0 {
                // Without the floor the bottom sinks well past the tolerance.
                assert!(
                    free_state.max_penetration_m > 5.0 * tolerance_m,
                    "{free_state:?}"
                );
                assert_eq!(state.touching, floor.len());
                // No touching node is pulled: the floor only pushes.
                let mut f = vec![V3::zeros(); x.len()];
                scene.total_forces(&x, None, &mut f);
                for i in 0..floor.len() {
                    assert!(
                        floor.pressing_force_n(i, &f) > -1e-9,
                        "node {}",
                        floor.nodes()[i]
                    );
                }
            } else {
                // Lifted: every node released, the same equilibrium as with no floor at all.
                assert!(solver.touching_contacts().iter().all(|on| !on));
                assert_eq!(report.contacts_released, floor.len());
                assert!(state.max_separation_m > 5.0 * tolerance_m, "{state:?}");
                let gap = x
                    .iter()
                    .zip(&x_free)
                    .map(|(a, b)| (a - b).norm())
                    .fold(0.0, f64::max);
                assert!(gap < 1e-8, "{gap} m from the free solution");
            }
        }
    }

    #[test]
    fn a_block_held_only_by_contact_converges_with_the_floor_carrying_its_weight() {
        // Two top nodes on vertical lines hold it sideways; vertically only the floor holds
        // it (the penalty law's tangent is zero at first touch: Newton stalled there).
        let cells = [4, 4, 2];
        let (mesh, lattice) = block(cells);
        let mut cs = ConstraintSet::new(mesh.node_count());
        for (i, l) in lattice.iter().enumerate() {
            if l[2] == cells[2] as u32 && (l[..2] == [2, 2] || l[..2] == [0, 0]) {
                let line = NodeConstraint::Line {
                    point_m: mesh.rest_positions_m[i],
                    direction: Vector3::z(),
                };
                cs.set(i as u32, line).unwrap();
            }
        }
        let mut scene = Scene::new(mesh.clone(), cs, gravity(-9.81)).unwrap();
        scene.one_sided = on_floor(&mesh, &lattice);
        let (x, report) = QuasiStaticSolver::new(&scene, QuasiStaticSettings::default())
            .unwrap()
            .solve(None)
            .unwrap();
        println!("held only by the floor: {report:?}");
        assert!(report.residual <= 1e-6, "{report:?}");
        assert_eq!(report.relaxation_steps, 0);
        let floor = &scene.one_sided;
        let state = floor.state(&x, 1e-7);
        assert!(state.max_penetration_m <= CONTACT_PENETRATION_FRACTION * EDGE_M);
        // The floor carries the weight: the free nodes' force along z, summed, is −m·g.
        let mut f = vec![V3::zeros(); x.len()];
        scene.total_forces(&x, None, &mut f);
        let pressing: f64 = (0..floor.len())
            .map(|i| floor.pressing_force_n(i, &f))
            .sum();
        let weight = scene.mesh.node_mass_kg.iter().sum::<f64>() * 9.81;
        assert!(
            (pressing - weight).abs() < 1e-6 * weight,
            "{pressing} N against {weight} N"
        );
    }
}
