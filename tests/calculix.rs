//! CalculiX cross-checks: the exported deck gives the same answer as the mass–spring model
//! where both are exact, and the composite refinement study behaves.
//!
//! These tests need `ccx`. Without it they fail (never skip) and say how to install it.
#![cfg(feature = "validation")]

use lungmotion::model::{
    ConstraintSet, Loads, Material, NodeConstraint, SurfacePressure, VoxelGrid,
};
use lungmotion::simulation::{QuasiStaticSettings, QuasiStaticSolver, Scene};
use lungmotion::validation::calculix::{self, CalculixOptions, CCX_INSTALL_HINT};
use lungmotion::validation::composite::{run_case, CompositeCase, CompositeOptions};
use nalgebra::{Matrix3, Rotation3, Vector3};

type V3 = Vector3<f64>;

fn require_ccx() {
    if calculix::ccx_path().is_none() {
        panic!("CalculiX (`ccx`) is required by this test but was not found: {CCX_INSTALL_HINT}");
    }
}

fn solve_ours(scene: &Scene, tolerance: f64) -> Vec<V3> {
    let settings = QuasiStaticSettings {
        tolerance,
        ..Default::default()
    };
    let (x, _) = QuasiStaticSolver::new(scene, settings)
        .unwrap()
        .solve(None)
        .unwrap();
    scene.displacements(&x)
}

/// A 2×2×2 block of 10 mm cubes in the frame `axes` (columns), with symmetry planes on its
/// three faces through the origin (one plane: slides on it; two: slides along their line;
/// three: fixed) and a uniform pressure on the faces at local x = 20 mm.
fn symmetric_block(axes: Matrix3<f64>, pressure_pa: f64) -> Scene {
    let material = Material::new(1000.0, 0.3, 1.0).unwrap();
    symmetric_cubes(2, material, axes, pressure_pa)
}

/// [`symmetric_block`] with `cells`³ cubes of `material`.
fn symmetric_cubes(
    cells: usize,
    material: Material,
    axes: Matrix3<f64>,
    pressure_pa: f64,
) -> Scene {
    let mut grid = VoxelGrid::filled_box([cells; 3], [0.01; 3], V3::zeros());
    grid.axes = axes;
    let gm = grid.to_mesh(material).unwrap();
    let mesh = gm.mesh;
    let mut cs = ConstraintSet::new(mesh.node_count());
    for (i, l) in gm.node_lattice.iter().enumerate() {
        let on: Vec<usize> = (0..3).filter(|&a| l[a] == 0).collect();
        let c = match on.len() {
            0 => continue,
            1 => NodeConstraint::Plane {
                point_m: V3::zeros(),
                normal: axes.column(on[0]).into(),
            },
            2 => NodeConstraint::Line {
                point_m: V3::zeros(),
                direction: axes.column(3 - on[0] - on[1]).into(),
            },
            _ => NodeConstraint::Fixed {
                target_m: V3::zeros(),
            },
        };
        cs.set(i as u32, c).unwrap();
    }
    let faces: Vec<[u32; 4]> = mesh
        .external_faces
        .iter()
        .copied()
        .filter(|f| {
            f.iter()
                .all(|&n| gm.node_lattice[n as usize][0] == cells as u32)
        })
        .collect();
    assert_eq!(faces.len(), cells * cells);
    let loads = Loads {
        pressures: vec![SurfacePressure {
            faces,
            pressure_pa,
            follows_deformation: false,
        }],
        ..Default::default()
    };
    Scene::new(mesh, cs, loads).unwrap()
}

fn max_norm(u: &[V3]) -> f64 {
    u.iter().map(|v| v.norm()).fold(0.0, f64::max)
}

fn max_diff(a: &[V3], b: &[V3]) -> f64 {
    a.iter()
        .zip(b)
        .map(|(x, y)| (x - y).norm())
        .fold(0.0, f64::max)
}

