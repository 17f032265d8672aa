//! DICOM CT series: reading (directory, zip or single file) into a [`Volume`] of HU, and
//! writing a volume as a CT Image Storage series.
//!
//! Convention (DICOM PS3.3 C.7.6.2): ImageOrientationPatient's first triplet is the LPS
//! direction in which the column index increases (along a row), the second the direction in
//! which the row index increases. Volume axis i is the first triplet, j the second, and k the
//! slice normal (first × second), oriented so that k increases with the slices' projections
//! on it; slices are ordered by that projection, never by file name or InstanceNumber. The
//! origin is ImagePositionPatient of the first slice in that order (the centre of its first
//! pixel). Spacing is `[PixelSpacing[1], PixelSpacing[0], slice spacing]` (PixelSpacing is
//! row spacing first). Voxel values are stored values × RescaleSlope + RescaleIntercept, per
//! slice: HU for CT. Each frame's pixels are copied in DICOM order, which is i-fastest.
//!
//! Identifying data (patient name, ID, birth date, …) is never copied into [`SeriesInfo`].

mod read;
mod study;
mod write;

use serde::Serialize;

use crate::formats::archive::ArchiveLimits;
use crate::volume::Volume;

pub(crate) use read::read_single_object;
pub use read::{
    read_dicom_series, read_dicom_series_cancellable, read_dicom_series_with, SeriesChoice,
};
pub use study::{ContentKey, DicomStudyContext, SliceReference};
pub(crate) use write::put_study_attributes;
pub use write::{write_ct_series, DerivedSeries, HuSample, RespiratoryPhase};

/// Choices for [`read_dicom_series_with`].
#[derive(Debug, Clone, Default)]
pub struct DicomReadOptions {
    /// The series to read when the input holds several (by UID, number or description);
    /// `None` reads the only CT series that is not a scout.
    pub series: Option<SeriesChoice>,
    /// Bounds for zip input.
    pub archive_limits: ArchiveLimits,
    /// Memory the parsed files may hold at once, bytes; `None`: half the memory available.
    pub memory_budget_bytes: Option<u64>,
}

/// Non-identifying description of the series that was read.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct SeriesInfo {
    /// SeriesInstanceUID (0020,000E).
    pub series_instance_uid: String,
    /// Modality (0008,0060), "CT".
    pub modality: String,
    /// SeriesDescription (0008,103E), if present.
    pub series_description: Option<String>,
    /// Manufacturer (0008,0070), if present.
    pub manufacturer: Option<String>,
    /// Transfer syntax UID of the first slice.
    pub transfer_syntax_uid: String,
    /// Human-readable name of that transfer syntax.
    pub transfer_syntax_name: String,
    /// Slices in the volume (after dropping exact duplicates).
    pub slice_count: usize,
    /// Rows (0028,0010): pixels along j.
    pub rows: usize,
    /// Columns (0028,0011): pixels along i.
    pub columns: usize,
    /// PatientPosition (0018,5100), e.g. "HFS", if present.
    pub patient_position: Option<String>,
}

/// A CT series read into a volume.
#[derive(Debug, Clone)]
pub struct DicomSeries {
    /// Voxels in HU on the series' grid (LPS millimetres).
    pub volume: Volume<f32>,
    /// What was read.
    pub info: SeriesInfo,
    /// Patient, study, frame of reference and slice instances, for derived DICOM objects.
    pub study: DicomStudyContext,
    /// Files skipped and oddities tolerated, one sentence each. Not logged here: they name
    /// files, and a hospital export may name folders after the patient, so the caller decides
    /// where they go (the CLI prints them, the service returns them to the uploader).
    pub warnings: Vec<String>,
}

/// Descriptive fields of a series written by [`write_ct_series`].
#[derive(Debug, Clone, PartialEq)]
pub struct CtSeriesMetadata {
    /// Seed of the generated UIDs: UIDs are deterministic in (seed, voxel data, geometry), so
    /// rewriting the same phantom gives byte-identical files and different volumes differ.
    pub uid_seed: u64,
    /// PatientName (fictitious).
    pub patient_name: String,
    /// PatientID (fictitious).
    pub patient_id: String,
    /// StudyDescription.
    pub study_description: String,
    /// SeriesDescription.
    pub series_description: String,
    /// SeriesNumber.
    pub series_number: u32,
    /// Manufacturer.
    pub manufacturer: String,
    /// PatientPosition, e.g. "HFS" (head first, supine).
    pub patient_position: String,
    /// A series derived from a planning CT (virtual 4D-CT phase, MIP, AIP): written into its
    /// patient, study and frame of reference, the fields above giving only the descriptions,
    /// manufacturer and series number; `None` starts a study of its own.
    pub derived: Option<DerivedSeries>,
}

impl Default for CtSeriesMetadata {
    fn default() -> Self {
        CtSeriesMetadata {
            uid_seed: 0,
            patient_name: "PHANTOM^THORAX".into(),
            patient_id: "LUNGMOTION-PHANTOM".into(),
            study_description: "lungmotion thorax phantom".into(),
            series_description: "synthetic CT".into(),
            series_number: 1,
            manufacturer: "lungmotion".into(),
            patient_position: "HFS".into(),
            derived: None,
        }
    }
}
