//! Treatment targets uploaded to a scan (`PUT /v1/scans/{id}/targets/{name}`): a label map
//! on the scan's CT grid or an RT Structure Set in its frame of reference, checked against
//! the CT when uploaded with the CLI's own checks, named in a simulation request
//! (`"target": {"upload": name, "label": n}` or `{"upload": name, "roi": "GTV"}`), and copied
//! into the job when it is submitted, so that replacing or deleting the upload later changes
//! no job. A job resolves its copy exactly as `lungmotion run --target` resolves a file.

use std::path::Path;

use serde::{Deserialize, Serialize};
use serde_json::Value;
use utoipa::ToSchema;

use super::problem::{ApiError, ApiResult};
use crate::formats::dicom::DicomStudyContext;
use crate::ingest::scan::ScanFormat;
use crate::outputs::radiotherapy::rtstruct::roi_names;
use crate::outputs::radiotherapy::target::{mask_label_counts, TargetSpec};
use crate::volume::VolumeGeometry;
use crate::{Error, Result};

/// Longest target name, characters.
pub const MAX_TARGET_NAME_CHARS: usize = 64;

/// Directory of a job's copy of its uploaded target, inside the job's directory.
pub const JOB_TARGET_DIR: &str = "target";

/// What an uploaded target file is.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum TargetKind {
    /// A NIfTI or NRRD label map on the scan's CT grid.
    Mask,
    /// A DICOM RT Structure Set whose ROIs lie in the scan's frame of reference.
    Rtstruct,
}

impl TargetKind {
    /// The kind of a received file from its content's format; `None` for a format that is
    /// no target (a zip).
    pub fn of_format(format: ScanFormat) -> Option<Self> {
        match format {
            ScanFormat::Nifti | ScanFormat::Nrrd => Some(TargetKind::Mask),
            ScanFormat::DicomFile => Some(TargetKind::Rtstruct),
            ScanFormat::DicomZip | ScanFormat::DicomDirectory => None,
        }
    }
}

/// A label of an uploaded mask.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct MaskLabel {
    /// The label's value (1–255).
    pub label: u8,
    /// CT voxels holding it.
    pub voxels: usize,
    /// Their volume, mL.
    pub volume_ml: f64,
}

/// An ROI of an uploaded structure set, as rasterised on the scan's CT.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct StructureRoi {
    /// ROIName, as stored.
    pub name: String,
    /// CT voxels inside its contours (none when it cannot be used).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub voxels: Option<usize>,
    /// Their volume, mL.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub volume_ml: Option<f64>,
    /// Why a simulation cannot follow it (contours off the CT's slices, another frame of
    /// reference, no closed planar contour…), as the CLI says it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub problem: Option<String>,
}

/// A target file as stored (`scans/<id>/targets/<name>/target.json`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct TargetRecord {
    /// The name the client gave it (the last segment of its URL).
    pub name: String,
    /// Mask or structure set.
    pub kind: TargetKind,
    /// What the upload was: `nifti`, `nrrd` or `dicom`.
    pub format: String,
    /// Bytes received.
    pub upload_bytes: u64,
    /// When it was uploaded (RFC 3339, UTC).
    pub created_at: String,
    /// The file's name inside its directory (`<name>.nii.gz`, `<name>.nii`, `<name>.nrrd` or
    /// `<name>.dcm`).
    pub file_name: String,
    /// A mask's labels present on the CT grid.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub labels: Vec<MaskLabel>,
    /// A structure set's ROIs.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub rois: Vec<StructureRoi>,
    /// Things the client should know (an RTSTRUCT on a CT without a DICOM frame of
    /// reference is placed by its coordinates alone).
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub notes: Vec<String>,
}

/// A target's name: the last segment of its URL and a file name in the store, so plain
/// (letters, digits, `.`, `_`, `-`, starting with a letter or digit, at most
/// [`MAX_TARGET_NAME_CHARS`]); what is wrong with it otherwise.
pub fn check_target_name(name: &str) -> std::result::Result<(), String> {
    let shown: String = name.chars().take(80).collect();
    if name.is_empty() || name.chars().count() > MAX_TARGET_NAME_CHARS {
        return Err(format!(
            "target name {shown:?}: 1 to {MAX_TARGET_NAME_CHARS} characters are needed"
        ));
    }
    let plain = |c: char| c.is_ascii_alphanumeric() || matches!(c, '.' | '_' | '-');
    if let Some(bad) = name.chars().find(|&c| !plain(c)) {
        return Err(format!(
            "target name {shown:?} holds {bad:?}: a name is letters, digits, '.', '_' and '-' \
             (no path: the file is uploaded in the body, never read from the server's disk)"
        ));
    }
    if !name.starts_with(|c: char| c.is_ascii_alphanumeric()) || name.contains("..") {
        return Err(format!(
            "target name {shown:?} must start with a letter or digit and hold no \"..\""
        ));
    }
    Ok(())
}

