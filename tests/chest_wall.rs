//! The chest wall that moves (issue 14, part 2): the costal wall sweeps the share of every
//! breath that was asked, the diaphragm takes the rest, a share of 0 is the rigid wall bit
//! for bit, the dynamic path moves the wall too, and bad shares are refused by name.

mod common;

use std::path::PathBuf;

use lungmotion::breathing::{BreathingTrace, OutputInstants};
use lungmotion::ingest::lung_model::{ConstraintGroup, LungModel};
use lungmotion::ingest::pipeline::ingest_scan;
use lungmotion::ingest::scan::load_ct;
use lungmotion::math::V3;
use lungmotion::model::Material;
use lungmotion::motion::dynamic::{run_dynamic, DynamicSettings};
use lungmotion::motion::{lung_scene, move_costal_wall, run_motion, MotionSettings};
use lungmotion::run::RunConfig;
use lungmotion::simulation::Scene;

/// The bundled phantom's lungs at 12 mm, as `lungmotion run` ingests them.
fn phantom_model() -> LungModel {
    let ct = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("sample-volumes/phantom-ct.nii.gz");
    let config = RunConfig::from_toml("element_size_mm = 12.0").unwrap();
    let scan = load_ct(&ct).unwrap();
    ingest_scan(&scan, &config.ingest_settings()).unwrap().model
}

/// A 300 mL breath in, sampled every 0.25 s over 2 s.
fn breath_in() -> BreathingTrace {
    let times: Vec<f64> = (0..=8).map(|i| i as f64 * 0.25).collect();
    let volumes = times
        .iter()
        .map(|t| 150.0 * (1.0 - (std::f64::consts::PI * t / 2.0).cos()))
        .collect();
    BreathingTrace::new(times, volumes).unwrap()
}

fn settings(share: f64) -> MotionSettings {
    MotionSettings {
        instants: OutputInstants::EverySample,
        rib_cage_share: share,
        ..MotionSettings::default()
    }
}

/// Every frame's node positions and summary of a quasi-static run.
fn run(scene: &Scene, share: f64) -> (lungmotion::motion::MotionReport, Vec<Vec<V3>>) {
    let mut positions = Vec::new();
    let report = run_motion(
        scene,
        &Material::LUNG,
        &breath_in(),
        &settings(share),
        &mut |_, x| {
            positions.push(x.to_vec());
            Ok(())
        },
    )
    .unwrap();
    (report, positions)
}

fn mean_dz_mm(model: &LungModel, scene: &Scene, x: &[V3], group: ConstraintGroup) -> f64 {
    let nodes = model.group_nodes(group);
    let rest = &scene.mesh.rest_positions_m;
    nodes
        .iter()
        .map(|&n| (x[n as usize].z - rest[n as usize].z) * 1e3)
        .sum::<f64>()
        / nodes.len() as f64
}

#[test]
fn the_wall_sweeps_the_share_asked_and_the_diaphragm_descends_less() {
    let model = phantom_model();
    let rigid = lung_scene(&model).unwrap();
    let mut moving = lung_scene(&model).unwrap();
    let wall = move_costal_wall(&mut moving, &model);
    assert!(
        wall.moving_nodes > wall.costal_nodes / 4 && wall.moving_nodes < wall.costal_nodes,
        "{wall:?}: the anterior and lateral costal wall moves, the posterior wall does not"
    );

    // The wall's motion has no step where the costal face meets a face that stays: a costal
    // node one edge from a mediastinal, diaphragmatic or apex node moves at most half as far
    // as the rule allows (1 mm per unit, times at most √2 for the two normal components).
    let rest = &moving.mesh.rest_positions_m;
    let still = |n: u32| {
        matches!(
            ConstraintGroup::from_code(model.node_group[n as usize]),
            Some(
                ConstraintGroup::Mediastinal
                    | ConstraintGroup::Diaphragmatic
                    | ConstraintGroup::Apex
            )
        )
    };
    let mut beside_still = vec![false; rest.len()];
    for corners in &moving.mesh.elements {
        for (a, b) in lungmotion::model::mesh::HEX_EDGES {
            let (a, b) = (corners[a], corners[b]);
            beside_still[a as usize] |= still(b);
            beside_still[b as usize] |= still(a);
        }
    }
    let mut checked = 0;
    for (n, c) in &moving.constraints.entries {
        if let lungmotion::model::NodeConstraint::Plane { point_m, normal } = c {
            let offset_mm = (point_m - rest[*n as usize]).dot(normal) * 1e3;
            if beside_still[*n as usize] && offset_mm > 0.0 {
                assert!(
                    offset_mm <= 0.5 * 2f64.sqrt() + 1e-9,
                    "node {n}: {offset_mm} mm"
                );
                checked += 1;
            }
        }
    }
    assert!(checked > 0);

    let (r0, x0) = run(&rigid, 0.0);
    let (r1, x1) = run(&moving, 1.0 / 3.0);
    assert_eq!(r0.chest_wall.scale, 0.0);
    assert!(r1.chest_wall.scale > 0.0, "{:?}", r1.chest_wall);
    for f in r1.frames.iter().filter(|f| f.simulated_volume_ml > 50.0) {
        let share = f.chest_wall_volume_ml / f.simulated_volume_ml;
        assert!(
            (share - 1.0 / 3.0).abs() < 0.02,
            "frame {} at {:.1} mL: the wall swept {:.1} mL, a share of {share:.3}",
            f.index,
            f.simulated_volume_ml,
            f.chest_wall_volume_ml
        );
        assert!(
            (f.simulated_volume_ml - f.target_volume_ml).abs() < 2.0,
            "{f:?}"
        );
    }
    // End-inhale (2 s, +300 mL): the base takes about two thirds of the breath instead of all.
    let end = r1.frames.len() - 1;
    assert!((r1.frames[end].target_volume_ml - 300.0).abs() < 1e-6);
    let base_rigid = mean_dz_mm(&model, &rigid, &x0[end], ConstraintGroup::Diaphragmatic);
    let base_moving = mean_dz_mm(&model, &moving, &x1[end], ConstraintGroup::Diaphragmatic);
    assert!(
        base_rigid < 0.0 && base_moving < 0.0 && base_moving > 0.85 * base_rigid,
        "base descends {base_moving:.2} mm with the moving wall, {base_rigid:.2} mm on a rigid one"
    );
    // The moving costal nodes stay on their moved planes, outward of where they were.
    let lambda = r1.frames[end].pressure_pa / lungmotion::motion::REFERENCE_PRESSURE_PA;
    let outward: Vec<f64> = model
        .group_nodes(ConstraintGroup::Costal)
        .iter()
        .filter_map(|&n| match moving.constraints.get(n)? {
            lungmotion::model::NodeConstraint::Plane { point_m, normal } => {
                let n = n as usize;
                let offset = (point_m - rest[n]).dot(normal) * lambda * r1.chest_wall.scale;
                let moved = (x1[end][n] - rest[n]).dot(normal);
                assert!(
                    (moved - offset).abs() < 1e-9,
                    "node {n}: {moved} vs {offset}"
                );
                (offset > 0.0).then_some(offset * 1e3)
            }
            _ => None,
        })
        .collect();
    assert_eq!(outward.len(), wall.moving_nodes);
    let largest = outward.iter().cloned().fold(0.0, f64::max);
    assert!(
        largest > 0.5 && largest < 20.0,
        "largest wall offset {largest:.2} mm"
    );
}

