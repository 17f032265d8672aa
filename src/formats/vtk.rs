//! VTK XML writers (to be written).
