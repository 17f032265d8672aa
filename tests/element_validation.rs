//! Single-element validation: patch tests against the closed forms of the thesis (§3.3,
//! extraction §1.6) and large-strain error curves against the thesis's published limits
//! (§3.3.4, Figs. 3.42, 3.43, 3.50).
#![cfg(feature = "validation")]

use lungmotion::model::{BrickCoefficients, BrickShape, Material};
use lungmotion::validation::patch::{
    grid_free_shear_ratio, kernel_linearisation_error, patch_case, predicted_free_shear_ratio,
    run_patch_tests, ForceModel, PatchConfig,
};
use lungmotion::validation::sweep::{
    bulk_curve, run_strain_sweeps, thesis, traction_curve, SweepConfig,
};

const CUBE: [f64; 3] = [0.01, 0.01, 0.01];
const BRICK: [f64; 3] = [0.010, 0.012, 0.009];

fn material(nu: f64) -> Material {
    Material::new(1000.0, nu, 700.0).unwrap()
}

#[test]
fn elements_reproduce_e_nu_and_k_at_small_strain() {
    for edges in [CUBE, BRICK] {
        for nu in [0.1, 0.3, 0.45] {
            // Exact on the linearised stiffness (the closed forms alone)…
            let lin = patch_case(edges, material(nu), 1e-7, ForceModel::Linearised).unwrap();
            assert!(
                lin.max_error_e_nu_k < 1e-8,
                "{edges:?} ν={nu} linearised: {lin:?}"
            );
            // …and to 1e-5 with the production force kernel at 1e-7 strain.
            let nl = patch_case(edges, material(nu), 1e-7, ForceModel::Nonlinear).unwrap();
            assert!(
                nl.max_error_e_nu_k < 1e-5,
                "{edges:?} ν={nu} kernel: {nl:?}"
            );
            assert_eq!(nl.poisson_ratio_ratios.len(), 6);
        }
    }
}

#[test]
fn cube_shear_is_exact_and_brick_shear_matches_the_published_ratios() {
    for nu in [0.1, 0.3, 0.45] {
        let cube = patch_case(CUBE, material(nu), 1e-7, ForceModel::Nonlinear).unwrap();
        for g in &cube.shear {
            assert!((g.affine_ratio - 1.0).abs() < 1e-5, "cube ν={nu}: {g:?}");
        }
    }
    // Extraction §1.6: 1.337, 0.752, 1.083 for planes xy, xz, yz of a 1 × 1.2 × 0.9 brick.
    let published = [1.337, 0.752, 1.083];
    for model in [ForceModel::Linearised, ForceModel::Nonlinear] {
        let brick = patch_case(BRICK, material(0.3), 1e-7, model).unwrap();
        for (g, want) in brick.shear.iter().zip(published) {
            assert!((g.affine_ratio - want).abs() < 5e-4, "{model:?} {g:?}");
            assert!(
                (g.affine_ratio / g.predicted_ratio - 1.0).abs() < 1e-5,
                "{g:?}"
            );
        }
    }
}

#[test]
fn free_traction_shear_relaxes_the_warping_mode_and_grids_recover_g() {
    // A lone element under pure-shear tractions is softer than under affine shear: its warping
    // mode puts the k-edges in series with the body diagonals. Cube: (1+4ν)/(2+4ν).
    for nu in [0.1, 0.3, 0.45] {
        let c = patch_case(CUBE, material(nu), 1e-7, ForceModel::Nonlinear).unwrap();
        let want = (1.0 + 4.0 * nu) / (2.0 + 4.0 * nu);
        for g in &c.shear {
            assert!(
                (g.free_ratio / want - 1.0).abs() < 1e-5,
                "ν={nu}: {g:?} vs {want}"
            );
            assert!(g.free_support_reaction < 1e-6, "{g:?}");
        }
    }
    let coeffs = BrickCoefficients::new(BrickShape { edges_m: BRICK }, material(0.3)).unwrap();
    let brick = patch_case(BRICK, material(0.3), 1e-7, ForceModel::Linearised).unwrap();
    for g in &brick.shear {
        let want = predicted_free_shear_ratio(&coeffs, g.plane);
        assert!((g.free_ratio / want - 1.0).abs() < 1e-8, "{g:?}");
    }
    // In a grid the mode must alternate between neighbours: G climbs back towards 1.
    let ratios: Vec<f64> = (1..=4)
        .map(|n| grid_free_shear_ratio(n, 0.01, material(0.3)).unwrap())
        .collect();
    assert!((ratios[0] - 0.6875).abs() < 1e-9, "{ratios:?}");
    assert!(ratios.windows(2).all(|w| w[1] > w[0]), "{ratios:?}");
    assert!(ratios[3] > 0.97, "{ratios:?}");
}

