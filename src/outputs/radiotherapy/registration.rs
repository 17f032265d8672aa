//! DICOM Deformable Spatial Registration objects (REG; PS3.3 A.39.2, C.20.3): one per output
//! instant, `frames/<k>/registration.dcm`, a grid of float32 vectors in millimetres over the
//! lungs that a planning system uses to carry contours or dose between the planning CT and
//! the breathing phase.
//!
//! Direction (PS3.3 C.20.3.1.1, C.20.3.1.3): the grid lies in the *Registered* RCS, the frame
//! of reference of the REG object itself; the Pre-deformation matrix is applied to a
//! registered point, the vector at that grid point is added, then the Post-deformation
//! matrix, and the result "addresses the sample point within the Source RCS". Both matrices
//! are the identity here, so: **grid point p + vector(p) = the point of the Source RCS that
//! corresponds to p**. We write p in the planning CT at rest and p + vector(p) where the
//! tissue at p is at this instant: the Registered RCS is the planning CT, the Source RCS is
//! the breathing phase (the virtual 4D-CT phase of that instant). This is the convention of
//! the displacement fields (`x + u(x)`), sampled on a coarser grid.
//!
//! Frames of reference: the virtual phases are written in the planning CT's frame of
//! reference (same patient, same table, same coordinates), so the REG's FrameOfReferenceUID
//! (the Registered RCS) and the SourceFrameOfReferenceUID are the same UID, the CT's. The
//! standard allows the REG to share its frame of reference with the images it references
//! (PS3.17 O.1: "The chosen Frame of Reference of the Registration SOP Instance may be the
//! same as one or more of the Referenced SOP Instances"), and C.20.3 puts no condition on
//! the Source UID differing. Because that frame of reference holds the planning CT and every
//! phase, the images the registration applies to are told apart by the Referenced Image
//! Sequence (PS3.3: required "if the registration applies to a subset of images within the
//! specified Source Frame of Reference"): it lists the phase's CT images when the caller
//! knows them ([`SourceImages`]), and is absent otherwise (then the registration reads as
//! applying to the frame of reference at that instant).
//!
//! Registration Type Code Sequence (type 2, zero or one item, baseline CID 7100 "RCS
//! Registration Method Type") is written empty: none of CID 7100's methods (fiducials, image
//! content, visual alignment, equipment, identity) describes a biomechanical model's
//! prediction; the Frame of Reference Transformation Comment says what made the vectors.
//!
//! Grid: the CT's row and column directions (the slice normal their cross product, as
//! C.20.3.1.1 defines Z), covering the lung mesh plus [`REGISTRATION_MARGIN_MM`], at a
//! spacing chosen in `[outputs] registration_spacing_mm` (default
//! [`DEFAULT_REGISTRATION_SPACING_MM`]); objects larger than
//! [`MAX_REGISTRATION_GRID_BYTES`] of vectors are refused.

use std::path::{Path, PathBuf};

use dicom_core::smallvec::SmallVec;
use dicom_core::value::DataSetSequence;
use dicom_core::{DataElement, PrimitiveValue, Tag, VR};
use dicom_dictionary_std::{tags, uids};
use dicom_object::{FileMetaTableBuilder, InMemDicomObject};
use nalgebra::Matrix3;
use rayon::prelude::*;

use super::PhaseMotion;
use crate::durable::write_atomic;
use crate::formats::dicom::{put_study_attributes, ContentKey, DicomStudyContext, SliceReference};
use crate::math::V3;
use crate::{Error, Result};

/// Default distance between the registration grid's points, mm: a third of the default
/// element edge, so the mesh's piecewise-trilinear motion is resampled within 0.1 mm (the
/// demo's tracked points: measured in `tests/dicom_registration.rs`), at about 10 MB an
/// object on a chest CT's lungs.
pub const DEFAULT_REGISTRATION_SPACING_MM: f64 = 3.0;
/// Finest registration grid spacing accepted, mm.
pub const MIN_REGISTRATION_SPACING_MM: f64 = 0.5;
/// Coarsest registration grid spacing accepted, mm.
pub const MAX_REGISTRATION_SPACING_MM: f64 = 20.0;
/// How far the grid reaches beyond the lung mesh on every side, mm.
pub const REGISTRATION_MARGIN_MM: f64 = 10.0;
/// Largest Vector Grid Data of one object, bytes (12 bytes a grid point): 10.6 million
/// points, a 1.5 mm grid over large lungs. Past it a planning system's import and the PACS
/// suffer more than the finer grid gains.
pub const MAX_REGISTRATION_GRID_BYTES: u64 = 128 << 20;

