//! Reading a CT series: gather files, group by series, check geometry, decode in parallel.

mod admit;
mod attributes;
mod budget;
mod enhanced;
mod pixels;
mod prescan;
mod series_choice;
mod vr_repair;
mod walk;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};

use dicom_core::value::{PrimitiveValue, Value};
use dicom_core::Tag;
use dicom_dictionary_std::{tags, uids};
use dicom_object::DefaultDicomObject;
use dicom_transfer_syntax_registry::{TransferSyntaxIndex, TransferSyntaxRegistry};
use nalgebra::Vector3;
use rayon::prelude::*;

use super::{DicomReadOptions, DicomSeries, DicomStudyContext, SeriesInfo, SliceReference};
use crate::formats::archive::{looks_like_zip, read_zip_file, ArchiveEntry};
use crate::volume::{Volume, VolumeGeometry, MAX_DIM};
use crate::{Error, IoContext, IoOp, Result};

use admit::{admit, Skipped};
use attributes::check_same_layout;
use budget::{default_budget_bytes, mb, MemoryBudget};
use enhanced::{expand_frames, FrameRef};
use pixels::decode_slice;
pub use series_choice::SeriesChoice;
use series_choice::{select_series, SeriesFiles};

/// Two slices closer than this along the normal are at the same position.
const DUPLICATE_TOLERANCE_MM: f64 = 0.01;
/// Absolute part of the slice-gap tolerance.
const GAP_TOLERANCE_MM: f64 = 0.01;
/// Relative part of the slice-gap tolerance.
const GAP_TOLERANCE_FRACTION: f64 = 0.01;
/// Slice positions may leave the normal by this much (absolute part), DS rounding included.
const TILT_TOLERANCE_MM: f64 = 0.01;
/// Slice positions may leave the normal by this fraction of their distance along it (0.06°).
const TILT_TOLERANCE_SLOPE: f64 = 1e-3;

/// Reads the single CT series in `input`: a directory (searched recursively), a zip file or
/// one DICOM file.
pub fn read_dicom_series(input: &Path) -> Result<DicomSeries> {
    read_dicom_series_with(input, &DicomReadOptions::default())
}

/// Reads a CT series from `input` with explicit options (series choice, zip limits).
pub fn read_dicom_series_with(input: &Path, options: &DicomReadOptions) -> Result<DicomSeries> {
    read_dicom_series_cancellable(input, options, None)
}

/// [`read_dicom_series_with`], stopped with [`Error::Cancelled`] once `cancel` is raised:
/// looked at before each file is parsed and each slice decoded (one atomic load per slice),
/// so a series of hundreds of slices stops within a slice's work per thread.
pub fn read_dicom_series_cancellable(
    input: &Path,
    options: &DicomReadOptions,
    cancel: Option<&AtomicBool>,
) -> Result<DicomSeries> {
    let what = input.display().to_string();
    let budget_bytes = options
        .memory_budget_bytes
        .unwrap_or_else(default_budget_bytes);
    let sources = gather_sources(input, options, budget_bytes)?;
    if sources.is_empty() {
        return Err(Error::scan(what, "no files found"));
    }
    check_cancel(cancel)?;
    let budget = MemoryBudget::new(budget_bytes);
    let parsed: Vec<std::result::Result<Parsed, Skipped>> = sources
        .into_par_iter()
        .map(|source| {
            check_cancel(cancel)?;
            Ok(parse_source(source, &budget))
        })
        .collect::<Result<_>>()?;
    let mut skipped = Vec::new();
    let mut files = Vec::new();
    let mut repairs: BTreeMap<String, Vec<String>> = BTreeMap::new();
    for p in parsed {
        match p {
            Ok(Parsed { file, repairs: r }) => {
                if let Some(f) = &file {
                    for repair in r {
                        repairs.entry(repair).or_default().push(f.name.clone());
                    }
                }
                files.extend(file);
            }
            Err(s) => skipped.push(s),
        }
    }
    if let Some(over) = skipped.iter().find(|s| s.over_read_budget) {
        return Err(Error::scan(
            what,
            format!(
                "the DICOM files need more memory than this read may use ({}, half the memory \
                 available): {}: {}",
                mb(budget_bytes),
                over.name,
                over.reason
            ),
        ));
    }
    let mut warnings: Vec<String> = skipped.iter().map(Skipped::to_string).collect();
    for (repair, names) in repairs {
        warnings.push(format!(
            "{} file(s) repaired on reading: {repair} ({})",
            names.len(),
            summarize(&names, 3)
        ));
    }
    if files.is_empty() {
        return Err(Error::scan(
            what,
            format!(
                "no readable DICOM image ({} skipped: {})",
                skipped.len(),
                summarize_skips(&skipped)
            ),
        ));
    }
    let series = select_series(&what, files, options, &mut warnings)?;
    build_volume(&what, series, warnings, cancel).map_err(|e| naming_skipped_files(e, &skipped))
}