/// Homogeneous uniaxial stress: C3D8 and Baudet's element are both exact, so the two codes
/// must agree to CalculiX's printed precision (7 significant digits) and match the closed form.
#[test]
#[cfg_attr(
    not(feature = "slow-tests"),
    ignore = "slow study (CalculiX): cargo test --features slow-tests"
)]
fn uniaxial_block_matches_calculix_linear() {
    require_ccx();
    let p = 1e-3; // Strain 1e-6: the mass–spring model's geometric non-linearity is O(1e-6).
    let scene = symmetric_block(Matrix3::identity(), p);
    let ccx = calculix::solve(&scene, &CalculixOptions::linear()).unwrap();
    // Forces come from length differences of 1e-6 relative size: round-off floors the
    // relative residual near 1e-10.
    let ours = solve_ours(&scene, 1e-9);
    let scale = max_norm(&ccx.displacements_m);
    let diff = max_diff(&ours, &ccx.displacements_m);
    eprintln!("uniaxial: max |Δu| / max |u| = {:.2e}", diff / scale);
    assert!(
        diff <= 1e-6 * scale,
        "mass–spring vs CalculiX: max |Δu| = {diff:.3e} m, {:.2e} of max |u| = {scale:.3e} m",
        diff / scale
    );
    // Closed form: u_x = −(p/E)·x, u_y = ν(p/E)·y, u_z = ν(p/E)·z.
    let (e, nu) = (1000.0, 0.3);
    for (r, u) in scene.mesh.rest_positions_m.iter().zip(&ccx.displacements_m) {
        let want = V3::new(-p / e * r.x, nu * p / e * r.y, nu * p / e * r.z);
        assert!(
            (u - want).norm() <= 1e-6 * scale,
            "node at {r:?}: {u:?} vs {want:?}"
        );
    }
}

/// General plane and line constraints go through `*TRANSFORM`: the rotated block must give
/// the rotated displacements of the axis-aligned one.
#[test]
#[cfg_attr(
    not(feature = "slow-tests"),
    ignore = "slow study (CalculiX): cargo test --features slow-tests"
)]
fn rotated_block_uses_transforms_correctly() {
    require_ccx();
    let rot = Rotation3::from_euler_angles(0.3, -0.5, 0.9);
    let aligned = symmetric_block(Matrix3::identity(), 1e-3);
    let rotated = symmetric_block(*rot.matrix(), 1e-3);
    let deck = calculix::write_deck(&rotated, &CalculixOptions::linear()).unwrap();
    assert!(deck.contains("*TRANSFORM"));
    let a = calculix::solve(&aligned, &CalculixOptions::linear()).unwrap();
    let b = calculix::solve(&rotated, &CalculixOptions::linear()).unwrap();
    let back: Vec<V3> = b
        .displacements_m
        .iter()
        .map(|u| rot.inverse() * u)
        .collect();
    let scale = max_norm(&a.displacements_m);
    let diff = max_diff(&back, &a.displacements_m);
    assert!(
        diff <= 2e-6 * scale,
        "rotated vs aligned: {diff:.3e} m of {scale:.3e} m"
    );
}

