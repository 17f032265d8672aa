//! The CIP lungs' 500 mL end-inhale frame at 8 mm against CalculiX (C3D8 reference, C3D8I
//! cross-check, both NLGEOM), on the same elements, constraints and follower pressure.
//!
//! Skips without the shared data; fails (never skips) without `ccx`, saying how to install it.
//!
//! Bounds come from the measured run (see the report this test writes), with headroom for
//! solver tolerances and platform round-off, not from what we would like: the two codes model
//! the same solid with different constitutive laws (Baudet's mass–spring element against St
//! Venant–Kirchhoff), so they agree to about 8 % of the mean displacement, not to round-off.
#![cfg(feature = "validation")]

use lungmotion::validation::calculix::{self, ElementType, CCX_INSTALL_HINT};
use lungmotion::validation::lung_calculix::{
    compare_end_inhale_with_calculix, LungCalculixSettings,
};

#[test]
#[cfg_attr(
    any(not(feature = "slow-tests"), not(shared_data)),
    ignore = "slow study (CalculiX on the CIP lungs): cargo test --features slow-tests with the shared CT data (../shared/data)"
)]
fn end_inhale_frame_agrees_with_calculix() {
    if lungmotion::datasets::cip_chest_ct64().is_none() {
        eprintln!("skipped: shared data not found");
        return;
    }
    if calculix::ccx_path().is_none() {
        panic!("CalculiX (`ccx`) is required by this test but was not found: {CCX_INSTALL_HINT}");
    }
    let settings = LungCalculixSettings::default();
    assert_eq!(
        settings.element_types,
        vec![ElementType::C3D8, ElementType::C3D8I]
    );
    let r = compare_end_inhale_with_calculix(&settings).unwrap();
    let dir = std::path::Path::new(env!("CARGO_TARGET_TMPDIR")).join("lung_calculix");
    r.write(&dir).unwrap();
    eprintln!("{}\nreport written to {}", r.to_markdown(), dir.display());

    // Our frame is the one asked for.
    let ours = &r.ours.field;
    assert!(
        (ours.volume_change_ml - settings.target_volume_ml).abs()
            <= settings.volume_tolerance_ml + 0.5,
        "{ours:?}"
    );
    assert!(
        r.pressure_pa < 0.0,
        "inhalation is suction: {}",
        r.pressure_pa
    );
    assert!(r.fixed_nodes > 0 && r.plane_nodes > 0 && r.line_nodes > 0);

    let c3d8 = &r.calculix[0];
    let ccx = &c3d8.field;
    // Both inflate, the base descends, and the largest motion is of the same size.
    assert!(
        ccx.volume_change_ml > 0.0 && ccx.diaphragm_mean_dz_mm < 0.0,
        "{ccx:?}"
    );
    assert!(ours.diaphragm_mean_dz_mm < 0.0, "{ours:?}");
    // Volume: measured 500 vs 455 mL (ours is softer in bulk at 10 % strain).
    let dv = (ours.volume_change_ml - ccx.volume_change_ml).abs() / ccx.volume_change_ml;
    assert!(dv <= 0.15, "volume changes differ by {:.1} %", 100.0 * dv);
    let dmax = (ours.max_displacement_mm - ccx.max_displacement_mm).abs() / ccx.max_displacement_mm;
    assert!(
        dmax <= 0.2,
        "max displacements differ by {:.1} %",
        100.0 * dmax
    );

    // Node by node (measured: mean 0.77 mm = 9.6 % of CalculiX's mean |u|, p95 1.81 mm,
    // max 2.7 mm on the diaphragm, where the displacement is largest).
    let d = &c3d8.ours_vs_calculix;
    assert!(d.mean_mm <= 1.2, "mean |Δu| {:.2} mm", d.mean_mm);
    assert!(
        d.mean_relative <= 0.15,
        "mean |Δu| / mean |u| = {:.3}",
        d.mean_relative
    );
    assert!(d.p95_mm <= 2.5, "95th percentile |Δu| {:.2} mm", d.p95_mm);
    assert!(d.max_mm <= 4.0, "max |Δu| {:.2} mm", d.max_mm);
    assert!(d.median_mm <= d.p95_mm && d.p95_mm <= d.max_mm);

    // The reference's own spread (C3D8 against C3D8I, measured 0.12 mm mean) is far below
    // the difference to ours: what separates the codes is the constitutive law, not locking.
    let spread = r.calculix_cross_check.as_ref().expect("C3D8I was run");
    assert!(
        spread.mean_mm <= 0.3,
        "C3D8 vs C3D8I mean {:.2} mm",
        spread.mean_mm
    );
    assert!(spread.mean_mm < 0.5 * d.mean_mm);

    // At 1 % of the pressure (linear CalculiX) the codes agree to 2.6 % of the mean |u| and
    // 1.6 % in volume: most of the end-inhale difference is the non-linear response (springs
    // linear in length against St Venant–Kirchhoff, whose Green strain stiffens in tension).
    let small = r.small_strain.as_ref().expect("small-strain check was run");
    let s = &small.ours_vs_calculix;
    assert!(
        s.mean_relative <= 0.05,
        "small strain: {:.3}",
        s.mean_relative
    );
    let dv_small = (small.ours_volume_change_ml - small.calculix_volume_change_ml).abs()
        / small.calculix_volume_change_ml.abs();
    assert!(
        dv_small <= 0.04,
        "small-strain volumes differ by {:.1} %",
        100.0 * dv_small
    );
    assert!(d.mean_relative > 2.0 * s.mean_relative);
}

