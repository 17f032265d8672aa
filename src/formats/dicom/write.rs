//! Writing a volume as a CT Image Storage series (one file per k-slice), as a study of its
//! own or derived from a planning CT (its patient, study and frame of reference), with the
//! respiratory phase a virtual 4D-CT series carries.

use std::path::{Path, PathBuf};

use dicom_core::smallvec::SmallVec;
use dicom_core::value::DataSetSequence;
use dicom_core::{DataElement, PrimitiveValue, Tag, VR};
use dicom_dictionary_std::{tags, uids};
use dicom_object::{FileMetaTableBuilder, InMemDicomObject};
use nalgebra::Vector3;
use rayon::prelude::*;

use super::{CtSeriesMetadata, DicomStudyContext};
use crate::durable::write_atomic;
use crate::volume::Volume;
use crate::{Error, Result};

/// Writes `volume` (HU) into `dir` as `IMG0001.dcm`, … one file per k-slice: CT Image
/// Storage, Explicit VR Little Endian, signed 16-bit pixels holding the rounded HU minus a
/// RescaleIntercept shared by all slices (0 whenever the values fit in int16). Each file is
/// written to a temporary sibling and renamed. Returns the paths in k order.
pub fn write_ct_series<T: HuSample>(
    volume: &Volume<T>,
    dir: &Path,
    meta: &CtSeriesMetadata,
) -> Result<Vec<PathBuf>> {
    let what = dir.display().to_string();
    check_volume_fits(volume, &what)?;
    let intercept = shared_rescale_intercept(volume, &what)?;
    std::fs::create_dir_all(dir)
        .map_err(|e| series_error(&what, format!("cannot create the directory: {e}")))?;
    let series = SeriesLayout::new(volume, meta, intercept);
    let g = volume.geometry;
    let width = g.dims[2].to_string().len().max(4);
    (0..g.dims[2])
        .into_par_iter()
        .map(|k| {
            let mut obj = InMemDicomObject::new_empty();
            put_identity_elements(&mut obj, volume, meta, &series, k);
            if let Some(derived) = &meta.derived {
                put_derived_elements(&mut obj, derived);
            }
            put_image_plane_elements(&mut obj, volume, &series, k);
            put_image_pixel_elements(&mut obj, volume, &series, k);
            let bytes = encode_slice_file(obj, volume, k, &what)?;
            let path = dir.join(format!("IMG{:0width$}.dcm", k + 1));
            write_atomic(&path, &bytes)?;
            Ok(path)
        })
        .collect()
}

/// A voxel type a CT series is written from: HU as f32 (rounded on writing) or whole HU as
/// int16 (the virtual CT's phases, half the memory of f32).
pub trait HuSample: Copy + Send + Sync {
    /// The value in HU.
    fn hu(self) -> f32;
}

impl HuSample for f32 {
    fn hu(self) -> f32 {
        self
    }
}

impl HuSample for i16 {
    fn hu(self) -> f32 {
        f32::from(self)
    }
}

/// What makes a series derived from a planning CT: its study, which series it is, and the
/// respiratory phase of a virtual 4D-CT.
#[derive(Debug, Clone, PartialEq)]
pub struct DerivedSeries {
    /// The planning CT's patient, study and frame of reference.
    pub study: DicomStudyContext,
    /// Tells the series derived from one CT apart (phase index, MIP, AIP): mixed into the
    /// series and instance UIDs with the voxels.
    pub series_key: u64,
    /// ImageType (0008,0008), e.g. `DERIVED\SECONDARY\AXIAL`.
    pub image_type: String,
    /// DerivationDescription (0008,2111): how the images were made.
    pub derivation_description: String,
    /// The breathing phase the series shows, for a virtual 4D-CT phase.
    pub respiratory: Option<RespiratoryPhase>,
}

