//! The demo job: the bundled phantom CT, a generated tidal breathing curve and the phantom's
//! landmarks as tracked points, so `lungmotion demo` needs no file from the user.

use std::path::{Path, PathBuf};

use super::{RunConfig, RunInputs, TrackedPoint};
use crate::breathing::LujanBreathing;
use crate::outputs::radiotherapy::target::TargetSpec;
use crate::{Error, IoContext, IoOp, Result};

/// Sample rate of the generated demo curve, Hz (a spirometer records 25–100 Hz).
pub const DEMO_SAMPLE_RATE_HZ: f64 = 25.0;
/// Breaths in the demo curve.
pub const DEMO_BREATHS: f64 = 2.0;
/// How far inside the lung the apex and base points are placed from the phantom's landmarks,
/// mm (the landmarks lie on the lung boundary).
const LANDMARK_INSET_MM: f64 = 15.0;
/// Label of the tumour in `phantom-truth.nii.gz`, the demo's target.
pub const PHANTOM_TUMOUR_LABEL: u8 = 8;

/// Where the bundled sample volumes are: `./sample-volumes` when run from the repository,
/// else the directory the binary was built from.
pub fn sample_volumes_dir() -> PathBuf {
    let here = PathBuf::from("sample-volumes");
    if here.join("phantom.json").is_file() {
        here
    } else {
        Path::new(env!("CARGO_MANIFEST_DIR")).join("sample-volumes")
    }
}

/// The demo's settings: elements of `element_size_mm` and every output a radiotherapy team
/// loads: the virtual 4D-CT as NIfTI and DICOM and the DICOM registrations.
pub fn demo_config(element_size_mm: f64) -> RunConfig {
    let mut config = RunConfig {
        element_size_mm,
        ..RunConfig::default()
    };
    config.outputs.registration = true;
    config.outputs.virtual_ct = crate::outputs::radiotherapy::virtual_ct::VirtualCtOutput::Both;
    config
}

/// Inputs of the demo: the phantom's DICOM series, two Lujan breaths of 500 mL (4 s period,
/// the CT at end-exhale), tracked points at the tumour, the right apex and the right base, and
/// the tumour as the target.
pub fn demo_inputs(sample_dir: &Path) -> Result<RunInputs> {
    let description = sample_dir.join("phantom.json");
    if !description.is_file() {
        return Err(Error::MissingData {
            what: "the demo's phantom description".into(),
            path: Some(description),
            hint: "run from the repository or regenerate it with `lungmotion phantom`".into(),
        });
    }
    let text = std::fs::read_to_string(&description).at(IoOp::Read, &description)?;
    let malformed = |reason: String| Error::Format {
        path: description.clone(),
        reason,
    };
    let json: serde_json::Value =
        serde_json::from_str(&text).map_err(|e| malformed(e.to_string()))?;
    let landmark = |name: &str, dz_mm: f64| -> Result<Option<TrackedPoint>> {
        let v = &json["landmarks"][format!("{name}_lps_mm")];
        if v.is_null() {
            return Ok(None);
        }
        let p: [f64; 3] = serde_json::from_value(v.clone())
            .map_err(|e| malformed(format!("landmark {name}: {e}")))?;
        Ok(Some(TrackedPoint {
            name: name.trim_end_matches("_centre").to_string(),
            rest_lps_mm: [p[0], p[1], p[2] + dz_mm],
        }))
    };
    let points = [
        landmark("tumour_centre", 0.0)?,
        landmark("right_lung_apex", -LANDMARK_INSET_MM)?,
        landmark("right_lung_base", LANDMARK_INSET_MM)?,
    ]
    .into_iter()
    .flatten()
    .collect();
    let curve = LujanBreathing::default();
    let trace = curve.trace(DEMO_BREATHS * curve.period_s, DEMO_SAMPLE_RATE_HZ)?;
    Ok(RunInputs {
        ct_path: sample_dir.join("phantom-dicom"),
        trace,
        trace_source: format!(
            "generated: Lujan cos^{} breathing, {} mL tidal, {} s period, {} breaths at {} Hz",
            2 * curve.exponent,
            curve.tidal_volume_ml,
            curve.period_s,
            DEMO_BREATHS,
            DEMO_SAMPLE_RATE_HZ
        ),
        points,
        // The phantom's tumour (label 8 of its truth labels, on the CT's grid).
        target: Some(TargetSpec::Mask {
            path: sample_dir.join("phantom-truth.nii.gz"),
            label: Some(PHANTOM_TUMOUR_LABEL),
        }),
    })
}
