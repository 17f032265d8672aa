//! Fuzzes the NIfTI-1/2 reader (raw or gzip) as a CT, a label map and a displacement field.

#![no_main]

use libfuzzer_sys::fuzz_target;
use lungmotion::formats::nifti::{
    read_nifti_bytes, read_nifti_labels_bytes, read_nifti_vector_field_bytes,
};

fuzz_target!(|data: &[u8]| {
    // Most inputs are refused at the header, so reading them three ways costs little.
    let _ = read_nifti_bytes(data, "fuzz.nii");
    let _ = read_nifti_labels_bytes(data, "fuzz.nii");
    let _ = read_nifti_vector_field_bytes(data, "fuzz.nii");
});