#[test]
fn force_kernel_linearises_to_the_element_stiffness() {
    for edges in [CUBE, BRICK] {
        for nu in [0.1, 0.3, 0.45] {
            let err = kernel_linearisation_error(edges, material(nu)).unwrap();
            assert!(err < 1e-7, "{edges:?} ν={nu}: {err:e}");
        }
    }
}

#[test]
fn patch_report_passes_and_renders() {
    let config = PatchConfig {
        grid_sizes: vec![1, 2],
        ..PatchConfig::default()
    };
    let report = run_patch_tests(&config).unwrap();
    assert!(report.passed);
    assert_eq!(report.cases.len(), 2 * 3 * 2);
    let md = report.to_markdown();
    assert!(md.contains("1.337") && md.contains("| 2 | 0.3 |"), "{md}");
    serde_json::to_string(&report).unwrap();
}

#[test]
fn traction_errors_match_the_thesis_at_ten_percent() {
    // Thesis §3.3.4: |E error| at 10 % strain is 2.75 % (ν = 0.3), 2 % (0.4), 1.75 % (→ 0.5).
    let config = SweepConfig {
        max_strain: 0.20,
        strain_step: 0.01,
        ..SweepConfig::default()
    };
    for (nu, published) in thesis::YOUNGS_ERROR_AT_10_PERCENT {
        let curve = traction_curve(&config, material(nu)).unwrap();
        let at10 = curve
            .points
            .iter()
            .find(|p| (p.strain - 0.10).abs() < 1e-12)
            .unwrap();
        assert!(
            (at10.youngs_error.abs() - published).abs() < 0.003,
            "ν={nu}: ours {:.4} vs thesis {published}",
            at10.youngs_error
        );
        for p in &curve.points {
            // Lateral faces are free and the cube contracts equally in y and z.
            assert!(p.lateral_reaction < 1e-9, "{p:?}");
            assert!(p.lateral_asymmetry < 1e-9, "{p:?}");
            assert!(p.production_solver_difference < 1e-7, "{p:?}");
        }
        // The ν error crosses 5 % near the thesis's 12 % (ours: 12.8–14.6 %).
        let nu_cross = curve.poisson_5_percent_strain.unwrap();
        assert!((0.11..0.16).contains(&nu_cross), "ν={nu}: {nu_cross}");
    }
    // E error crosses 5 % at 17.5 % for ν = 0.3 (thesis: 16 %).
    let c = traction_curve(&config, material(0.3)).unwrap();
    let e_cross = c.youngs_5_percent_strain.unwrap();
    assert!((0.15..0.19).contains(&e_cross), "{e_cross}");
}

#[test]
fn bulk_error_follows_its_closed_form_and_stays_near_five_percent_at_fifteen() {
    let config = SweepConfig::default();
    for nu in [0.1, 0.49] {
        let curve = bulk_curve(&config, material(nu)).unwrap();
        for p in &curve.points {
            assert!(
                (p.bulk_error - p.predicted_bulk_error).abs() < 1e-9,
                "ν={nu}: {p:?}"
            );
        }
        // Thesis: |K error| < 5 % within ±15 % volume. Ours: 5 % is reached at −13.8 % in
        // compression and +16.3 % in inflation.
        let c = curve.compression_5_percent_volume.unwrap();
        let i = curve.inflation_5_percent_volume.unwrap();
        assert!((c - 0.138).abs() < 0.002, "{c}");
        assert!((i - 0.163).abs() < 0.002, "{i}");
    }
}