/// The target a simulation request names when it is an upload.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct TargetChoice {
    /// The target's name on the scan (`PUT /v1/scans/{id}/targets/{name}`).
    pub upload: String,
    /// A mask's label to follow (else every nonzero voxel).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub label: Option<u8>,
    /// A structure set's ROI to follow (its ROIName; compared ignoring case when no exact
    /// match exists, as the CLI does).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub roi: Option<String>,
    /// The job's copy, in its directory's `target/` (set when the job is submitted).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub file: Option<String>,
}

/// A job's target as its `request.json` holds it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(untagged)]
pub enum JobTarget {
    /// `point:<x>,<y>,<z>:r=<radius mm>`, as the request gave it.
    Point(String),
    /// A file uploaded to the scan, copied into the job.
    Upload(TargetChoice),
}

impl JobTarget {
    /// The CLI's target: the point parsed, or the job's copy of the upload (in
    /// `job_target_dir`) as a mask with its label or a structure set with its ROI.
    pub fn spec(&self, job_target_dir: &Path) -> Result<TargetSpec> {
        match self {
            JobTarget::Point(text) => text.parse(),
            JobTarget::Upload(choice) => {
                let file = choice.file.as_deref().ok_or_else(|| Error::Store {
                    record: "request.json".into(),
                    reason: format!(
                        "target upload {:?} has no copy in the job (submitted before it was \
                         stored)",
                        choice.upload
                    ),
                })?;
                let path = job_target_dir.join(file);
                Ok(match &choice.roi {
                    Some(roi) => TargetSpec::Rtstruct {
                        path,
                        roi: roi.clone(),
                    },
                    None => TargetSpec::Mask {
                        path,
                        label: choice.label,
                    },
                })
            }
        }
    }
}

/// A 422 with the slug every unusable target in a simulation request gets.
fn invalid(message: String) -> ApiError {
    ApiError::unprocessable("invalid-simulation", message)
}

/// A request's `target`: a point string (checked as the CLI checks it) or an upload's name
/// with a label or an ROI (checked for form; against the scan's uploads by [`choose`]).
pub fn parse_request_target(value: Value) -> ApiResult<JobTarget> {
    match value {
        Value::String(text) => {
            check_point(&text)?;
            Ok(JobTarget::Point(text))
        }
        Value::Object(_) => {
            let choice: TargetChoice = serde_json::from_value(value).map_err(|e| {
                invalid(format!(
                    "target: {e} (an uploaded target is {{\"upload\": name, \"label\": n}} for a \
                     mask or {{\"upload\": name, \"roi\": ROI name}} for an RTSTRUCT)"
                ))
            })?;
            check_target_name(&choice.upload).map_err(|m| invalid(format!("target: {m}")))?;
            if choice.file.is_some() {
                return Err(invalid("target: unknown field `file`".into()));
            }
            if choice.label == Some(0) {
                return Err(invalid(
                    "target: label 0 is the background; a label is 1 to 255".into(),
                ));
            }
            match &choice.roi {
                Some(_) if choice.label.is_some() => Err(invalid(format!(
                    "target {:?}: a label (of a mask) and an roi (of an RTSTRUCT) together; \
                     give the one its upload has",
                    choice.upload
                ))),
                Some(roi) if roi.trim().is_empty() => Err(invalid(format!(
                    "target {:?}: the roi is empty",
                    choice.upload
                ))),
                _ => Ok(JobTarget::Upload(choice)),
            }
        }
        other => Err(invalid(format!(
            "target {other}: a target is \"point:<x>,<y>,<z>:r=<radius mm>\" or an uploaded \
             file, {{\"upload\": name, \"label\": n}} or {{\"upload\": name, \"roi\": \"GTV\"}}"
        ))),
    }
}

