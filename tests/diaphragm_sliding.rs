//! The diaphragm the base slides on (issue 14, part 3): with `diaphragm = "sliding"` the
//! diaphragmatic nodes stay on their descending surfaces and slide along them (the piston's
//! nodes keep their x and y), the rib cage makes the share of the volume asked, the dome
//! flattens as asked, and what the mode cannot do is refused by name.

mod boundary_support;

use boundary_support::{breath_in, end_inhale, phantom_model};
use lungmotion::ingest::lung_model::{ConstraintGroup, LungModel};
use lungmotion::math::V3;
use lungmotion::model::NodeConstraint;
use lungmotion::motion::dynamic::{run_dynamic, DynamicSettings};
use lungmotion::motion::{run_scene, WallMotion};
use lungmotion::run::RunConfig;
use lungmotion::simulation::Scene;

/// Mean horizontal (LPS x–y) displacement of the diaphragmatic nodes, mm.
fn mean_horizontal_mm(model: &LungModel, scene: &Scene, x: &[V3]) -> f64 {
    let nodes = model.group_nodes(ConstraintGroup::Diaphragmatic);
    let rest = &scene.mesh.rest_positions_m;
    nodes
        .iter()
        .map(|&n| {
            let d = x[n as usize] - rest[n as usize];
            d.x.hypot(d.y) * 1e3
        })
        .sum::<f64>()
        / nodes.len() as f64
}

/// Vertical descent per unit of motion implied by each diaphragmatic plane's offset, with
/// the node's rest height and lung: a plane moved down by δ moves by −δ·n_z along n.
fn plane_descents(model: &LungModel, scene: &Scene) -> Vec<(f64, f64, u8)> {
    let rest = &scene.mesh.rest_positions_m;
    let lung = model.node_lung();
    model
        .group_nodes(ConstraintGroup::Diaphragmatic)
        .into_iter()
        .filter_map(|n| match scene.constraints.get(n) {
            Some(NodeConstraint::Plane { point_m, normal }) if normal.z < -0.3 => {
                let r = rest[n as usize];
                Some(((point_m - r).dot(normal) / -normal.z, r.z, lung[n as usize]))
            }
            _ => None,
        })
        .collect()
}

#[test]
fn the_base_slides_on_the_descending_dome_and_the_piston_does_not() {
    let share = 1.0 / 3.0;
    let sliding = phantom_model("diaphragm = \"sliding\"");
    let piston = phantom_model("diaphragm = \"cranio_caudal\"");
    let walls = WallMotion {
        rib_cage_share: share,
        dome_flattening: 0.0,
        ..WallMotion::default()
    };
    let scene = run_scene(&sliding, &walls).unwrap();
    let costal_part = scene.walls_make_volume.expect("the walls make the volume");
    let piston_scene = run_scene(&piston, &walls).unwrap();
    assert!(piston_scene.walls_make_volume.is_none());

    let (report, x) = end_inhale(&scene, share);
    let (_, xp) = end_inhale(&piston_scene, share);
    let end = report.frames.last().unwrap();
    assert!((end.target_volume_ml - 400.0).abs() < 1e-6);
    assert!((end.simulated_volume_ml - 400.0).abs() < 2.0, "{end:?}");

    // Every diaphragmatic node is on its surface where the walls have gone.
    let factor =
        end.pressure_pa / lungmotion::motion::REFERENCE_PRESSURE_PA * report.chest_wall.scale;
    let rest = &scene.mesh.rest_positions_m;
    let moved = scene.constraints.at_load_factor(rest, factor);
    let mut held = 0;
    for n in sliding.group_nodes(ConstraintGroup::Diaphragmatic) {
        let Some(NodeConstraint::Plane { point_m, normal }) = moved.get(n) else {
            continue;
        };
        let off_mm = (x[n as usize] - point_m).dot(normal).abs() * 1e3;
        assert!(
            off_mm < 1e-6,
            "node {n} is {off_mm} mm off its descended plane"
        );
        held += 1;
    }
    assert!(held > 20, "{held} diaphragmatic nodes on planes");

    // The base descends and slides along the dome; the piston's nodes keep x and y.
    let descent_mm = sliding
        .group_nodes(ConstraintGroup::Diaphragmatic)
        .iter()
        .map(|&n| (x[n as usize].z - rest[n as usize].z) * 1e3)
        .sum::<f64>()
        / held as f64;
    assert!(descent_mm < -1.0, "the base moved {descent_mm} mm in z");
    let slide_mm = mean_horizontal_mm(&sliding, &scene, &x);
    let piston_slide_mm = mean_horizontal_mm(&piston, &piston_scene, &xp);
    assert!(
        piston_slide_mm < 1e-9,
        "the piston's base moved {piston_slide_mm} mm sideways"
    );
    assert!(
        slide_mm > 0.1,
        "the sliding base moved only {slide_mm} mm sideways"
    );

    // The rib cage makes the share of the volume asked: its sweep was raised above the
    // share of the walls' sweep, because the lung also slides along the walls and the
    // pressure swells it, which neither wall sweeps.
    assert!(
        costal_part > share && costal_part < share + 0.1,
        "the costal wall makes {costal_part} of the walls' sweep"
    );
    for f in report
        .frames
        .iter()
        .filter(|f| f.simulated_volume_ml > 50.0)
    {
        let walls_ml = f.chest_wall_volume_ml / costal_part;
        let reported = f.chest_wall_volume_ml / f.simulated_volume_ml;
        assert!(
            (walls_ml - f.simulated_volume_ml).abs() < 0.15 * f.simulated_volume_ml,
            "frame {}: the walls swept {walls_ml:.1} of {:.1} mL",
            f.index,
            f.simulated_volume_ml
        );
        assert!(
            (reported - share).abs() < 0.02,
            "frame {}: a rib-cage share of {reported:.3}",
            f.index
        );
    }
}

