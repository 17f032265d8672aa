//! The model's pressure–volume curve: the pleural pressure the volume driver needs to inflate
//! the CIP lungs from the scanned state to +2 L, for each material law, beside the
//! physiological shape.
//!
//! Each curve is one breathing run's load path: the CIP expert lungs at the given element
//! size, the run's scene ([`run_scene`]: hilum fixed, sliding walls, the costal wall moving
//! with the rib cage's share), one [`BreathingDriver`] stepping its volume target up by
//! `step_ml` (each step warm-started from the last). A material that cannot reach a volume
//! stops there and the failure is reported (volume reached, the most compressed element, the
//! solver's cause): a measured failure is a result. The pressure reported is the distending
//! pressure, the negative of the surface pressure (suction inflates).
//!
//! The physiological curve is the exponential of Salazar and Knowles (J. Appl. Physiol. 19,
//! 97–104, 1964), V = V_max·(1 − e^(−P·C₀/V_max)), linear over the tidal range (slope C₀ at
//! rest) and flattening towards total capacity, as `domain.md` describes it: C₀ = 2 mL/Pa
//! (0.2 L/cmH₂O for both lungs) and V_max the lungs' rest volume (the volume at most doubles).

use std::path::Path;
use std::time::Instant;

use serde::Serialize;

use crate::ingest::lung_model::LungModel;
use crate::model::{Material, SpringLaw};
use crate::motion::{
    elastic_compliance_ml_per_pa, run_scene, WallMotion, BREATHING_SOLVER_TOLERANCE,
    PHYSIOLOGICAL_RIB_CAGE_SHARE, REFERENCE_PRESSURE_PA,
};
use crate::outputs::plots::{render_line_chart, LineSeries};
use crate::simulation::{BreathingDriver, CancelFlag, QuasiStaticSettings};
use crate::{Error, Result};

/// File name of the P–V plot in the validation report's directory.
pub const PRESSURE_VOLUME_PNG: &str = "pressure-volume.png";
/// Static compliance of both lungs in the tidal range, mL/Pa (`domain.md`: ≈ 0.2 L/cmH₂O).
pub const PHYSIOLOGICAL_COMPLIANCE_ML_PER_PA: f64 = 2.0;

/// One material law of the study.
#[derive(Debug, Clone, Serialize)]
pub struct PvMaterial {
    /// Name in the report (e.g. `linear`, `cubic:8.6667`).
    pub name: String,
    /// The material.
    pub material: Material,
}

/// What the study inflates and how.
#[derive(Debug, Clone, Serialize)]
pub struct PressureVolumeConfig {
    /// Edge of the cubic elements, mm.
    pub element_size_mm: f64,
    /// Volume step between two points, mL.
    pub step_ml: f64,
    /// Largest volume change asked for, mL.
    pub max_volume_ml: f64,
    /// Share of each volume change the costal wall makes (the run's default).
    pub rib_cage_share: f64,
    /// Tolerance on each volume, mL.
    pub volume_tolerance_ml: f64,
    /// Wall time one curve may take before it is stopped, s.
    pub time_budget_s: f64,
    /// The laws, one curve each.
    pub materials: Vec<PvMaterial>,
}

impl PressureVolumeConfig {
    /// The study: 8 mm elements, 0 → 2000 mL by 100 mL, the run's chest wall, linear springs, the fitted cubic law, Boux de Casson's ratio and
    /// linear springs with the volumetric hyperfoam law; 10 minutes per curve at most.
    pub fn standard() -> Self {
        let with = |name: &str, spring_law, volumetric_law| PvMaterial {
            name: name.into(),
            material: Material {
                spring_law,
                volumetric_law,
                ..Material::LUNG
            },
        };
        PressureVolumeConfig {
            element_size_mm: 8.0,
            step_ml: 100.0,
            max_volume_ml: 2000.0,
            rib_cage_share: PHYSIOLOGICAL_RIB_CAGE_SHARE,
            volume_tolerance_ml: 2.0,
            time_budget_s: 600.0,
            materials: vec![
                with("linear", SpringLaw::Linear, None),
                with("cubic (fitted)", SpringLaw::CubicNeoHookean, None),
                with("cubic:8.6667", SpringLaw::Cubic(1.3 / 0.15), None),
                with(
                    "linear + hyperfoam",
                    SpringLaw::Linear,
                    Some(crate::model::ContinuumLaw::Hyperfoam),
                ),
            ],
        }
    }
}

