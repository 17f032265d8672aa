//! The mediastinal face against the heart (issue 14, part 4): with `mediastinum = "contact"`
//! the face slides along the heart or leaves it, never enters it, and is never pulled by it;
//! held on the wall (the default) parts of it are pulled.

mod boundary_support;

use boundary_support::{end_inhale, phantom_model};
use lungmotion::ingest::lung_model::ConstraintGroup;
use lungmotion::math::V3;
use lungmotion::motion::{run_scene, MediastinumContact, WallMotion, REFERENCE_PRESSURE_PA};
use lungmotion::simulation::Scene;

/// Total force on every node of `scene` at `x` under the pressure `pressure_pa`.
fn forces_at(scene: &Scene, x: &[V3], pressure_pa: f64) -> Vec<V3> {
    let (mut f, mut ext) = (vec![V3::zeros(); x.len()], vec![V3::zeros(); x.len()]);
    scene.internal_forces(x, None, &mut f);
    scene.external_forces(x, &mut ext);
    let factor = pressure_pa / REFERENCE_PRESSURE_PA;
    f.iter_mut().zip(&ext).for_each(|(f, e)| *f += e * factor);
    f
}

#[test]
fn the_mediastinal_face_never_enters_the_heart_and_is_never_pulled_by_it() {
    let model = phantom_model("");
    let walls = |mediastinum| WallMotion {
        mediastinum,
        ..WallMotion::default()
    };
    let sliding = run_scene(&model, &walls(MediastinumContact::Sliding)).unwrap();
    let contact = run_scene(&model, &walls(MediastinumContact::Contact)).unwrap();
    let planes = &contact.one_sided;
    assert!(sliding.one_sided.is_empty());
    assert_eq!(
        planes.len(),
        model.group_nodes(ConstraintGroup::Mediastinal).len()
    );
    for &n in planes.nodes() {
        assert!(
            contact.constraints.get(n).is_none(),
            "node {n} is still held on the wall"
        );
        assert!(
            sliding.constraints.get(n).is_some(),
            "node {n} does not slide by default"
        );
    }
    let share = WallMotion::default().rib_cage_share;
    let (report_s, xs) = end_inhale(&sliding, share);
    let (report_c, xc) = end_inhale(&contact, share);
    let last = |r: &lungmotion::motion::MotionReport| r.frames.last().unwrap().clone();
    let (fs, fc) = (last(&report_s), last(&report_c));
    assert!(
        (fc.simulated_volume_ml - fc.target_volume_ml).abs() < 2.5,
        "{fc:?}"
    );
    // Held on the wall, part of the face is pulled by it: a force a heart cannot exert.
    let force_s = forces_at(&sliding, &xs, fs.pressure_pa);
    let force_c = forces_at(&contact, &xc, fc.pressure_pa);
    let pressing = |f: &[V3]| -> Vec<f64> {
        (0..planes.len())
            .map(|i| planes.pressing_force_n(i, f))
            .collect()
    };
    let (press_s, press_c) = (pressing(&force_s), pressing(&force_c));
    let mean = press_c.iter().map(|p| p.abs()).sum::<f64>() / press_c.len() as f64;
    let pulled_s = press_s.iter().filter(|p| **p < -0.05 * mean).count();
    let state = planes.state(&xc, 1e-4);
    println!(
        "phantom at 12 mm, 400 mL: {} mediastinal nodes; held on the wall {pulled_s} are pulled \
         by it; in contact {} touch, largest separation {:.3} mm, deepest {:.4} mm; volume \
         {:.2} mL",
        planes.len(),
        state.touching,
        state.max_separation_m * 1e3,
        state.max_penetration_m * 1e3,
        fc.simulated_volume_ml
    );
    assert!(
        pulled_s > 0,
        "no mediastinal node is pulled by the wall when sliding"
    );
    // In contact: nothing inside the heart beyond the solver's tolerance (a thousandth of
    // the 12 mm edge), and every touching node pressed onto it, not pulled.
    assert!(state.max_penetration_m < 0.012e-3, "{state:?}");
    assert!(
        state.touching < planes.len(),
        "no node left the heart: {state:?}"
    );
    for (i, p) in press_c.iter().enumerate() {
        let touching = planes.penetration_m(i, &xc) > -1e-4;
        assert!(
            !touching || *p > -0.05 * mean,
            "node {} touches the heart and is pulled by {p} N (mean pressing {mean} N)",
            planes.nodes()[i]
        );
    }
}

#[test]
fn in_the_dynamic_path_the_face_stays_out_of_the_heart_at_every_frame() {
    use lungmotion::motion::dynamic::{run_dynamic, DynamicSettings};
    let model = phantom_model("");
    let scene = run_scene(
        &model,
        &WallMotion {
            mediastinum: MediastinumContact::Contact,
            rib_cage_share: 0.0,
            ..WallMotion::default()
        },
    )
    .unwrap();
    let trace = boundary_support::breath_in();
    let times: Vec<f64> = trace.time_s.clone();
    let planes = &scene.one_sided;
    let (mut deepest, mut farthest) = (0.0f64, 0.0f64);
    run_dynamic(
        &scene,
        &trace,
        &DynamicSettings::default(),
        &times,
        &mut |_, x| {
            let s = planes.state(x, 1e-4);
            deepest = deepest.max(s.max_penetration_m);
            farthest = farthest.max(s.max_separation_m);
            Ok(())
        },
    )
    .unwrap();
    println!(
        "dynamic, 400 mL: deepest {:.2e} mm, farthest {:.3} mm",
        deepest * 1e3,
        farthest * 1e3
    );
    // Projected on every step: nothing inside but round-off.
    assert!(deepest < 1e-9, "{deepest} m inside the heart");
    assert!(farthest > 1e-4, "no node left the heart ({farthest} m)");
}
