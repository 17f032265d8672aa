//! Large-strain limits of one cubic element (thesis §3.3.4, Figs. 3.42, 3.43, 3.50): how far
//! the measured E, ν and K drift from the imposed values as the strain grows, using the
//! continuum definitions (2.3), (2.4) and (2.6) on the deformed element.
//!
//! The element is derived by a first-order expansion about zero strain, so the drift is the
//! model's, not the solver's: every point is a converged equilibrium of the production force
//! kernel (dense Newton on the 24 DOFs).

use serde::Serialize;

use super::patch::{
    face_corners, face_mean, hold_axes, positive_faces, single_element_mesh, symmetry_constraints,
    DenseNewton, Equilibrium,
};
use crate::math::V3;
use crate::model::element::CORNER_SIGNS;
use crate::model::{Loads, Material, SurfacePressure};
use crate::simulation::{QuasiStaticSettings, QuasiStaticSolver, Scene};
use crate::Result;

/// The thesis's stated limits for a cube (§3.3.4), for side-by-side tables.
pub mod thesis {
    /// (ν, |E error| at 10 % traction strain): 2.75 %, 2 %, 1.75 % (ν → 0.5).
    pub const YOUNGS_ERROR_AT_10_PERCENT: [(f64, f64); 3] =
        [(0.3, 0.0275), (0.4, 0.02), (0.49, 0.0175)];
    /// The E error exceeds 5 % past this traction strain.
    pub const YOUNGS_5_PERCENT_STRAIN: f64 = 0.16;
    /// The ν error exceeds 5 % past this traction strain, for ν in [0.3, 0.5).
    pub const POISSON_5_PERCENT_STRAIN: f64 = 0.12;
    /// The K error stays under 5 % within this relative volume change, both signs.
    pub const BULK_5_PERCENT_VOLUME: f64 = 0.15;
}

/// What the sweeps run.
#[derive(Debug, Clone, Serialize)]
pub struct SweepConfig {
    /// Cube edge in metres.
    pub edge_m: f64,
    /// Poisson ratios of the curves.
    pub poisson_ratios: Vec<f64>,
    /// Young's moduli: every curve is run at each, to show the errors do not depend on E.
    pub youngs_moduli_pa: Vec<f64>,
    /// Density in kg/m³ (irrelevant to statics; needed to build the material).
    pub density_kg_per_m3: f64,
    /// Largest traction strain.
    pub max_strain: f64,
    /// Increment of the imposed traction strain.
    pub strain_step: f64,
    /// Relative volume changes the bulk test aims at (pressure P = −K·ΔV/V0 of the continuum).
    pub volume_changes: Vec<f64>,
}

impl Default for SweepConfig {
    fn default() -> Self {
        SweepConfig {
            edge_m: 0.01,
            poisson_ratios: vec![0.1, 0.3, 0.4, 0.49],
            youngs_moduli_pa: vec![100.0, 1.0e5],
            density_kg_per_m3: 700.0,
            max_strain: 0.20,
            strain_step: 0.005,
            volume_changes: (1..=18)
                .flat_map(|k| [-(k as f64) * 0.01, k as f64 * 0.01])
                .collect(),
        }
    }
}

/// One equilibrium of the traction sweep.
#[derive(Debug, Clone, Serialize)]
pub struct TractionPoint {
    /// Imposed axial strain η/h0.
    pub strain: f64,
    /// E_measured/E − 1 with E = (F/S0)·(h0/η), F the reaction on the loaded face.
    pub youngs_error: f64,
    /// ν_measured/ν − 1 with ν = −(lateral strain)/(axial strain), lateral strain of the +y face.
    pub poisson_error: f64,
    /// E_measured/E − 1 with the true (deformed-area) stress F/S instead of F/S0.
    pub youngs_error_true_stress: f64,
    /// |ν_y − ν_z| / ν: the cube must contract equally in both lateral directions.
    pub lateral_asymmetry: f64,
    /// Largest reaction on the lateral symmetry planes over F (zero: lateral faces are free).
    pub lateral_reaction: f64,
    /// Newton iterations of this increment.
    pub newton_iterations: usize,
    /// max |x_production − x_Newton| / (edge·strain): the production `QuasiStaticSolver`,
    /// started from the previous increment, against the dense Newton on the same scene.
    pub production_solver_difference: f64,
}

