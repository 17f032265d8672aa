//! Smoke test of the motion benchmark's quick mode on the CIP case (8 mm, one cycle):
//! the report must be coherent, whatever the speed of the machine.
#![cfg(feature = "bench")]

use lungmotion::bench::motion::{run_motion_bench, MotionBenchOptions};
use lungmotion::bench::Outcome;

#[test]
#[cfg_attr(
    any(not(feature = "slow-tests"), not(shared_data)),
    ignore = "slow study (motion benchmark): cargo test --features slow-tests with the shared CT data (../shared/data)"
)]
fn quick_motion_bench_reports_a_coherent_cycle() {
    let report = run_motion_bench(&MotionBenchOptions::quick()).expect("benchmark ran");
    let md = report.to_markdown();
    let json = serde_json::to_string(&report).expect("report serialises");
    assert!(md.contains("## 8 mm elements"), "{md}");
    if lungmotion::datasets::cip_chest_ct64().is_none() {
        assert!(
            matches!(report.sizes[0].cycle, Outcome::Skipped(_)),
            "{json}"
        );
        println!("skipped: shared data not found");
        return;
    }
    println!("{md}");
    assert_eq!(report.sizes.len(), 1);
    let size = &report.sizes[0];
    let build = size.build.measured().expect("model built");
    assert!(build.elements > 0 && build.nodes > build.elements, "{json}");
    assert!(build.sampled_voxels > 0, "{json}");
    let cycle = size.cycle.measured().expect("8 mm cycle ran");
    assert_eq!(cycle.frames, 10);
    assert_eq!(cycle.frame_wall_s.len(), 10);
    assert!(cycle.time.median_s > 0.0 && cycle.time.median_s.is_finite());
    assert!(cycle.keys >= 3, "{json}");
    assert!((cycle.tidal_volume_ml - 500.0).abs() < 25.0, "{json}");
    let curved = size.wall_surface.measured().expect("curved-wall cycle ran");
    assert_eq!(curved.cycle.frames, 10);
    assert!(curved.ratio_to_tangent_planes > 0.0 && curved.ratio_to_tangent_planes.is_finite());
    assert!(curved.nodes_on_planes < build.nodes, "{json}");
    assert!(
        (curved.cycle.tidal_volume_ml - 500.0).abs() < 25.0,
        "{json}"
    );
    let serving = size.serving.measured().expect("fields served");
    assert_eq!(serving.fields, 10);
    assert!(serving.fields_per_s > 0.0 && serving.fields_per_s.is_finite());
    // Producing node positions alone cannot be slower than positions plus sampling.
    assert!(serving.node_states_per_s >= serving.fields_per_s, "{json}");
    let accuracy = size.accuracy.measured().expect("accuracy measured");
    assert_eq!(accuracy.frames.len(), 10);
    for f in &accuracy.frames {
        assert!(f.node_difference_mm.is_finite() && f.field_difference_mm.is_finite());
        assert!(f.interpolated_volume_ml.is_finite() && f.direct_volume_ml.is_finite());
    }
    // Some frame moves: the interpolated and direct volumes follow a 500 mL curve.
    let largest = accuracy
        .frames
        .iter()
        .map(|f| f.direct_volume_ml)
        .fold(0.0, f64::max);
    assert!(largest > 400.0, "{json}");
}

#[test]
#[cfg_attr(
    any(not(feature = "slow-tests"), not(shared_data)),
    ignore = "slow study (motion benchmark on the POPI CT): cargo test --features slow-tests with the shared CT data (../shared/data)"
)]
fn popi_serving_alone_reports_lung_box_fields_on_the_full_ct() {
    let options = MotionBenchOptions {
        element_sizes_mm: Vec::new(),
        popi_serving: true,
        ..MotionBenchOptions::quick()
    };
    let report = run_motion_bench(&options).expect("benchmark ran");
    let json = serde_json::to_string(&report).expect("report serialises");
    if lungmotion::datasets::popi_chest_ct().is_none() {
        assert!(matches!(report.popi, Outcome::Skipped(_)), "{json}");
        println!("skipped: shared data not found");
        return;
    }
    let md = report.to_markdown();
    println!("{md}");
    assert!(md.contains("the POPI CT"), "{md}");
    let popi = report.popi.measured().expect("POPI fields served");
    assert_eq!(popi.build.ct_dims, [512, 512, 141], "{json}");
    assert_eq!(popi.element_size_mm, 6.0, "the run's default element size");
    let serving = &popi.serving;
    assert_eq!(serving.fields, 10);
    // The lung box, not the CT grid: a fraction of the CT's 37 M voxels, far more than CIP's.
    let ct_voxels = 512 * 512 * 141;
    assert!(
        serving.voxels_per_field > 1_000_000 && serving.voxels_per_field < ct_voxels / 2,
        "{json}"
    );
    assert!(serving.fields_per_s > 0.0 && serving.fields_per_s.is_finite());
    assert!(serving.node_states_per_s >= serving.fields_per_s, "{json}");
}