#[test]
fn error_curves_do_not_depend_on_youngs_modulus() {
    let config = SweepConfig {
        poisson_ratios: vec![0.3],
        youngs_moduli_pa: vec![100.0, 1.0e5],
        strain_step: 0.02,
        volume_changes: vec![-0.15, -0.05, 0.05, 0.15],
        ..SweepConfig::default()
    };
    let report = run_strain_sweeps(&config).unwrap();
    assert_eq!(report.traction.len(), 2);
    assert!(
        report.youngs_modulus_dependence < 1e-9,
        "{}",
        report.youngs_modulus_dependence
    );
    assert!(report.production_solver_difference < 1e-7);
    let md = report.to_markdown();
    assert!(md.contains("2.75 %"), "{md}");
}

/// The cubic springs and the volumetric laws change nothing at small strain: E, ν and K stay
/// Baudet's (the cubic term is O(d³), the volumetric correction O((J − 1)²)).
#[test]
fn cubic_springs_and_volumetric_laws_keep_e_nu_and_k_at_small_strain() {
    use lungmotion::model::{ContinuumLaw, SpringLaw};
    for edges in [CUBE, BRICK] {
        for (spring, vol) in [
            (SpringLaw::Cubic(5.0), None),
            (SpringLaw::Linear, Some(ContinuumLaw::Hyperfoam)),
            (SpringLaw::Cubic(2.0), Some(ContinuumLaw::LungBirzle)),
            (SpringLaw::Linear, Some(ContinuumLaw::NeoHookean)),
        ] {
            let m = material(0.3)
                .with_spring_law(spring)
                .unwrap()
                .with_volumetric_law(vol);
            let nl = patch_case(edges, m, 1e-7, ForceModel::Nonlinear).unwrap();
            assert!(
                nl.max_error_e_nu_k < 1e-5,
                "{edges:?} {spring:?} {vol:?}: {nl:?}"
            );
            let err = kernel_linearisation_error(edges, m).unwrap();
            assert!(err < 1e-7, "{edges:?} {spring:?} {vol:?}: {err:e}");
        }
    }
}

/// The continuum correction changes nothing at small strain where Baudet's element is already
/// exact: E, ν and K of the nonlinear patch tests keep 1e-5 on cubes and bricks (uniaxial
/// loads: the brick is exact there), and on a cube the kernel's linearisation is still the
/// element's small-strain stiffness (the cube is exact in shear too, so the correction is
/// second order). On a non-cubic brick it is not: Baudet's brick is not exact in shear, and the
/// correction makes its homogeneous shear the law's, a first-order change (measured, printed).
#[test]
fn the_continuum_correction_keeps_e_nu_and_k_at_small_strain() {
    use lungmotion::model::{ContinuumLaw, HourglassLaw, SpringLaw};
    for edges in [CUBE, BRICK] {
        for (spring, law) in [
            (SpringLaw::Linear, ContinuumLaw::NeoHookean),
            (SpringLaw::Cubic(2.0), ContinuumLaw::Hyperfoam),
            (SpringLaw::Linear, ContinuumLaw::LungBirzle),
        ] {
            for hourglass in [
                HourglassLaw::Springs,
                HourglassLaw::IncompatibleModes,
                HourglassLaw::FullIntegration,
            ] {
                let m = material(0.3)
                    .with_spring_law(spring)
                    .unwrap()
                    .with_continuum_correction(Some(law))
                    .unwrap()
                    .with_hourglass(hourglass);
                let nl = patch_case(edges, m, 1e-7, ForceModel::Nonlinear).unwrap();
                assert!(
                    nl.max_error_e_nu_k < 1e-5,
                    "{edges:?} {spring:?} {law:?} {hourglass:?}: {nl:?}"
                );
                // The hourglass correction is in `linear_stiffness()` too, so the kernel still
                // linearises to it.
                let err = kernel_linearisation_error(edges, m).unwrap();
                eprintln!(
                    "{edges:?} {spring:?} {law:?} {hourglass:?}: linearisation differs by {err:e}"
                );
                if edges == CUBE {
                    assert!(err < 1e-7, "{edges:?} {spring:?} {law:?}: {err:e}");
                }
            }
        }
    }
}
