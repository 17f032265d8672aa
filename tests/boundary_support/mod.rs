//! Helpers shared by the boundary tests (the curved wall, the sliding diaphragm): the bundled
//! phantom's lungs at 12 mm under a given configuration, a 400 mL breath in, and the
//! end-inhale state of a quasi-static run through it.

use std::path::PathBuf;

use lungmotion::breathing::{BreathingTrace, OutputInstants};
use lungmotion::ingest::lung_model::LungModel;
use lungmotion::ingest::pipeline::ingest_scan;
use lungmotion::ingest::scan::load_ct;
use lungmotion::math::V3;
use lungmotion::model::Material;
use lungmotion::motion::{run_motion, MotionReport, MotionSettings};
use lungmotion::run::RunConfig;
use lungmotion::simulation::Scene;

/// The bundled phantom's lungs at 12 mm, built with the run configuration lines `config`.
pub fn phantom_model(config: &str) -> LungModel {
    let ct = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("sample-volumes/phantom-ct.nii.gz");
    let config = RunConfig::from_toml(&format!("element_size_mm = 12.0\n{config}")).unwrap();
    let scan = load_ct(&ct).unwrap();
    ingest_scan(&scan, &config.ingest_settings()).unwrap().model
}

/// A 400 mL breath in, sampled every 0.5 s over 2 s.
pub fn breath_in() -> BreathingTrace {
    let times: Vec<f64> = (0..=4).map(|i| i as f64 * 0.5).collect();
    let volumes = times
        .iter()
        .map(|t| 200.0 * (1.0 - (std::f64::consts::PI * t / 2.0).cos()))
        .collect();
    BreathingTrace::new(times, volumes).unwrap()
}

/// The report of a quasi-static run of `scene` through [`breath_in`] with the rib cage making
/// `share` of it, and its end-inhale positions.
pub fn end_inhale(scene: &Scene, share: f64) -> (MotionReport, Vec<V3>) {
    let settings = MotionSettings {
        instants: OutputInstants::EverySample,
        rib_cage_share: share,
        ..MotionSettings::default()
    };
    let mut last = Vec::new();
    let report = run_motion(
        scene,
        &Material::LUNG,
        &breath_in(),
        &settings,
        &mut |_, x| {
            last = x.to_vec();
            Ok(())
        },
    )
    .unwrap();
    (report, last)
}
