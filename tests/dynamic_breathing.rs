//! The optional dynamic breathing mode: bellows law P = V/C + R·V' + I·V'' on the trace,
//! explicit integration with Voigt dampers. Hysteresis appears with R > 0 and vanishes in
//! the slow, undamped, R = I = 0 limit, where frames match quasi-static equilibria.

use lungmotion::breathing::{BreathingTrace, LujanBreathing};
use lungmotion::model::Material;
use lungmotion::motion::dynamic::{run_dynamic, DynamicReport, DynamicSettings};
use lungmotion::motion::REFERENCE_PRESSURE_PA;
use lungmotion::simulation::cases::symmetric_block_under_pressure;
use lungmotion::simulation::{BreathingDriver, QuasiStaticSettings, Scene};
use nalgebra::Vector3;

type V3 = Vector3<f64>;

/// One octant of a 8 × 8 × 8 cm block of lung (10 mm elements), inflated by suction.
fn block() -> (Scene, f64) {
    let scene = symmetric_block_under_pressure([4, 4, 4], 0.01, Material::LUNG, -1.0).unwrap();
    let v0 = scene.mesh.enclosed_volume_m3(&scene.mesh.rest_positions_m) * 1e6;
    (scene, v0)
}

/// One symmetric breath (sin², inhalation over the first half) of `tidal_ml`.
fn breath(period_s: f64, tidal_ml: f64) -> BreathingTrace {
    LujanBreathing {
        period_s,
        tidal_volume_ml: tidal_ml,
        baseline_ml: 0.0,
        exponent: 1,
    }
    .trace(period_s, 100.0)
    .unwrap()
}

fn run(
    scene: &Scene,
    trace: &BreathingTrace,
    settings: &DynamicSettings,
    times: &[f64],
) -> (DynamicReport, Vec<Vec<V3>>) {
    let mut positions = Vec::new();
    let report = run_dynamic(scene, trace, settings, times, &mut |f, x| {
        assert_eq!(f.index, positions.len());
        positions.push(x.to_vec());
        Ok(())
    })
    .unwrap();
    (report, positions)
}

/// Largest node distance between each frame and the quasi-static equilibrium at the frame's
/// surface pressure, as a fraction of the largest quasi-static displacement of the run.
fn distance_to_quasi_static(scene: &Scene, report: &DynamicReport, frames: &[Vec<V3>]) -> f64 {
    let mut driver = BreathingDriver::new(
        scene,
        REFERENCE_PRESSURE_PA,
        1.0,
        QuasiStaticSettings::default(),
    )
    .unwrap();
    let rest = &scene.mesh.rest_positions_m;
    let (mut worst, mut scale) = (0.0f64, 0.0f64);
    for (f, x) in report.frames.iter().zip(frames) {
        let qs = driver.solve_pressure(f.surface_pressure_pa).unwrap();
        for ((a, b), r) in x.iter().zip(&qs.positions_m).zip(rest) {
            worst = worst.max((a - b).norm());
            scale = scale.max((b - r).norm());
        }
    }
    worst / scale
}

#[test]
fn slow_undamped_breathing_without_resistance_is_quasi_static() {
    let (scene, v0) = block();
    let tidal = 0.08 * v0;
    let settings = DynamicSettings {
        voigt_damping_ratio: 0.02,
        ..Default::default()
    };
    let slow = breath(8.0, tidal);
    let times: Vec<f64> = (1..8).map(|i| i as f64).collect();
    let (r, x) = run(&scene, &slow, &settings, &times);
    assert!(r.compliance_calibrated && r.compliance_ml_per_pa > 0.0);
    assert_eq!(r.frames.len(), 7);
    let slow_error = distance_to_quasi_static(&scene, &r, &x);
    // The trace's own volume is met (C is the secant compliance at its peak).
    assert!(
        r.max_volume_difference_ml <= 0.03 * tidal,
        "{} mL of {tidal} mL",
        r.max_volume_difference_ml
    );
    // The same breath 16 times faster excites the block's own modes.
    let fast = breath(0.5, tidal);
    let times: Vec<f64> = (1..8).map(|i| i as f64 / 16.0).collect();
    let (rf, xf) = run(&scene, &fast, &settings, &times);
    let fast_error = distance_to_quasi_static(&scene, &rf, &xf);
    eprintln!(
        "dynamic vs quasi-static: slow {slow_error:.4}, fast {fast_error:.4} of max |u|; step \
         {:.3e} s, {} steps",
        r.time_step.step_s, r.steps
    );
    assert!(slow_error <= 0.02, "slow breath: {slow_error}");
    assert!(
        fast_error > 3.0 * slow_error,
        "{fast_error} vs {slow_error}"
    );
}

