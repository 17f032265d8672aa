//! Outputs a physicist looks at or loads into planning tools.

pub mod displacement_field;
pub mod ingest_files;
pub mod quicklook;