/// [`Error::Cancelled`] once `cancel` is raised.
fn check_cancel(cancel: Option<&AtomicBool>) -> Result<()> {
    match cancel {
        Some(flag) if flag.load(Ordering::Relaxed) => Err(Error::Cancelled(
            "stopped while reading the DICOM series".into(),
        )),
        _ => Ok(()),
    }
}

/// A series refused as a whole (a gap, too few slices) may be refused because of files that
/// were skipped; their reasons are the fault to fix, so the refusal carries them.
fn naming_skipped_files(error: Error, skipped: &[Skipped]) -> Error {
    match error {
        Error::InvalidScan { scan, reason } if !skipped.is_empty() => Error::InvalidScan {
            scan,
            reason: format!(
                "{reason}; {} file(s) were skipped and may be the missing part: {}",
                skipped.len(),
                summarize_skips(skipped)
            ),
        },
        other => other,
    }
}

/// A file to parse: on disk or already in memory (from a zip).
enum Source {
    File(PathBuf),
    Entry { zip: String, entry: ArchiveEntry },
}

/// The files of `input`; a zip's entries are decompressed into memory, so all of them
/// together may take no more than the read's memory budget, `budget_bytes`.
fn gather_sources(
    input: &Path,
    options: &DicomReadOptions,
    budget_bytes: u64,
) -> Result<Vec<Source>> {
    let meta = std::fs::metadata(input).at(IoOp::Metadata, input)?;
    if meta.is_dir() {
        let mut paths = Vec::new();
        collect_files(input, &mut paths)?;
        paths.sort();
        Ok(paths.into_iter().map(Source::File).collect())
    } else if looks_like_zip(input) {
        let zip = input.display().to_string();
        let mut limits = options.archive_limits;
        if budget_bytes < limits.max_total_uncompressed_bytes {
            limits.max_total_uncompressed_bytes = budget_bytes;
            limits.total_limit_name =
                "the memory this DICOM read may use (half the memory available)";
        }
        let entries = read_zip_file(input, &limits)?;
        Ok(entries
            .into_iter()
            .filter(|e| !is_dicomdir_name(&e.name))
            .map(|entry| Source::Entry {
                zip: zip.clone(),
                entry,
            })
            .collect())
    } else {
        Ok(vec![Source::File(input.to_path_buf())])
    }
}

fn collect_files(dir: &Path, out: &mut Vec<PathBuf>) -> Result<()> {
    let listing = std::fs::read_dir(dir).at(IoOp::List, dir)?;
    for entry in listing {
        let entry = entry.at(IoOp::List, dir)?;
        let path = entry.path();
        // Follows symlinked files but not symlinked directories, which could loop.
        let kind = entry.file_type().at(IoOp::Metadata, &path)?;
        if kind.is_dir() {
            collect_files(&path, out)?;
        } else if (kind.is_file() || path.is_file())
            && !is_dicomdir_name(&entry.file_name().to_string_lossy())
        {
            out.push(path);
        }
    }
    Ok(())
}