#[test]
fn airway_resistance_opens_a_pressure_volume_loop() {
    let (scene, v0) = block();
    let tidal = 0.08 * v0;
    let period = 8.0;
    let trace = breath(period, tidal);
    // Mid-inhalation and mid-exhalation: the same trace volume, opposite flows ±πA/T.
    let times = [0.25 * period, 0.75 * period];
    let base = DynamicSettings {
        voigt_damping_ratio: 0.05,
        ..Default::default()
    };
    let (no_r, _) = run(&scene, &trace, &base, &times);
    let c = no_r.compliance_ml_per_pa;
    let [a, b] = [&no_r.frames[0], &no_r.frames[1]];
    assert!((a.bellows.volume_ml - b.bellows.volume_ml).abs() < 1e-6 * tidal);
    assert!(
        (a.simulated_volume_ml - b.simulated_volume_ml).abs() <= 0.02 * tidal,
        "no resistance, no loop: {} vs {} mL",
        a.simulated_volume_ml,
        b.simulated_volume_ml
    );

    // R such that the resistive pressure at peak flow is 20 % of the tidal elastic one.
    let r = 0.2 * period / (std::f64::consts::PI * c);
    let settings = DynamicSettings {
        compliance_ml_per_pa: Some(c),
        resistance_pa_s_per_ml: r,
        ..base
    };
    let (with_r, _) = run(&scene, &trace, &settings, &times);
    let [inh, exh] = [&with_r.frames[0], &with_r.frames[1]];
    let peak_flow = std::f64::consts::PI * tidal / period;
    assert!((inh.bellows.flow_ml_per_s - peak_flow).abs() < 0.01 * peak_flow);
    // Inhalation needs more suction than exhalation at the same trace volume…
    assert!(inh.surface_pressure_pa < exh.surface_pressure_pa);
    // …and the lung, following that pressure with its compliance, holds more air: the gap
    // is 2·C·R·V' = 40 % of the tidal volume for a quasi-static lung.
    let gap = inh.simulated_volume_ml - exh.simulated_volume_ml;
    let expected = 2.0 * c * r * peak_flow;
    eprintln!(
        "R = {r:.3} Pa·s/mL, C = {c:.4} mL/Pa: inhale {:.3} mL, exhale {:.3} mL, gap {gap:.3} \
         (quasi-static {expected:.3})",
        inh.simulated_volume_ml, exh.simulated_volume_ml
    );
    assert!(
        (gap - expected).abs() <= 0.1 * expected,
        "{gap} vs {expected}"
    );
}

#[test]
fn bad_inputs_are_refused_with_reasons() {
    let (scene, v0) = block();
    let trace = breath(4.0, 0.05 * v0);
    let settings = DynamicSettings::default();
    let err = run_dynamic(&scene, &trace, &settings, &[5.0], &mut |_, _| Ok(()))
        .unwrap_err()
        .to_string();
    assert!(err.contains("outside the trace"), "{err}");
    let flat = BreathingTrace::new(vec![0.0, 1.0], vec![0.0, 0.0]).unwrap();
    let err = run_dynamic(&scene, &flat, &settings, &[0.5], &mut |_, _| Ok(()))
        .unwrap_err()
        .to_string();
    assert!(err.contains("compliance"), "{err}");
}

/// Cost of one 4 s tidal cycle of the CIP lungs at 8 mm (measured: step 5.4 ms, 752 steps,
/// about 4 s of integration after 8–10 s of calibration). R is a quarter of the physiological
/// 0.2 Pa·s/mL: the whole bellows pressure loads the tissue, and at 0.2 Pa·s/mL the inhaling
/// lung (C ≈ 7 mL/Pa here) would take ≈ 150 Pa, beyond the ≈ 80 Pa this mesh survives.
#[test]
#[cfg_attr(
    any(not(feature = "slow-tests"), not(shared_data)),
    ignore = "slow study (large grid: CIP lungs): cargo test --features slow-tests with the shared CT data (../shared/data)"
)]
fn cip_lungs_one_dynamic_cycle() {
    if lungmotion::datasets::cip_chest_ct64().is_none() {
        eprintln!("skipped: shared data not found");
        return;
    }
    let model = lungmotion::datasets::cip_lung_model(8.0).unwrap();
    let scene = lungmotion::motion::lung_scene(&model).unwrap();
    let trace = LujanBreathing::default().trace(4.0, 25.0).unwrap();
    let settings = DynamicSettings {
        resistance_pa_s_per_ml: 0.05,
        inertance_pa_s2_per_ml: 0.001,
        ..Default::default()
    };
    let times: Vec<f64> = (0..=16).map(|i| i as f64 * 0.25).collect();
    let (r, _) = run(&scene, &trace, &settings, &times);
    eprintln!(
        "CIP 8 mm dynamic cycle: {} nodes, step {:.3e} s (critical {:.3e}), {} steps, setup \
         {:.1} s, integration {:.1} s, C {:.2} mL/Pa",
        scene.node_count(),
        r.time_step.step_s,
        r.time_step.critical_step_s,
        r.steps,
        r.setup_wall_time_s,
        r.integration_wall_time_s,
        r.compliance_ml_per_pa
    );
    for f in &r.frames {
        eprintln!(
            "  t {:.2} s: trace {:.0} mL, P {:.1} Pa, simulated {:.0} mL, max |u| {:.1} mm",
            f.time_s,
            f.bellows.volume_ml,
            f.bellows.pressure_pa,
            f.simulated_volume_ml,
            f.max_displacement_mm
        );
    }
    assert_eq!(r.frames.len(), times.len());
    let peak = r
        .frames
        .iter()
        .max_by(|a, b| a.simulated_volume_ml.total_cmp(&b.simulated_volume_ml))
        .unwrap();
    // The lung inhales about the trace's tidal volume around mid-cycle.
    assert!(peak.simulated_volume_ml > 300.0, "{peak:?}");
    assert!((1.0..=3.0).contains(&peak.time_s), "{peak:?}");
    // Hysteresis: at the same trace volume the inhaling lung holds more air than the
    // exhaling one (frames 6 and 10: t = 1.5 s and 2.5 s).
    let (inh, exh) = (&r.frames[6], &r.frames[10]);
    assert!((inh.bellows.volume_ml - exh.bellows.volume_ml).abs() < 1e-6);
    assert!(
        inh.simulated_volume_ml > exh.simulated_volume_ml + 100.0,
        "{inh:?} {exh:?}"
    );
}