/// E and ν errors against traction strain for one (E, ν).
#[derive(Debug, Clone, Serialize)]
pub struct TractionCurve {
    /// Young's modulus imposed, Pa.
    pub youngs_modulus_pa: f64,
    /// Poisson ratio imposed.
    pub poisson_ratio: f64,
    /// Every increment.
    pub points: Vec<TractionPoint>,
    /// Strain at which |E error| first exceeds 5 % (interpolated), if it does.
    pub youngs_5_percent_strain: Option<f64>,
    /// Strain at which |ν error| first exceeds 5 % (interpolated), if it does.
    pub poisson_5_percent_strain: Option<f64>,
}

/// One equilibrium of the bulk sweep.
#[derive(Debug, Clone, Serialize)]
pub struct BulkPoint {
    /// Volume change the pressure was chosen for (P = −K·target).
    pub target_volume_change: f64,
    /// Pressure applied, Pa (positive compresses).
    pub pressure_pa: f64,
    /// Measured ΔV/V0 (enclosed volume of the deformed element).
    pub volume_change: f64,
    /// K_measured/K − 1 with K = −P/(ΔV/V0).
    pub bulk_error: f64,
    /// What the closed form for a cube under dead pressure predicts: the response stays a
    /// uniform stretch s = −P/(3K) exactly (forces are linear in s), so
    /// K_measured/K − 1 = 3s/((1+s)³ − 1) − 1.
    pub predicted_bulk_error: f64,
    /// max |x_production − x_Newton| / (edge·|ΔV/V0|), as for traction.
    pub production_solver_difference: f64,
}

/// K error against volume change for one (E, ν).
#[derive(Debug, Clone, Serialize)]
pub struct BulkCurve {
    /// Young's modulus imposed, Pa.
    pub youngs_modulus_pa: f64,
    /// Poisson ratio imposed.
    pub poisson_ratio: f64,
    /// Every pressure, sorted by volume change.
    pub points: Vec<BulkPoint>,
    /// Largest |ΔV/V0| under compression before |K error| exceeds 5 % (interpolated).
    pub compression_5_percent_volume: Option<f64>,
    /// Largest ΔV/V0 under inflation before |K error| exceeds 5 % (interpolated).
    pub inflation_5_percent_volume: Option<f64>,
}

/// Outcome of the strain sweeps.
#[derive(Debug, Clone, Serialize)]
pub struct SweepReport {
    /// What was run.
    pub config: SweepConfig,
    /// Traction curves, every (E, ν).
    pub traction: Vec<TractionCurve>,
    /// Bulk curves, every (E, ν).
    pub bulk: Vec<BulkCurve>,
    /// Largest difference of any error between two Young's moduli at the same ν and strain.
    pub youngs_modulus_dependence: f64,
    /// Largest `production_solver_difference` over every point of every curve.
    pub production_solver_difference: f64,
}