/// A point target over HTTP, checked as the CLI checks it; any other text would name a file
/// on the server's disk, which is not the client's to read.
fn check_point(text: &str) -> ApiResult<TargetSpec> {
    if !text.starts_with("point:") {
        return Err(invalid(format!(
            "target {:?}: as text a target is a point and a radius, \
             point:<x>,<y>,<z>:r=<radius mm> (LPS mm); a mask or an RTSTRUCT is uploaded to \
             the scan (PUT /v1/scans/{{id}}/targets/{{name}}) and named as {{\"upload\": \
             name, \"label\": n}} or {{\"upload\": name, \"roi\": \"GTV\"}}, never as a path",
            text.chars().take(100).collect::<String>()
        )));
    }
    text.parse::<TargetSpec>()
        .map_err(|e| invalid(e.to_string()))
}

/// Checks `choice` against the scan's uploaded target `record` (`None`: no such upload;
/// `uploaded` lists the names there are): the label present in the mask, the ROI in the
/// structure set and usable.
pub fn choose(
    choice: &TargetChoice,
    record: Option<&TargetRecord>,
    uploaded: &[String],
) -> ApiResult<()> {
    let name = &choice.upload;
    let Some(record) = record else {
        return Err(invalid(format!(
            "target: the scan has no uploaded target {name:?} ({}); upload it first with PUT \
             /v1/scans/{{id}}/targets/{name}",
            if uploaded.is_empty() {
                "it has none".to_string()
            } else {
                format!("it has {}", uploaded.join(", "))
            }
        )));
    };
    match record.kind {
        TargetKind::Mask => {
            if choice.roi.is_some() {
                return Err(invalid(format!(
                    "target {name:?} is a mask: name a label (\"label\": n), not an roi; \
                     labels present: {}",
                    label_list(&record.labels)
                )));
            }
            if let Some(l) = choice.label {
                if !record.labels.iter().any(|m| m.label == l) {
                    return Err(invalid(format!(
                        "target {name:?}: label {l} is not in the mask; labels present: {}",
                        label_list(&record.labels)
                    )));
                }
            }
            Ok(())
        }
        TargetKind::Rtstruct => {
            let names: Vec<&str> = record.rois.iter().map(|r| r.name.as_str()).collect();
            if choice.label.is_some() {
                return Err(invalid(format!(
                    "target {name:?} is an RTSTRUCT: name an ROI (\"roi\": ...), not a label; \
                     ROIs present: {}",
                    names.join(", ")
                )));
            }
            let Some(roi) = &choice.roi else {
                return Err(invalid(format!(
                    "target {name:?} is an RTSTRUCT: name its ROI (\"roi\": ...); ROIs \
                     present: {}",
                    names.join(", ")
                )));
            };
            // The CLI's rule: the exact name, else the one name equal ignoring case.
            let exact = record.rois.iter().find(|r| &r.name == roi);
            let loose: Vec<&StructureRoi> = record
                .rois
                .iter()
                .filter(|r| r.name.trim().eq_ignore_ascii_case(roi.trim()))
                .collect();
            let found = exact.or(if loose.len() == 1 {
                Some(loose[0])
            } else {
                None
            });
            match found {
                None => Err(invalid(format!(
                    "target {name:?}: no ROI named `{roi}`; ROIs present: {}",
                    names.join(", ")
                ))),
                Some(StructureRoi {
                    problem: Some(problem),
                    ..
                }) => Err(invalid(format!(
                    "target {name:?}: ROI `{roi}` cannot be followed: {problem}"
                ))),
                Some(_) => Ok(()),
            }
        }
    }
}

/// Labels as `8 (17.0 mL), 3 (2.1 mL)`.
fn label_list(labels: &[MaskLabel]) -> String {
    if labels.is_empty() {
        return "none".into();
    }
    labels
        .iter()
        .map(|m| format!("{} ({:.1} mL)", m.label, m.volume_ml))
        .collect::<Vec<_>>()
        .join(", ")
}

/// What checking an uploaded target against the CT found.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct TargetContents {
    /// A mask's labels.
    pub labels: Vec<MaskLabel>,
    /// A structure set's ROIs.
    pub rois: Vec<StructureRoi>,
    /// Notes for the client.
    pub notes: Vec<String>,
}

