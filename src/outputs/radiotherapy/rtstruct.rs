//! DICOM RT Structure Sets on the planning CT: masks written as closed planar contours (the
//! ITV and the per-phase targets) and an ROI of a structure set read back into a mask.
//!
//! Holes: every closed polygon of a slice is its own CLOSED_PLANAR contour, and a contour
//! lying inside another is a hole (the even-odd rule Eclipse, RayStation, Orthanc Stone and
//! the pydicom-based converters apply); no keyhole cuts. The reader applies the same rule.

use std::path::Path;

use dicom_core::value::DataSetSequence;
use dicom_core::{DataElement, PrimitiveValue, Tag, VR};
use dicom_dictionary_std::{tags, uids};
use dicom_object::{FileMetaTableBuilder, InMemDicomObject};
use nalgebra::Vector3;

use super::contours::{fill_even_odd, slice_contours, SliceContour};
use crate::durable::write_atomic;
use crate::formats::dicom::{
    put_study_attributes, read_single_object, ContentKey, DicomStudyContext,
};
use crate::volume::{Volume, VolumeGeometry};
use crate::{Error, Result};

/// `derived_uid` kind of the structure set's series.
const SERIES_UID_KIND: u64 = 0x5254_5301;
/// `derived_uid` kind of the structure set's SOP instance.
const INSTANCE_UID_KIND: u64 = 0x5254_5302;
/// Implementation Class UID of files written by lungmotion (the one the CT writer uses).
const IMPLEMENTATION_CLASS_UID: &str = "2.25.240518131208190432779384431735391361291";
/// Detached Study Management SOP class, which RTReferencedStudySequence names by convention.
const STUDY_COMPONENT_SOP_CLASS: &str = "1.2.840.10008.3.1.2.3.1";
/// A contour lies on a CT slice when its points are within this fraction of the slice
/// spacing of the slice's plane.
const ON_SLICE_TOLERANCE: f64 = 0.05;

/// A polygon on CT slice k, in that slice's voxel indices (i, j).
type SlicePolygon = (usize, Vec<[f64; 2]>);

/// One ROI to write: its name, RT ROI Interpreted Type and colour, and its mask's contours.
#[derive(Debug, Clone)]
pub struct RoiContours {
    /// ROIName, e.g. `ITV` or `GTV phase 30%`.
    pub name: String,
    /// RTROIInterpretedType (3006,00A4): `ITV`, `GTV`, `CTV`, …
    pub interpreted_type: &'static str,
    /// ROIDisplayColor, RGB.
    pub colour_rgb: [u8; 3],
    /// The CT slices k that hold contours, with their polygons in that slice's voxel
    /// indices (i, j).
    pub slices: Vec<(usize, Vec<SliceContour>)>,
}

impl RoiContours {
    /// The contours of the nonzero voxels of `mask`, slice by slice (marching squares).
    pub fn of_mask(
        name: impl Into<String>,
        interpreted_type: &'static str,
        colour_rgb: [u8; 3],
        mask: &Volume<u8>,
    ) -> Self {
        let [ni, nj, nk] = mask.geometry.dims;
        let slices = (0..nk)
            .filter_map(|k| {
                let slice = &mask.as_slice()[k * ni * nj..(k + 1) * ni * nj];
                let contours = slice_contours(slice, ni, nj, |v| v != 0);
                (!contours.is_empty()).then_some((k, contours))
            })
            .collect();
        RoiContours {
            name: name.into(),
            interpreted_type,
            colour_rgb,
            slices,
        }
    }

    /// Number of polygons over all slices.
    pub fn contour_count(&self) -> usize {
        self.slices.iter().map(|(_, c)| c.len()).sum()
    }
}

