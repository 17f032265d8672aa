//! The quasi-static solver against closed forms and against the explicit integrator.

use lungmotion::model::{
    BrickCoefficients, BrickShape, ConstraintSet, HexMesh, Loads, Material, NodeConstraint,
    SignedDistanceField, VoxelGrid,
};
use lungmotion::simulation::cases::symmetric_block_under_pressure;
use lungmotion::simulation::{
    ExplicitIntegrator, ExplicitSettings, QuasiStaticSettings, QuasiStaticSolver, Scene,
};
use lungmotion::Error;
use nalgebra::Vector3;

/// A beam of `cells` cubes along x, clamped at x = 0, under gravity along −z; springs damped
/// at `damping_ratio` × critical.
fn cantilever_under_gravity(
    cells: [usize; 3],
    edge_m: f64,
    mat: Material,
    damping_ratio: f64,
) -> Scene {
    let grid = VoxelGrid::filled_box(cells, [edge_m; 3], Vector3::zeros());
    let mut gm = grid.to_mesh(mat).unwrap();
    gm.mesh.classes[0] = gm.mesh.classes[0].clone().with_damping_ratio(damping_ratio);
    let mut cs = ConstraintSet::new(gm.mesh.node_count());
    for (i, l) in gm.node_lattice.iter().enumerate() {
        if l[0] == 0 {
            cs.fix(i as u32, gm.mesh.rest_positions_m[i]).unwrap();
        }
    }
    let loads = Loads {
        gravity_m_per_s2: Vector3::new(0.0, 0.0, -9.81),
        ..Loads::default()
    };
    Scene::new(gm.mesh, cs, loads).unwrap()
}

fn volume_strain(scene: &Scene, x: &[Vector3<f64>]) -> f64 {
    let v0 = scene.mesh.enclosed_volume_m3(&scene.mesh.rest_positions_m);
    (scene.mesh.enclosed_volume_m3(x) - v0) / v0
}

#[test]
fn small_pressure_gives_the_bulk_modulus_on_a_composed_block() {
    // A composed block must keep the element's exact bulk modulus: ΔV/V = −p/K at small strain.
    for nu in [0.1, 0.3, 0.45] {
        let mat = Material::new(1000.0, nu, 700.0).unwrap();
        let p = 1e-3;
        let scene = symmetric_block_under_pressure([6, 5, 4], 0.004, mat, p).unwrap();
        let mut solver = QuasiStaticSolver::new(&scene, QuasiStaticSettings::default()).unwrap();
        let (x, report) = solver.solve(None).unwrap();
        assert!(report.residual <= 1e-6, "{report:?}");
        let measured = -p / volume_strain(&scene, &x);
        let k = mat.bulk_modulus_pa();
        assert!(
            (measured - k).abs() / k < 1e-4,
            "ν = {nu}: K = {measured}, want {k}"
        );
    }
}

#[test]
fn multigrid_and_block_jacobi_agree_and_converge() {
    // 16³ builds a 3-level hierarchy; the residual must reach the tolerance either way.
    let scene = symmetric_block_under_pressure([16, 16, 16], 0.005, Material::LUNG, -20.0).unwrap();
    let mut solver = QuasiStaticSolver::new(&scene, QuasiStaticSettings::default()).unwrap();
    let (x, report) = solver.solve(None).unwrap();
    assert!(report.multigrid_levels >= 3, "{report:?}");
    assert!(report.residual <= 1e-6);
    // Inflation by −20 Pa on lung tissue: about 6 % volume, follower load, non-linear.
    let strain = volume_strain(&scene, &x);
    let linear = 20.0 / Material::LUNG.bulk_modulus_pa();
    assert!(
        strain > 0.9 * linear && strain < 1.2 * linear,
        "{strain} vs {linear}"
    );
    // Warm start from the solution: converged already, no Newton step needed.
    let (_, again) = solver.solve(Some(&x)).unwrap();
    assert_eq!(again.newton_iterations, 0);
}

#[test]
fn agrees_with_explicit_dynamics_at_equilibrium() {
    // Cantilever of 2×2×6 cubes under gravity, clamped at x = 0, dampers for the dynamics.
    let mat = Material::new(50_000.0, 0.3, 1000.0).unwrap();
    let scene = cantilever_under_gravity([6, 2, 2], 0.01, mat, 1.0);
    let (xq, _) = QuasiStaticSolver::new(&scene, QuasiStaticSettings::default())
        .unwrap()
        .solve(None)
        .unwrap();
    let mut dynamic = ExplicitIntegrator::new(&scene);
    let report = dynamic
        .run_to_equilibrium(&ExplicitSettings {
            residual_tolerance: 1e-7,
            ..ExplicitSettings::default()
        })
        .unwrap();
    assert!(report.converged, "{report:?}");
    let tip_q = scene
        .displacements(&xq)
        .iter()
        .map(|u| u.norm())
        .fold(0.0, f64::max);
    let diff = xq
        .iter()
        .zip(&dynamic.positions)
        .map(|(a, b)| (a - b).norm())
        .fold(0.0, f64::max);
    assert!(tip_q > 1e-3, "the beam must sag visibly: {tip_q}");
    // Both stop at a relative force residual of 1e-7, so their states agree to about that.
    assert!(
        diff < 1e-4 * tip_q,
        "max difference {diff} m vs tip {tip_q} m"
    );
}