/// One point of a P–V curve.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct PvPoint {
    /// Lung volume change from the scanned state, mL.
    pub volume_ml: f64,
    /// Distending pressure (the negative of the surface pressure), Pa.
    pub pressure_pa: f64,
    /// Equilibrium solves spent on this point (0 for the reference curves).
    pub solves: usize,
    /// Solver wall time of this point, s.
    pub wall_time_s: f64,
}

/// Where and why a curve stopped before its last volume.
#[derive(Debug, Clone, Serialize)]
pub struct PvFailure {
    /// The volume asked for, mL.
    pub target_ml: f64,
    /// Volume of the last equilibrium reached, mL.
    pub reached_ml: f64,
    /// The most compressed element there, its rest centre (LPS mm), volume ratio and
    /// anatomical groups, when the solver named one.
    pub element: Option<usize>,
    /// Rest centre of that element, LPS mm.
    pub centre_lps_mm: Option<[f64; 3]>,
    /// Its volume over its rest volume.
    pub volume_ratio: Option<f64>,
    /// Anatomical groups of its nodes.
    pub groups: Option<String>,
    /// The solver's message.
    pub cause: String,
}

/// One material's P–V curve.
#[derive(Debug, Clone, Serialize)]
pub struct PvCurve {
    /// The law's name.
    pub name: String,
    /// Spring law and volumetric law as configured.
    pub material: Material,
    /// The scanned state, then one point per volume reached.
    pub points: Vec<PvPoint>,
    /// Why the curve stopped early, if it did.
    pub failure: Option<PvFailure>,
    /// Wall time of the whole curve (model, preconditioner, solves), s.
    pub wall_time_s: f64,
}

impl PvCurve {
    /// Largest volume change reached, mL.
    pub fn reached_ml(&self) -> f64 {
        self.points.last().map_or(0.0, |p| p.volume_ml)
    }
}

/// The study's result.
#[derive(Debug, Clone, Serialize)]
pub struct PressureVolumeReport {
    /// Settings.
    pub config: PressureVolumeConfig,
    /// Which CT and lungs.
    pub lungs: String,
    /// Volume inside the lung surface at rest, mL.
    pub rest_volume_ml: f64,
    /// Elements and nodes of the mesh.
    pub elements: usize,
    /// Nodes of the mesh.
    pub nodes: usize,
    /// Small-strain compliance of the homogeneous linear lung, 3V₀(1 − 2ν)/E, mL/Pa.
    pub elastic_compliance_ml_per_pa: f64,
    /// The physiological curve (Salazar–Knowles, see the module doc).
    pub physiological: Vec<PvPoint>,
    /// The first curve's compliance over its first step, mL/Pa (the model at rest).
    pub model_compliance_at_rest_ml_per_pa: f64,
    /// The physiological shape with the model's compliance at rest as C₀: how the model's
    /// curve would bend if it stiffened as lungs do.
    pub physiological_shape_at_model_compliance: Vec<PvPoint>,
    /// The model's curves.
    pub curves: Vec<PvCurve>,
    /// Wall time of the study, s.
    pub wall_time_s: f64,
}

/// Distending pressure of the physiological curve at volume change `volume_ml`, Pa:
/// P = −(V_max/C₀)·ln(1 − V/V_max); infinite at and beyond `max_volume_ml`.
pub fn physiological_pressure_pa(
    volume_ml: f64,
    compliance_ml_per_pa: f64,
    max_volume_ml: f64,
) -> f64 {
    if volume_ml >= max_volume_ml {
        return f64::INFINITY;
    }
    -(max_volume_ml / compliance_ml_per_pa) * (1.0 - volume_ml / max_volume_ml).ln()
}