/// Pressure on all six faces (every C3D8 face number S1…S6) of a block held only against rigid
/// motion (3-2-1 supports): CalculiX must return the closed-form hydrostatic compression, which
/// it does only if every face number points at the right face.
#[test]
#[cfg_attr(
    not(feature = "slow-tests"),
    ignore = "slow study (CalculiX): cargo test --features slow-tests"
)]
fn all_face_numbers_give_hydrostatic_compression_in_calculix() {
    require_ccx();
    let gm = VoxelGrid::filled_box([2, 2, 2], [0.01; 3], V3::zeros())
        .to_mesh(Material::new(1000.0, 0.3, 1.0).unwrap())
        .unwrap();
    let mesh = gm.mesh;
    let node_at = |l: [u32; 3]| gm.node_lattice.iter().position(|&x| x == l).unwrap() as u32;
    let mut cs = ConstraintSet::new(mesh.node_count());
    cs.fix(node_at([0, 0, 0]), V3::zeros()).unwrap();
    cs.set(
        node_at([2, 0, 0]),
        NodeConstraint::Line {
            point_m: V3::zeros(),
            direction: V3::x(),
        },
    )
    .unwrap();
    cs.set(
        node_at([0, 2, 0]),
        NodeConstraint::Plane {
            point_m: V3::zeros(),
            normal: V3::z(),
        },
    )
    .unwrap();
    let p = 1e-3;
    let loads = Loads {
        pressures: vec![SurfacePressure {
            faces: mesh.external_faces.clone(),
            pressure_pa: p,
            follows_deformation: true,
        }],
        ..Default::default()
    };
    let scene = Scene::new(mesh, cs, loads).unwrap();
    let ccx = calculix::solve(&scene, &CalculixOptions::linear()).unwrap();
    // u = −p/(3K)·x with K = E / (3(1 − 2ν)).
    let k = 1000.0 / (3.0 * (1.0 - 2.0 * 0.3));
    let scale = p / (3.0 * k) * 0.02;
    for (r, u) in scene.mesh.rest_positions_m.iter().zip(&ccx.displacements_m) {
        let want = -r * (p / (3.0 * k));
        assert!(
            (u - want).norm() <= 1e-6 * scale,
            "node at {r:?}: {u:?} vs {want:?}"
        );
    }
}

/// Follower pressure on every face of a symmetric block under NLGEOM (≈ 7 % volume loss): both
/// codes must lose the same volume within the mass–spring model's bulk-modulus error, which the
/// thesis bounds by 5 % up to ±15 % volume change (Fig. 3.50).
///
/// Symmetry planes rather than 3-2-1 supports: with only 3-2-1 supports Baudet's element leaves
/// checkerboard twist modes (u_z ∝ (−1)^(i+j), …) with zero stiffness, and compression buckles
/// them.
#[test]
#[cfg_attr(
    not(feature = "slow-tests"),
    ignore = "slow study (CalculiX): cargo test --features slow-tests"
)]
fn all_face_pressure_gives_same_volume_change_nlgeom() {
    require_ccx();
    let mut scene = symmetric_block(Matrix3::identity(), 60.0);
    scene.loads.pressures[0].faces = scene.mesh.external_faces.clone();
    scene.loads.pressures[0].follows_deformation = true;
    let ccx = calculix::solve(&scene, &CalculixOptions::default()).unwrap();
    let ours = solve_ours(&scene, 1e-9);
    let m = &scene.mesh;
    let v0 = m.enclosed_volume_m3(&m.rest_positions_m);
    let moved = |u: &[V3]| -> Vec<V3> {
        m.rest_positions_m
            .iter()
            .zip(u)
            .map(|(r, d)| r + d)
            .collect()
    };
    let dv_ccx = m.enclosed_volume_m3(&moved(&ccx.displacements_m)) / v0 - 1.0;
    let dv_ours = m.enclosed_volume_m3(&moved(&ours)) / v0 - 1.0;
    eprintln!("volume change: CalculiX {dv_ccx:.5}, mass–spring {dv_ours:.5}");
    assert!(
        dv_ccx < -0.05 && dv_ccx > -0.10,
        "CalculiX volume change {dv_ccx}"
    );
    let rel = (dv_ours - dv_ccx).abs() / dv_ccx.abs();
    assert!(rel < 0.05, "volume change differs by {:.2} %", 100.0 * rel);
}