/// `derived_uid` kinds of the REG series and instances ("REG" in ASCII, then 1 and 2).
const REG_SERIES_UID_KIND: u64 = 0x0052_4547_0001;
const REG_INSTANCE_UID_KIND: u64 = 0x0052_4547_0002;
/// SeriesNumber of frame k's REG series is this plus k.
const REG_SERIES_NUMBER_BASE: usize = 8001;
/// Implementation Class UID of files written by lungmotion (as the CT writer's).
const IMPLEMENTATION_CLASS_UID: &str = "2.25.240518131208190432779384431735391361291";

/// A regular grid of points in LPS millimetres: origin, the CT's row and column directions
/// and their cross product, one spacing on all three axes.
#[derive(Debug, Clone, PartialEq)]
pub struct RegistrationGrid {
    origin_lps_mm: V3,
    axes: [V3; 3],
    spacing_mm: f64,
    dims: [usize; 3],
}

impl RegistrationGrid {
    /// The grid of `spacing_mm` along the row and column directions of `ct_direction`
    /// (columns: the CT's i, j, k axes) covering `points_lps_mm` and `margin_mm` around
    /// them; refuses a bad spacing, no points, or a grid over [`MAX_REGISTRATION_GRID_BYTES`].
    pub fn around(
        points_lps_mm: impl Iterator<Item = V3>,
        ct_direction: &Matrix3<f64>,
        spacing_mm: f64,
        margin_mm: f64,
    ) -> Result<Self> {
        check_spacing(spacing_mm)?;
        let x: V3 = ct_direction.column(0).normalize();
        let y: V3 = ct_direction.column(1).normalize();
        let axes = [x, y, x.cross(&y).normalize()];
        let mut lo = V3::repeat(f64::INFINITY);
        let mut hi = V3::repeat(f64::NEG_INFINITY);
        for p in points_lps_mm {
            let q = V3::new(p.dot(&axes[0]), p.dot(&axes[1]), p.dot(&axes[2]));
            lo = lo.inf(&q);
            hi = hi.sup(&q);
        }
        if !(lo.iter().chain(hi.iter()).all(|v| v.is_finite())) {
            return Err(grid_error(
                "there is no finite lung point to cover".to_string(),
            ));
        }
        let lo = lo.add_scalar(-margin_mm);
        let hi = hi.add_scalar(margin_mm);
        let count = |a: usize| ((hi[a] - lo[a]) / spacing_mm).ceil().max(0.0) + 1.0;
        let (nx, ny, nz) = (count(0), count(1), count(2));
        let bytes = nx * ny * nz * 12.0;
        if bytes > MAX_REGISTRATION_GRID_BYTES as f64 {
            return Err(grid_error(format!(
                "{nx} × {ny} × {nz} points at {spacing_mm} mm would hold {:.0} MB of vectors \
                 per object, more than the {} MB limit; choose a larger \
                 outputs.registration_spacing_mm",
                bytes / 1e6,
                MAX_REGISTRATION_GRID_BYTES >> 20
            )));
        }
        Ok(RegistrationGrid {
            origin_lps_mm: axes[0] * lo[0] + axes[1] * lo[1] + axes[2] * lo[2],
            axes,
            spacing_mm,
            dims: [nx as usize, ny as usize, nz as usize],
        })
    }

    /// Points along the row, column and slice directions.
    pub fn dims(&self) -> [usize; 3] {
        self.dims
    }

    /// Distance between neighbouring points, mm.
    pub fn spacing_mm(&self) -> f64 {
        self.spacing_mm
    }

    /// Number of grid points.
    pub fn point_count(&self) -> usize {
        self.dims.iter().product()
    }

    /// Bytes of one object's Vector Grid Data.
    pub fn vector_bytes(&self) -> u64 {
        self.point_count() as u64 * 12
    }

    /// LPS position of grid point (i, j, k), mm.
    pub fn point_lps_mm(&self, i: usize, j: usize, k: usize) -> V3 {
        self.origin_lps_mm
            + (self.axes[0] * i as f64 + self.axes[1] * j as f64 + self.axes[2] * k as f64)
                * self.spacing_mm
    }

