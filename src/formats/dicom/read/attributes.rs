//! Where a slice's geometry and rescale are read (a single-frame file's data set, or a frame's
//! functional groups in an Enhanced CT file) and the checked values read there.

use dicom_core::Tag;
use dicom_dictionary_std::tags;
use dicom_object::mem::InMemElement;
use dicom_object::InMemDicomObject;
use nalgebra::Vector3;

use super::FrameLayout;
use crate::{Error, Result};

/// Tolerance on direction cosines and pixel spacing between slices of one series.
const CONSISTENCY_TOLERANCE: f64 = 1e-4;

/// The data sets a slice's attributes are looked up in, most specific first.
pub(super) struct AttributeScope<'a> {
    /// The frame's item of the PerFrameFunctionalGroupsSequence (multi-frame files).
    pub per_frame: Option<&'a InMemDicomObject>,
    /// The item of the SharedFunctionalGroupsSequence (multi-frame files).
    pub shared: Option<&'a InMemDicomObject>,
    /// The file's top-level data set.
    pub top: &'a InMemDicomObject,
}

/// The functional group macro (PS3.3 C.7.6.16.2) that carries `tag` in a multi-frame file.
fn functional_group(tag: Tag) -> Option<Tag> {
    match tag {
        tags::IMAGE_POSITION_PATIENT => Some(tags::PLANE_POSITION_SEQUENCE),
        tags::IMAGE_ORIENTATION_PATIENT => Some(tags::PLANE_ORIENTATION_SEQUENCE),
        tags::PIXEL_SPACING | tags::SLICE_THICKNESS => Some(tags::PIXEL_MEASURES_SEQUENCE),
        tags::RESCALE_SLOPE | tags::RESCALE_INTERCEPT => {
            Some(tags::PIXEL_VALUE_TRANSFORMATION_SEQUENCE)
        }
        _ => None,
    }
}

impl<'a> AttributeScope<'a> {
    /// The scope of a single-frame file.
    pub fn single_frame(top: &'a InMemDicomObject) -> Self {
        AttributeScope {
            per_frame: None,
            shared: None,
            top,
        }
    }

    /// `tag` from the frame's functional group, else the shared one, else the top level.
    pub fn get(&self, tag: Tag) -> Option<&'a InMemElement> {
        let in_group = |group: Option<&'a InMemDicomObject>| {
            let sequence = functional_group(tag)?;
            group?.get(sequence)?.items()?.first()?.get(tag)
        };
        in_group(self.per_frame)
            .or_else(|| in_group(self.shared))
            .or_else(|| self.top.get(tag))
    }

    /// `count` finite numbers of `tag`; `name` is the slice's name in errors.
    pub fn floats(&self, name: &str, tag: Tag, tag_name: &str, count: usize) -> Result<Vec<f64>> {
        let bad = |m: String| {
            Error::scan(
                name,
                format!("{tag_name} ({:04X},{:04X}) {m}", tag.0, tag.1),
            )
        };
        let element = self.get(tag).ok_or_else(|| bad("is missing".into()))?;
        let values = element
            .to_multi_float64()
            .map_err(|e| bad(format!("is not numeric ({e})")))?;
        if values.len() != count {
            return Err(bad(format!(
                "has {} values, {count} expected",
                values.len()
            )));
        }
        if values.iter().any(|v| !v.is_finite()) {
            return Err(bad(format!("is not finite: {values:?}")));
        }
        Ok(values)
    }

    /// An unsigned integer `tag`.
    pub fn unsigned(&self, name: &str, tag: Tag, tag_name: &str) -> Result<usize> {
        let bad = |m: &str| {
            Error::scan(
                name,
                format!("{tag_name} ({:04X},{:04X}) {m}", tag.0, tag.1),
            )
        };
        let element = self.get(tag).ok_or_else(|| bad("is missing"))?;
        element
            .to_int::<u32>()
            .map(|v| v as usize)
            .map_err(|_| bad("is not an unsigned integer"))
    }

    /// RescaleSlope or RescaleIntercept: `None` when absent, `default` when not finite.
    pub fn rescale(
        &self,
        name: &str,
        tag: Tag,
        tag_name: &str,
        default: f64,
    ) -> Result<Option<f64>> {
        if self.get(tag).is_none() {
            return Ok(None);
        }
        let v = self.floats(name, tag, tag_name, 1)?[0];
        Ok(Some(if v.is_finite() { v } else { default }))
    }

    /// Image size, orientation and pixel spacing, checked.
    pub fn frame_layout(&self, name: &str) -> Result<FrameLayout> {
        let bad = |m: String| Error::scan(name, m);
        let rows = self.unsigned(name, tags::ROWS, "Rows")?;
        let columns = self.unsigned(name, tags::COLUMNS, "Columns")?;
        if rows == 0 || columns == 0 {
            return Err(bad(format!(
                "empty image ({rows} rows × {columns} columns)"
            )));
        }
        let iop = self.floats(
            name,
            tags::IMAGE_ORIENTATION_PATIENT,
            "ImageOrientationPatient",
            6,
        )?;
        let row_direction = Vector3::new(iop[0], iop[1], iop[2]);
        let column_direction = Vector3::new(iop[3], iop[4], iop[5]);
        let orthonormal = (row_direction.norm() - 1.0).abs() < 1e-3
            && (column_direction.norm() - 1.0).abs() < 1e-3
            && row_direction.dot(&column_direction).abs() < 1e-3;
        if !orthonormal {
            return Err(bad(format!(
                "ImageOrientationPatient {iop:?} is not two orthogonal unit vectors"
            )));
        }
        let spacing = self.floats(name, tags::PIXEL_SPACING, "PixelSpacing", 2)?;
        if spacing.iter().any(|&s| s <= 0.0) {
            return Err(bad(format!(
                "PixelSpacing {spacing:?} mm: spacings must be positive"
            )));
        }
        Ok(FrameLayout {
            rows,
            columns,
            row_direction: row_direction.normalize(),
            column_direction: column_direction.normalize(),
            pixel_spacing_mm: [spacing[0], spacing[1]],
        })
    }
}

/// Refuses a slice whose size, orientation or pixel spacing differs from the first one's.
pub(super) fn check_same_layout(
    reference: &FrameLayout,
    name_ref: &str,
    other: &FrameLayout,
    name: &str,
) -> Result<()> {
    let bad = |m: String| {
        Err(Error::scan(
            name,
            format!("{m} differs from {name_ref} in the same series"),
        ))
    };
    if (other.rows, other.columns) != (reference.rows, reference.columns) {
        return bad(format!(
            "image size {}×{} (rows×columns) vs {}×{}",
            other.rows, other.columns, reference.rows, reference.columns
        ));
    }
    let direction_change = (other.row_direction - reference.row_direction)
        .abs()
        .max()
        .max(
            (other.column_direction - reference.column_direction)
                .abs()
                .max(),
        );
    if direction_change > CONSISTENCY_TOLERANCE {
        return bad("ImageOrientationPatient".into());
    }
    let close = |a: f64, b: f64| (a - b).abs() <= CONSISTENCY_TOLERANCE * a.abs().max(1.0);
    if !close(other.pixel_spacing_mm[0], reference.pixel_spacing_mm[0])
        || !close(other.pixel_spacing_mm[1], reference.pixel_spacing_mm[1])
    {
        return bad(format!(
            "PixelSpacing {:?} vs {:?}",
            other.pixel_spacing_mm, reference.pixel_spacing_mm
        ));
    }
    Ok(())
}