/// The respiratory attributes of one virtual 4D-CT phase (PS3.3 C.7.6.16.2.17 and the
/// Respiratory Synchronization Module, carried by a classic CT image as standard extended
/// attributes).
#[derive(Debug, Clone, PartialEq)]
pub struct RespiratoryPhase {
    /// NominalPercentageOfRespiratoryPhase (0020,9245): 0 at end-inhale; `None` when the
    /// instants are not phases of one cycle.
    pub nominal_percentage: Option<f32>,
    /// StartingRespiratoryPhase (0020,9247): INSPIRATION, MAXIMUM, EXPIRATION or MINIMUM.
    pub cycle_position: &'static str,
    /// NominalRespiratoryTriggerDelayTime (0020,9255): time since the cycle's end-inhale, ms.
    pub time_since_end_inhale_ms: f64,
    /// RespiratoryIntervalTime (0020,9254): the cycle's length, ms, when known.
    pub interval_ms: Option<f64>,
    /// TemporalPositionIdentifier (0020,0100), 1-based.
    pub temporal_position: u32,
    /// NumberOfTemporalPositions (0020,0105).
    pub temporal_positions: u32,
}

/// The study of a series written without a planning CT: the fictitious patient of `meta`.
fn fictitious_study(meta: &CtSeriesMetadata) -> DicomStudyContext {
    DicomStudyContext {
        patient_name: meta.patient_name.clone(),
        patient_id: meta.patient_id.clone(),
        patient_sex: "O".into(),
        study_id: "1".into(),
        study_description: meta.study_description.clone(),
        ..DicomStudyContext::generated(0)
    }
}

/// DerivationDescription and, for a virtual 4D-CT phase, the respiratory attributes: the
/// compensation technique, signal source and trigger type at the top level, the phase in a
/// one-item RespiratorySynchronizationSequence as the Enhanced CT functional group holds it,
/// and the temporal position among the phases.
fn put_derived_elements(obj: &mut InMemDicomObject, derived: &DerivedSeries) {
    put_text(
        obj,
        tags::DERIVATION_DESCRIPTION,
        VR::ST,
        derived.derivation_description.clone(),
    );
    let Some(phase) = &derived.respiratory else {
        return;
    };
    put_text(
        obj,
        tags::RESPIRATORY_MOTION_COMPENSATION_TECHNIQUE,
        VR::CS,
        "RETROSPECTIVE".into(),
    );
    put_text(
        obj,
        tags::RESPIRATORY_MOTION_COMPENSATION_TECHNIQUE_DESCRIPTION,
        VR::ST,
        "virtual 4D-CT: the planning CT deformed to this instant of the breathing trace by \
         the lungmotion model, not an acquisition"
            .into(),
    );
    put_text(
        obj,
        tags::RESPIRATORY_SIGNAL_SOURCE,
        VR::CS,
        "SPIROMETER".into(),
    );
    put_text(obj, tags::RESPIRATORY_TRIGGER_TYPE, VR::CS, "TIME".into());
    put_text(
        obj,
        tags::TEMPORAL_POSITION_IDENTIFIER,
        VR::IS,
        phase.temporal_position.to_string(),
    );
    put_text(
        obj,
        tags::NUMBER_OF_TEMPORAL_POSITIONS,
        VR::IS,
        phase.temporal_positions.to_string(),
    );
    let mut item = InMemDicomObject::new_empty();
    if let Some(percent) = phase.nominal_percentage {
        item.put(DataElement::new(
            tags::NOMINAL_PERCENTAGE_OF_RESPIRATORY_PHASE,
            VR::FL,
            PrimitiveValue::from(percent),
        ));
    }
    item.put(DataElement::new(
        tags::NOMINAL_RESPIRATORY_TRIGGER_DELAY_TIME,
        VR::FD,
        PrimitiveValue::from(phase.time_since_end_inhale_ms),
    ));
    if let Some(interval) = phase.interval_ms {
        item.put(DataElement::new(
            tags::RESPIRATORY_INTERVAL_TIME,
            VR::FD,
            PrimitiveValue::from(interval),
        ));
    }
    put_text(
        &mut item,
        tags::STARTING_RESPIRATORY_PHASE,
        VR::CS,
        phase.cycle_position.into(),
    );
    obj.put(DataElement::new(
        tags::RESPIRATORY_SYNCHRONIZATION_SEQUENCE,
        VR::SQ,
        DataSetSequence::from(vec![item]),
    ));
}

