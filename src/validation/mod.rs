//! Measured accuracy against references nobody here wrote: closed forms (patch tests), the
//! thesis's published results (strain sweeps, composite cases) and CalculiX.

pub mod calculix;
pub mod composite;
pub mod contact;
pub mod four_dct;
pub mod landmarks;
pub mod lung_calculix;
pub mod material_laws;
pub mod patch;
pub mod pressure_volume;
pub mod report;
pub mod stability;
pub mod sweep;