#[test]
fn non_lattice_mesh_uses_block_jacobi_and_converges() {
    // Two bricks of different shapes: no common lattice, so no multigrid.
    let mat = Material::new(1000.0, 0.3, 1.0).unwrap();
    let a = BrickCoefficients::new(BrickShape::cube(1.0), mat).unwrap();
    let b = BrickCoefficients::new(
        BrickShape {
            edges_m: [1.2, 1.0, 1.0],
        },
        mat,
    )
    .unwrap();
    let mut pos = Vec::new();
    for x in [0.0, 1.0, 2.2] {
        for (y, z) in [(0.0, 0.0), (1.0, 0.0), (1.0, 1.0), (0.0, 1.0)] {
            pos.push(Vector3::new(x, y, z));
        }
    }
    // Node (x index i, corner c of the yz square) = 4i + c; VTK order per element.
    let el = |i: u32| {
        [
            4 * i,
            4 * i + 4,
            4 * i + 5,
            4 * i + 1,
            4 * i + 3,
            4 * i + 7,
            4 * i + 6,
            4 * i + 2,
        ]
    };
    let mesh = HexMesh::new(pos, vec![el(0), el(1)], vec![0, 1], vec![a, b]).unwrap();
    let mut cs = ConstraintSet::new(mesh.node_count());
    for n in 0..4 {
        cs.fix(n, mesh.rest_positions_m[n as usize]).unwrap();
    }
    let loads = Loads {
        point_forces_n: (8..12).map(|n| (n, Vector3::new(1.0, 0.0, 0.0))).collect(),
        ..Loads::default()
    };
    let scene = Scene::new(mesh, cs, loads).unwrap();
    let (x, report) = QuasiStaticSolver::new(&scene, QuasiStaticSettings::default())
        .unwrap()
        .solve(None)
        .unwrap();
    assert_eq!(report.multigrid_levels, 1);
    assert!(report.residual <= 1e-6);
    assert!(x[8].x > 2.2);
}

#[test]
fn sliding_nodes_stay_on_their_surface() {
    // A column pressed from above whose bottom nodes slide on a sphere of radius 1 m.
    let mat = Material::new(1000.0, 0.3, 1.0).unwrap();
    let grid = VoxelGrid::filled_box([2, 2, 2], [0.05; 3], Vector3::new(-0.05, -0.05, 1.0));
    let gm = grid.to_mesh(mat).unwrap();
    let mut cs = ConstraintSet::new(gm.mesh.node_count());
    // Sampled at 10 mm, coarse like a CT-derived chest wall: the normal comes from central
    // differences of the interpolant, continuous across cells, so equilibrium is reachable.
    let sphere = SignedDistanceField::from_fn(
        Vector3::new(-0.3, -0.3, 0.8),
        Vector3::new(0.3, 0.3, 1.2),
        0.01,
        |p| p.norm() - 1.0,
    )
    .unwrap();
    let s = cs.add_surface(sphere);
    for (i, l) in gm.node_lattice.iter().enumerate() {
        if l[2] == 0 {
            cs.set(i as u32, NodeConstraint::surface(s, 0.0)).unwrap();
        }
        if l[2] == 0 && l[1] == 1 && l[0] >= 1 {
            // Two bottom nodes are pinned: with one, turning about the vertical through it
            // would keep every sliding node on the sphere (a zero-stiffness mode).
            let p = gm.mesh.rest_positions_m[i];
            cs.fix(i as u32, p).unwrap();
        }
    }
    let top: Vec<u32> = (0..gm.node_lattice.len() as u32)
        .filter(|&i| gm.node_lattice[i as usize][2] == 2)
        .collect();
    let loads = Loads {
        point_forces_n: top
            .iter()
            .map(|&n| (n, Vector3::new(3e-3, 0.0, -1e-2)))
            .collect(),
        ..Loads::default()
    };
    let scene = Scene::new(gm.mesh, cs, loads).unwrap();
    let (x, report) = QuasiStaticSolver::new(&scene, QuasiStaticSettings::default())
        .unwrap()
        .solve(None)
        .unwrap();
    assert!(report.residual <= 1e-6, "{report:?}");
    for (i, xi) in x.iter().enumerate() {
        if matches!(
            scene.constraints.get(i as u32),
            Some(NodeConstraint::Surface { .. })
        ) {
            // Trilinear sampling of the field limits how exactly the sphere is represented.
            assert!(
                (xi.norm() - 1.0).abs() < 1e-4,
                "node {i}: |x| = {}",
                xi.norm()
            );
        }
    }
    // The reaction forces balance the applied load (eq. 4.1: constraints visible as forces).
    let reactions = scene.reactions(&x);
    let total: Vector3<f64> = reactions.iter().map(|(_, f)| f).sum();
    let applied = Vector3::new(3e-3, 0.0, -1e-2) * top.len() as f64;
    assert!(
        (total + applied).norm() < 1e-3 * applied.norm(),
        "{total:?}"
    );
}