    /// A key of this grid and `vectors` on it, for the UIDs of the object holding them.
    pub fn content_key(&self, vectors: &[f32]) -> u64 {
        let mut key = ContentKey::default();
        self.dims.iter().for_each(|&d| key.mix(d as u64));
        std::iter::once(self.spacing_mm)
            .chain(self.origin_lps_mm.iter().copied())
            .chain(self.axes.iter().flat_map(|a| a.iter().copied()))
            .for_each(|v| key.mix(v.to_bits()));
        vectors.iter().for_each(|v| key.mix(u64::from(v.to_bits())));
        key.finish()
    }

    /// The vectors `moved − p` of `motion` at every grid point, x fastest then y then z, as
    /// Vector Grid Data wants; refuses a motion that is not finite somewhere.
    pub fn sample_vectors_mm(&self, motion: &dyn PhaseMotion) -> Result<Vec<f32>> {
        let [nx, ny, _] = self.dims;
        let mut out = vec![0.0f32; self.point_count() * 3];
        out.par_chunks_mut(nx * ny * 3)
            .enumerate()
            .try_for_each(|(k, plane)| {
                for (n, v) in plane.chunks_exact_mut(3).enumerate() {
                    let p = self.point_lps_mm(n % nx, n / nx, k);
                    let moved = V3::from(motion.moved_lps_mm(p.into()));
                    let d = moved - p;
                    if !d.iter().all(|c| c.is_finite()) {
                        return Err(grid_error(format!(
                            "the motion is not finite at LPS ({:.1}, {:.1}, {:.1}) mm",
                            p.x, p.y, p.z
                        )));
                    }
                    v.copy_from_slice(&[d.x as f32, d.y as f32, d.z as f32]);
                }
                Ok(())
            })?;
        Ok(out)
    }
}

/// Refuses a grid spacing outside the accepted range.
pub fn check_spacing(spacing_mm: f64) -> Result<()> {
    if spacing_mm.is_finite()
        && (MIN_REGISTRATION_SPACING_MM..=MAX_REGISTRATION_SPACING_MM).contains(&spacing_mm)
    {
        Ok(())
    } else {
        Err(grid_error(format!(
            "outputs.registration_spacing_mm = {spacing_mm} mm is not within \
             {MIN_REGISTRATION_SPACING_MM}–{MAX_REGISTRATION_SPACING_MM} mm"
        )))
    }
}

/// The error about the registration grid.
fn grid_error(reason: String) -> Error {
    Error::argument("DICOM registration grid", reason)
}

/// The CT images of the phase a registration maps to (its virtual 4D-CT series), when they
/// are written as DICOM: referenced so that a reader knows which images of the shared frame
/// of reference are the Source.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct SourceImages {
    /// SeriesInstanceUID of the phase's series.
    pub series_instance_uid: String,
    /// Its images.
    pub images: Vec<SliceReference>,
}

/// What identifies one phase's REG object.
struct PhaseObject<'a> {
    frame_index: usize,
    label: &'a str,
    series_uid: String,
    instance_uid: String,
}

/// Writes one REG object per output instant into `frames/<k>/registration.dcm`.
pub struct RegistrationWriter {
    study: DicomStudyContext,
    grid: RegistrationGrid,
    frames_dir: PathBuf,
    content_date: String,
    content_time: String,
    bytes_written: u64,
}

impl RegistrationWriter {
    /// A writer for `study`'s CT on `grid`, into `frames_dir/<k>/`; content date and time are
    /// now (UTC).
    pub fn new(study: DicomStudyContext, grid: RegistrationGrid, frames_dir: &Path) -> Self {
        let (content_date, content_time) = utc_now_da_tm();
        RegistrationWriter {
            study,
            grid,
            frames_dir: frames_dir.to_path_buf(),
            content_date,
            content_time,
            bytes_written: 0,
        }
    }

    /// The grid every object samples.
    pub fn grid(&self) -> &RegistrationGrid {
        &self.grid
    }

    /// Bytes of the files written so far.
    pub fn bytes_written(&self) -> u64 {
        self.bytes_written
    }