fn is_dicomdir_name(name: &str) -> bool {
    name.rsplit(['/', '\\'])
        .next()
        .is_some_and(|base| base.eq_ignore_ascii_case("DICOMDIR"))
}

/// One parsed DICOM file with the attributes needed to group it.
struct ParsedFile {
    name: String,
    object: DefaultDicomObject,
    series_uid: String,
    modality: String,
    description: Option<String>,
}

/// A parsed source: the file (`None` for one deliberately ignored, a DICOMDIR) and the
/// repairs its bytes needed.
struct Parsed {
    file: Option<ParsedFile>,
    repairs: Vec<String>,
}

/// Parses one DICOM file that is not part of a CT series (an RTSTRUCT), after the same
/// structure and memory checks as a CT slice.
pub(crate) fn read_single_object(path: &Path) -> Result<DefaultDicomObject> {
    let budget = MemoryBudget::new(default_budget_bytes());
    admit(Source::File(path.to_path_buf()), &budget)
        .map(|admitted| admitted.object)
        .map_err(|skipped| Error::format(path, skipped.reason))
}

/// Parses one source within the read's memory budget; `Err` names a skipped file and why.
fn parse_source(source: Source, budget: &MemoryBudget) -> std::result::Result<Parsed, Skipped> {
    let admitted = admit(source, budget)?;
    let (name, object) = (admitted.name, admitted.object);
    let dropped = |reason: Option<String>| {
        // Its memory is no longer held by this read.
        budget.release(0, admitted.parsed_bytes);
        match reason {
            Some(reason) => Err(Skipped::new(&name, reason)),
            None => Ok(Parsed {
                file: None,
                repairs: Vec::new(),
            }),
        }
    };
    if object.meta().media_storage_sop_class_uid() == uids::MEDIA_STORAGE_DIRECTORY_STORAGE {
        return dropped(None);
    }
    if let Err(why) = check_image_complete(&object) {
        return dropped(Some(why));
    }
    let series_uid = text(&object, tags::SERIES_INSTANCE_UID)
        .unwrap_or_else(|| "(no SeriesInstanceUID)".to_string());
    let modality = text(&object, tags::MODALITY).unwrap_or_else(|| "(no Modality)".to_string());
    let description = text(&object, tags::SERIES_DESCRIPTION);
    Ok(Parsed {
        file: Some(ParsedFile {
            name,
            object,
            series_uid,
            modality,
            description,
        }),
        repairs: admitted.repairs,
    })
}

/// Refuses objects without an image, naming what is missing, and native pixel data shorter
/// than its header announces: the parser accepts a file that ends early at an element
/// boundary.
fn check_image_complete(object: &DefaultDicomObject) -> std::result::Result<(), String> {
    let Some(pixel_data) = object.get(tags::PIXEL_DATA) else {
        let float = [
            (tags::FLOAT_PIXEL_DATA, "Float Pixel Data (7FE0,0008)"),
            (
                tags::DOUBLE_FLOAT_PIXEL_DATA,
                "Double Float Pixel Data (7FE0,0009)",
            ),
        ];
        if let Some((_, name)) = float.iter().find(|(tag, _)| object.get(*tag).is_some()) {
            return Err(format!(
                "its pixels are floating point ({name}), as in parametric maps: not supported; \
                 a CT image stores integers in Pixel Data (7FE0,0010)"
            ));
        }
        return Err(
            "no Pixel Data (7FE0,0010): not an image (a report, a presentation state …) or a \
             file cut before its pixels"
                .into(),
        );
    };
    let number = |tag: Tag| {
        object
            .get(tag)
            .and_then(|e| e.to_int::<u32>().ok())
            .map(|v| v as usize)
    };
    let (rows, columns) = match (number(tags::ROWS), number(tags::COLUMNS)) {
        (Some(rows), Some(columns)) => (rows, columns),
        (rows, _) => {
            let (tag, tag_name) = if rows.is_none() {
                (tags::ROWS, "Rows")
            } else {
                (tags::COLUMNS, "Columns")
            };
            let state = if object.get(tag).is_some() {
                "is not a number"
            } else {
                "is missing"
            };
            return Err(format!(
                "{tag_name} ({:04X},{:04X}) {state}: the image size is unknown",
                tag.0, tag.1
            ));
        }
    };
    let Some(bytes) = pixel_data
        .value()
        .primitive()
        .map(|v| v.calculate_byte_len())
    else {
        // Encapsulated fragments: their decoder reports truncation.
        return Ok(());
    };
    if rows > MAX_DIM || columns > MAX_DIM {
        // Left for the geometry check, which names the absurd size.
        return Ok(());
    }
    let bits = number(tags::BITS_ALLOCATED).unwrap_or(16);
    let samples = number(tags::SAMPLES_PER_PIXEL).unwrap_or(1);
    let frames = number(tags::NUMBER_OF_FRAMES).unwrap_or(1).max(1);
    let expected = rows * columns * samples * frames * bits.div_ceil(8);
    if bytes < expected {
        return Err(format!(
            "pixel data holds {bytes} bytes where {rows}×{columns}×{frames} pixels of {bits} \
             bits need {expected} (truncated file?)"
        ));
    }
    Ok(())
}

