//! Breathing curves: the lung-volume trace that drives the model, the standard test curves
//! that stand in for a spirometer, and the instants at which displacement fields are wanted.

pub mod airflow;
mod columns;
pub mod generator;
pub mod instants;
pub mod trace;

pub use generator::{IrregularBreathing, LujanBreathing};
pub use instants::{InstantPlan, OutputInstants};
pub use trace::{BreathingTrace, TraceFormat, TraceOptions, TraceReading, VolumeReference};