/// Writes `rois` as one RT Structure Set on the planning CT of `study` (grid `ct`) at `path`:
/// the CT's patient, study and frame of reference, each contour referencing the CT image of
/// its slice. Refuses a study without the CT's images (a NIfTI or NRRD input): a structure
/// set that references no image is not loaded by planning systems.
pub fn write_rtstruct(
    path: &Path,
    study: &DicomStudyContext,
    ct: &VolumeGeometry,
    rois: &[RoiContours],
    label: &str,
) -> Result<()> {
    check_study(study, ct)?;
    let mut obj = InMemDicomObject::new_empty();
    put_identity(&mut obj, study, label, content_key(rois, label));
    put_referenced_frame_of_reference(&mut obj, study);
    let numbered = || rois.iter().enumerate().map(|(n, roi)| (n as i32 + 1, roi));
    let structure_set_rois = numbered()
        .map(|(number, roi)| {
            let mut item = InMemDicomObject::new_empty();
            put_int(&mut item, tags::ROI_NUMBER, number);
            put_text(
                &mut item,
                tags::REFERENCED_FRAME_OF_REFERENCE_UID,
                VR::UI,
                &study.frame_of_reference_uid,
            );
            put_text(&mut item, tags::ROI_NAME, VR::LO, &roi.name);
            put_text(
                &mut item,
                tags::ROI_GENERATION_ALGORITHM,
                VR::CS,
                "AUTOMATIC",
            );
            item
        })
        .collect();
    put_sequence(
        &mut obj,
        tags::STRUCTURE_SET_ROI_SEQUENCE,
        structure_set_rois,
    );
    let roi_contours = numbered()
        .map(|(number, roi)| roi_contour_item(number, roi, study, ct))
        .collect();
    put_sequence(&mut obj, tags::ROI_CONTOUR_SEQUENCE, roi_contours);
    let observations = numbered()
        .map(|(number, roi)| {
            let mut item = InMemDicomObject::new_empty();
            put_int(&mut item, tags::OBSERVATION_NUMBER, number);
            put_int(&mut item, tags::REFERENCED_ROI_NUMBER, number);
            put_text(
                &mut item,
                tags::RTROI_INTERPRETED_TYPE,
                VR::CS,
                roi.interpreted_type,
            );
            put_text(&mut item, tags::ROI_INTERPRETER, VR::PN, "");
            item
        })
        .collect();
    put_sequence(&mut obj, tags::RTROI_OBSERVATIONS_SEQUENCE, observations);
    put_text(&mut obj, tags::APPROVAL_STATUS, VR::CS, "UNAPPROVED");
    let file = obj
        .with_meta(
            FileMetaTableBuilder::new()
                .transfer_syntax(uids::EXPLICIT_VR_LITTLE_ENDIAN)
                .implementation_class_uid(IMPLEMENTATION_CLASS_UID)
                .implementation_version_name("LUNGMOTION"),
        )
        .map_err(|e| Error::format(path, format!("cannot build the file meta group ({e})")))?;
    let mut bytes = Vec::new();
    file.write_all(&mut bytes)
        .map_err(|e| Error::format(path, format!("cannot encode the RT Structure Set ({e})")))?;
    write_atomic(path, &bytes)
}

/// Refuses a study whose slice references do not match the CT grid's slices.
fn check_study(study: &DicomStudyContext, ct: &VolumeGeometry) -> Result<()> {
    if study.slices.is_empty() {
        return Err(Error::argument(
            "RT Structure Set",
            "the planning CT was not read from DICOM (a NIfTI or NRRD input), so there are \
             no CT images for the structure set to reference and a planning system would \
             not place it; the target's masks are written as NIfTI instead (give the CT as \
             its DICOM series to get an RTSTRUCT)",
        ));
    }
    if study.slices.len() != ct.dims[2] {
        return Err(Error::argument(
            "RT Structure Set",
            format!(
                "the planning CT has {} slices but its study lists {} images",
                ct.dims[2],
                study.slices.len()
            ),
        ));
    }
    Ok(())
}

/// Puts a text element.
fn put_text(obj: &mut InMemDicomObject, tag: Tag, vr: VR, value: &str) {
    obj.put(DataElement::new(
        tag,
        vr,
        PrimitiveValue::from(value.to_string()),
    ));
}

/// Puts an integer string (IS) element.
fn put_int(obj: &mut InMemDicomObject, tag: Tag, value: i32) {
    put_text(obj, tag, VR::IS, &value.to_string());
}

/// Puts a sequence of `items`.
fn put_sequence(obj: &mut InMemDicomObject, tag: Tag, items: Vec<InMemDicomObject>) {
    obj.put(DataElement::new(tag, VR::SQ, DataSetSequence::from(items)));
}