/// The same frame with both codes following the compressible neo-Hookean law (ours through the
/// volumetric correction, CalculiX through `*HYPERELASTIC, NEO HOOKE`), against the linear
/// springs on the same CalculiX solution: what the volumetric law is worth at end-inhale; and
/// the cubic springs fitted to that law (`spring_law = "cubic"`).
#[test]
#[cfg_attr(
    any(not(feature = "slow-tests"), not(shared_data)),
    ignore = "slow study (CalculiX on the CIP lungs): cargo test --features slow-tests with the shared CT data (../shared/data)"
)]
fn end_inhale_frame_with_the_neo_hookean_law() {
    use lungmotion::model::{ContinuumLaw, Material, SpringLaw};
    if calculix::ccx_path().is_none() {
        panic!("CalculiX (`ccx`) is required by this test but was not found: {CCX_INSTALL_HINT}");
    }
    let law = Some(ContinuumLaw::NeoHookean);
    let mut means = Vec::new();
    let cubic = Material::LUNG
        .with_spring_law(SpringLaw::CubicNeoHookean)
        .unwrap();
    for ours in [
        Material::LUNG,
        Material::LUNG.with_volumetric_law(law),
        cubic,
    ] {
        let settings = LungCalculixSettings {
            material: ours,
            calculix_material: Some(Material::LUNG.with_volumetric_law(law)),
            element_types: vec![ElementType::C3D8],
            small_strain_fraction: None,
            ..LungCalculixSettings::default()
        };
        let r = compare_end_inhale_with_calculix(&settings).unwrap();
        eprintln!("{}", r.to_markdown());
        means.push(r.calculix[0].ours_vs_calculix.mean_mm);
    }
    eprintln!("mean |Δu| against CalculiX neo-Hookean: linear springs {:.3} mm, volumetric neo-Hookean {:.3} mm, cubic springs fitted to it {:.3} mm", means[0], means[1], means[2]);
    assert!(means.iter().all(|m| m.is_finite() && *m < 2.0), "{means:?}");
}

/// The same frame with our elements following neo-Hookean under any homogeneous deformation
/// (`continuum_correction = "neo_hookean"`) against CalculiX `NEO HOOKE`: issue 16's target
/// (mean |Δu| ≤ 0.3 mm, max ≤ 1 mm) at 500 mL; 1 500 mL is solved and reported too (printed,
/// not asserted: either code may stop before it).
#[test]
#[cfg_attr(
    any(not(feature = "slow-tests"), not(shared_data)),
    ignore = "slow study (CalculiX on the CIP lungs): cargo test --features slow-tests with the shared CT data (../shared/data)"
)]
fn end_inhale_frame_with_the_continuum_correction() {
    continuum_correction_against_calculix(&[500.0]);
}

/// The same at 1 500 mL: by hand only. Our volume search took about 8 minutes at that load
/// and CalculiX had not finished after 13 (2026-12-05), far beyond CI's budget.
#[test]
#[ignore = "very slow (CalculiX at 1 500 mL did not finish in 13 minutes): cargo test --release --features slow-tests --test lung_calculix -- --ignored deep_breath"]
fn end_inhale_frame_with_the_continuum_correction_deep_breath() {
    continuum_correction_against_calculix(&[1500.0]);
}

/// Our element with the continuum correction against CalculiX `NEO HOOKE` at each volume.
fn continuum_correction_against_calculix(volumes_ml: &[f64]) {
    use lungmotion::model::{ContinuumLaw, Material};
    if calculix::ccx_path().is_none() {
        panic!("CalculiX (`ccx`) is required by this test but was not found: {CCX_INSTALL_HINT}");
    }
    let law = Some(ContinuumLaw::NeoHookean);
    let ours = Material::LUNG.with_continuum_correction(law).unwrap();
    for &target_volume_ml in volumes_ml {
        let settings = LungCalculixSettings {
            material: ours,
            calculix_material: Some(Material::LUNG.with_volumetric_law(law)),
            element_types: vec![ElementType::C3D8],
            small_strain_fraction: None,
            target_volume_ml,
            ..LungCalculixSettings::default()
        };
        let r = match compare_end_inhale_with_calculix(&settings) {
            Ok(r) => r,
            Err(e) if target_volume_ml > 500.0 => {
                eprintln!("{target_volume_ml} mL: not solved: {e}");
                continue;
            }
            Err(e) => panic!("{target_volume_ml} mL: {e}"),
        };
        eprintln!("{}", r.to_markdown());
        let c = &r.calculix[0];
        let d = &c.ours_vs_calculix;
        eprintln!(
            "continuum neo-Hookean, {target_volume_ml} mL: pressure {:.2} Pa → CalculiX ΔV {:.0} mL \
             (ours {:.0} mL); mean |Δu| {:.3} mm ({:.1} % of mean |u|), p95 {:.2} mm, max {:.2} mm; \
             our pressure solve {:.2} s ({} Newton), volume search {:.2} s; CalculiX {:.1} s",
            r.pressure_pa,
            c.field.volume_change_ml,
            r.ours.field.volume_change_ml,
            d.mean_mm,
            100.0 * d.mean_relative,
            d.p95_mm,
            d.max_mm,
            r.ours.pressure_solve_wall_time_s,
            r.ours.newton_iterations,
            r.ours.volume_solve_wall_time_s,
            c.wall_time_s
        );
        if target_volume_ml == 500.0 {
            // Bounds from the measured run with headroom, not the target (see README).
            assert!(d.mean_mm.is_finite() && d.mean_mm < 2.0, "{d:?}");
        }
    }
}