/// Runs the traction and bulk sweeps.
pub fn run_strain_sweeps(config: &SweepConfig) -> Result<SweepReport> {
    let mut traction = Vec::new();
    let mut bulk = Vec::new();
    for &nu in &config.poisson_ratios {
        for &e in &config.youngs_moduli_pa {
            let material = Material::new(e, nu, config.density_kg_per_m3)?;
            traction.push(traction_curve(config, material)?);
            bulk.push(bulk_curve(config, material)?);
        }
    }
    let mut dependence: f64 = 0.0;
    for a in &traction {
        for b in traction
            .iter()
            .filter(|b| b.poisson_ratio == a.poisson_ratio)
        {
            for (p, q) in a.points.iter().zip(&b.points) {
                dependence = dependence
                    .max((p.youngs_error - q.youngs_error).abs())
                    .max((p.poisson_error - q.poisson_error).abs());
            }
        }
    }
    for a in &bulk {
        for b in bulk.iter().filter(|b| b.poisson_ratio == a.poisson_ratio) {
            for (p, q) in a.points.iter().zip(&b.points) {
                dependence = dependence.max((p.bulk_error - q.bulk_error).abs());
            }
        }
    }
    let production_solver_difference = traction
        .iter()
        .flat_map(|c| c.points.iter().map(|p| p.production_solver_difference))
        .chain(
            bulk.iter()
                .flat_map(|c| c.points.iter().map(|p| p.production_solver_difference)),
        )
        .fold(0.0, f64::max);
    Ok(SweepReport {
        config: config.clone(),
        traction,
        bulk,
        youngs_modulus_dependence: dependence,
        production_solver_difference,
    })
}

/// Uniaxial traction of one cube by imposed displacement of its +x face (the thesis's
/// Fig. 3.9 loop): −x face sliding on x = 0, +x face sliding on x = a(1+ε), symmetry planes
/// y = 0 and z = 0 on the −y and −z faces, lateral faces otherwise free.
pub fn traction_curve(config: &SweepConfig, material: Material) -> Result<TractionCurve> {
    let a = config.edge_m;
    let mesh = single_element_mesh([a; 3], material)?;
    let cs = symmetry_constraints(&mesh)?;
    let mut scene = Scene::new(mesh, cs, Loads::default())?;
    let rest = scene.mesh.rest_positions_m.clone();
    let newton = DenseNewton::default();
    let mut x = rest.clone();
    let mut prev_strain = 0.0;
    let mut points = Vec::new();
    let steps = (config.max_strain / config.strain_step).round() as usize;
    for k in 1..=steps {
        let strain = k as f64 * config.strain_step;
        for n in face_corners(0, 1.0) {
            let s = CORNER_SIGNS[n as usize];
            let target = rest[n as usize] + V3::new(a * strain, 0.0, 0.0);
            if let Some(c) = hold_axes(target, [true, s[1] < 0.0, s[2] < 0.0]) {
                scene.constraints.set(n, c)?;
            }
        }
        // Predictor: scale the previous displacement field to the new strain.
        let scale = if prev_strain > 0.0 {
            strain / prev_strain
        } else {
            1.0
        };
        let guess: Vec<V3> = x
            .iter()
            .zip(&rest)
            .map(|(p, r)| r + (p - r) * scale)
            .collect();
        let (sol, report) = newton.solve(&scene, &guess)?;
        let production = production_solve(&scene, &x)?;
        let production_solver_difference = max_distance(&production, &sol) / (a * strain);
        x = sol;
        prev_strain = strain;
        let mut f = vec![V3::zeros(); 8];
        scene.total_forces(&x, None, &mut f);
        let eq = Equilibrium {
            positions_m: x.clone(),
            total_force_n: f,
        };
        let force: f64 = face_corners(0, 1.0)
            .map(|n| eq.reaction(&scene, n, 0))
            .sum();
        let lateral_y = face_mean(&eq, &scene, 1, 1.0, 1) / a;
        let lateral_z = face_mean(&eq, &scene, 2, 1.0, 2) / a;
        let nu = material.poisson_ratio;
        let youngs = force / (a * a) / strain;
        let youngs_true = force / (a * a * (1.0 + lateral_y) * (1.0 + lateral_z)) / strain;
        let lateral_reaction = (0..8u32)
            .flat_map(|n| [1, 2].map(|d| eq.reaction(&scene, n, d).abs()))
            .fold(0.0, f64::max)
            / force.abs();
        points.push(TractionPoint {
            strain,
            youngs_error: youngs / material.youngs_modulus_pa - 1.0,
            poisson_error: -lateral_y / strain / nu - 1.0,
            youngs_error_true_stress: youngs_true / material.youngs_modulus_pa - 1.0,
            lateral_asymmetry: (lateral_y - lateral_z).abs() / strain / nu,
            lateral_reaction,
            newton_iterations: report.iterations,
            production_solver_difference,
        });
    }
    let crossing = |err: &dyn Fn(&TractionPoint) -> f64| {
        first_crossing(points.iter().map(|p| (p.strain, err(p).abs())), 0.05)
    };
    Ok(TractionCurve {
        youngs_modulus_pa: material.youngs_modulus_pa,
        poisson_ratio: material.poisson_ratio,
        youngs_5_percent_strain: crossing(&|p| p.youngs_error),
        poisson_5_percent_strain: crossing(&|p| p.poisson_error),
        points,
    })
}