#[test]
fn refuses_bad_settings_and_states() {
    let scene = symmetric_block_under_pressure([2, 2, 2], 0.01, Material::LUNG, -1.0).unwrap();
    let bad = QuasiStaticSettings {
        tolerance: f64::NAN,
        ..QuasiStaticSettings::default()
    };
    assert!(QuasiStaticSolver::new(&scene, bad).is_err());
    let mut solver = QuasiStaticSolver::new(&scene, QuasiStaticSettings::default()).unwrap();
    let mut x = scene.mesh.rest_positions_m.clone();
    x[5].y = f64::NAN;
    match solver.solve(Some(&x)) {
        Err(Error::Diverged { cause, .. }) => assert!(cause.contains("node 5"), "{cause}"),
        other => panic!("expected a blow-up error, got {other:?}"),
    }
    assert!(solver.solve(Some(&x[..3])).is_err());
}

#[test]
fn mechanism_is_solved_and_flagged() {
    // A 1×1×4 cantilever: the element's three twist modes (no edge or diagonal changes
    // length) are not suppressed by neighbours, so the small-strain stiffness is singular and
    // plain Newton stalls. The solver must still return a verified equilibrium and say, in its
    // report, that it needed pseudo-time steps or relaxation. The equilibrium of a mechanism
    // is not unique, so it is checked by its residual, not against another solver's state.
    let mat = Material::new(1000.0, 0.3, 2.0).unwrap();
    let scene = cantilever_under_gravity([4, 1, 1], 0.1, mat, 0.0);
    let (x, report) = QuasiStaticSolver::new(&scene, QuasiStaticSettings::default())
        .unwrap()
        .solve(None)
        .unwrap();
    assert!(report.pseudo_time_steps > 0, "{report:?}");
    let n = scene.node_count();
    let (mut a, mut b) = (vec![Vector3::zeros(); n], vec![Vector3::zeros(); n]);
    let residual = scene.relative_residual(&x, (&mut a, &mut b));
    assert!(residual <= 1e-6, "residual {residual}, {report:?}");
    let sag = -scene
        .displacements(&x)
        .iter()
        .map(|u| u.z)
        .fold(0.0, f64::min);
    assert!(sag > 0.01 && sag < 0.4, "tip sag {sag} m");
    // Without the fallback the same problem is reported as not converged, not silently wrong.
    let strict = QuasiStaticSettings {
        relaxation_max_steps: 0,
        ..QuasiStaticSettings::default()
    };
    match QuasiStaticSolver::new(&scene, strict).unwrap().solve(None) {
        Err(Error::NotConverged { residual, .. }) => assert!(residual > 1e-6),
        Ok((_, r)) => assert!(r.residual <= 1e-6),
        Err(e) => panic!("unexpected error {e}"),
    }
}