/// Quick refinement study: the mass–spring error against CalculiX on the finest mesh run falls
/// as elements shrink, in both composite cases, and stays within bounds taken from the thesis:
///
/// * L: no worse than the thesis's own error at that resolution, 7 % of the object size at 2³
///   and 0.65 % at 16³, interpolated as a power law (≈ 3.2 % at 4³). The thesis measured
///   against a 16³ reference; ours here is 4³, so this is a sanity bound, not a reproduction.
/// * Cantilever: within 5 % of the largest reference displacement at 4×4×16, the resolution the
///   thesis calls "a good approximation" (5 % is its accuracy claim at strains ≤ 10 %); coarser
///   beams are "far off" in the thesis (one or two elements through the thickness, 20 % of the
///   mass on clamped nodes at 1×1×4), so only the fall of their error is asserted. 1×1×4 is a
///   mechanism at rest (zero-energy twist modes), which exercises the explicit fallback.
#[test]
#[cfg_attr(
    not(feature = "slow-tests"),
    ignore = "slow study (CalculiX): cargo test --features slow-tests"
)]
fn composite_error_falls_with_refinement() {
    require_ccx();
    let options = CompositeOptions {
        check_reference_with_c3d8i: false,
        ..CompositeOptions::quick()
    };
    for (case, res) in [
        (CompositeCase::L, vec![2, 4]),
        (CompositeCase::Cantilever, vec![1, 2, 4]),
    ] {
        let report = run_case(case, &res, &options).unwrap();
        let u_ref = report.reference_max_displacement_m;
        let mut errors = Vec::new();
        for r in &report.rows {
            let ours = r
                .mass_spring_error
                .unwrap_or_else(|| panic!("{case:?} {}: {:?}", r.label, r.mass_spring_failure));
            eprintln!(
                "{case:?} {}: ours {:.2} ± {:.2} mm ({:.2} % of size), CalculiX {:.2} mm, \
                 max |u_ref| {:.1} mm, by {}",
                r.label,
                ours.mean_m * 1e3,
                ours.sd_m * 1e3,
                ours.mean_percent_of_size,
                r.calculix_error.unwrap().mean_m * 1e3,
                u_ref * 1e3,
                r.mass_spring_method.as_deref().unwrap_or("?")
            );
            let bound_m = match case {
                CompositeCase::L => {
                    let slope = (7.0f64 / 0.65).ln() / 8.0f64.ln();
                    let percent = 7.0 * (r.resolution as f64 / 2.0).powf(-slope);
                    Some(percent / 100.0 * report.object_size_m)
                }
                CompositeCase::Cantilever => (r.resolution >= 4).then_some(0.05 * u_ref),
            };
            if let Some(b) = bound_m {
                assert!(
                    ours.mean_m <= b,
                    "{case:?} {}: mean error {:.2} mm above the bound {:.2} mm",
                    r.label,
                    ours.mean_m * 1e3,
                    b * 1e3
                );
            }
            errors.push(ours.mean_m);
        }
        assert!(
            errors.windows(2).all(|w| w[1] < w[0]),
            "{case:?}: error did not fall with refinement: {errors:?}"
        );
    }
}