/// Hydrostatic inflation and deflation of one cube by a dead pressure on its three positive
/// faces (rest area and normal, as the thesis applies pressure), symmetry planes on the others.
pub fn bulk_curve(config: &SweepConfig, material: Material) -> Result<BulkCurve> {
    let a = config.edge_m;
    let k = material.bulk_modulus_pa();
    let mesh = single_element_mesh([a; 3], material)?;
    let cs = symmetry_constraints(&mesh)?;
    let loads = Loads {
        pressures: vec![SurfacePressure {
            faces: positive_faces(&mesh),
            pressure_pa: 0.0,
            follows_deformation: false,
        }],
        ..Default::default()
    };
    let mut scene = Scene::new(mesh, cs, loads)?;
    let rest = scene.mesh.rest_positions_m.clone();
    let v0 = scene.mesh.enclosed_volume_m3(&rest);
    let newton = DenseNewton::default();
    let mut points = Vec::new();
    // Walk outwards from zero on each side so each solve starts near its answer.
    for sign in [-1.0, 1.0] {
        let mut targets: Vec<f64> = config
            .volume_changes
            .iter()
            .copied()
            .filter(|v| v * sign > 0.0)
            .collect();
        targets.sort_by(|p, q| p.abs().total_cmp(&q.abs()));
        let mut x = rest.clone();
        for target in targets {
            let pressure = -k * target;
            scene.loads.pressures[0].pressure_pa = pressure;
            let (sol, _) = newton.solve(&scene, &x)?;
            let production = production_solve(&scene, &x)?;
            let production_solver_difference = max_distance(&production, &sol) / (a * target.abs());
            x = sol;
            let volume_change = scene.mesh.enclosed_volume_m3(&x) / v0 - 1.0;
            let s = -pressure / (3.0 * k);
            points.push(BulkPoint {
                target_volume_change: target,
                pressure_pa: pressure,
                volume_change,
                bulk_error: -pressure / volume_change / k - 1.0,
                predicted_bulk_error: 3.0 * s / ((1.0 + s).powi(3) - 1.0) - 1.0,
                production_solver_difference,
            });
        }
    }
    points.sort_by(|p, q| p.volume_change.total_cmp(&q.volume_change));
    let side = |sign: f64| {
        let mut pts: Vec<(f64, f64)> = points
            .iter()
            .filter(|p| p.volume_change * sign > 0.0)
            .map(|p| (p.volume_change.abs(), p.bulk_error.abs()))
            .collect();
        pts.sort_by(|p, q| p.0.total_cmp(&q.0));
        first_crossing(pts.into_iter(), 0.05)
    };
    Ok(BulkCurve {
        youngs_modulus_pa: material.youngs_modulus_pa,
        poisson_ratio: material.poisson_ratio,
        compression_5_percent_volume: side(-1.0),
        inflation_5_percent_volume: side(1.0),
        points,
    })
}

