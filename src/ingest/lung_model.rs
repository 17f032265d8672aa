//! Cubic elements and constraint groups from a lung mask (to be written).
