//! lungmotion: predicts how every point of a patient's lungs moves while they breathe.
//!
//! The crate is organised as a pipeline, each stage a module:
//!
//! * [`volume`] and [`formats`]: CT and label volumes in DICOM patient space (LPS mm), read
//!   from DICOM series, NIfTI and NRRD, written as NIfTI, DICOM and VTK.
//! * [`ingest`]: lung segmentation, cubic elements and anatomical constraint groups.
//! * [`phantom`]: the procedural thorax phantom behind `sample-volumes/`.
//! * [`breathing`]: breathing traces (CSV/JSON), standard test curves, output instants.
//! * [`model`]: the mechanical model: materials, Baudet's parameterised hexahedral
//!   mass–spring element, index-based meshes, constraints and loads.
//! * [`simulation`]: force evaluation, the explicit velocity-Verlet integrator with its
//!   automatic time step, the quasi-static solver, and blow-up detection.
//! * [`outputs`]: quick-look images and the files planning tools load.
//! * [`validation`]: measured accuracy against closed forms, the thesis's published
//!   results and CalculiX.
//!
//! # Example
//!
//! A 4 × 4 × 4 block of 5 mm lung-tissue cubes, one octant with symmetry planes, inflated by a
//! uniform −20 Pa follower pressure and solved quasi-statically:
//!
//! ```
//! use lungmotion::model::Material;
//! use lungmotion::simulation::{QuasiStaticSettings, QuasiStaticSolver};
//! use lungmotion::simulation::cases::symmetric_block_under_pressure;
//!
//! let scene = symmetric_block_under_pressure([4, 4, 4], 0.005, Material::LUNG, -20.0)?;
//! let mut solver = QuasiStaticSolver::new(&scene, QuasiStaticSettings::default())?;
//! let (positions, report) = solver.solve(None)?;
//! assert!(report.residual <= 1e-6);
//!
//! // Small-strain theory: ΔV/V = −p/K with K the bulk modulus (E, ν exact in this element).
//! let mesh = &scene.mesh;
//! let v0 = mesh.enclosed_volume_m3(&mesh.rest_positions_m);
//! let dv = (mesh.enclosed_volume_m3(&positions) - v0) / v0;
//! let linear = 20.0 / Material::LUNG.bulk_modulus_pa();
//! assert!((dv - linear).abs() < 0.1 * linear);
//! # Ok::<(), lungmotion::Error>(())
//! ```
//!
//! Units: the mechanical core works in SI (metres, newtons, pascals, kilograms, seconds);
//! names carry the unit (`_m`, `_pa`, `_kg`) wherever a value crosses a module boundary.

#![warn(missing_docs)]

#[cfg(feature = "bench")]
pub mod bench;
pub mod breathing;
pub mod datasets;
pub mod durable;
pub mod error;
pub mod formats;
pub mod ingest;
pub mod markdown;
pub mod math;
pub mod model;
pub mod motion;
pub mod outputs;
#[cfg(feature = "service")]
pub mod pacs;
pub mod phantom;
pub mod process;
pub mod run;
#[cfg(feature = "service")]
pub mod service;
pub mod simulation;
#[cfg(feature = "validation")]
pub mod validation;
pub mod volume;

pub use error::{BudgetKind, BudgetStop, Error, IoContext, IoOp, Result, UnreachableVolume};