/// The error for series `what` with message `m`.
fn series_error(what: &str, m: String) -> Error {
    Error::argument(format!("DICOM series {what}"), m)
}

/// Refuses an invalid grid, a volume that does not fill it, and slices larger than DICOM's
/// 16-bit Rows/Columns can describe.
fn check_volume_fits<T: HuSample>(volume: &Volume<T>, what: &str) -> Result<()> {
    let g = volume.geometry;
    g.validate(&format!("DICOM series {what}"))?;
    if volume.as_slice().len() != g.voxel_count() {
        return Err(series_error(
            what,
            format!(
                "volume holds {} voxels, its grid {:?} needs {}",
                volume.as_slice().len(),
                g.dims,
                g.voxel_count()
            ),
        ));
    }
    if g.dims[0] > u16::MAX as usize || g.dims[1] > u16::MAX as usize {
        return Err(series_error(
            what,
            format!("slices of {:?} exceed DICOM's 65535 rows/columns", g.dims),
        ));
    }
    Ok(())
}

/// The RescaleIntercept shared by all slices: 0 when the rounded HU fit in int16, else the
/// shift that puts the minimum at −32768; values must be finite and span at most 16 bits.
fn shared_rescale_intercept<T: HuSample>(volume: &Volume<T>, what: &str) -> Result<f64> {
    let (min_hu, max_hu) = volume
        .as_slice()
        .par_iter()
        .try_fold(
            || (f32::INFINITY, f32::NEG_INFINITY),
            |(lo, hi), &v| {
                let v = v.hu();
                v.is_finite().then(|| (lo.min(v), hi.max(v)))
            },
        )
        .try_reduce(
            || (f32::INFINITY, f32::NEG_INFINITY),
            |a, b| Some((a.0.min(b.0), a.1.max(b.1))),
        )
        .ok_or_else(|| series_error(what, "the volume holds non-finite values".into()))?;
    let (min_hu, max_hu) = (min_hu.round() as f64, max_hu.round() as f64);
    if max_hu - min_hu > 65_535.0 {
        return Err(series_error(
            what,
            format!("values span {min_hu}…{max_hu} HU, more than 16 bits can hold"),
        ));
    }
    Ok(if min_hu >= i16::MIN as f64 && max_hu <= i16::MAX as f64 {
        0.0
    } else {
        min_hu - i16::MIN as f64
    })
}

/// What every slice of the series shares: orientation, UIDs and the rescale intercept.
struct SeriesLayout {
    row_direction: Vector3<f64>,
    column_direction: Vector3<f64>,
    /// Direction of increasing k (the slice positions step along it).
    k_axis: Vector3<f64>,
    /// Row × column direction: SliceLocation is the position along it.
    normal: Vector3<f64>,
    uid_root: UidRoot,
    study_uid: String,
    series_uid: String,
    frame_of_reference_uid: String,
    intercept: f64,
}

impl SeriesLayout {
    /// The layout of `volume` written with `meta`'s UID seed and the shared `intercept`.
    fn new<T: HuSample>(volume: &Volume<T>, meta: &CtSeriesMetadata, intercept: f64) -> Self {
        let direction = volume.geometry.direction();
        let row_direction: Vector3<f64> = direction.column(0).into();
        let column_direction: Vector3<f64> = direction.column(1).into();
        let k_axis: Vector3<f64> = direction.column(2).into();
        let normal = row_direction.cross(&column_direction);
        let (uid_root, study_uid, frame_of_reference_uid) = match &meta.derived {
            None => {
                let root = UidRoot::new(meta.uid_seed, volume);
                let (study, frame) = (root.uid(1, 0), root.uid(3, 0));
                (root, study, frame)
            }
            Some(d) => {
                // The planning CT's series and the derived series' key join the voxels in
                // the seed: each phase gets a series of its own, the same on a rerun.
                let seed = meta.uid_seed
                    ^ super::study::fnv1a(d.study.series_instance_uid.as_bytes())
                    ^ super::study::splitmix64(d.series_key);
                (
                    UidRoot::new(seed, volume),
                    d.study.study_instance_uid.clone(),
                    d.study.frame_of_reference_uid.clone(),
                )
            }
        };
        let series_uid = uid_root.uid(2, 0);
        SeriesLayout {
            row_direction,
            column_direction,
            k_axis,
            normal,
            uid_root,
            study_uid,
            series_uid,
            frame_of_reference_uid,
            intercept,
        }
    }