    /// Writes frame `frame_index`'s REG (`label` names the instant) from `motion`.
    pub fn frame(
        &mut self,
        frame_index: usize,
        label: &str,
        motion: &dyn PhaseMotion,
    ) -> Result<()> {
        self.frame_with_source(frame_index, label, motion, None)
            .map(|_| ())
    }

    /// [`RegistrationWriter::frame`] referencing the phase's own CT images when given;
    /// returns the file written.
    pub fn frame_with_source(
        &mut self,
        frame_index: usize,
        label: &str,
        motion: &dyn PhaseMotion,
        source: Option<&SourceImages>,
    ) -> Result<PathBuf> {
        let vectors = self.grid.sample_vectors_mm(motion)?;
        // The UIDs follow what the object shows: another run's motion on the same CT is
        // a new object a PACS stores, a rerun's the same one it already holds.
        let content = self.grid.content_key(&vectors);
        let phase = PhaseObject {
            frame_index,
            label,
            series_uid: self
                .study
                .content_uid(REG_SERIES_UID_KIND, frame_index as u64, content),
            instance_uid: self.study.content_uid(
                REG_INSTANCE_UID_KIND,
                frame_index as u64,
                content,
            ),
        };
        let obj = self.dataset(&phase, vectors, source);
        let path = self
            .frames_dir
            .join(frame_index.to_string())
            .join("registration.dcm");
        let bytes = encode_file(obj, &path)?;
        if let Some(dir) = path.parent() {
            std::fs::create_dir_all(dir).map_err(|e| Error::io(crate::IoOp::CreateDir, dir, e))?;
        }
        write_atomic(&path, &bytes)?;
        self.bytes_written += bytes.len() as u64;
        Ok(path)
    }

    /// The whole REG data set of one phase.
    fn dataset(
        &self,
        phase: &PhaseObject,
        vectors: Vec<f32>,
        source: Option<&SourceImages>,
    ) -> InMemDicomObject {
        let mut obj = InMemDicomObject::new_empty();
        self.put_patient_study_series(&mut obj, phase);
        put_equipment(&mut obj);
        put_text(&mut obj, tags::CONTENT_DATE, VR::DA, &self.content_date);
        put_text(&mut obj, tags::CONTENT_TIME, VR::TM, &self.content_time);
        put_text(&mut obj, tags::INSTANCE_NUMBER, VR::IS, "1");
        put_text(
            &mut obj,
            tags::CONTENT_LABEL,
            VR::CS,
            &content_label(phase.label, phase.frame_index),
        );
        put_text(
            &mut obj,
            tags::CONTENT_DESCRIPTION,
            VR::LO,
            &long_string(&format!("lungmotion {}", phase.label)),
        );
        put_text(&mut obj, tags::CONTENT_CREATOR_NAME, VR::PN, "");
        let item = self.registration_item(vectors, source);
        put_sequence(&mut obj, tags::DEFORMABLE_REGISTRATION_SEQUENCE, vec![item]);
        if let Some(source) = source {
            put_common_instance_reference(&mut obj, source);
        }
        obj
    }

    /// SOP common, patient, general study, general and REG series, frame of reference.
    fn put_patient_study_series(&self, obj: &mut InMemDicomObject, phase: &PhaseObject) {
        let s = &self.study;
        let mut put = |tag: Tag, vr: VR, value: &str| put_text(obj, tag, vr, value);
        put(tags::SPECIFIC_CHARACTER_SET, VR::CS, "ISO_IR 192");
        put(
            tags::SOP_CLASS_UID,
            VR::UI,
            uids::DEFORMABLE_SPATIAL_REGISTRATION_STORAGE,
        );
        put(tags::SOP_INSTANCE_UID, VR::UI, &phase.instance_uid);
        put(tags::INSTANCE_CREATION_DATE, VR::DA, &self.content_date);
        put(tags::INSTANCE_CREATION_TIME, VR::TM, &self.content_time);
        put(tags::MODALITY, VR::CS, "REG");
        // The chest, an unpaired part: Laterality (2C, for paired parts) stays absent.
        put(tags::BODY_PART_EXAMINED, VR::CS, "CHEST");
        put(
            tags::SERIES_DESCRIPTION,
            VR::LO,
            &long_string(&format!("lungmotion REG {}", phase.label)),
        );
        put(tags::SERIES_INSTANCE_UID, VR::UI, &phase.series_uid);
        put(
            tags::SERIES_NUMBER,
            VR::IS,
            &(REG_SERIES_NUMBER_BASE + phase.frame_index).to_string(),
        );
        put(
            tags::FRAME_OF_REFERENCE_UID,
            VR::UI,
            &s.frame_of_reference_uid,
        );
        put(tags::POSITION_REFERENCE_INDICATOR, VR::LO, "");
        put_study_attributes(obj, s);
    }

