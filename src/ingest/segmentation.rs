//! Lung segmentation (to be written).