/// Equilibrium by the production quasi-static solver, started from `initial`.
fn production_solve(scene: &Scene, initial: &[V3]) -> Result<Vec<V3>> {
    let settings = QuasiStaticSettings {
        tolerance: 1e-11,
        ..Default::default()
    };
    let (x, _) = QuasiStaticSolver::new(scene, settings)?.solve(Some(initial))?;
    Ok(x)
}

fn max_distance(a: &[V3], b: &[V3]) -> f64 {
    a.iter()
        .zip(b)
        .map(|(p, q)| (p - q).norm())
        .fold(0.0, f64::max)
}

/// First abscissa where the ordinate rises through `level`, linearly interpolated from the
/// previous point (from the origin if the very first point is above it).
fn first_crossing(points: impl Iterator<Item = (f64, f64)>, level: f64) -> Option<f64> {
    let mut prev = (0.0, 0.0);
    for (x, y) in points {
        if y > level {
            let t = (level - prev.1) / (y - prev.1);
            return Some(prev.0 + t * (x - prev.0));
        }
        prev = (x, y);
    }
    None
}

fn pct(v: f64) -> String {
    format!("{:+.2} %", 100.0 * v)
}

fn opt_pct(v: Option<f64>, beyond: f64) -> String {
    match v {
        Some(v) => format!("{:.1} %", 100.0 * v),
        None => format!("> {:.0} %", 100.0 * beyond),
    }
}