/// A text attribute, trimmed; a value left as bytes (VR UN or OB) is read as text, never
/// shown as numbers.
fn text(object: &DefaultDicomObject, tag: Tag) -> Option<String> {
    let element = object.get(tag)?;
    let value = match element.value() {
        Value::Primitive(PrimitiveValue::U8(bytes)) => String::from_utf8_lossy(bytes).into_owned(),
        _ => element.to_str().ok()?.into_owned(),
    };
    let trimmed = value.trim_matches(|c: char| c.is_whitespace() || c == '\0');
    (!trimmed.is_empty()).then(|| trimmed.to_string())
}

/// One slice after checking: a single-frame file or one frame of a multi-frame file.
struct Slice<'a> {
    file: &'a ParsedFile,
    /// Frame index in a multi-frame file.
    frame: Option<usize>,
    /// Frames in the file.
    frame_count: usize,
    /// The file's name (and frame) in messages.
    name: String,
    position_lps_mm: Vector3<f64>,
    rescale_slope: f64,
    rescale_intercept: f64,
}

/// Geometry every slice of the series must share.
struct FrameLayout {
    rows: usize,
    columns: usize,
    row_direction: Vector3<f64>,
    column_direction: Vector3<f64>,
    /// PixelSpacing as stored: row spacing (between rows), then column spacing.
    pixel_spacing_mm: [f64; 2],
}

/// Names the series in its errors: "{what}: series {uid}: …".
struct SeriesLabel<'a> {
    what: &'a str,
    uid: &'a str,
}

impl SeriesLabel<'_> {
    /// The error for this series with message `m`.
    fn error(&self, m: String) -> Error {
        Error::scan(self.what, format!("series {}: {m}", self.uid))
    }
}

impl Slice<'_> {
    /// Position along the slice normal, mm: the slices' order and spacing.
    fn along_mm(&self, normal: &Vector3<f64>) -> f64 {
        self.position_lps_mm.dot(normal)
    }
}