/// Runs the study on the CIP lungs (needs the shared data).
pub fn run_pressure_volume_study(config: &PressureVolumeConfig) -> Result<PressureVolumeReport> {
    let start = Instant::now();
    if !(config.step_ml > 0.0 && config.max_volume_ml >= config.step_ml) {
        return Err(Error::Argument {
            what: "pressure–volume study".into(),
            reason: format!(
                "step {} mL and largest volume {} mL: the step must be positive and not above \
                 the largest volume",
                config.step_ml, config.max_volume_ml
            ),
        });
    }
    let mut curves = Vec::new();
    let mut lungs = None;
    for m in &config.materials {
        let t0 = Instant::now();
        let model = crate::datasets::cip_lung_model_of(config.element_size_mm, m.material)?;
        let mut curve = inflate(&model, m, config)?;
        curve.wall_time_s = t0.elapsed().as_secs_f64();
        tracing::info!(law = %m.name, reached_ml = curve.reached_ml(), "P–V curve");
        curves.push(curve);
        lungs.get_or_insert(model);
    }
    let Some(model) = lungs else {
        return Err(Error::Argument {
            what: "pressure–volume study".into(),
            reason: "no material to inflate".into(),
        });
    };
    let mesh = &model.mesh.mesh;
    let rest_volume_ml = mesh.enclosed_volume_m3(&mesh.rest_positions_m) * 1e6;
    let reference = |c0: f64| -> Vec<PvPoint> {
        (0..)
            .map(|k| k as f64 * config.step_ml)
            .take_while(|&v| v <= config.max_volume_ml + 1e-9 && v < rest_volume_ml)
            .map(|v| PvPoint {
                volume_ml: v,
                pressure_pa: physiological_pressure_pa(v, c0, rest_volume_ml),
                solves: 0,
                wall_time_s: 0.0,
            })
            .collect()
    };
    let model_c0 = curves[0]
        .points
        .get(1)
        .map_or(f64::NAN, |p| p.volume_ml / p.pressure_pa);
    let physiological = reference(PHYSIOLOGICAL_COMPLIANCE_ML_PER_PA);
    let physiological_shape_at_model_compliance = if model_c0.is_finite() && model_c0 > 0.0 {
        reference(model_c0)
    } else {
        Vec::new()
    };
    Ok(PressureVolumeReport {
        config: config.clone(),
        lungs: "CIP chest CT ct-64, expert lung labels".into(),
        rest_volume_ml,
        elements: mesh.element_count(),
        nodes: mesh.rest_positions_m.len(),
        elastic_compliance_ml_per_pa: elastic_compliance_ml_per_pa(rest_volume_ml, &Material::LUNG),
        physiological,
        model_compliance_at_rest_ml_per_pa: model_c0,
        physiological_shape_at_model_compliance,
        curves,
        wall_time_s: start.elapsed().as_secs_f64(),
    })
}