    /// ImagePositionPatient of slice `k`, LPS mm.
    fn position_lps_mm<T>(&self, volume: &Volume<T>, k: usize) -> Vector3<f64> {
        let g = &volume.geometry;
        g.origin() + self.k_axis * (k as f64 * g.spacing_mm[2])
    }
}

/// Puts a text element (every VR but US and OW here).
fn put_text(obj: &mut InMemDicomObject, tag: Tag, vr: VR, value: String) {
    obj.put(DataElement::new(tag, vr, PrimitiveValue::from(value)));
}

/// The patient and general-study attributes every object derived from `study` carries
/// (patient's name, ID, birth date and sex; study UID, date, time, ID, accession number,
/// referring physician and description), so a planning system or PACS files the virtual CT,
/// the REGs and the RTSTRUCT under the planning CT's patient and study.
pub(crate) fn put_study_attributes(obj: &mut InMemDicomObject, study: &DicomStudyContext) {
    for (tag, vr, value) in [
        (tags::PATIENT_NAME, VR::PN, &study.patient_name),
        (tags::PATIENT_ID, VR::LO, &study.patient_id),
        (tags::PATIENT_BIRTH_DATE, VR::DA, &study.patient_birth_date),
        (tags::PATIENT_SEX, VR::CS, &study.patient_sex),
        (tags::STUDY_INSTANCE_UID, VR::UI, &study.study_instance_uid),
        (tags::STUDY_DATE, VR::DA, &study.study_date),
        (tags::STUDY_TIME, VR::TM, &study.study_time),
        (tags::STUDY_ID, VR::SH, &study.study_id),
        (tags::ACCESSION_NUMBER, VR::SH, &study.accession_number),
        (
            tags::REFERRING_PHYSICIAN_NAME,
            VR::PN,
            &study.referring_physician_name,
        ),
        (tags::STUDY_DESCRIPTION, VR::LO, &study.study_description),
    ] {
        put_text(obj, tag, vr, value.clone());
    }
}

/// SOP, study, series, patient and instance elements of slice `k` (the patient's are
/// fictitious, from `meta`).
fn put_identity_elements<T>(
    obj: &mut InMemDicomObject,
    volume: &Volume<T>,
    meta: &CtSeriesMetadata,
    series: &SeriesLayout,
    k: usize,
) {
    let mut put = |tag: Tag, vr: VR, value: String| put_text(obj, tag, vr, value);
    let sop_uid = series.uid_root.uid(4, k as u64 + 1);
    put(tags::SPECIFIC_CHARACTER_SET, VR::CS, "ISO_IR 100".into());
    let image_type = meta
        .derived
        .as_ref()
        .map_or("DERIVED\\SECONDARY\\AXIAL", |d| d.image_type.as_str());
    put(tags::IMAGE_TYPE, VR::CS, image_type.into());
    put(tags::SOP_CLASS_UID, VR::UI, uids::CT_IMAGE_STORAGE.into());
    put(tags::SOP_INSTANCE_UID, VR::UI, sop_uid);
    let fictitious;
    let study = match &meta.derived {
        Some(d) => &d.study,
        None => {
            fictitious = DicomStudyContext {
                study_instance_uid: series.study_uid.clone(),
                ..fictitious_study(meta)
            };
            &fictitious
        }
    };
    put(tags::MODALITY, VR::CS, "CT".into());
    put(tags::MANUFACTURER, VR::LO, meta.manufacturer.clone());
    put(
        tags::SERIES_DESCRIPTION,
        VR::LO,
        meta.series_description.clone(),
    );
    put(tags::KVP, VR::DS, String::new());
    put(
        tags::SLICE_THICKNESS,
        VR::DS,
        ds(volume.geometry.spacing_mm[2]),
    );
    let position = if study.patient_position.is_empty() {
        meta.patient_position.clone()
    } else {
        study.patient_position.clone()
    };
    put(tags::PATIENT_POSITION, VR::CS, position);
    put(tags::SERIES_INSTANCE_UID, VR::UI, series.series_uid.clone());
    put(tags::SERIES_NUMBER, VR::IS, meta.series_number.to_string());
    put(tags::ACQUISITION_NUMBER, VR::IS, "1".into());
    put(tags::INSTANCE_NUMBER, VR::IS, (k + 1).to_string());
    put_study_attributes(obj, study);
}