/// Turns the chosen series into a volume: checks, orders and decodes its slices (the
/// single-frame files, or the frames of Enhanced CT files).
fn build_volume(
    what: &str,
    series: SeriesFiles,
    mut warnings: Vec<String>,
    cancel: Option<&AtomicBool>,
) -> Result<DicomSeries> {
    let SeriesFiles { uid, files } = series;
    let label = SeriesLabel { what, uid: &uid };
    let frames = expand_frames(&files, &label)?;
    let (layout, slices) = read_slice_attributes(frames, &label, &mut warnings)?;
    let normal = layout
        .row_direction
        .cross(&layout.column_direction)
        .normalize();
    let slices = order_along_normal(slices, &normal);
    let slices = drop_duplicate_slices(slices, &normal, &label, &mut warnings)?;
    check_no_gantry_tilt(&slices, &normal, &label)?;
    let slice_spacing_mm = uniform_slice_spacing_mm(&slices, &normal, &label)?;

    let geometry = VolumeGeometry {
        dims: [layout.columns, layout.rows, slices.len()],
        spacing_mm: [
            layout.pixel_spacing_mm[1],
            layout.pixel_spacing_mm[0],
            slice_spacing_mm,
        ],
        origin_lps_mm: slices[0].position_lps_mm.into(),
        direction_lps: [
            layout.row_direction.into(),
            layout.column_direction.into(),
            normal.into(),
        ],
    };
    geometry.validate(&format!("{what}: series {uid}"))?;
    let data = decode_slices(&slices, &layout, geometry.voxel_count(), cancel)?;
    let info = describe_series(&label, &slices, &layout, &mut warnings);
    let study = study_context(&slices, &uid);
    let volume = Volume::from_data(geometry, data)?;
    Ok(DicomSeries {
        volume,
        info,
        study,
        warnings,
    })
}

/// The patient, study and frame of reference of the series (from its first slice) and the
/// instance each slice came from, for the DICOM objects a run derives from this CT.
fn study_context(slices: &[Slice], series_uid: &str) -> DicomStudyContext {
    let first = &slices[0].file.object;
    let field = |tag| text(first, tag).unwrap_or_default();
    DicomStudyContext {
        patient_name: field(tags::PATIENT_NAME),
        patient_id: field(tags::PATIENT_ID),
        patient_birth_date: field(tags::PATIENT_BIRTH_DATE),
        patient_sex: field(tags::PATIENT_SEX),
        study_instance_uid: field(tags::STUDY_INSTANCE_UID),
        study_date: field(tags::STUDY_DATE),
        study_time: field(tags::STUDY_TIME),
        study_id: field(tags::STUDY_ID),
        accession_number: field(tags::ACCESSION_NUMBER),
        referring_physician_name: field(tags::REFERRING_PHYSICIAN_NAME),
        study_description: field(tags::STUDY_DESCRIPTION),
        frame_of_reference_uid: field(tags::FRAME_OF_REFERENCE_UID),
        series_instance_uid: series_uid.to_string(),
        patient_position: field(tags::PATIENT_POSITION),
        slices: slices
            .iter()
            .map(|s| SliceReference {
                sop_class_uid: text(&s.file.object, tags::SOP_CLASS_UID).unwrap_or_default(),
                sop_instance_uid: text(&s.file.object, tags::SOP_INSTANCE_UID).unwrap_or_default(),
                frame_number: s.frame.map(|f| f as u32 + 1),
            })
            .collect(),
        from_input: true,
    }
}

/// Reads each slice's frame layout (checked against the first slice's), position and
/// rescale; a missing rescale is taken as HU with one warning for the series.
fn read_slice_attributes<'a>(
    frames: Vec<FrameRef<'a>>,
    label: &SeriesLabel,
    warnings: &mut Vec<String>,
) -> Result<(FrameLayout, Vec<Slice<'a>>)> {
    let layout = frames[0].scope.frame_layout(&frames[0].name)?;
    let mut slices: Vec<Slice<'a>> = Vec::with_capacity(frames.len());
    let mut missing_rescale = 0usize;
    for frame in frames {
        let FrameRef {
            file,
            frame,
            frame_count,
            name,
            scope,
        } = frame;
        let this = scope.frame_layout(&name)?;
        if let Some(first) = slices.first() {
            check_same_layout(&layout, &first.name, &this, &name)?;
        }
        let ipp = scope.floats(
            &name,
            tags::IMAGE_POSITION_PATIENT,
            "ImagePositionPatient",
            3,
        )?;
        let slope = scope.rescale(&name, tags::RESCALE_SLOPE, "RescaleSlope", 1.0)?;
        let intercept = scope.rescale(&name, tags::RESCALE_INTERCEPT, "RescaleIntercept", 0.0)?;
        if slope.is_none() || intercept.is_none() {
            missing_rescale += 1;
        }
        let slope = slope.unwrap_or(1.0);
        if slope == 0.0 {
            return Err(label.error(format!("{name}: RescaleSlope is 0")));
        }
        slices.push(Slice {
            file,
            frame,
            frame_count,
            name,
            position_lps_mm: Vector3::new(ipp[0], ipp[1], ipp[2]),
            rescale_slope: slope,
            rescale_intercept: intercept.unwrap_or(0.0),
        });
    }
    if missing_rescale > 0 {
        let w = format!(
            "{}: {missing_rescale} slice(s) lack RescaleSlope/RescaleIntercept; stored \
             values taken as HU (slope 1, intercept 0)",
            label.what
        );
        warnings.push(w);
    }
    Ok((layout, slices))
}