/// One material's load path from rest to the largest volume, or to where it fails.
fn inflate(model: &LungModel, m: &PvMaterial, config: &PressureVolumeConfig) -> Result<PvCurve> {
    let scene = run_scene(
        model,
        &WallMotion {
            rib_cage_share: config.rib_cage_share,
            dome_flattening: 0.0,
            ..WallMotion::default()
        },
    )?;
    let rest_ml = scene.mesh.enclosed_volume_m3(&scene.mesh.rest_positions_m) * 1e6;
    let settings = QuasiStaticSettings {
        tolerance: BREATHING_SOLVER_TOLERANCE,
        ..QuasiStaticSettings::default()
    };
    let mut driver = BreathingDriver::new(
        &scene,
        REFERENCE_PRESSURE_PA,
        elastic_compliance_ml_per_pa(rest_ml, &m.material),
        settings,
    )?;
    // A curve that grinds past its budget is stopped at its next check, as a run would be.
    let cancel = CancelFlag::default();
    driver.set_cancel(cancel.clone());
    driver.share_volume_with_imposed_motion(config.rib_cage_share)?;
    let mut points = vec![PvPoint {
        volume_ml: 0.0,
        pressure_pa: 0.0,
        solves: 0,
        wall_time_s: 0.0,
    }];
    let mut failure = None;
    let (stop, stopped) = std::sync::mpsc::channel::<()>();
    let budget = std::time::Duration::from_secs_f64(config.time_budget_s);
    std::thread::scope(|s| {
        let flag = cancel.clone();
        s.spawn(move || {
            if let Err(std::sync::mpsc::RecvTimeoutError::Timeout) = stopped.recv_timeout(budget) {
                flag.store(true, std::sync::atomic::Ordering::SeqCst);
            }
        });
        let steps = (config.max_volume_ml / config.step_ml).round() as usize;
        for k in 1..=steps {
            let target = (k as f64 * config.step_ml).min(config.max_volume_ml);
            match driver.solve_volume(target, config.volume_tolerance_ml) {
                Ok(s) => points.push(PvPoint {
                    volume_ml: s.volume_change_ml,
                    pressure_pa: -s.pressure_pa,
                    solves: s.solves,
                    wall_time_s: s.wall_time_s,
                }),
                Err(e) => {
                    failure = Some(describe_failure(e, target, &points, model));
                    break;
                }
            }
        }
        drop(stop);
    });
    Ok(PvCurve {
        name: m.name.clone(),
        material: m.material,
        points,
        failure,
        wall_time_s: 0.0,
    })
}

/// The failure on the way to `target_ml`, with the element the solver names.
fn describe_failure(e: Error, target_ml: f64, points: &[PvPoint], model: &LungModel) -> PvFailure {
    let reached_ml = points.last().map_or(0.0, |p| p.volume_ml);
    let unnamed = |cause: String| PvFailure {
        target_ml,
        reached_ml,
        element: None,
        centre_lps_mm: None,
        volume_ratio: None,
        groups: None,
        cause,
    };
    match crate::run::name_element_groups(e, model) {
        Error::VolumeUnreachable(u) => PvFailure {
            element: Some(u.element),
            centre_lps_mm: Some(u.centre_lps_mm),
            volume_ratio: Some(u.volume_ratio),
            groups: u.group.clone(),
            cause: u.cause.clone(),
            ..unnamed(String::new())
        },
        Error::Cancelled(_) => unnamed("stopped by the study's time budget".into()),
        other => unnamed(other.to_string()),
    }
}

