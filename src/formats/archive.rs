//! Safe zip extraction (to be written).