#[test]
fn rotated_lattice_converges_like_an_aligned_one() {
    // The same pressurised block, built on a lattice whose axes are rotated in space: the
    // physics is identical, so the solution (rotated back) and the iteration counts must match.
    use nalgebra::Rotation3;
    let mat = Material::LUNG;
    let aligned = symmetric_block_under_pressure([8, 8, 8], 0.005, mat, -20.0).unwrap();
    let (xa, ra) = QuasiStaticSolver::new(&aligned, QuasiStaticSettings::default())
        .unwrap()
        .solve(None)
        .unwrap();
    let rot = Rotation3::from_euler_angles(0.4, -0.3, 0.9);
    let r = *rot.matrix();
    let mut mesh = aligned.mesh.clone();
    mesh.rest_positions_m.iter_mut().for_each(|p| *p = r * *p);
    let mut cs = ConstraintSet::new(mesh.node_count());
    for (node, c) in &aligned.constraints.entries {
        let c = match *c {
            NodeConstraint::Fixed { target_m } => NodeConstraint::Fixed {
                target_m: r * target_m,
            },
            NodeConstraint::Plane { point_m, normal } => NodeConstraint::Plane {
                point_m: r * point_m,
                normal: r * normal,
            },
            NodeConstraint::Line { point_m, direction } => NodeConstraint::Line {
                point_m: r * point_m,
                direction: r * direction,
            },
            NodeConstraint::Surface { .. } => unreachable!("the block has no surface constraints"),
        };
        cs.set(*node, c).unwrap();
    }
    let mesh = HexMesh::new(
        mesh.rest_positions_m,
        mesh.elements,
        mesh.element_class,
        mesh.classes,
    )
    .unwrap();
    let rotated = Scene::new(mesh, cs, aligned.loads.clone()).unwrap();
    let (xr, rr) = QuasiStaticSolver::new(&rotated, QuasiStaticSettings::default())
        .unwrap()
        .solve(None)
        .unwrap();
    assert!(rr.multigrid_levels >= 2, "{rr:?}");
    assert!(
        rr.linear_iterations <= ra.linear_iterations + 2,
        "{ra:?} vs {rr:?}"
    );
    let scale = aligned
        .displacements(&xa)
        .iter()
        .map(|u| u.norm())
        .fold(0.0, f64::max);
    let worst = xa
        .iter()
        .zip(&xr)
        .map(|(a, b)| (r * a - b).norm())
        .fold(0.0, f64::max);
    assert!(
        worst < 1e-5 * scale,
        "rotated solution differs by {worst} m (scale {scale} m)"
    );
}

#[test]
fn a_cancel_raised_during_one_long_solve_stops_that_solve() {
    // A tolerance below round-off keeps Newton, then the explicit fallback, busy for far longer
    // than the flag takes to rise: only checks inside the solve can end it as a cancellation.
    let scene = symmetric_block_under_pressure([16, 16, 16], 0.005, Material::LUNG, -20.0).unwrap();
    let flag = lungmotion::simulation::CancelFlag::default();
    let settings = QuasiStaticSettings {
        tolerance: 1e-300,
        max_newton_iterations: 1_000_000,
        cancel: Some(flag.clone()),
        ..QuasiStaticSettings::default()
    };
    let mut solver = QuasiStaticSolver::new(&scene, settings).unwrap();
    let raiser = std::thread::spawn(move || {
        std::thread::sleep(std::time::Duration::from_millis(200));
        flag.store(true, std::sync::atomic::Ordering::SeqCst);
    });
    let r = solver.solve(None);
    raiser.join().unwrap();
    assert!(matches!(r, Err(Error::Cancelled(_))), "{r:?}");
}

#[test]
fn an_explicit_relaxation_that_stagnates_gives_up_instead_of_running_to_its_step_limit() {
    // A tolerance below round-off cannot be met: without the stagnation rule this would take
    // all ten million steps.
    let scene = cantilever_under_gravity(
        [4, 1, 1],
        0.01,
        Material::new(1e5, 0.3, 1000.0).unwrap(),
        1.0,
    );
    let mut integrator = ExplicitIntegrator::new(&scene);
    let report = integrator
        .run_to_equilibrium(&ExplicitSettings {
            residual_tolerance: 1e-300,
            kinetic_energy_fraction: 1.0,
            max_steps: 10_000_000,
            stall_steps: Some(20_000),
            ..ExplicitSettings::default()
        })
        .unwrap();
    assert!(!report.converged);
    assert!(report.steps < 1_000_000, "{report:?}");
}

#[test]
fn a_solve_that_may_bisect_gives_up_after_two_krylov_solves_at_their_limit() {
    // One Krylov iteration per Newton step cannot reach the linear tolerance on a block
    // under a large pressure: every Krylov solve stops at its limit.
    let scene = symmetric_block_under_pressure([6, 5, 4], 0.004, Material::LUNG, -40.0).unwrap();
    let settings = QuasiStaticSettings {
        max_linear_iterations: 1,
        relaxation_max_steps: 0,
        ..QuasiStaticSettings::default()
    };
    // A caller that bisects its load step on failure (the breathing driver) hears at once.
    let mut solver = QuasiStaticSolver::new(&scene, settings.clone()).unwrap();
    match solver.solve_load_factor_from(None, 1.0, false) {
        Err(Error::NotConverged { iterations, .. }) => assert_eq!(iterations, 2),
        other => panic!("expected NotConverged after 2 iterations, got {other:?}"),
    }
    // One that cannot bisect keeps its Newton iterations.
    let mut solver = QuasiStaticSolver::new(&scene, settings).unwrap();
    match solver.solve_load_factor_from(None, 1.0, true) {
        Err(Error::NotConverged { iterations, .. }) => assert!(iterations > 2, "{iterations}"),
        Ok((_, report)) => assert!(report.newton_iterations > 2, "{report:?}"),
        other => panic!("{other:?}"),
    }
}