impl PressureVolumeReport {
    /// The section of the validation report, with the PNG linked.
    pub fn to_markdown(&self) -> String {
        let c = &self.config;
        let mut s = format!(
            "## Pressure–volume curve\n\n{}, {} mm elements ({} elements, {} nodes), rest volume \
             {:.0} mL; the run's scene (hilum fixed, sliding walls, costal wall making {:.3} of \
             each volume change), volume driver from the scanned state by {} mL to {} mL \
             (tolerance {} mL), one load path per law, at most {} s each. Pressure = distending \
             pressure (the negative of the surface pressure). Physiological: Salazar–Knowles \
             V = V_max(1 − exp(−P·C₀/V_max)), C₀ = {} mL/Pa, V_max = the rest volume; beside it \
             the same shape with the model's compliance at rest as C₀ ({:.2} mL/Pa, the first \
             law's first step). Linear elastic C = 3V₀(1 − 2ν)/E = {:.3} mL/Pa. Study wall time \
             {:.0} s.\n\n\
             ![P–V curves]({PRESSURE_VOLUME_PNG})\n\n",
            self.lungs,
            c.element_size_mm,
            self.elements,
            self.nodes,
            self.rest_volume_ml,
            c.rib_cage_share,
            c.step_ml,
            c.max_volume_ml,
            c.volume_tolerance_ml,
            c.time_budget_s,
            PHYSIOLOGICAL_COMPLIANCE_ML_PER_PA,
            self.model_compliance_at_rest_ml_per_pa,
            self.elastic_compliance_ml_per_pa,
            self.wall_time_s,
        );
        s.push_str("| volume (mL) | physiological (Pa) | same shape, model's C₀ (Pa) |");
        for curve in &self.curves {
            s.push_str(&format!(" {} (Pa) |", curve.name));
        }
        s.push_str("\n|---|---|---|");
        s.push_str(&"---|".repeat(self.curves.len()));
        s.push('\n');
        let steps = (c.max_volume_ml / c.step_ml).round() as usize;
        for k in 0..=steps {
            let v = k as f64 * c.step_ml;
            let phys = physiological_pressure_pa(
                v,
                PHYSIOLOGICAL_COMPLIANCE_ML_PER_PA,
                self.rest_volume_ml,
            );
            let shape = physiological_pressure_pa(
                v,
                self.model_compliance_at_rest_ml_per_pa,
                self.rest_volume_ml,
            );
            s.push_str(&format!(
                "| {v:.0} | {} | {} |",
                fmt_pa(phys),
                fmt_pa(shape)
            ));
            for curve in &self.curves {
                let at = curve
                    .points
                    .iter()
                    .find(|p| (p.volume_ml - v).abs() <= c.volume_tolerance_ml + 1e-9);
                match at {
                    Some(p) => s.push_str(&format!(" {} |", fmt_pa(p.pressure_pa))),
                    None => s.push_str(" — |"),
                }
            }
            s.push('\n');
        }
        s.push_str("\n| law | reached | why it stopped | wall time |\n|---|---|---|---|\n");
        for curve in &self.curves {
            let why = match &curve.failure {
                None => "completed".to_string(),
                Some(f) => failure_text(f),
            };
            s.push_str(&format!(
                "| {} | {:+.0} mL | {} | {:.0} s |\n",
                curve.name,
                curve.reached_ml(),
                why,
                curve.wall_time_s
            ));
        }
        s
    }

    /// The plot: volume against distending pressure, one line per law, the physiological
    /// curve and the linear elastic compliance dashed.
    pub fn render_png(&self) -> Result<crate::outputs::quicklook::RgbImage> {
        let mut series: Vec<LineSeries> = self
            .curves
            .iter()
            .map(|c| LineSeries {
                name: c.name.clone(),
                points: c
                    .points
                    .iter()
                    .map(|p| [p.pressure_pa, p.volume_ml])
                    .collect(),
                dashed: false,
                end_note: c
                    .failure
                    .as_ref()
                    .map(|f| format!("stops at {:+.0} mL", f.reached_ml)),
            })
            .collect();
        series.push(LineSeries {
            name: "physiological".into(),
            points: self
                .physiological
                .iter()
                .map(|p| [p.pressure_pa, p.volume_ml])
                .collect(),
            dashed: true,
            end_note: None,
        });
        series.push(LineSeries {
            name: "same shape, model C0".into(),
            points: self
                .physiological_shape_at_model_compliance
                .iter()
                .map(|p| [p.pressure_pa, p.volume_ml])
                .collect(),
            dashed: true,
            end_note: None,
        });
        let v_max = self.config.max_volume_ml;
        series.push(LineSeries {
            name: "linear elastic C".into(),
            points: vec![
                [0.0, 0.0],
                [v_max / self.elastic_compliance_ml_per_pa, v_max],
            ],
            dashed: true,
            end_note: None,
        });
        let title = format!(
            "Pressure-volume, CIP lungs, {} mm elements, volume driver",
            self.config.element_size_mm
        );
        let (image, _) = render_line_chart(
            &title,
            "distending pressure (Pa)",
            "volume change (mL)",
            &series,
        )?;
        Ok(image)
    }

    /// Writes [`PRESSURE_VOLUME_PNG`] into `dir`.
    pub fn write_png(&self, dir: &Path) -> Result<()> {
        crate::outputs::quicklook::write_png(&dir.join(PRESSURE_VOLUME_PNG), &self.render_png()?)
    }
}

/// A pressure with a sign-free width, or ∞ beyond the physiological curve.
fn fmt_pa(p: f64) -> String {
    if p.is_finite() {
        // No "-0.0" for a pressure that is zero.
        format!("{:.1}", p + 0.0)
    } else {
        "∞".into()
    }
}

