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

use lungmotion::model::HourglassLaw;
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

/// The same frame with the default element (`continuum_correction = "neo_hookean"`,
/// `hourglass = "full_integration"`: C3D8 with the neo-Hookean law at small strain) against
/// CalculiX C3D8 `NEO HOOKE`: issue 16's target (mean |Δu| ≤ 0.3 mm, max ≤ 1 mm) at 500 mL.
#[test]
#[cfg_attr(
    any(not(feature = "slow-tests"), not(shared_data)),
    ignore = "slow study (CalculiX on the CIP lungs): cargo test --features slow-tests with the shared CT data (../shared/data)"
)]
fn end_inhale_frame_of_the_default_element_meets_the_calculix_target() {
    continuum_correction_against_calculix(&[500.0], HourglassLaw::FullIntegration);
}

/// The same with the continuum correction but the springs' own hourglass response (the default
/// before 2026-12-05, measured 0.40 mm mean, 2.17 mm max). By hand (one more CalculiX run of the
/// lungs, about 4 minutes): `cargo test --release --features slow-tests --test lung_calculix --
/// --ignored springs_hourglass`.
#[test]
#[ignore = "slow study (CalculiX on the CIP lungs), by hand: cargo test --release --features slow-tests --test lung_calculix -- --ignored springs_hourglass"]
fn end_inhale_frame_with_the_continuum_correction_and_the_springs_hourglass() {
    continuum_correction_against_calculix(&[500.0], HourglassLaw::Springs);
}

/// The default element at 1 500 mL: by hand only. With the springs' hourglass response our
/// volume search took about 8 minutes at that load and CalculiX had not finished after 13;
/// with the default element CalculiX diverged in its first increment (2026-12-05).
#[test]
#[ignore = "by hand (CalculiX at 1 500 mL: unfinished after 13 minutes, then diverged in its first increment, 2026-12-05): cargo test --release --features slow-tests --test lung_calculix -- --ignored deep_breath"]
fn end_inhale_frame_of_the_default_element_deep_breath() {
    continuum_correction_against_calculix(&[1500.0], HourglassLaw::FullIntegration);
}

/// Our element with the continuum correction (and the hourglass response `hourglass`) against
/// CalculiX `NEO HOOKE` at each volume.
fn continuum_correction_against_calculix(volumes_ml: &[f64], hourglass: HourglassLaw) {
    use lungmotion::model::{ContinuumLaw, Material};
    if calculix::ccx_path().is_none() {
        panic!("CalculiX (`ccx`) is required by this test but was not found: {CCX_INSTALL_HINT}");
    }
    let law = Some(ContinuumLaw::NeoHookean);
    let ours = Material::LUNG
        .with_continuum_correction(law)
        .unwrap()
        .with_hourglass(hourglass);
    if hourglass == HourglassLaw::FullIntegration {
        assert_eq!(ours, Material::default(), "the run's default element");
    }
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
            if hourglass == HourglassLaw::FullIntegration {
                // Issue 16's target (measured 2026-12-05 at the same pressure: 0.03 mm mean,
                // 0.46 mm max).
                assert!(d.mean_mm <= 0.3 && d.max_mm <= 1.0, "{d:?}");
            }
        }
    }
}