/// A key of the structure set's label, ROIs and contours: its UIDs follow what it shows, so
/// a job with other settings on the same CT writes a new structure set a PACS stores.
fn content_key(rois: &[RoiContours], label: &str) -> u64 {
    let mut key = ContentKey::default();
    key.mix_str(label);
    for roi in rois {
        key.mix_str(&roi.name);
        key.mix_str(roi.interpreted_type);
        roi.colour_rgb.iter().for_each(|&c| key.mix(u64::from(c)));
        for (k, polygons) in &roi.slices {
            key.mix(*k as u64);
            for polygon in polygons {
                key.mix(u64::from(polygon.hole));
                key.mix(polygon.points_ij.len() as u64);
                polygon
                    .points_ij
                    .iter()
                    .flatten()
                    .for_each(|v| key.mix(v.to_bits()));
            }
        }
    }
    key.finish()
}

/// SOP common, patient, study, RT series, equipment and structure set label elements.
fn put_identity(
    obj: &mut InMemDicomObject,
    study: &DicomStudyContext,
    label: &str,
    content_key: u64,
) {
    let mut put = |tag: Tag, vr: VR, value: &str| put_text(obj, tag, vr, value);
    put(tags::SPECIFIC_CHARACTER_SET, VR::CS, "ISO_IR 192");
    put(tags::SOP_CLASS_UID, VR::UI, uids::RT_STRUCTURE_SET_STORAGE);
    put(
        tags::SOP_INSTANCE_UID,
        VR::UI,
        &study.content_uid(INSTANCE_UID_KIND, 0, content_key),
    );
    put(tags::MODALITY, VR::CS, "RTSTRUCT");
    put(tags::MANUFACTURER, VR::LO, "lungmotion");
    put(tags::SERIES_DESCRIPTION, VR::LO, label);
    put(tags::OPERATORS_NAME, VR::PN, "");
    put(tags::SOFTWARE_VERSIONS, VR::LO, env!("CARGO_PKG_VERSION"));
    put(
        tags::SERIES_INSTANCE_UID,
        VR::UI,
        &study.content_uid(SERIES_UID_KIND, 0, content_key),
    );
    put(tags::SERIES_NUMBER, VR::IS, "9001");
    put(tags::INSTANCE_NUMBER, VR::IS, "1");
    put(tags::STRUCTURE_SET_LABEL, VR::SH, "lungmotion");
    put(tags::STRUCTURE_SET_NAME, VR::LO, label);
    put(tags::STRUCTURE_SET_DATE, VR::DA, "");
    put(tags::STRUCTURE_SET_TIME, VR::TM, "");
    put_study_attributes(obj, study);
}

/// A ContourImageSequence item naming CT slice `k`.
fn contour_image_item(study: &DicomStudyContext, k: usize) -> InMemDicomObject {
    let slice = &study.slices[k];
    let mut item = InMemDicomObject::new_empty();
    put_text(
        &mut item,
        tags::REFERENCED_SOP_CLASS_UID,
        VR::UI,
        &slice.sop_class_uid,
    );
    put_text(
        &mut item,
        tags::REFERENCED_SOP_INSTANCE_UID,
        VR::UI,
        &slice.sop_instance_uid,
    );
    if let Some(frame) = slice.frame_number {
        put_int(&mut item, tags::REFERENCED_FRAME_NUMBER, frame as i32);
    }
    item
}