/// Sorts the slices by their position along the normal, never by file name or
/// InstanceNumber, which exports do not keep in anatomical order.
fn order_along_normal<'a>(mut slices: Vec<Slice<'a>>, normal: &Vector3<f64>) -> Vec<Slice<'a>> {
    slices.sort_by(|a, b| a.along_mm(normal).total_cmp(&b.along_mm(normal)));
    slices
}

/// Duplicates: identical pixels and rescale are dropped (exports repeat files), anything else
/// at the same position is refused; at least 2 distinct positions must remain.
/// Attributes that tell the phases or repeats of a 4D-CT apart when they share one series.
const PHASE_TAGS: [(Tag, &str); 4] = [
    (
        tags::TEMPORAL_POSITION_IDENTIFIER,
        "TemporalPositionIdentifier",
    ),
    (tags::ACQUISITION_NUMBER, "AcquisitionNumber"),
    (tags::TRIGGER_TIME, "TriggerTime"),
    (tags::ACQUISITION_TIME, "AcquisitionTime"),
];

/// Why two images may share a position: the first phase attribute whose values differ,
/// named so the user can split the series (lungmotion reads one breathing phase).
fn phase_hint(a: &ParsedFile, b: &ParsedFile) -> String {
    PHASE_TAGS
        .iter()
        .find_map(|&(tag, name)| {
            let (x, y) = (text(&a.object, tag)?, text(&b.object, tag)?);
            (x != y).then(|| {
                format!(
                    "; they differ in {name} ({x} and {y}): a 4D-CT whose phases share one \
                     series? lungmotion reads one phase: give it one phase's files (split by \
                     {name}) or a series per phase"
                )
            })
        })
        .unwrap_or_default()
}

fn drop_duplicate_slices<'a>(
    slices: Vec<Slice<'a>>,
    normal: &Vector3<f64>,
    label: &SeriesLabel,
    warnings: &mut Vec<String>,
) -> Result<Vec<Slice<'a>>> {
    let along = |s: &Slice| s.along_mm(normal);
    let mut kept: Vec<Slice<'a>> = Vec::with_capacity(slices.len());
    for slice in slices {
        if let Some(previous) = kept.last() {
            if (along(&slice) - along(previous)).abs() < DUPLICATE_TOLERANCE_MM {
                // Frames of a multi-frame file share one pixel data element: never "the same".
                let single_frames = previous.frame.is_none() && slice.frame.is_none();
                let same_pixels = single_frames
                    && previous
                        .file
                        .object
                        .get(tags::PIXEL_DATA)
                        .map(|e| e.value())
                        == slice.file.object.get(tags::PIXEL_DATA).map(|e| e.value());
                let same_rescale = previous.rescale_slope == slice.rescale_slope
                    && previous.rescale_intercept == slice.rescale_intercept;
                if same_pixels && same_rescale {
                    let w = format!(
                        "{}: dropped, an exact duplicate of {} (same position {:.3} mm along the \
                         slice normal, same pixels)",
                        slice.name,
                        previous.name,
                        along(&slice)
                    );
                    warnings.push(w);
                    continue;
                }
                return Err(label.error(format!(
                    "{} and {} are both at {:.3} mm along the slice normal but hold different \
                     images (duplicate slice position){}",
                    previous.name,
                    slice.name,
                    along(&slice),
                    phase_hint(previous.file, slice.file)
                )));
            }
        }
        kept.push(slice);
    }
    if kept.len() < 2 {
        return Err(label.error("only 1 distinct slice position: a volume needs at least 2".into()));
    }
    Ok(kept)
}