impl SweepReport {
    /// Markdown tables of the error curves, ours beside the thesis's stated numbers.
    pub fn to_markdown(&self) -> String {
        use crate::markdown::Table;
        let mut s = String::new();
        let e0 = self
            .config
            .youngs_moduli_pa
            .first()
            .copied()
            .unwrap_or(f64::NAN);
        s.push_str("## Large-strain limits of one cube (thesis §3.3.4)\n\n");
        s.push_str(&format!(
            "Traction: +x face displaced in {:.1} % increments up to {:.0} %, −x face sliding, \
             symmetry planes on −y and −z, lateral faces free; E = (F/S0)·(h0/η), F the \
             reaction on the loaded face; ν = −(lateral strain)/(axial strain). Bulk: dead \
             pressure on the three positive faces, P = −K·(target ΔV/V0); \
             K = −P/(ΔV/V0) with ΔV from the deformed element. Errors are measured/imposed − 1 \
             (signed; the thesis plots magnitudes). Curves for E = {} Pa; every curve was also \
             run at E = {:?} Pa and the largest difference of any error between moduli is \
             **{:.1e}**. Every point is a dense Newton equilibrium of the production force \
             kernel; the production `QuasiStaticSolver` lands on the same positions to \
             **{:.1e}** of the imposed displacement.\n\n",
            100.0 * self.config.strain_step,
            100.0 * self.config.max_strain,
            e0,
            self.config.youngs_moduli_pa,
            self.youngs_modulus_dependence,
            self.production_solver_difference
        ));
        s.push_str("### Summary against the thesis\n\n");
        let mut summary = Table::new([
            "ν",
            "E error at 10 % (ours)",
            "thesis",
            "strain where the E error passes 5 % (ours)",
            "thesis",
            "strain where the ν error passes 5 % (ours)",
            "thesis",
        ]);
        for c in self.traction.iter().filter(|c| c.youngs_modulus_pa == e0) {
            let at10 = c
                .points
                .iter()
                .find(|p| (p.strain - 0.10).abs() < 1e-9)
                .map(|p| pct(p.youngs_error))
                .unwrap_or_else(|| "–".into());
            let thesis_at10 = thesis::YOUNGS_ERROR_AT_10_PERCENT
                .iter()
                .find(|(nu, _)| (nu - c.poisson_ratio).abs() < 1e-9)
                .map(|(nu, e)| {
                    // The thesis's last curve is "ν → 0.5"; 0.49 stands in for it.
                    let limit = if *nu > 0.45 { " (ν → 0.5)" } else { "" };
                    format!("{:.2} %{limit}", 100.0 * e)
                })
                .unwrap_or_else(|| "larger than at ν = 0.3".into());
            let thesis_nu = if c.poisson_ratio >= 0.3 {
                format!("{:.0} %", 100.0 * thesis::POISSON_5_PERCENT_STRAIN)
            } else {
                "not stated".into()
            };
            summary.row([
                c.poisson_ratio.to_string(),
                at10,
                thesis_at10,
                opt_pct(c.youngs_5_percent_strain, self.config.max_strain),
                format!("{:.0} %", 100.0 * thesis::YOUNGS_5_PERCENT_STRAIN),
                opt_pct(c.poisson_5_percent_strain, self.config.max_strain),
                thesis_nu,
            ]);
        }
        summary.write_to(&mut s);
        s.push('\n');
        let mut bulk_summary = Table::new([
            "ν",
            "K error within 5 % in compression down to ΔV/V0 = (ours)",
            "in inflation up to (ours)",
            "thesis",
        ]);
        let vmax = self
            .config
            .volume_changes
            .iter()
            .fold(0.0f64, |m, v| m.max(v.abs()));
        for c in self.bulk.iter().filter(|c| c.youngs_modulus_pa == e0) {
            bulk_summary.row([
                c.poisson_ratio.to_string(),
                format!("−{}", opt_pct(c.compression_5_percent_volume, vmax)),
                format!("+{}", opt_pct(c.inflation_5_percent_volume, vmax)),
                format!("±{:.0} %", 100.0 * thesis::BULK_5_PERCENT_VOLUME),
            ]);
        }
        bulk_summary.write_to(&mut s);
        s.push_str("\n### Traction: E error (F/S0), ν error, and E error with true stress F/S\n\n");
        let curves: Vec<&TractionCurve> = self
            .traction
            .iter()
            .filter(|c| c.youngs_modulus_pa == e0)
            .collect();
        let mut header = vec!["strain".to_string()];
        for c in &curves {
            let nu = c.poisson_ratio;
            header.extend([
                format!("E err ν={nu}"),
                format!("ν err ν={nu}"),
                format!("E err (F/S) ν={nu}"),
            ]);
        }
        let mut traction = Table::new(header);
        if let Some(first) = curves.first() {
            for (i, p) in first.points.iter().enumerate() {
                let k = (p.strain / 0.01).round();
                if (p.strain - k * 0.01).abs() > 1e-9 {
                    continue;
                }
                let mut row = vec![format!("{:.0} %", 100.0 * p.strain)];
                for c in &curves {
                    let q = &c.points[i];
                    row.extend([
                        pct(q.youngs_error),
                        pct(q.poisson_error),
                        pct(q.youngs_error_true_stress),
                    ]);
                }
                traction.row(row);
            }
        }
        traction.write_to(&mut s);
        s.push_str("\n### Bulk: K error against measured volume change\n\n");
        let bulks: Vec<&BulkCurve> = self
            .bulk
            .iter()
            .filter(|c| c.youngs_modulus_pa == e0)
            .collect();
        let mut header = vec!["target ΔV/V0".to_string(), "measured ΔV/V0".into()];
        header.extend(bulks.iter().map(|c| format!("K err ν={}", c.poisson_ratio)));
        header.push("closed form".into());
        let mut bulk = Table::new(header);
        if let Some(first) = bulks.first() {
            for (i, p) in first.points.iter().enumerate() {
                let k = (p.target_volume_change / 0.01).round() as i64;
                if k % 3 != 0 && k.abs() != 1 {
                    continue;
                }
                let mut row = vec![pct(p.target_volume_change), pct(p.volume_change)];
                row.extend(bulks.iter().map(|c| pct(c.points[i].bulk_error)));
                row.push(pct(p.predicted_bulk_error));
                bulk.row(row);
            }
        }
        bulk.write_to(&mut s);
        s
    }
}