/// ReferencedFrameOfReferenceSequence → RTReferencedStudySequence → RTReferencedSeriesSequence
/// → ContourImageSequence with every CT slice.
fn put_referenced_frame_of_reference(obj: &mut InMemDicomObject, study: &DicomStudyContext) {
    let mut series = InMemDicomObject::new_empty();
    put_text(
        &mut series,
        tags::SERIES_INSTANCE_UID,
        VR::UI,
        &study.series_instance_uid,
    );
    let images = (0..study.slices.len())
        .map(|k| contour_image_item(study, k))
        .collect();
    put_sequence(&mut series, tags::CONTOUR_IMAGE_SEQUENCE, images);
    let mut referenced_study = InMemDicomObject::new_empty();
    put_text(
        &mut referenced_study,
        tags::REFERENCED_SOP_CLASS_UID,
        VR::UI,
        STUDY_COMPONENT_SOP_CLASS,
    );
    put_text(
        &mut referenced_study,
        tags::REFERENCED_SOP_INSTANCE_UID,
        VR::UI,
        &study.study_instance_uid,
    );
    put_sequence(
        &mut referenced_study,
        tags::RT_REFERENCED_SERIES_SEQUENCE,
        vec![series],
    );
    let mut frame = InMemDicomObject::new_empty();
    put_text(
        &mut frame,
        tags::FRAME_OF_REFERENCE_UID,
        VR::UI,
        &study.frame_of_reference_uid,
    );
    put_sequence(
        &mut frame,
        tags::RT_REFERENCED_STUDY_SEQUENCE,
        vec![referenced_study],
    );
    put_sequence(
        obj,
        tags::REFERENCED_FRAME_OF_REFERENCE_SEQUENCE,
        vec![frame],
    );
}

/// One ROIContourSequence item: colour, ROI number and a CLOSED_PLANAR contour per polygon,
/// in LPS mm, each naming the CT image of its slice.
fn roi_contour_item(
    number: i32,
    roi: &RoiContours,
    study: &DicomStudyContext,
    ct: &VolumeGeometry,
) -> InMemDicomObject {
    let mut item = InMemDicomObject::new_empty();
    put_text(
        &mut item,
        tags::ROI_DISPLAY_COLOR,
        VR::IS,
        &roi.colour_rgb.map(|c| c.to_string()).join("\\"),
    );
    put_int(&mut item, tags::REFERENCED_ROI_NUMBER, number);
    let mut contour_number = 0;
    let mut contours = Vec::with_capacity(roi.contour_count());
    for (k, polygons) in &roi.slices {
        for polygon in polygons {
            contour_number += 1;
            let mut contour = InMemDicomObject::new_empty();
            put_sequence(
                &mut contour,
                tags::CONTOUR_IMAGE_SEQUENCE,
                vec![contour_image_item(study, *k)],
            );
            put_text(
                &mut contour,
                tags::CONTOUR_GEOMETRIC_TYPE,
                VR::CS,
                "CLOSED_PLANAR",
            );
            put_int(
                &mut contour,
                tags::NUMBER_OF_CONTOUR_POINTS,
                polygon.points_ij.len() as i32,
            );
            put_int(&mut contour, tags::CONTOUR_NUMBER, contour_number);
            put_text(
                &mut contour,
                tags::CONTOUR_DATA,
                VR::DS,
                &contour_data(&polygon.points_ij, *k, ct),
            );
            contours.push(contour);
        }
    }
    put_sequence(&mut item, tags::CONTOUR_SEQUENCE, contours);
    item
}

/// The polygon's points on slice `k` as LPS mm, `x\y\z\x\y\z…` with 0.001 mm resolution.
fn contour_data(points_ij: &[[f64; 2]], k: usize, ct: &VolumeGeometry) -> String {
    let mut text = String::with_capacity(points_ij.len() * 30);
    for (n, p) in points_ij.iter().enumerate() {
        let lps = ct.voxel_to_lps_mm(Vector3::new(p[0], p[1], k as f64));
        for (c, v) in lps.iter().enumerate() {
            if n > 0 || c > 0 {
                text.push('\\');
            }
            text.push_str(&decimal(*v));
        }
    }
    text
}

/// `v` with at most three decimals, trailing zeros dropped (at most 16 characters for any
/// coordinate within a metre and a half of the origin… and far beyond).
fn decimal(v: f64) -> String {
    let s = format!("{v:.3}");
    let s = s.trim_end_matches('0').trim_end_matches('.');
    if s == "-0" {
        "0".into()
    } else {
        s.into()
    }
}