/// Gantry tilt: positions must move along the normal only, since a sheared stack does not
/// fit a volume's orthogonal grid; the worst slice is named.
fn check_no_gantry_tilt(
    slices: &[Slice],
    normal: &Vector3<f64>,
    label: &SeriesLabel,
) -> Result<()> {
    let first_position = slices[0].position_lps_mm;
    let mut worst: Option<(f64, f64, usize)> = None;
    for (k, s) in slices.iter().enumerate().skip(1) {
        let step = s.position_lps_mm - first_position;
        let along_mm = step.dot(normal);
        let lateral_mm = (step - normal * along_mm).norm();
        if lateral_mm > TILT_TOLERANCE_MM + TILT_TOLERANCE_SLOPE * along_mm.abs()
            && worst.is_none_or(|(l, _, _)| lateral_mm > l)
        {
            worst = Some((lateral_mm, along_mm, k));
        }
    }
    if let Some((lateral_mm, along_mm, k)) = worst {
        let tilt_deg = lateral_mm.atan2(along_mm.abs()).to_degrees();
        let declared = text(&slices[k].file.object, tags::GANTRY_DETECTOR_TILT)
            .map(|t| format!(" (GantryDetectorTilt says {t}°)"))
            .unwrap_or_default();
        return Err(label.error(format!(
            "slice positions leave the slice normal by {lateral_mm:.2} mm over {along_mm:.2} mm \
             ({} vs {}): gantry tilt of about {tilt_deg:.2}°{declared}; sheared volumes are not \
             supported, resample the series first",
            slices[k].name, slices[0].name
        )));
    }
    Ok(())
}

/// Uniform spacing: every gap must match the median one (a missing slice is named); the
/// spacing is the mean over the whole stack.
fn uniform_slice_spacing_mm(
    slices: &[Slice],
    normal: &Vector3<f64>,
    label: &SeriesLabel,
) -> Result<f64> {
    let along = |s: &Slice| s.along_mm(normal);
    let gaps: Vec<f64> = slices
        .windows(2)
        .map(|w| along(&w[1]) - along(&w[0]))
        .collect();
    let mut sorted_gaps = gaps.clone();
    sorted_gaps.sort_by(f64::total_cmp);
    let typical_gap = sorted_gaps[sorted_gaps.len() / 2];
    let tolerance = GAP_TOLERANCE_MM.max(GAP_TOLERANCE_FRACTION * typical_gap);
    let irregular: Vec<String> = gaps
        .iter()
        .enumerate()
        .filter(|(_, g)| (*g - typical_gap).abs() > tolerance)
        .map(|(k, g)| {
            format!(
                "{g:.3} mm between {} and {}",
                slices[k].name,
                slices[k + 1].name
            )
        })
        .collect();
    if !irregular.is_empty() {
        return Err(label.error(format!(
            "non-uniform slice spacing (typical {typical_gap:.3} mm; missing slice?): {} gap(s) \
             differ: {}",
            irregular.len(),
            summarize(&irregular, 8)
        )));
    }
    let n = slices.len();
    Ok((along(&slices[n - 1]) - along(&slices[0])) / (n - 1) as f64)
}