#[test]
fn a_share_of_zero_puts_the_whole_breath_on_the_diaphragm() {
    let model = phantom_model("diaphragm = \"sliding\"");
    let walls = WallMotion {
        rib_cage_share: 0.0,
        dome_flattening: 0.0,
        ..WallMotion::default()
    };
    let scene = run_scene(&model, &walls).unwrap();
    let costal = model.group_nodes(ConstraintGroup::Costal);
    let rest = &scene.mesh.rest_positions_m;
    assert_eq!(scene.imposed_sweep_ml(|n| costal.contains(&n)), 0.0);
    let sweep = scene.imposed_sweep_ml(|_| true);
    assert!((sweep - 1.0).abs() < 1e-6, "one unit sweeps {sweep} mL");
    let (report, x) = end_inhale(&scene, 0.0);
    let end = report.frames.last().unwrap();
    assert_eq!(end.chest_wall_volume_ml, 0.0);
    assert!((end.simulated_volume_ml - 400.0).abs() < 2.0, "{end:?}");
    let base_dz_mm = model
        .group_nodes(ConstraintGroup::Diaphragmatic)
        .iter()
        .map(|&n| (x[n as usize].z - rest[n as usize].z) * 1e3)
        .fold(0.0, f64::min);
    assert!(
        base_dz_mm < -2.0,
        "the base descended at most {base_dz_mm} mm"
    );
}

#[test]
fn the_dome_flattens_as_asked() {
    let model = phantom_model("diaphragm = \"sliding\"");
    for flattening in [0.0, 0.5] {
        let walls = WallMotion {
            rib_cage_share: 1.0 / 3.0,
            dome_flattening: flattening,
            ..WallMotion::default()
        };
        let scene = run_scene(&model, &walls).unwrap();
        for lung in [1u8, 2] {
            let d: Vec<(f64, f64)> = plane_descents(&model, &scene)
                .into_iter()
                .filter(|p| p.2 == lung)
                .map(|(d, z, _)| (d, z))
                .collect();
            assert!(d.len() > 5, "lung {lung}: {} planes", d.len());
            let lowest =
                d.iter()
                    .cloned()
                    .fold((0.0, f64::INFINITY), |a, b| if b.1 < a.1 { b } else { a });
            let highest =
                d.iter().cloned().fold(
                    (0.0, f64::NEG_INFINITY),
                    |a, b| {
                        if b.1 > a.1 {
                            b
                        } else {
                            a
                        }
                    },
                );
            assert!(lowest.0 > 0.0 && highest.0 > 0.0, "lung {lung}: {d:?}");
            // The rim (lowest node) descends 1 − F of the top's way: the extreme nodes of
            // the face may have steep planes, so compare the planes' own descents.
            let ratio = lowest.0 / highest.0;
            assert!(
                ratio <= 1.0 - flattening + 0.2 && ratio >= (1.0 - flattening) * 0.9 - 1e-9,
                "lung {lung}, flattening {flattening}: rim/top descent {ratio}"
            );
        }
    }
}

#[test]
fn what_the_sliding_diaphragm_cannot_do_is_refused_by_name() {
    let err = |t: &str| RunConfig::from_toml(t).unwrap_err().to_string();
    let flat = err("diaphragm = \"sliding\"\n[motion]\ndome_flattening = 0.95");
    assert!(
        flat.contains("motion.dome_flattening") && flat.contains("0.95"),
        "{flat}"
    );
    let negative = err("[motion]\ndome_flattening = -0.1");
    assert!(negative.contains("dome_flattening"), "{negative}");
    let dynamic = err("diaphragm = \"sliding\"\n[motion.dynamic]\nresistance_pa_s_per_ml = 0.05");
    assert!(
        dynamic.contains("diaphragm") && dynamic.contains("quasi-static"),
        "{dynamic}"
    );
    let compliance = err(
        "diaphragm = \"sliding\"\n[motion]\ndriver = { kind = \"compliance\", compliance_ml_per_pa = 2.0 }",
    );
    assert!(
        compliance.contains("motion.driver") && compliance.contains("walls make the volume"),
        "{compliance}"
    );
    let unknown = err("diaphragm = \"trampoline\"");
    assert!(
        unknown.contains("trampoline") && unknown.contains("sliding"),
        "{unknown}"
    );

    // The library refuses the dynamic path on such a scene too, before any work.
    let model = phantom_model("diaphragm = \"sliding\"");
    let scene = run_scene(&model, &WallMotion::default()).unwrap();
    let e = run_dynamic(
        &scene,
        &breath_in(),
        &DynamicSettings::default(),
        &[0.0, 1.0],
        &mut |_, _| Ok(()),
    )
    .unwrap_err()
    .to_string();
    assert!(e.contains("sliding diaphragm"), "{e}");
    // A flattening out of range reaches the scene builder only through the library.
    let e = run_scene(
        &model,
        &WallMotion {
            rib_cage_share: 0.3,
            dome_flattening: 1.5,
            ..WallMotion::default()
        },
    )
    .unwrap_err()
    .to_string();
    assert!(e.contains("dome_flattening 1.5"), "{e}");
}
