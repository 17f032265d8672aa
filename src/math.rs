//! Vector aliases shared by the mechanical core and its callers.

use nalgebra::Vector3;

/// A 3-vector of `f64`; the unit and frame (metres or millimetres, LPS) are the caller's and
/// are named on the value (`_m`, `_mm`).
pub type V3 = Vector3<f64>;
