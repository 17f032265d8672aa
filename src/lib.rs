//! lungmotion: predicts how every point of a patient's lungs moves while they breathe.
//!
//! The crate is organised as a pipeline, each stage a module:
//!
//! * [`model`]: the mechanical model: materials, Baudet's parameterised hexahedral
//!   mass–spring element, index-based meshes, constraints and loads.
//! * [`simulation`]: force evaluation, the explicit velocity-Verlet integrator with its
//!   automatic time step, the quasi-static solver, and blow-up detection.
//! * [`validation`]: measured accuracy against closed forms, the thesis's published
//!   results and CalculiX.
//!
//! Units: the mechanical core works in SI (metres, newtons, pascals, kilograms, seconds);
//! names carry the unit (`_m`, `_pa`, `_kg`) wherever a value crosses a module boundary.

pub mod bench;
pub mod error;
pub mod model;
pub mod simulation;
pub mod validation;

pub use error::{Error, Result};