    /// The one item of the Deformable Registration Sequence: source frame, images, the
    /// identity matrices around the deformation and the grid.
    fn registration_item(
        &self,
        vectors: Vec<f32>,
        source: Option<&SourceImages>,
    ) -> InMemDicomObject {
        let mut item = InMemDicomObject::new_empty();
        put_text(
            &mut item,
            tags::SOURCE_FRAME_OF_REFERENCE_UID,
            VR::UI,
            &self.study.frame_of_reference_uid,
        );
        if let Some(source) = source {
            let images = source.images.iter().map(image_reference).collect();
            put_sequence(&mut item, tags::REFERENCED_IMAGE_SEQUENCE, images);
        }
        // LO: 64 characters; the instant is in the series and content descriptions.
        put_text(
            &mut item,
            tags::FRAME_OF_REFERENCE_TRANSFORMATION_COMMENT,
            VR::LO,
            "lungmotion lung model: tissue at p is at p + vector(p), LPS mm",
        );
        put_sequence(&mut item, tags::REGISTRATION_TYPE_CODE_SEQUENCE, Vec::new());
        put_sequence(
            &mut item,
            tags::PRE_DEFORMATION_MATRIX_REGISTRATION_SEQUENCE,
            vec![identity_matrix_item()],
        );
        put_sequence(
            &mut item,
            tags::POST_DEFORMATION_MATRIX_REGISTRATION_SEQUENCE,
            vec![identity_matrix_item()],
        );
        let grid = self.grid_item(vectors);
        put_sequence(
            &mut item,
            tags::DEFORMABLE_REGISTRATION_GRID_SEQUENCE,
            vec![grid],
        );
        item
    }

    /// The Deformable Registration Grid Sequence's item.
    fn grid_item(&self, vectors: Vec<f32>) -> InMemDicomObject {
        let g = &self.grid;
        let (x, y) = (g.axes[0], g.axes[1]);
        let mut item = InMemDicomObject::new_empty();
        put_text(
            &mut item,
            tags::IMAGE_ORIENTATION_PATIENT,
            VR::DS,
            &ds_list(&[x.x, x.y, x.z, y.x, y.y, y.z]),
        );
        put_text(
            &mut item,
            tags::IMAGE_POSITION_PATIENT,
            VR::DS,
            &ds_list(g.origin_lps_mm.as_slice()),
        );
        item.put(DataElement::new(
            tags::GRID_DIMENSIONS,
            VR::UL,
            PrimitiveValue::U32(g.dims.iter().map(|&d| d as u32).collect()),
        ));
        item.put(DataElement::new(
            tags::GRID_RESOLUTION,
            VR::FD,
            PrimitiveValue::F64(SmallVec::from_slice(&[g.spacing_mm; 3])),
        ));
        item.put(DataElement::new(
            tags::VECTOR_GRID_DATA,
            VR::OF,
            PrimitiveValue::F32(SmallVec::from_vec(vectors)),
        ));
        item
    }
}

/// Puts a text element.
fn put_text(obj: &mut InMemDicomObject, tag: Tag, vr: VR, value: &str) {
    obj.put(DataElement::new(tag, vr, PrimitiveValue::from(value)));
}

/// Puts a sequence of `items` (possibly none).
fn put_sequence(obj: &mut InMemDicomObject, tag: Tag, items: Vec<InMemDicomObject>) {
    obj.put(DataElement::new(tag, VR::SQ, DataSetSequence::from(items)));
}

/// General and Enhanced General Equipment.
fn put_equipment(obj: &mut InMemDicomObject) {
    put_text(obj, tags::MANUFACTURER, VR::LO, "lungmotion");
    put_text(obj, tags::MANUFACTURER_MODEL_NAME, VR::LO, "lungmotion");
    put_text(obj, tags::DEVICE_SERIAL_NUMBER, VR::LO, "lungmotion");
    put_text(
        obj,
        tags::SOFTWARE_VERSIONS,
        VR::LO,
        env!("CARGO_PKG_VERSION"),
    );
}