/// Image plane elements of slice `k`: position, orientation, frame of reference and
/// SliceLocation.
fn put_image_plane_elements<T>(
    obj: &mut InMemDicomObject,
    volume: &Volume<T>,
    series: &SeriesLayout,
    k: usize,
) {
    let position = series.position_lps_mm(volume, k);
    let (row, column) = (series.row_direction, series.column_direction);
    let mut put = |tag: Tag, vr: VR, value: String| put_text(obj, tag, vr, value);
    put(
        tags::IMAGE_POSITION_PATIENT,
        VR::DS,
        ds_list(position.as_slice()),
    );
    put(
        tags::IMAGE_ORIENTATION_PATIENT,
        VR::DS,
        ds_list(&[row.x, row.y, row.z, column.x, column.y, column.z]),
    );
    put(
        tags::FRAME_OF_REFERENCE_UID,
        VR::UI,
        series.frame_of_reference_uid.clone(),
    );
    put(tags::POSITION_REFERENCE_INDICATOR, VR::LO, String::new());
    put(
        tags::SLICE_LOCATION,
        VR::DS,
        ds(position.dot(&series.normal)),
    );
}

/// Image pixel elements of slice `k`: spacing, rescale, window, the int16 layout and the
/// pixels (rounded HU minus the shared intercept).
fn put_image_pixel_elements<T: HuSample>(
    obj: &mut InMemDicomObject,
    volume: &Volume<T>,
    series: &SeriesLayout,
    k: usize,
) {
    let g = volume.geometry;
    let frame_len = g.dims[0] * g.dims[1];
    let intercept = series.intercept;
    let pixels: Vec<u16> = volume.as_slice()[k * frame_len..(k + 1) * frame_len]
        .iter()
        .map(|&v| ((v.hu().round() as f64 - intercept) as i16) as u16)
        .collect();
    let mut put = |tag: Tag, vr: VR, value: String| put_text(obj, tag, vr, value);
    put(
        tags::PHOTOMETRIC_INTERPRETATION,
        VR::CS,
        "MONOCHROME2".into(),
    );
    put(
        tags::PIXEL_SPACING,
        VR::DS,
        ds_list(&[g.spacing_mm[1], g.spacing_mm[0]]),
    );
    put(tags::RESCALE_INTERCEPT, VR::DS, ds(intercept));
    put(tags::RESCALE_SLOPE, VR::DS, "1".into());
    put(tags::RESCALE_TYPE, VR::LO, "HU".into());
    put(tags::WINDOW_CENTER, VR::DS, "-600".into());
    put(tags::WINDOW_WIDTH, VR::DS, "1500".into());
    let mut put_us = |tag: Tag, v: u16| {
        obj.put(DataElement::new(tag, VR::US, PrimitiveValue::from(v)));
    };
    put_us(tags::SAMPLES_PER_PIXEL, 1);
    put_us(tags::ROWS, g.dims[1] as u16);
    put_us(tags::COLUMNS, g.dims[0] as u16);
    put_us(tags::BITS_ALLOCATED, 16);
    put_us(tags::BITS_STORED, 16);
    put_us(tags::HIGH_BIT, 15);
    put_us(tags::PIXEL_REPRESENTATION, 1);
    obj.put(DataElement::new(
        tags::PIXEL_DATA,
        VR::OW,
        PrimitiveValue::U16(SmallVec::from_vec(pixels)),
    ));
}