/// The ROI `roi` of the RT Structure Set at `path` as a mask on the CT grid `ct`: its
/// closed planar contours filled slice by slice (even-odd rule). Refuses a file that is not
/// a structure set, a missing ROI (listing the names present), a frame of reference other
/// than `ct_frame_of_reference` (when the CT has one), and contours off the CT's slices.
pub fn read_roi_mask(
    path: &Path,
    roi: &str,
    ct: &VolumeGeometry,
    ct_frame_of_reference: Option<&str>,
) -> Result<Volume<u8>> {
    let obj = read_structure_set(path)?;
    let bad = |reason: String| Error::format(path, reason);
    let (number, roi_frame) = find_roi(&obj, roi).map_err(bad)?;
    if let Some(ct_frame) = ct_frame_of_reference {
        if roi_frame != ct_frame {
            return Err(bad(format!(
                "ROI {roi} is in frame of reference {roi_frame} (ReferencedFrameOfReferenceUID), \
                 the CT in {ct_frame} (FrameOfReferenceUID): the structure set belongs to \
                 another scan or another registration of this patient"
            )));
        }
    }
    let polygons = roi_polygons(&obj, number, roi, ct).map_err(bad)?;
    let mut by_slice: std::collections::BTreeMap<usize, Vec<Vec<[f64; 2]>>> = Default::default();
    for (k, polygon) in polygons {
        by_slice.entry(k).or_default().push(polygon);
    }
    let [ni, nj, _] = ct.dims;
    let mut mask = Volume::filled(*ct, 0u8)?;
    for (k, on_slice) in by_slice {
        let slice = &mut mask.as_slice_mut()[k * ni * nj..(k + 1) * ni * nj];
        fill_even_odd(&on_slice, ni, nj, slice);
    }
    Ok(mask)
}

/// The ROI names (ROIName of StructureSetROISequence, in file order) of the RT Structure Set
/// at `path`; refuses a DICOM file that is not a structure set.
pub fn roi_names(path: &Path) -> Result<Vec<String>> {
    let obj = read_structure_set(path)?;
    Ok(items_of(&obj, tags::STRUCTURE_SET_ROI_SEQUENCE)
        .iter()
        .map(|item| text_of(item, tags::ROI_NAME))
        .collect())
}

/// The DICOM object at `path`, refused unless it is an RT Structure Set.
fn read_structure_set(path: &Path) -> Result<dicom_object::DefaultDicomObject> {
    let obj = read_single_object(path)?;
    let sop_class = text_of(&obj, tags::SOP_CLASS_UID);
    if sop_class != uids::RT_STRUCTURE_SET_STORAGE {
        return Err(Error::format(
            path,
            format!(
                "not an RT Structure Set (SOPClassUID is `{sop_class}`, Modality `{}`)",
                text_of(&obj, tags::MODALITY)
            ),
        ));
    }
    Ok(obj)
}

/// An element's text, trimmed, or empty.
fn text_of(obj: &InMemDicomObject, tag: Tag) -> String {
    obj.get(tag)
        .and_then(|e| e.to_str().ok())
        .map(|s| {
            s.trim_matches(|c: char| c.is_whitespace() || c == '\0')
                .to_string()
        })
        .unwrap_or_default()
}

/// The items of sequence `tag` (none when absent).
fn items_of(obj: &InMemDicomObject, tag: Tag) -> &[InMemDicomObject] {
    obj.get(tag).and_then(|e| e.items()).unwrap_or(&[])
}

/// ROINumber and ReferencedFrameOfReferenceUID of ROI `roi` (its exact name, else the one
/// name equal to it ignoring case and surrounding spaces).
fn find_roi(obj: &InMemDicomObject, roi: &str) -> std::result::Result<(String, String), String> {
    let rois: Vec<(String, String, String)> = items_of(obj, tags::STRUCTURE_SET_ROI_SEQUENCE)
        .iter()
        .map(|item| {
            (
                text_of(item, tags::ROI_NAME),
                text_of(item, tags::ROI_NUMBER),
                text_of(item, tags::REFERENCED_FRAME_OF_REFERENCE_UID),
            )
        })
        .collect();
    let exact = rois.iter().find(|r| r.0 == roi);
    let loose: Vec<_> = rois
        .iter()
        .filter(|r| r.0.trim().eq_ignore_ascii_case(roi.trim()))
        .collect();
    let found = exact.or(if loose.len() == 1 {
        Some(loose[0])
    } else {
        None
    });
    match found {
        Some((_, number, frame)) => Ok((number.clone(), frame.clone())),
        None => {
            let names: Vec<&str> = rois.iter().map(|r| r.0.as_str()).collect();
            Err(format!(
                "no ROI named `{roi}` (StructureSetROISequence); ROIs present: {}",
                if names.is_empty() {
                    "none".to_string()
                } else {
                    names.join(", ")
                }
            ))
        }
    }
}

