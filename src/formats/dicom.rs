//! DICOM series reader and writer (to be written).
