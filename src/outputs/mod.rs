//! Outputs a physicist looks at or loads into planning tools.

pub mod displacement_field;
pub mod ingest_files;
pub mod ingest_quicklooks;
pub mod plots;
pub mod quicklook;
pub mod radiotherapy;
pub mod raster_text;
pub mod trajectories;
