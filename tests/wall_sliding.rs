//! Sliding on the curved wall (issue 14, part 1): with `sliding = "wall_surface"` the costal,
//! mediastinal and apex nodes keep their rest distance to the wall as they slide, on a rigid
//! wall and on one that moves out with the rib cage's share; tangent planes do not.

mod boundary_support;

use boundary_support::{end_inhale, phantom_model};
use lungmotion::ingest::lung_model::{ConstraintGroup, LungModel};
use lungmotion::math::V3;
use lungmotion::model::NodeConstraint;
use lungmotion::motion::{lung_scene, move_costal_wall};
use lungmotion::simulation::Scene;

/// Largest |change of wall distance − the wall's own outward motion| over the costal nodes
/// held as `held` selects, in mm (`wall_factor`: how far the moving wall has gone).
fn worst_gap_change_mm(
    model: &LungModel,
    scene: &Scene,
    x: &[V3],
    wall_factor: f64,
    held: impl Fn(&NodeConstraint) -> Option<f64>,
) -> (f64, usize) {
    let rest = &scene.mesh.rest_positions_m;
    let mut worst = 0.0f64;
    let mut count = 0;
    for n in model.group_nodes(ConstraintGroup::Costal) {
        let Some(offset_m) = scene.constraints.get(n).and_then(&held) else {
            continue;
        };
        let n = n as usize;
        let change = model.wall.spline(x[n]).0 - model.wall.spline(rest[n]).0;
        worst = worst.max((change - offset_m * wall_factor).abs() * 1e3);
        count += 1;
    }
    (worst, count)
}

#[test]
fn sliding_nodes_keep_their_distance_to_the_curved_wall_and_planes_do_not() {
    let surface = phantom_model("sliding = \"wall_surface\"");
    let planes = phantom_model("sliding = \"tangent_plane\"");
    let sliding: usize = ["costal", "mediastinal", "apex"]
        .iter()
        .map(|g| surface.report.group_nodes[*g])
        .sum();
    let on_planes = surface.report.wall_surface_plane_nodes;
    assert!(
        on_planes * 10 < sliding,
        "{on_planes} of {sliding} sliding nodes fell back to tangent planes"
    );
    assert_eq!(planes.report.wall_surface_plane_nodes, 0);

    let rigid_surface = lung_scene(&surface).unwrap();
    let rigid_planes = lung_scene(&planes).unwrap();
    let (_, xs) = end_inhale(&rigid_surface, 0.0);
    let (_, xp) = end_inhale(&rigid_planes, 0.0);
    let on_surface = |c: &NodeConstraint| match c {
        NodeConstraint::Surface { .. } => Some(0.0),
        _ => None,
    };
    let on_plane = |c: &NodeConstraint| match c {
        NodeConstraint::Plane { .. } => Some(0.0),
        _ => None,
    };
    let (surface_mm, held) = worst_gap_change_mm(&surface, &rigid_surface, &xs, 0.0, on_surface);
    let (planes_mm, _) = worst_gap_change_mm(&planes, &rigid_planes, &xp, 0.0, on_plane);
    assert!(held > 0);
    // The projection stops within 1e-13 m of the level; the solver's tolerance leaves the
    // rest.
    assert!(
        surface_mm < 1e-3,
        "a costal node on the curved wall moved {surface_mm} mm off its level"
    );
    assert!(
        planes_mm > 100.0 * surface_mm.max(1e-4),
        "tangent planes departed from the curved wall by only {planes_mm} mm"
    );
}

#[test]
fn the_curved_wall_moves_out_with_the_rib_cage_and_sweeps_the_share_asked() {
    let model = phantom_model("sliding = \"wall_surface\"");
    let mut scene = lung_scene(&model).unwrap();
    let wall = move_costal_wall(&mut scene, &model);
    assert!(
        wall.moving_nodes > wall.costal_nodes / 4,
        "{wall:?}: the anterior and lateral costal wall moves"
    );
    let (report, x) = end_inhale(&scene, 1.0 / 3.0);
    for f in report
        .frames
        .iter()
        .filter(|f| f.simulated_volume_ml > 50.0)
    {
        let share = f.chest_wall_volume_ml / f.simulated_volume_ml;
        assert!(
            (share - 1.0 / 3.0).abs() < 0.03,
            "frame {} at {:.1} mL: a share of {share:.3}",
            f.index,
            f.simulated_volume_ml
        );
    }
    let end = report.frames.last().unwrap();
    assert!((end.target_volume_ml - 400.0).abs() < 1e-6);
    assert!((end.simulated_volume_ml - 400.0).abs() < 2.0, "{end:?}");
    // Each costal node on the wall is where the moved wall is: its level rose by the wall's
    // offset times how far the wall has gone.
    let factor =
        end.pressure_pa / lungmotion::motion::REFERENCE_PRESSURE_PA * report.chest_wall.scale;
    let (worst_mm, held) = worst_gap_change_mm(&model, &scene, &x, factor, |c| match c {
        NodeConstraint::Surface {
            level_m,
            rest_level_m,
            ..
        } => Some(level_m - rest_level_m),
        _ => None,
    });
    assert!(held > 0);
    assert!(worst_mm < 1e-3, "{worst_mm} mm off the moved wall");
}