/// Decodes every slice in parallel into its frame of the volume, HU after rescale.
fn decode_slices(
    slices: &[Slice],
    layout: &FrameLayout,
    voxel_count: usize,
    cancel: Option<&AtomicBool>,
) -> Result<Vec<f32>> {
    let frame_len = layout.columns * layout.rows;
    let mut data = vec![0f32; voxel_count];
    data.par_chunks_mut(frame_len)
        .zip(slices.par_iter())
        .try_for_each(|(out, slice)| {
            check_cancel(cancel)?;
            decode_slice(slice, layout, out)
        })?;
    Ok(data)
}

/// The non-identifying description of the series, from its first slice; a series mixing
/// transfer syntaxes is worth a warning (usually a partial re-export).
fn describe_series(
    label: &SeriesLabel,
    slices: &[Slice],
    layout: &FrameLayout,
    warnings: &mut Vec<String>,
) -> SeriesInfo {
    let first = &slices[0].file;
    let transfer_syntax_uid = first
        .object
        .meta()
        .transfer_syntax()
        .trim_end_matches('\0')
        .to_string();
    let syntax_of = |s: &Slice| {
        s.file
            .object
            .meta()
            .transfer_syntax()
            .trim_end_matches('\0')
            .to_string()
    };
    if let Some(other) = slices.iter().find(|s| syntax_of(s) != transfer_syntax_uid) {
        let w = format!(
            "{}: the series mixes transfer syntaxes ({} in {}, {} in {})",
            label.what,
            transfer_syntax_uid,
            first.name,
            syntax_of(other),
            other.name
        );
        warnings.push(w);
    }
    let transfer_syntax_name = TransferSyntaxRegistry
        .get(&transfer_syntax_uid)
        .map(|ts| ts.name().to_string())
        .unwrap_or_else(|| "unknown transfer syntax".into());
    SeriesInfo {
        series_instance_uid: label.uid.to_string(),
        modality: first.modality.clone(),
        series_description: first.description.clone(),
        manufacturer: text(&first.object, tags::MANUFACTURER),
        transfer_syntax_uid,
        transfer_syntax_name,
        slice_count: slices.len(),
        rows: layout.rows,
        columns: layout.columns,
        patient_position: text(&first.object, tags::PATIENT_POSITION),
    }
}

fn summarize(items: &[String], max: usize) -> String {
    let mut s = items
        .iter()
        .take(max)
        .cloned()
        .collect::<Vec<_>>()
        .join("; ");
    if items.len() > max {
        s.push_str(&format!("; … {} more", items.len() - max));
    }
    s
}

/// The reasons files were skipped, most common first, each with a few of its files.
fn summarize_skips(skipped: &[Skipped]) -> String {
    let mut by_reason: BTreeMap<&str, Vec<String>> = BTreeMap::new();
    for s in skipped {
        by_reason.entry(&s.reason).or_default().push(s.name.clone());
    }
    let mut groups: Vec<(&str, Vec<String>)> = by_reason.into_iter().collect();
    groups.sort_by_key(|(_, names)| std::cmp::Reverse(names.len()));
    let described: Vec<String> = groups
        .iter()
        .map(|(reason, names)| match names.as_slice() {
            [one] => format!("{one}: {reason}"),
            _ => format!("{} files: {reason} ({})", names.len(), summarize(names, 3)),
        })
        .collect();
    summarize(&described, 3)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_raised_flag_stops_the_series_read_and_a_lowered_one_does_not() {
        let series = Path::new(env!("CARGO_MANIFEST_DIR")).join("sample-volumes/phantom-dicom");
        let options = DicomReadOptions::default();
        let flag = AtomicBool::new(true);
        let e = read_dicom_series_cancellable(&series, &options, Some(&flag)).unwrap_err();
        assert!(matches!(e, Error::Cancelled(_)), "{e}");
        flag.store(false, Ordering::SeqCst);
        let read = read_dicom_series_cancellable(&series, &options, Some(&flag)).unwrap();
        assert!(read.info.slice_count > 10, "{}", read.info.slice_count);
    }
}