/// The closed planar contours of ROI `number` as (CT slice k, polygon in that slice's voxel
/// indices); refuses contours off the CT's slices or with malformed ContourData.
fn roi_polygons(
    obj: &InMemDicomObject,
    number: String,
    roi: &str,
    ct: &VolumeGeometry,
) -> std::result::Result<Vec<SlicePolygon>, String> {
    let item = items_of(obj, tags::ROI_CONTOUR_SEQUENCE)
        .iter()
        .find(|item| text_of(item, tags::REFERENCED_ROI_NUMBER) == number)
        .ok_or_else(|| format!("ROI {roi} (number {number}) has no ROIContourSequence item"))?;
    let mut polygons = Vec::new();
    for (n, contour) in items_of(item, tags::CONTOUR_SEQUENCE).iter().enumerate() {
        let kind = text_of(contour, tags::CONTOUR_GEOMETRIC_TYPE);
        if kind != "CLOSED_PLANAR" {
            continue;
        }
        let values = contour
            .get(tags::CONTOUR_DATA)
            .and_then(|e| e.to_multi_float64().ok())
            .unwrap_or_default();
        if values.len() < 9 || values.len() % 3 != 0 || values.iter().any(|v| !v.is_finite()) {
            return Err(format!(
                "ROI {roi}, contour {}: ContourData holds {} numbers, not 3 per point for at \
                 least 3 finite points",
                n + 1,
                values.len()
            ));
        }
        polygons.push(
            on_ct_slice(&values, ct)
                .map_err(|why| format!("ROI {roi}, contour {}: {why}", n + 1))?,
        );
    }
    if polygons.is_empty() {
        return Err(format!("ROI {roi} has no CLOSED_PLANAR contour"));
    }
    Ok(polygons)
}

/// The CT slice a contour's LPS points lie on and the points in its voxel indices (i, j).
fn on_ct_slice(
    values: &[f64],
    ct: &VolumeGeometry,
) -> std::result::Result<(usize, Vec<[f64; 2]>), String> {
    let mut k_of_first = None;
    let mut points = Vec::with_capacity(values.len() / 3);
    for p in values.chunks_exact(3) {
        let v = ct.lps_mm_to_voxel(Vector3::new(p[0], p[1], p[2]));
        let k = v[2].round();
        let off_mm = (v[2] - k).abs() * ct.spacing_mm[2];
        if (v[2] - k).abs() > ON_SLICE_TOLERANCE {
            let position = |k: f64| ct.voxel_to_lps_mm(Vector3::new(0.0, 0.0, k));
            return Err(format!(
                "point ({}, {}, {}) mm lies {off_mm:.2} mm off the CT's slices (between slice \
                 {} at z {:.2} mm and slice {} at z {:.2} mm along the slice axis): the \
                 structure set was drawn on another scan's slices",
                p[0],
                p[1],
                p[2],
                v[2].floor(),
                position(v[2].floor())[2],
                v[2].floor() + 1.0,
                position(v[2].floor() + 1.0)[2],
            ));
        }
        match k_of_first {
            None => k_of_first = Some(k),
            Some(k0) if k0 != k => {
                return Err(format!(
                    "its points lie on CT slices {k0} and {k}: a CLOSED_PLANAR contour lies \
                     in one slice's plane"
                ))
            }
            Some(_) => {}
        }
        points.push([v[0], v[1]]);
    }
    let k = k_of_first.unwrap_or(0.0);
    if k < 0.0 || k >= ct.dims[2] as f64 {
        return Err(format!(
            "it lies on slice {k} of a CT with slices 0–{}: outside the scan",
            ct.dims[2] - 1
        ));
    }
    Ok((k as usize, points))
}
