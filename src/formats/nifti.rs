//! NIfTI-1 and NIfTI-2 reader and writer (to be written).
