//! The public readers: CT values, label maps and displacement fields from NIfTI bytes.

use std::path::Path;

use rayon::prelude::*;

use super::image::{parse_image, read_file, Components};
use super::samples::decode_samples;
use super::{first_position, refuse_non_finite, voxel_ijk, INTENT_DISPLACEMENT, INTENT_VECTOR};
use crate::formats::budget::ScanBudget;
use crate::volume::{Volume, VolumeGeometry};
use crate::{Error, Result};

/// Reads a 3-D NIfTI-1 or NIfTI-2 file (raw or gzipped) into f32 values (HU for CT), within
/// [`ScanBudget::for_this_machine`].
pub fn read_nifti(path: &Path) -> Result<Volume<f32>> {
    let bytes = read_file(path)?;
    read_nifti_bytes(&bytes, &path.display().to_string())
}

/// Reads NIfTI bytes (an upload) within [`ScanBudget::for_this_machine`]; `what` names the
/// source in errors.
pub fn read_nifti_bytes(bytes: &[u8], what: &str) -> Result<Volume<f32>> {
    read_nifti_bytes_within(bytes, what, &ScanBudget::for_this_machine())
}

/// Reads NIfTI bytes within `budget` (its ratio cap applies to gzip files).
pub fn read_nifti_bytes_within(
    bytes: &[u8],
    what: &str,
    budget: &ScanBudget,
) -> Result<Volume<f32>> {
    let image = parse_image(bytes, what, Components::Scalar, budget)?;
    let mut data = vec![0f32; image.geometry.voxel_count()];
    let (slope, inter) = image.scaling;
    decode_samples(&image, &mut data, |v| (v * slope + inter) as f32);
    refuse_non_finite(&data, &image.geometry, what)?;
    Volume::from_data(image.geometry, data)
}

/// Reads a NIfTI label map; values must be integers in 0..=255 after scaling.
pub fn read_nifti_labels(path: &Path) -> Result<Volume<u8>> {
    let bytes = read_file(path)?;
    read_nifti_labels_bytes(&bytes, &path.display().to_string())
}

/// Reads NIfTI label-map bytes; `what` names the source in errors.
pub fn read_nifti_labels_bytes(bytes: &[u8], what: &str) -> Result<Volume<u8>> {
    let budget = ScanBudget::for_this_machine().without_ratio_cap();
    let image = parse_image(bytes, what, Components::Scalar, &budget)?;
    let (slope, inter) = image.scaling;
    // 256 marks a voxel that is no label, so the conversion needs no error path per voxel.
    let mut codes = vec![0u16; image.geometry.voxel_count()];
    decode_samples(&image, &mut codes, |v| {
        let v = v * slope + inter;
        if v.fract() == 0.0 && (0.0..=255.0).contains(&v) {
            v as u16
        } else {
            256
        }
    });
    if let Some(first) = first_position(&codes, |&c| c > 255) {
        let count = codes.par_iter().filter(|&&c| c > 255).count();
        let value = image.sample(first) * slope + inter;
        let [i, j, k] = voxel_ijk(first, &image.geometry);
        return Err(Error::scan(
            what,
            format!(
                "not a label map: {count} voxels are not integers in 0..=255 \
             (first at voxel ({i}, {j}, {k}) = {value})"
            ),
        ));
    }
    let labels = codes.par_iter().map(|&c| c as u8).collect();
    Volume::from_data(image.geometry, labels)
}

/// Reads a displacement field written as ITK does (see the module doc): the grid and one
/// LPS-millimetre vector per voxel, i fastest.
pub fn read_nifti_vector_field(path: &Path) -> Result<(VolumeGeometry, Vec<[f32; 3]>)> {
    let bytes = read_file(path)?;
    read_nifti_vector_field_bytes(&bytes, &path.display().to_string())
}

/// Reads displacement-field bytes; `what` names the source in errors.
pub fn read_nifti_vector_field_bytes(
    bytes: &[u8],
    what: &str,
) -> Result<(VolumeGeometry, Vec<[f32; 3]>)> {
    let budget = ScanBudget::for_this_machine().without_ratio_cap();
    let image = parse_image(bytes, what, Components::Vector3, &budget)?;
    if image.intent_code != INTENT_VECTOR && image.intent_code != INTENT_DISPLACEMENT {
        tracing::warn!(
            "{what}: intent_code {} is not a vector intent (1006/1007); reading the 3 \
             components as LPS millimetres anyway",
            image.intent_code
        );
    }
    let n = image.geometry.voxel_count();
    let (slope, inter) = image.scaling;
    let mut planes = vec![0f32; 3 * n];
    decode_samples(&image, &mut planes, |v| (v * slope + inter) as f32);
    refuse_non_finite(
        &planes[..n],
        &image.geometry,
        &format!("{what} (x component)"),
    )?;
    refuse_non_finite(
        &planes[n..2 * n],
        &image.geometry,
        &format!("{what} (y component)"),
    )?;
    refuse_non_finite(
        &planes[2 * n..],
        &image.geometry,
        &format!("{what} (z component)"),
    )?;
    let (x, rest) = planes.split_at(n);
    let (y, z) = rest.split_at(n);
    let vectors = (0..n).into_par_iter().map(|v| [x[v], y[v], z[v]]).collect();
    Ok((image.geometry, vectors))
}