/// Adds the file meta group (Explicit VR Little Endian) and encodes slice `k` to bytes.
fn encode_slice_file<T>(
    obj: InMemDicomObject,
    volume: &Volume<T>,
    k: usize,
    what: &str,
) -> Result<Vec<u8>> {
    let frame_len = volume.geometry.dims[0] * volume.geometry.dims[1];
    let file = obj
        .with_meta(
            FileMetaTableBuilder::new()
                .transfer_syntax(uids::EXPLICIT_VR_LITTLE_ENDIAN)
                .implementation_class_uid(IMPLEMENTATION_CLASS_UID)
                .implementation_version_name("LUNGMOTION"),
        )
        .map_err(|e| {
            series_error(
                what,
                format!("slice {k}: cannot build the file meta group ({e})"),
            )
        })?;
    let mut bytes = Vec::with_capacity(frame_len * 2 + 4096);
    file.write_all(&mut bytes)
        .map_err(|e| series_error(what, format!("slice {k}: cannot encode ({e})")))?;
    Ok(bytes)
}

/// Implementation Class UID of files written by lungmotion (under the UUID-derived 2.25 root).
const IMPLEMENTATION_CLASS_UID: &str = "2.25.240518131208190432779384431735391361291";

/// Deterministic UID generator: 2.25 arc followed by a 128-bit number mixed from the seed,
/// the grid and the voxel values.
struct UidRoot {
    key: u64,
}

impl UidRoot {
    fn new<T: HuSample>(seed: u64, volume: &Volume<T>) -> Self {
        // FNV-1a over the voxel bits: identical volumes share UIDs, different ones do not.
        let mut h: u64 = 0xcbf2_9ce4_8422_2325 ^ seed;
        let mut mix = |x: u64| {
            h ^= x;
            h = h.wrapping_mul(0x0000_0100_0000_01b3);
        };
        let g = &volume.geometry;
        g.dims.iter().for_each(|&d| mix(d as u64));
        g.spacing_mm
            .iter()
            .chain(&g.origin_lps_mm)
            .chain(g.direction_lps.iter().flatten())
            .for_each(|v| mix(v.to_bits()));
        volume
            .as_slice()
            .iter()
            .for_each(|v| mix(u64::from(v.hu().to_bits())));
        UidRoot { key: h }
    }

    fn uid(&self, kind: u64, index: u64) -> String {
        super::study::derived_uid(self.key, kind, index)
    }
}

/// A decimal string (DS) of at most 16 characters with as many digits as fit.
fn ds(v: f64) -> String {
    for decimals in (0..=12).rev() {
        let s = format!("{v:.decimals$}");
        let s = if s.contains('.') {
            s.trim_end_matches('0').trim_end_matches('.').to_string()
        } else {
            s
        };
        let s = if s == "-0" { "0".to_string() } else { s };
        if s.len() <= 16 {
            return s;
        }
    }
    format!("{v:.6e}")
}

fn ds_list(values: &[f64]) -> String {
    values.iter().map(|&v| ds(v)).collect::<Vec<_>>().join("\\")
}

#[cfg(test)]
mod tests {
    use super::ds;

    #[test]
    fn decimal_strings_fit_16_characters_and_keep_precision() {
        for v in [
            0.0,
            -0.0,
            1.0,
            -128.414,
            0.866_025_403_784_438_6,
            -360.256_123_456_789,
            123_456.789_012_345,
            1e-9,
        ] {
            let s = ds(v);
            assert!(s.len() <= 16, "{v} -> {s}");
            let back: f64 = s.parse().unwrap();
            assert!(
                (back - v).abs() <= 1e-9_f64.max(v.abs() * 1e-10),
                "{v} -> {s}"
            );
        }
        assert_eq!(ds(-0.0), "0");
        assert_eq!(ds(3.0), "3");
    }
}
