//! File formats, each in both directions where the project writes it, each stating its
//! convention: medical images convert to and from [`crate::volume::Volume`] (LPS millimetres).

pub mod archive;
pub mod budget;
pub mod dicom;
pub mod metaimage;
pub mod nifti;
pub mod nrrd;
pub mod vtk;
