//! Where the third-party reference CTs live: `$LUNGMOTION_SHARED_DATA` if set, otherwise
//! `../shared/data` beside the checkout. Tests and benchmarks that need them report
//! themselves skipped when they are absent, so a fresh machine runs on the bundled phantom.

use std::path::PathBuf;

/// Environment variable that points at the reference data directory.
pub const SHARED_DATA_ENV: &str = "LUNGMOTION_SHARED_DATA";

/// The reference data directory, if it exists.
pub fn shared_data_dir() -> Option<PathBuf> {
    let dir = match std::env::var_os(SHARED_DATA_ENV) {
        Some(d) => PathBuf::from(d),
        None => PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../shared/data"),
    };
    dir.is_dir().then_some(dir)
}

/// The CIP chest CT case (`ct-64.nrrd`, `lm-64.nrrd`, `dicom/`), if present.
pub fn cip_chest_ct64() -> Option<PathBuf> {
    shared_data_dir()
        .map(|d| d.join("cip-chest-ct64"))
        .filter(|d| d.is_dir())
}

/// The POPI full-resolution chest CT DICOM series (512 × 512 × 141), if present.
pub fn popi_chest_ct() -> Option<PathBuf> {
    shared_data_dir()
        .map(|d| d.join("popi-chest-ct").join("dicom"))
        .filter(|d| d.is_dir())
}

/// The MIMIC respiration waveform (a chest belt's signal, `time_s,value` at 125 Hz), if present.
pub fn mimic_respiration_waveform() -> Option<PathBuf> {
    shared_data_dir()
        .map(|d| d.join("respiration-mimic").join("03700181_RESP.csv"))
        .filter(|f| f.is_file())
}

/// The TotalSegmentator abdomen case (JPEG 2000 DICOM and a RAS NIfTI), if present.
pub fn totalseg_abdomen_ct() -> Option<PathBuf> {
    shared_data_dir()
        .map(|d| d.join("totalseg-abdomen-ct"))
        .filter(|d| d.is_dir())
}

/// Code of the trachea and main bronchi outside the lungs in [`cip_expert_labels`].
pub const CIP_AIRWAY_LABEL: u8 = 3;

/// Decodes the CIP expert map `lm-64.nrrd` (`region + 256 × type`, see the data's README) into
/// 1 right lung, 2 left lung, [`CIP_AIRWAY_LABEL`] trachea and main bronchi outside the lungs.
pub fn cip_expert_labels(lm: &crate::volume::Volume<f32>) -> crate::volume::Volume<u8> {
    lm.map(|v| {
        let code = v as u32;
        match code & 0xFF {
            12..=14 => 1,
            9..=11 => 2,
            _ if code == 512 => CIP_AIRWAY_LABEL,
            _ => 0,
        }
    })
}

/// The CIP expert map split as the lung model takes it: lungs (1 right, 2 left) and the
/// airways outside them (1); `None` without the shared data.
pub fn cip_expert_lung_masks(
) -> Option<crate::Result<(crate::volume::Volume<u8>, crate::volume::Volume<u8>)>> {
    let dir = cip_chest_ct64()?;
    Some(
        crate::formats::nrrd::read_nrrd(&dir.join("lm-64.nrrd")).map(|lm| {
            let labels = cip_expert_labels(&lm);
            let lungs = labels.map(|l| if l == CIP_AIRWAY_LABEL { 0 } else { l });
            let airways = labels.map(|l| u8::from(l == CIP_AIRWAY_LABEL));
            (lungs, airways)
        }),
    )
}

/// Builds the CIP chest CT's lung model (expert lung labels, airways for the hilum) at
/// `element_size_mm`; fails naming the directory when the shared data is missing.
pub fn cip_lung_model(element_size_mm: f64) -> crate::Result<crate::ingest::lung_model::LungModel> {
    cip_lung_model_of(element_size_mm, crate::model::Material::default())
}

/// [`cip_lung_model`] with another material.
pub fn cip_lung_model_of(
    element_size_mm: f64,
    material: crate::model::Material,
) -> crate::Result<crate::ingest::lung_model::LungModel> {
    let (lungs, airways) = cip_expert_lung_masks().ok_or_else(|| crate::Error::MissingData {
        what: "the CIP chest CT (cip-chest-ct64)".into(),
        path: None,
        hint: format!("set {SHARED_DATA_ENV} to the shared data directory"),
    })??;
    crate::ingest::lung_model::build_lung_model(
        &lungs,
        &airways,
        &crate::ingest::lung_model::LungModelSettings {
            element_size_mm,
            material,
            ..Default::default()
        },
    )
}