/// Where the continuum-corrected element's remaining difference from CalculiX `NEO HOOKE` comes
/// from (issue 16, part 2): dumps the CIP 8 mm scene, our fields and CalculiX decks for the
/// by-hand analysis in `docs/studies/ccx_gap/` (CalculiX element variants, refined meshes, the
/// difference by group, direction and element). By hand only:
/// `LUNGMOTION_CCX_STUDY_DIR=/tmp/ccx-study cargo test --release --features slow-tests --test
/// lung_calculix -- --ignored --nocapture ccx_gap_study_dump`.
#[test]
#[ignore = "by-hand study (dumps the CIP scene and our fields for docs/studies/ccx_gap)"]
fn ccx_gap_study_dump() {
    use lungmotion::model::{
        BrickCoefficients, BrickShape, ContinuumLaw, Material, NodeConstraint,
    };
    use lungmotion::motion::{elastic_compliance_ml_per_pa, lung_scene, REFERENCE_PRESSURE_PA};
    use lungmotion::simulation::{BreathingDriver, QuasiStaticSettings, Scene};
    use lungmotion::validation::calculix::{write_deck, CalculixOptions};
    use std::io::Write as _;

    let dir = std::path::PathBuf::from(
        std::env::var("LUNGMOTION_CCX_STUDY_DIR").unwrap_or_else(|_| "/tmp/ccx-study".into()),
    );
    std::fs::create_dir_all(&dir).unwrap();
    let law = Some(ContinuumLaw::NeoHookean);
    let ours_material = Material::LUNG.with_continuum_correction(law).unwrap();
    let ccx_material = Material::LUNG.with_volumetric_law(law);
    let extra_volumes: Vec<f64> = std::env::var("LUNGMOTION_CCX_STUDY_VOLUMES")
        .ok()
        .map(|s| s.split(',').map(|v| v.trim().parse().unwrap()).collect())
        .unwrap_or_default();
    let model = lungmotion::datasets::cip_lung_model_of(8.0, ours_material).unwrap();
    let scene = lung_scene(&model).unwrap();
    let rest = scene.mesh.rest_positions_m.clone();
    let rest_volume_ml = scene.mesh.enclosed_volume_m3(&rest) * 1e6;
    let compliance = elastic_compliance_ml_per_pa(rest_volume_ml, &ours_material);
    let settings = QuasiStaticSettings::default();

    let write_field = |name: &str, u: &[lungmotion::math::V3]| {
        let mut f = std::io::BufWriter::new(std::fs::File::create(dir.join(name)).unwrap());
        for v in u {
            writeln!(f, "{:.15e} {:.15e} {:.15e}", v.x, v.y, v.z).unwrap();
        }
    };
    let scaled = |s: &Scene, factor: f64| {
        let mut s = s.clone();
        for p in &mut s.loads.pressures {
            p.pressure_pa *= factor;
        }
        for class in &mut s.mesh.classes {
            class.material = ccx_material;
        }
        s
    };

    // The mesh, groups and constraints.
    {
        let mut f = std::io::BufWriter::new(std::fs::File::create(dir.join("nodes.txt")).unwrap());
        for (p, g) in rest.iter().zip(&model.node_group) {
            writeln!(f, "{:.15e} {:.15e} {:.15e} {}", p.x, p.y, p.z, g).unwrap();
        }
        let mut f =
            std::io::BufWriter::new(std::fs::File::create(dir.join("elements.txt")).unwrap());
        for e in &scene.mesh.elements {
            let s: Vec<String> = e.iter().map(|c| c.to_string()).collect();
            writeln!(f, "{}", s.join(" ")).unwrap();
        }
        let mut f = std::io::BufWriter::new(std::fs::File::create(dir.join("faces.txt")).unwrap());
        for e in &scene.mesh.external_faces {
            let s: Vec<String> = e.iter().map(|c| c.to_string()).collect();
            writeln!(f, "{}", s.join(" ")).unwrap();
        }
        let mut f =
            std::io::BufWriter::new(std::fs::File::create(dir.join("constraints.txt")).unwrap());
        for (n, c) in &scene.constraints.entries {
            match c {
                NodeConstraint::Fixed { target_m: t } => {
                    writeln!(f, "{n} fixed {:.15e} {:.15e} {:.15e}", t.x, t.y, t.z)
                }
                NodeConstraint::Plane {
                    point_m: p,
                    normal: d,
                } => writeln!(
                    f,
                    "{n} plane {:.15e} {:.15e} {:.15e} {:.15e} {:.15e} {:.15e}",
                    p.x, p.y, p.z, d.x, d.y, d.z
                ),
                NodeConstraint::Line {
                    point_m: p,
                    direction: d,
                } => writeln!(
                    f,
                    "{n} line {:.15e} {:.15e} {:.15e} {:.15e} {:.15e} {:.15e}",
                    p.x, p.y, p.z, d.x, d.y, d.z
                ),
                NodeConstraint::Surface { .. } => writeln!(f, "{n} surface"),
            }
            .unwrap();
        }
    }
    // One 8 mm cube's small-strain stiffness (corner offsets, then the 24 × 24 matrix).
    for (name, m) in [("linear", Material::LUNG), ("corrected", ours_material)] {
        let c = BrickCoefficients::new(BrickShape::cube(8e-3), m).unwrap();
        let k = c.linear_stiffness();
        let mut f = std::fs::File::create(dir.join(format!("cube_k_{name}.txt"))).unwrap();
        for o in c.corner_offsets_m() {
            writeln!(f, "{:.15e} {:.15e} {:.15e}", o.x, o.y, o.z).unwrap();
        }
        for r in 0..24 {
            let row: Vec<String> = (0..24).map(|c| format!("{:.15e}", k[(r, c)])).collect();
            writeln!(f, "{}", row.join(" ")).unwrap();
        }
    }

    // The corrected cube's tangent stiffness (central differences of its corner forces) at a few
    // homogeneous states F: the 24 × 24 matrix after the row "F" with F row-major.
    {
        let c = BrickCoefficients::new(BrickShape::cube(8e-3), ours_material).unwrap();
        let offsets = c.corner_offsets_m();
        let mut out = String::new();
        let states: [[f64; 9]; 5] = [
            [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
            [1.0323, 0.0, 0.0, 0.0, 1.0323, 0.0, 0.0, 0.0, 1.0323],
            [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.1],
            [1.05, 0.0, 0.0, 0.0, 1.05, 0.0, 0.0, 0.0, 1.1],
            [1.03, 0.1, 0.0, 0.0, 1.03, 0.0, 0.0, 0.0, 1.03],
        ];
        for fs in states {
            let f = nalgebra::Matrix3::from_row_slice(&fs);
            let x0 = offsets.map(|o| f * o);
            let h = 1e-9;
            out += &format!("F {}\n", fs.map(|v| v.to_string()).join(" "));
            let mut k = vec![[0.0f64; 24]; 24];
            for col in 0..24 {
                let (mut xp, mut xm) = (x0, x0);
                xp[col / 3][col % 3] += h;
                xm[col / 3][col % 3] -= h;
                let (fp, fm) = (c.corner_forces(&xp, None), c.corner_forces(&xm, None));
                for row in 0..24 {
                    // force = −K·u
                    k[row][col] = -(fp[row / 3][row % 3] - fm[row / 3][row % 3]) / (2.0 * h);
                }
            }
            for row in k {
                out += &row.map(|v| format!("{v:.12e}")).join(" ");
                out += "\n";
            }
        }
        std::fs::write(dir.join("cube_tangents_corrected.txt"), out).unwrap();
    }

    // Ours at 500 mL (volume search, then a fresh solve from rest at that pressure, as the
    // comparison does), at 1 % of that pressure, and at the extra volumes asked for.
    let mut driver =
        BreathingDriver::new(&scene, REFERENCE_PRESSURE_PA, compliance, settings.clone()).unwrap();
    let p = driver.solve_volume(500.0, 2.5).unwrap().pressure_pa;
    let mut summary = format!("rest_volume_ml {rest_volume_ml}\npressure_pa {p}\n");
    let mut fresh =
        BreathingDriver::new(&scene, REFERENCE_PRESSURE_PA, compliance, settings.clone()).unwrap();
    let s = fresh.solve_pressure(p).unwrap();
    summary += &format!("ours_500_volume_ml {}\n", s.volume_change_ml);
    write_field("u_ours_500.txt", &scene.displacements(&s.positions_m));
    let mut fresh =
        BreathingDriver::new(&scene, REFERENCE_PRESSURE_PA, compliance, settings.clone()).unwrap();
    let s = fresh.solve_pressure(0.01 * p).unwrap();
    summary += &format!("ours_small_volume_ml {}\n", s.volume_change_ml);
    write_field("u_ours_small.txt", &scene.displacements(&s.positions_m));
    for v in extra_volumes {
        let s = driver.solve_volume(v, 0.2).unwrap();
        summary += &format!(
            "ours_{v}_pressure_pa {}\nours_{v}_volume_ml {}\n",
            s.pressure_pa, s.volume_change_ml
        );
        write_field(
            &format!("u_ours_{v}.txt"),
            &scene.displacements(&s.positions_m),
        );
    }
    // The same frame with the hourglass response of a continuum element (issue 16's gap study):
    // at CalculiX's pressure p (the comparison's frame) and at 500 mL, and at 1 % of p.
    if std::env::var("LUNGMOTION_CCX_STUDY_HOURGLASS").is_ok() {
        for (name, law) in [
            ("inc", HourglassLaw::IncompatibleModes),
            ("full", HourglassLaw::FullIntegration),
        ] {
            let m = ours_material.with_hourglass(law);
            let model = lungmotion::datasets::cip_lung_model_of(8.0, m).unwrap();
            let scene = lung_scene(&model).unwrap();
            for (tag, pressure) in [("p", p), ("small", 0.01 * p)] {
                let mut d = BreathingDriver::new(
                    &scene,
                    REFERENCE_PRESSURE_PA,
                    compliance,
                    settings.clone(),
                )
                .unwrap();
                let t = std::time::Instant::now();
                let s = d.solve_pressure(pressure).unwrap();
                summary += &format!(
                    "hg_{name}_{tag}_volume_ml {} ({} Newton, {:.2} s)\n",
                    s.volume_change_ml,
                    s.newton_iterations,
                    t.elapsed().as_secs_f64()
                );
                write_field(
                    &format!("u_hg_{name}_{tag}.txt"),
                    &scene.displacements(&s.positions_m),
                );
            }
            let mut d =
                BreathingDriver::new(&scene, REFERENCE_PRESSURE_PA, compliance, settings.clone())
                    .unwrap();
            let s = d.solve_volume(500.0, 0.5).unwrap();
            summary += &format!("hg_{name}_500_pressure_pa {}\n", s.pressure_pa);
            write_field(
                &format!("u_hg_{name}_500.txt"),
                &scene.displacements(&s.positions_m),
            );
        }
    }
    std::fs::write(dir.join("summary.txt"), &summary).unwrap();
    eprintln!("{summary}");

    // CalculiX decks at that pressure (NLGEOM, neo-Hookean) and at 1 % (linear).
    let deck = write_deck(
        &scaled(&scene, p / REFERENCE_PRESSURE_PA),
        &CalculixOptions::default(),
    )
    .unwrap();
    std::fs::write(dir.join("c3d8_nh.inp"), deck).unwrap();
    let deck = write_deck(
        &scaled(&scene, 0.01 * p / REFERENCE_PRESSURE_PA),
        &CalculixOptions::linear(),
    )
    .unwrap();
    std::fs::write(dir.join("c3d8_small.inp"), deck).unwrap();
    eprintln!("written to {}", dir.display());
}