/// Checks the target file at `path` against the scan's CT grid `ct` (and its DICOM `study`,
/// whose frame of reference an RTSTRUCT must share) with the CLI's own checks: a mask must
/// lie on the grid and hold a label; a structure set must hold an ROI the CLI can rasterise
/// on the CT. Each ROI's problem is kept for a request that names it; the file is refused
/// only when none is usable. `shown` replaces the server path in the messages.
pub fn examine(
    path: &Path,
    kind: TargetKind,
    ct: &VolumeGeometry,
    study: Option<&DicomStudyContext>,
    shown: &str,
) -> Result<TargetContents> {
    let ml_per_voxel = ct.voxel_volume_mm3() / 1000.0;
    let redact = |text: String| text.replace(&path.display().to_string(), shown);
    match kind {
        TargetKind::Mask => {
            let labels: Vec<MaskLabel> = mask_label_counts(path, ct)?
                .into_iter()
                .map(|(label, voxels)| MaskLabel {
                    label,
                    voxels,
                    volume_ml: voxels as f64 * ml_per_voxel,
                })
                .collect();
            if labels.is_empty() {
                return Err(Error::scan(path, "the mask is empty: no voxel is labelled"));
            }
            Ok(TargetContents {
                labels,
                ..TargetContents::default()
            })
        }
        TargetKind::Rtstruct => {
            let names = roi_names(path)?;
            if names.is_empty() {
                return Err(Error::format(
                    path,
                    "the structure set holds no ROI (StructureSetROISequence is empty)",
                ));
            }
            let mut contents = TargetContents::default();
            for name in names {
                let spec = TargetSpec::Rtstruct {
                    path: path.to_path_buf(),
                    roi: name.clone(),
                };
                let roi = match spec.resolve(ct, study) {
                    Ok(mask) => {
                        let voxels = mask.voxel_count();
                        for note in mask.notes {
                            let note = redact(note);
                            if !contents.notes.contains(&note) {
                                contents.notes.push(note);
                            }
                        }
                        StructureRoi {
                            name,
                            voxels: Some(voxels),
                            volume_ml: Some(voxels as f64 * ml_per_voxel),
                            problem: None,
                        }
                    }
                    Err(e) => StructureRoi {
                        name,
                        voxels: None,
                        volume_ml: None,
                        problem: Some(redact(e.to_string())),
                    },
                };
                contents.rois.push(roi);
            }
            if contents.rois.iter().all(|r| r.problem.is_some()) {
                let mut problems: Vec<&str> = contents
                    .rois
                    .iter()
                    .filter_map(|r| r.problem.as_deref())
                    .collect();
                problems.dedup();
                return Err(Error::format(
                    path,
                    format!(
                        "no ROI of the structure set can be followed on this scan's CT: {}",
                        problems.join("; ")
                    ),
                ));
            }
            Ok(contents)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn mask_record(labels: &[u8]) -> TargetRecord {
        TargetRecord {
            name: "tumour".into(),
            kind: TargetKind::Mask,
            format: "nifti".into(),
            upload_bytes: 10,
            created_at: "2026-12-03T08:00:00Z".into(),
            file_name: "tumour.nii.gz".into(),
            labels: labels
                .iter()
                .map(|&label| MaskLabel {
                    label,
                    voxels: 10,
                    volume_ml: 1.0,
                })
                .collect(),
            rois: vec![],
            notes: vec![],
        }
    }

    fn rtstruct_record() -> TargetRecord {
        TargetRecord {
            kind: TargetKind::Rtstruct,
            format: "dicom".into(),
            file_name: "plan.dcm".into(),
            labels: vec![],
            rois: vec![
                StructureRoi {
                    name: "GTV".into(),
                    voxels: Some(40),
                    volume_ml: Some(4.0),
                    problem: None,
                },
                StructureRoi {
                    name: "Cord".into(),
                    voxels: None,
                    volume_ml: None,
                    problem: Some("ROI Cord, contour 1: off the CT's slices".into()),
                },
            ],
            ..mask_record(&[])
        }
    }

    #[test]
    fn names_are_plain_file_names_and_paths_are_refused_by_name() {
        for good in ["tumour", "GTV-mask_2.v1", "a", &"x".repeat(64)] {
            assert!(check_target_name(good).is_ok(), "{good}");
        }
        for (bad, says) in [
            ("", "1 to 64"),
            (&"x".repeat(65), "1 to 64"),
            ("../scan", "'/'"),
            ("a/b", "'/'"),
            ("a\\b", "'\\\\'"),
            ("..", "no \"..\""),
            (".hidden", "start with a letter"),
            ("a..b", "no \"..\""),
            ("tümor", "'ü'"),
            ("a b", "' '"),
        ] {
            let e = check_target_name(bad).unwrap_err();
            assert!(e.contains(says), "{bad:?}: {e}");
        }
    }

    #[test]
    fn request_targets_are_a_point_or_an_upload_with_a_label_or_an_roi() {
        let point = parse_request_target(Value::from("point:1,2,3:r=5")).unwrap();
        assert_eq!(point, JobTarget::Point("point:1,2,3:r=5".into()));
        let upload =
            parse_request_target(serde_json::json!({"upload": "tumour", "label": 8})).unwrap();
        let JobTarget::Upload(choice) = &upload else {
            panic!("{upload:?}")
        };
        assert_eq!((choice.label, choice.roi.as_deref()), (Some(8), None));
        // A stored request reads back as it was written, and an old point string still reads.
        let stored: JobTarget =
            serde_json::from_str(&serde_json::to_string(&upload).unwrap()).unwrap();
        assert_eq!(stored, upload);
        let old: JobTarget = serde_json::from_str("\"point:1,2,3:r=5\"").unwrap();
        assert_eq!(old, point);
        for (bad, says) in [
            (Value::from("/etc/passwd:label=1"), "never as a path"),
            (Value::from("point:1,2:r=5"), "2 coordinate(s)"),
            (serde_json::json!({"upload": "../x"}), "'/'"),
            (serde_json::json!({"upload": "t", "label": 0}), "background"),
            (serde_json::json!({"upload": "t", "label": 300}), "300"),
            (
                serde_json::json!({"upload": "t", "label": 1, "roi": "GTV"}),
                "together",
            ),
            (serde_json::json!({"upload": "t", "roi": " "}), "empty"),
            (serde_json::json!({"upload": "t", "path": "/x"}), "path"),
            (serde_json::json!({"upload": "t", "file": "/x"}), "file"),
            (serde_json::json!({"label": 2}), "upload"),
            (serde_json::json!(7), "a target is"),
        ] {
            let e = parse_request_target(bad.clone()).unwrap_err();
            assert!(
                e.status == 422 && e.detail.contains(says),
                "{bad}: {e} (wanted {says:?})"
            );
        }
    }

    #[test]
    fn a_choice_is_checked_against_the_scans_upload() {
        let choice = |label: Option<u8>, roi: Option<&str>| TargetChoice {
            upload: "tumour".into(),
            label,
            roi: roi.map(Into::into),
            file: None,
        };
        let mask = mask_record(&[3, 8]);
        assert!(choose(&choice(Some(8), None), Some(&mask), &[]).is_ok());
        assert!(choose(&choice(None, None), Some(&mask), &[]).is_ok());
        let rs = rtstruct_record();
        assert!(choose(&choice(None, Some("GTV")), Some(&rs), &[]).is_ok());
        assert!(choose(&choice(None, Some(" gtv ")), Some(&rs), &[]).is_ok());
        for (c, record, says) in [
            (
                choice(Some(8), None),
                None,
                "no uploaded target \"tumour\" (it has a, b)",
            ),
            (
                choice(Some(5), None),
                Some(&mask),
                "label 5 is not in the mask; labels present: 3 (1.0 mL), 8 (1.0 mL)",
            ),
            (choice(None, Some("GTV")), Some(&mask), "is a mask"),
            (choice(None, None), Some(&rs), "ROIs present: GTV, Cord"),
            (choice(Some(1), Some("GTV")), Some(&rs), "not a label"),
            (
                choice(None, Some("PTV")),
                Some(&rs),
                "no ROI named `PTV`; ROIs present: GTV, Cord",
            ),
            (choice(None, Some("Cord")), Some(&rs), "off the CT's slices"),
        ] {
            let e = choose(&c, record, &["a".into(), "b".into()]).unwrap_err();
            assert!(
                e.status == 422 && e.detail.contains(says),
                "{e} (wanted {says:?})"
            );
        }
    }

    #[test]
    fn a_job_target_becomes_the_clis_spec_on_the_jobs_copy() {
        let dir = Path::new("/store/jobs/j/target");
        let rs = JobTarget::Upload(TargetChoice {
            upload: "plan".into(),
            label: None,
            roi: Some("GTV".into()),
            file: Some("plan.dcm".into()),
        });
        assert_eq!(
            rs.spec(dir).unwrap(),
            TargetSpec::Rtstruct {
                path: dir.join("plan.dcm"),
                roi: "GTV".into()
            }
        );
        let mask = JobTarget::Upload(TargetChoice {
            upload: "tumour".into(),
            label: Some(8),
            roi: None,
            file: Some("tumour.nii.gz".into()),
        });
        assert_eq!(
            mask.spec(dir).unwrap(),
            TargetSpec::Mask {
                path: dir.join("tumour.nii.gz"),
                label: Some(8)
            }
        );
        let uncopied = JobTarget::Upload(TargetChoice {
            file: None,
            ..match mask {
                JobTarget::Upload(c) => c,
                JobTarget::Point(_) => unreachable!(),
            }
        });
        assert!(uncopied.spec(dir).is_err());
    }
}