/// Common Instance Reference: the phase series whose images the registration references.
fn put_common_instance_reference(obj: &mut InMemDicomObject, source: &SourceImages) {
    let mut series = InMemDicomObject::new_empty();
    put_text(
        &mut series,
        tags::SERIES_INSTANCE_UID,
        VR::UI,
        &source.series_instance_uid,
    );
    let instances = source.images.iter().map(image_reference).collect();
    put_sequence(&mut series, tags::REFERENCED_INSTANCE_SEQUENCE, instances);
    put_sequence(obj, tags::REFERENCED_SERIES_SEQUENCE, vec![series]);
}

/// An Image SOP Instance Reference Macro item.
fn image_reference(image: &SliceReference) -> InMemDicomObject {
    let mut item = InMemDicomObject::new_empty();
    put_text(
        &mut item,
        tags::REFERENCED_SOP_CLASS_UID,
        VR::UI,
        &image.sop_class_uid,
    );
    put_text(
        &mut item,
        tags::REFERENCED_SOP_INSTANCE_UID,
        VR::UI,
        &image.sop_instance_uid,
    );
    if let Some(frame) = image.frame_number {
        put_text(
            &mut item,
            tags::REFERENCED_FRAME_NUMBER,
            VR::IS,
            &frame.to_string(),
        );
    }
    item
}

/// A Pre/Post Deformation Matrix Registration item holding the identity.
fn identity_matrix_item() -> InMemDicomObject {
    let mut item = InMemDicomObject::new_empty();
    put_text(
        &mut item,
        tags::FRAME_OF_REFERENCE_TRANSFORMATION_MATRIX,
        VR::DS,
        "1\\0\\0\\0\\0\\1\\0\\0\\0\\0\\1\\0\\0\\0\\0\\1",
    );
    put_text(
        &mut item,
        tags::FRAME_OF_REFERENCE_TRANSFORMATION_MATRIX_TYPE,
        VR::CS,
        "RIGID",
    );
    item
}

/// Adds the file meta group (Explicit VR Little Endian) and encodes.
fn encode_file(obj: InMemDicomObject, path: &Path) -> Result<Vec<u8>> {
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
        .map_err(|e| Error::format(path, format!("cannot encode the registration ({e})")))?;
    Ok(bytes)
}

/// Content Label (CS: upper-case letters, digits, space and underscore, 16 characters) from
/// the instant's label; `REG_<k>` when nothing of it is left.
fn content_label(label: &str, frame_index: usize) -> String {
    let mut out = String::with_capacity(16);
    for c in label.chars() {
        let c = if c.is_ascii_alphanumeric() {
            c.to_ascii_uppercase()
        } else {
            '_'
        };
        if !(c == '_' && (out.is_empty() || out.ends_with('_'))) {
            out.push(c);
        }
    }
    let out = out.trim_end_matches('_');
    let out: String = out.chars().take(16).collect();
    let out = out.trim_end_matches('_').to_string();
    if out.is_empty() {
        format!("REG_{frame_index}")
    } else {
        out
    }
}

/// A Long String value: no backslash or control character, at most 64 characters.
fn long_string(text: &str) -> String {
    text.chars()
        .map(|c| if c == '\\' || c.is_control() { ' ' } else { c })
        .take(64)
        .collect()
}