#[test]
fn a_share_of_zero_is_the_rigid_wall_bit_for_bit() {
    let model = phantom_model();
    let rigid = lung_scene(&model).unwrap();
    let mut moving = lung_scene(&model).unwrap();
    move_costal_wall(&mut moving, &model);
    let (_, x0) = run(&rigid, 0.0);
    let (_, x1) = run(&moving, 0.0);
    assert_eq!(x0, x1);
}

#[test]
fn a_share_without_a_moving_wall_or_out_of_range_is_refused_by_name() {
    let model = phantom_model();
    let rigid = lung_scene(&model).unwrap();
    let err = run_motion(
        &rigid,
        &Material::LUNG,
        &breath_in(),
        &settings(0.3),
        &mut |_, _| Ok(()),
    )
    .unwrap_err()
    .to_string();
    assert!(err.contains("no constraint of this scene moves"), "{err}");
    for bad in ["0.95", "-0.1", "nan"] {
        let err = RunConfig::from_toml(&format!("[motion]\nrib_cage_share = {bad}"))
            .and_then(|c| c.validate())
            .unwrap_err()
            .to_string();
        assert!(err.contains("motion.rib_cage_share"), "{bad}: {err}");
    }
    assert_eq!(
        RunConfig::default().motion.rib_cage_share,
        lungmotion::motion::PHYSIOLOGICAL_RIB_CAGE_SHARE
    );
    let out = common::absent_temp_dir("chest-wall-cli");
    let cli = common::bin()
        .args(["run", "--ct"])
        .arg(common::sample("phantom-ct.nii.gz"))
        .args(["--trace", "missing.csv", "--out"])
        .arg(&out)
        .args(["--rib-cage-share", "1.5"])
        .output()
        .unwrap();
    assert_eq!(cli.status.code(), Some(2));
    let stderr = String::from_utf8_lossy(&cli.stderr);
    assert!(stderr.contains("rib_cage_share 1.5"), "{stderr}");
    assert!(!out.exists());
}

#[test]
fn the_dynamic_path_moves_the_wall_with_the_bellows_pressure() {
    let model = phantom_model();
    let mut moving = lung_scene(&model).unwrap();
    move_costal_wall(&mut moving, &model);
    let settings = DynamicSettings {
        rib_cage_share: 1.0 / 3.0,
        ..DynamicSettings::default()
    };
    let times = [1.0, 2.0];
    let report = run_dynamic(&moving, &breath_in(), &settings, &times, &mut |_, x| {
        assert!(x.iter().all(|p| p.iter().all(|c| c.is_finite())));
        Ok(())
    })
    .unwrap();
    assert!(report.chest_wall.scale > 0.0);
    let last = report.frames.last().unwrap();
    let share = last.chest_wall_volume_ml / last.simulated_volume_ml;
    assert!(
        (share - 1.0 / 3.0).abs() < 0.05,
        "end-inhale: wall {:.1} mL of {:.1} mL ({share:.3})",
        last.chest_wall_volume_ml,
        last.simulated_volume_ml
    );
}
