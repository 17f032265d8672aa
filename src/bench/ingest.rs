//! Ingest benchmarks: segmentation time and memory (to be written).