/// One line on why a curve stopped.
fn failure_text(f: &PvFailure) -> String {
    let mut s = format!("fails on the way to {:+.0} mL", f.target_ml);
    if let (Some(e), Some(r)) = (f.element, f.volume_ratio) {
        s.push_str(&format!(
            ": element {e} at {:.0} % of its volume",
            100.0 * r
        ));
        if let Some(c) = f.centre_lps_mm {
            s.push_str(&format!(", LPS ({:.0}, {:.0}, {:.0}) mm", c[0], c[1], c[2]));
        }
        if let Some(g) = &f.groups {
            s.push_str(&format!(" ({g})"));
        }
    }
    let cause: String = f.cause.chars().take(160).collect();
    s.push_str(&format!("; {}", cause.replace('|', "/")));
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_physiological_curve_is_linear_at_rest_and_stiffens_towards_capacity() {
        let (c0, v_max) = (2.0, 3000.0);
        // Slope C₀ at rest.
        let p = physiological_pressure_pa(1.0, c0, v_max);
        assert!((1.0 / p - c0).abs() < 1e-3 * c0, "{p}");
        // Closed form at two thirds of capacity: P = (V_max/C₀)·ln 3.
        let p = physiological_pressure_pa(2000.0, c0, v_max);
        assert!((p - 1500.0 * 3f64.ln()).abs() < 1e-9, "{p}");
        assert!(p > 2000.0 / c0, "stiffer than linear");
        assert!(physiological_pressure_pa(3000.0, c0, v_max).is_infinite());
    }

    #[test]
    fn a_report_renders_its_table_and_plot_with_a_failed_curve() {
        let point = |v: f64, p: f64| PvPoint {
            volume_ml: v,
            pressure_pa: p,
            solves: 1,
            wall_time_s: 0.1,
        };
        let mut config = PressureVolumeConfig::standard();
        config.step_ml = 250.0;
        config.materials.truncate(2);
        let report = PressureVolumeReport {
            lungs: "test".into(),
            rest_volume_ml: 3000.0,
            elements: 10,
            nodes: 27,
            elastic_compliance_ml_per_pa: 8.0,
            physiological: vec![point(0.0, 0.0), point(250.0, 130.0)],
            model_compliance_at_rest_ml_per_pa: 8.0,
            physiological_shape_at_model_compliance: vec![point(0.0, 0.0), point(250.0, 32.0)],
            curves: vec![
                PvCurve {
                    name: "linear".into(),
                    material: Material::LUNG,
                    points: vec![point(0.0, 0.0), point(250.5, 30.0), point(500.0, 61.0)],
                    failure: Some(PvFailure {
                        target_ml: 750.0,
                        reached_ml: 500.0,
                        element: Some(2363),
                        centre_lps_mm: Some([-33.0, -147.0, -201.0]),
                        volume_ratio: Some(0.02),
                        groups: Some("costal, interior".into()),
                        cause: "did not converge".into(),
                    }),
                    wall_time_s: 3.0,
                },
                PvCurve {
                    name: "cubic".into(),
                    material: Material::LUNG,
                    points: vec![point(0.0, 0.0), point(250.0, 31.0)],
                    failure: None,
                    wall_time_s: 2.0,
                },
            ],
            config,
            wall_time_s: 5.0,
        };
        let md = report.to_markdown();
        assert!(md.contains("| 0 | 0.0 | 0.0 | 0.0 | 0.0 |"), "{md}");
        assert!(md.contains("| 250 | 130.5 | 32.6 | 30.0 | 31.0 |"), "{md}");
        assert!(md.contains("| 750 | 431.5 | 107.9 | — | — |"), "{md}");
        assert!(
            md.contains(
                "element 2363 at 2 % of its volume, LPS (-33, -147, -201) mm (costal, interior)"
            ),
            "{md}"
        );
        assert!(md.contains(PRESSURE_VOLUME_PNG));
        let image = report.render_png().unwrap();
        assert!(image.width > 0 && image.pixels.iter().any(|&b| b != 255));
    }
}