/// A decimal string (DS) of at most 16 characters.
fn ds(v: f64) -> String {
    for decimals in (0..=10).rev() {
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

/// Backslash-separated decimal strings.
fn ds_list(values: &[f64]) -> String {
    values.iter().map(|&v| ds(v)).collect::<Vec<_>>().join("\\")
}

/// Today's date (DA, YYYYMMDD) and the time (TM, HHMMSS), UTC.
fn utc_now_da_tm() -> (String, String) {
    let secs = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.as_secs());
    let days = (secs / 86_400) as i64;
    let s = secs % 86_400;
    // Civil date from days since 1970-01-01 (H. Hinnant's algorithm).
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z - era * 146_097;
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let day = doy - (153 * mp + 2) / 5 + 1;
    let month = if mp < 10 { mp + 3 } else { mp - 9 };
    let year = yoe + era * 400 + i64::from(month <= 2);
    (
        format!("{year:04}{month:02}{day:02}"),
        format!("{:02}{:02}{:02}", s / 3600, (s / 60) % 60, s % 60),
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A translation by `t` mm.
    struct Shift([f64; 3]);

    impl PhaseMotion for Shift {
        fn moved_lps_mm(&self, p: [f64; 3]) -> [f64; 3] {
            [p[0] + self.0[0], p[1] + self.0[1], p[2] + self.0[2]]
        }
        fn source_lps_mm(&self, y: [f64; 3]) -> [f64; 3] {
            [y[0] - self.0[0], y[1] - self.0[1], y[2] - self.0[2]]
        }
    }

    fn corners() -> Vec<V3> {
        vec![V3::new(-100.0, -50.0, -200.0), V3::new(100.0, 80.0, 20.0)]
    }

    #[test]
    fn the_grid_covers_the_points_with_the_margin_on_the_ct_axes() {
        let g = RegistrationGrid::around(corners().into_iter(), &Matrix3::identity(), 3.0, 10.0)
            .unwrap();
        assert_eq!(g.point_lps_mm(0, 0, 0), V3::new(-110.0, -60.0, -210.0));
        // 220 mm / 3 mm = 73.3: 74 steps, 75 points, the last one past +110.
        assert_eq!(g.dims(), [75, 51, 81]);
        let last = g.point_lps_mm(74, 50, 80);
        assert!(
            last.x >= 110.0 && last.y >= 90.0 && last.z >= 30.0,
            "{last}"
        );
        let v = g.sample_vectors_mm(&Shift([1.0, -2.0, 0.5])).unwrap();
        assert_eq!(v.len(), g.point_count() * 3);
        assert_eq!(&v[v.len() - 3..], &[1.0, -2.0, 0.5]);
    }

    #[test]
    fn a_flipped_slice_axis_becomes_row_cross_column() {
        // The CT's k axis points to the feet; C.20.3.1.1 takes row × column (the head).
        let dir = Matrix3::new(1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, -1.0);
        let g = RegistrationGrid::around(corners().into_iter(), &dir, 5.0, 0.0).unwrap();
        assert_eq!(g.axes[2], V3::new(0.0, 0.0, 1.0));
        assert_eq!(g.point_lps_mm(0, 0, 0).z, -200.0);
    }

    #[test]
    fn bad_spacings_and_oversized_grids_are_refused_by_name() {
        for bad in [0.0, -3.0, f64::NAN, 0.1, 50.0] {
            let e =
                RegistrationGrid::around(corners().into_iter(), &Matrix3::identity(), bad, 10.0)
                    .unwrap_err()
                    .to_string();
            assert!(e.contains("registration_spacing_mm"), "{bad}: {e}");
        }
        let huge = vec![V3::zeros(), V3::new(500.0, 500.0, 500.0)];
        let e = RegistrationGrid::around(huge.into_iter(), &Matrix3::identity(), 1.0, 10.0)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("521 × 521 × 521") && e.contains("128 MB limit"),
            "{e}"
        );
        let e = RegistrationGrid::around(std::iter::empty(), &Matrix3::identity(), 3.0, 10.0)
            .unwrap_err()
            .to_string();
        assert!(e.contains("no finite lung point"), "{e}");
    }

    #[test]
    fn a_motion_that_is_not_finite_is_refused_with_the_point() {
        let g = RegistrationGrid::around(corners().into_iter(), &Matrix3::identity(), 10.0, 0.0)
            .unwrap();
        let e = g
            .sample_vectors_mm(&Shift([f64::NAN, 0.0, 0.0]))
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("not finite at LPS (-100.0, -50.0, -200.0)"),
            "{e}"
        );
    }

    #[test]
    fn content_labels_are_code_strings() {
        assert_eq!(
            content_label("frame 3 t=1.20s +250 mL", 3),
            "FRAME_3_T_1_20S"
        );
        assert_eq!(content_label("30% (inhale)", 1), "30_INHALE");
        assert_eq!(content_label("%%", 7), "REG_7");
        assert_eq!(long_string("a\\b").as_str(), "a b");
    }

    #[test]
    fn utc_dates_are_well_formed() {
        let (d, t) = utc_now_da_tm();
        assert_eq!((d.len(), t.len()), (8, 6));
        assert!(d.as_str() >= "20240101" && t.as_str() < "240000", "{d} {t}");
    }
}
