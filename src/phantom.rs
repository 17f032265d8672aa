//! Procedural thorax phantom (to be written).
