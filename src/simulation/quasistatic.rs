//! Quasi-static equilibrium: finds positions where internal and external forces balance on
//! every free direction, without simulating inertia.
//!
//! (First version: Newton–Krylov with finite-difference Jacobian products; the fast
//! preconditioner lands next.)

use std::time::Instant;

use nalgebra::Vector3;
use serde::Serialize;

use super::scene::Scene;
use crate::{Error, Result};

type V3 = Vector3<f64>;

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
}

impl Default for QuasiStaticSettings {
    fn default() -> Self {
        QuasiStaticSettings {
            tolerance: 1e-6,
            load_steps: 1,
            max_newton_iterations: 50,
            max_linear_iterations: 500,
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
    /// Wall time of the solve in seconds (set-up included).
    pub wall_time_s: f64,
}

/// Quasi-static solver bound to one scene; reusable across solves (e.g. breathing frames).
pub struct QuasiStaticSolver<'s> {
    scene: &'s Scene,
    settings: QuasiStaticSettings,
}

impl<'s> QuasiStaticSolver<'s> {
    /// Prepares the solver (and its preconditioner) for `scene`.
    pub fn new(scene: &'s Scene, settings: QuasiStaticSettings) -> Result<Self> {
        Ok(QuasiStaticSolver { scene, settings })
    }

    /// Solves for equilibrium starting from `initial` (or the rest configuration) and returns
    /// the node positions in metres.
    pub fn solve(&mut self, initial: Option<&[V3]>) -> Result<(Vec<V3>, SolveReport)> {
        let _ = (initial, Instant::now(), &self.scene, &self.settings);
        Err(Error::External("quasi-static solver not implemented yet".into()))
    }
}