/// The neo-Hookean closed form (`ContinuumLaw`, which the volumetric correction and the spring
/// fits are built on) and the CalculiX card written for it (`material_card`) agree: one C3D8
/// cube is exact for a homogeneous state, so CalculiX's stretch under a dead uniaxial load must
/// be the closed form's, in tension and in compression. The hyperfoam card is not checked here:
/// Debian's CalculiX 2.20 exits with status 255 inside its solver on `*HYPERFOAM` even for this
/// one cube.
#[test]
#[cfg_attr(
    not(feature = "slow-tests"),
    ignore = "slow study (CalculiX): cargo test --features slow-tests"
)]
fn continuum_laws_match_calculix_hyperelastic_cards() {
    use lungmotion::model::ContinuumLaw;
    require_ccx();
    let edge = 0.01;
    for law in [ContinuumLaw::NeoHookean] {
        let material = Material::new(1000.0, 0.3, 1.0)
            .unwrap()
            .with_volumetric_law(Some(law));
        let (g, k) = (material.shear_modulus_pa(), material.bulk_modulus_pa());
        for nominal_pa in [150.0, -150.0] {
            // Closed form: lateral faces free, axial nominal stress = the dead load.
            let lateral = |l: f64| bisect(0.5, 1.5, |m| law.nominal_stress_pa([l, m, m], g, k)[1]);
            let axial = bisect(0.5, 1.6, |l| {
                law.nominal_stress_pa([l, lateral(l), lateral(l)], g, k)[0] - nominal_pa
            });
            let scene = symmetric_cubes(1, material, Matrix3::identity(), -nominal_pa);
            let options = CalculixOptions {
                initial_increment: 0.05,
                ..CalculixOptions::default()
            };
            let ccx = calculix::solve(&scene, &options).unwrap();
            let ux = ccx
                .displacements_m
                .iter()
                .map(|u| u.x)
                .max_by(|a, b| a.abs().total_cmp(&b.abs()))
                .unwrap();
            let uy = ccx
                .displacements_m
                .iter()
                .map(|u| u.y.abs())
                .fold(0.0, f64::max);
            let (want_x, want_y) = ((axial - 1.0) * edge, (lateral(axial) - 1.0).abs() * edge);
            eprintln!(
                "{law:?} P = {nominal_pa} Pa: CalculiX stretch {:.6} lateral {:.6}; closed form {axial:.6} {:.6}",
                1.0 + ux / edge,
                1.0 - uy / edge,
                lateral(axial)
            );
            assert!(
                (ux - want_x).abs() < 2e-4 * edge,
                "{law:?} {nominal_pa}: axial {ux} vs {want_x}"
            );
            assert!(
                (uy - want_y).abs() < 2e-4 * edge,
                "{law:?} {nominal_pa}: lateral {uy} vs {want_y}"
            );
        }
    }
}

/// Root of an increasing function on [lo, hi].
fn bisect(mut lo: f64, mut hi: f64, f: impl Fn(f64) -> f64) -> f64 {
    for _ in 0..80 {
        let mid = 0.5 * (lo + hi);
        if f(mid) > 0.0 {
            hi = mid;
        } else {
            lo = mid;
        }
    }
    0.5 * (lo + hi)
}

/// The cantilever and L refinement studies with both codes following compressible
/// neo-Hookean (ours: `continuum_correction = "neo_hookean"`; CalculiX: `*HYPERELASTIC, NEO
/// HOOKE`), printed beside the thesis's comparison (Baudet's springs against `*ELASTIC`) run on
/// the same meshes: what the correction changes in bending-dominated cases at ≤ 10 % strain.
/// The error must still fall with refinement.
#[test]
#[cfg_attr(
    not(feature = "slow-tests"),
    ignore = "slow study (CalculiX): cargo test --features slow-tests"
)]
fn composite_cases_with_the_continuum_correction() {
    use lungmotion::model::ContinuumLaw;
    require_ccx();
    for law in [None, Some(ContinuumLaw::NeoHookean)] {
        let options = CompositeOptions {
            check_reference_with_c3d8i: false,
            continuum_law: law,
            ..CompositeOptions::quick()
        };
        for (case, res) in [
            (CompositeCase::L, vec![2, 4]),
            (CompositeCase::Cantilever, vec![1, 2, 4]),
        ] {
            let report = run_case(case, &res, &options).unwrap();
            let mut errors = Vec::new();
            for r in &report.rows {
                let ours = r.mass_spring_error.unwrap_or_else(|| {
                    panic!("{law:?} {case:?} {}: {:?}", r.label, r.mass_spring_failure)
                });
                eprintln!(
                    "{law:?} {case:?} {}: ours {:.3} ± {:.3} mm ({:.2} % of size), max {:.3} mm; \
                     CalculiX {:.3} mm; max |u_ref| {:.2} mm",
                    r.label,
                    ours.mean_m * 1e3,
                    ours.sd_m * 1e3,
                    ours.mean_percent_of_size,
                    ours.max_m * 1e3,
                    r.calculix_error.unwrap().mean_m * 1e3,
                    report.reference_max_displacement_m * 1e3,
                );
                errors.push(ours.mean_m);
            }
            assert!(
                errors.windows(2).all(|w| w[1] < w[0]),
                "{law:?} {case:?}: error did not fall with refinement: {errors:?}"
            );
        }
    }
}
