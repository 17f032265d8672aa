//! Simulation: force evaluation, explicit dynamics, quasi-static equilibrium, blow-up checks.

pub mod cases;
pub mod driver;
pub mod explicit;
pub mod forces;
pub mod keyframes;
mod lanes;
pub mod linalg;
pub mod multigrid;
pub mod quasistatic;
pub mod scene;

pub use driver::{
    BreathingDriver, CancelFlag, DrivenState, ImposedMotionShare, SolveProgress, SolveProgressSink,
};
pub use explicit::{ExplicitIntegrator, ExplicitSettings, TimeStepBound};
pub use forces::ForceEvaluator;
pub use quasistatic::{PreconditionerKind, QuasiStaticSettings, QuasiStaticSolver, SolveReport};
pub use scene::Scene;
