//! The mechanical model: material, element, mesh, constraints, contact and loads.

pub mod constraints;
pub mod contact;
pub mod continuum_correction;
pub mod cube_lattice;
pub mod element;
pub mod grid;
pub mod hourglass;
pub mod loads;
pub mod material;
pub mod mesh;
pub mod one_sided;
pub mod sdf;
pub mod spring_law;
pub mod tissue;
pub mod volumetric;

pub use constraints::{ConstraintSet, NodeConstraint};
pub use contact::{Contact, HuntCrossley, Obstacle, ObstacleMotion};
pub use continuum_correction::ContinuumCorrection;
pub use cube_lattice::CubeLattice;
pub use element::{BrickCoefficients, BrickShape};
pub use grid::VoxelGrid;
pub use hourglass::{HourglassCorrection, HourglassLaw};
pub use loads::{Loads, SurfacePressure};
pub use material::Material;
pub use mesh::HexMesh;
pub use one_sided::OneSidedPlanes;
pub use sdf::SignedDistanceField;
pub use spring_law::{ContinuumLaw, SpringLaw};
pub use volumetric::VolumetricCorrection;
