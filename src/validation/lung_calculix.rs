//! The end-inhale frame of a real patient's lungs against CalculiX: the same hexahedra, the
//! same hilum (fixed DOFs), sliding (tangent planes as `*TRANSFORM` + one fixed DOF) and
//! diaphragm (lines along LPS z: two fixed DOFs) constraints, the same follower pressure
//! (`*DLOAD Pn` on every external face) and geometric non-linearity (`*STEP, NLGEOM`).
//!
//! Our volume driver first finds the pleural pressure that inflates the lungs by the target
//! volume; both codes are then solved at exactly that pressure from rest, and their nodal
//! displacements are compared node by node. They are different models of the same solid:
//! Baudet's mass–spring element against CalculiX's St Venant–Kirchhoff C3D8 (and C3D8I as a
//! cross-check of C3D8's shear locking), so they agree to the extent the two constitutive
//! laws agree at the strains reached (≈ 10 %); the report measures how far that is.
//!
//! Reports are JSON (serde, field names as below, lengths in the unit their name carries,
//! positions in DICOM LPS millimetres) and markdown, written like the validation suite's.

use std::fmt::Write as _;
use std::path::Path;
use std::time::Instant;

use serde::Serialize;

use super::calculix::{self, CalculixOptions, ElementType};
use crate::durable::write_atomic;
use crate::ingest::lung_model::{ConstraintGroup, LungModel};
use crate::math::V3;
use crate::model::{Material, NodeConstraint};
use crate::motion::{elastic_compliance_ml_per_pa, lung_scene, REFERENCE_PRESSURE_PA};
use crate::simulation::{BreathingDriver, QuasiStaticSettings, Scene};
use crate::{Error, IoContext, IoOp, Result};

/// Settings of the end-inhale comparison.
#[derive(Debug, Clone, Serialize)]
pub struct LungCalculixSettings {
    /// Edge of the cubic elements, mm.
    pub element_size_mm: f64,
    /// The lungs' material: CalculiX gets its law's card (`calculix::material_card`).
    pub material: Material,
    /// CalculiX's material when it differs from ours (the same moduli, another law).
    pub calculix_material: Option<Material>,
    /// Inhaled volume of the end-inhale frame, mL (tidal breathing: 500).
    pub target_volume_ml: f64,
    /// Tolerance of our volume driver on that volume, mL.
    pub volume_tolerance_ml: f64,
    /// Element formulations CalculiX solves the frame with; the first is the reference.
    pub element_types: Vec<ElementType>,
    /// Threads given to CalculiX (`OMP_NUM_THREADS`).
    pub ccx_threads: usize,
    /// Our equilibrium solver.
    pub solver: QuasiStaticSettings,
    /// Also compare at this fraction of the frame's pressure, CalculiX linear (C3D8, no
    /// NLGEOM): separates the linear discretisation difference from the non-linear one.
    pub small_strain_fraction: Option<f64>,
}

impl Default for LungCalculixSettings {
    fn default() -> Self {
        LungCalculixSettings {
            element_size_mm: 8.0,
            material: Material::LUNG,
            calculix_material: None,
            target_volume_ml: 500.0,
            volume_tolerance_ml: 2.5,
            element_types: vec![ElementType::C3D8, ElementType::C3D8I],
            ccx_threads: 2,
            solver: QuasiStaticSettings::default(),
            small_strain_fraction: Some(0.01),
        }
    }
}

/// Statistics of |u_a − u_b| over the nodes of one constraint group.
#[derive(Debug, Clone, Serialize)]
pub struct GroupDifference {
    /// Group name (`interior` for nodes in no group).
    pub group: String,
    /// Nodes in the group.
    pub nodes: usize,
    /// Mean |Δu|, mm.
    pub mean_mm: f64,
    /// Largest |Δu|, mm.
    pub max_mm: f64,
    /// Mean |u| of the reference (second) solution on the group, mm.
    pub reference_mean_displacement_mm: f64,
}

/// Node-by-node difference between two displacement fields of the same mesh.
#[derive(Debug, Clone, Serialize)]
pub struct DisplacementDifference {
    /// Mean |Δu| over all nodes, mm.
    pub mean_mm: f64,
    /// Median |Δu|, mm.
    pub median_mm: f64,
    /// 95th percentile of |Δu|, mm.
    pub p95_mm: f64,
    /// Largest |Δu|, mm.
    pub max_mm: f64,
    /// Mean |Δu| divided by the mean |u| of the reference solution.
    pub mean_relative: f64,
    /// Node (0-based) of the largest difference.
    pub max_node: usize,
    /// Constraint group of that node.
    pub max_group: String,
    /// Rest position of that node, LPS mm.
    pub max_position_lps_mm: [f64; 3],
    /// Displacement of that node in the first field, LPS mm.
    pub max_node_displacement_a_mm: [f64; 3],
    /// Displacement of that node in the reference field, LPS mm.
    pub max_node_displacement_b_mm: [f64; 3],
    /// The same statistics per constraint group.
    pub per_group: Vec<GroupDifference>,
}

/// One displacement field's own summary.
#[derive(Debug, Clone, Serialize)]
pub struct FieldSummary {
    /// Largest |u|, mm.
    pub max_displacement_mm: f64,
    /// Mean |u|, mm.
    pub mean_displacement_mm: f64,
    /// Mean u_z (LPS, + superior) of the diaphragmatic nodes, mm: the base's descent.
    pub diaphragm_mean_dz_mm: f64,
    /// Volume change of the lung surface, mL.
    pub volume_change_ml: f64,
}

/// Our solve of the frame.
#[derive(Debug, Clone, Serialize)]
pub struct OurRun {
    /// The displacement field.
    pub field: FieldSummary,
    /// Volume driver (search of the pressure for the target volume, from rest), s.
    pub volume_solve_wall_time_s: f64,
    /// Pressure solves the volume driver spent.
    pub volume_solves: usize,
    /// One solve at the found pressure from rest, preconditioner set-up included, s: the
    /// work CalculiX does.
    pub pressure_solve_wall_time_s: f64,
    /// Newton iterations of that solve.
    pub newton_iterations: usize,
    /// Relative force residual of that solve.
    pub residual: f64,
}

/// CalculiX's solve of the frame with one element formulation.
#[derive(Debug, Clone, Serialize)]
pub struct CalculixRun {
    /// Element formulation.
    pub element_type: ElementType,
    /// The displacement field.
    pub field: FieldSummary,
    /// Wall time of the `ccx` process, s.
    pub wall_time_s: f64,
    /// Peak resident memory of `ccx` (VmHWM), MB, when `/proc` shows it.
    pub peak_memory_mb: Option<f64>,
    /// Load increments CalculiX reported (NLGEOM cuts the step into increments).
    pub increments: usize,
    /// Ours against this run.
    pub ours_vs_calculix: DisplacementDifference,
}

/// Both codes at a small fraction of the frame's pressure, CalculiX linear.
#[derive(Debug, Clone, Serialize)]
pub struct SmallStrainCheck {
    /// Surface pressure, Pa.
    pub pressure_pa: f64,
    /// Our volume change, mL.
    pub ours_volume_change_ml: f64,
    /// CalculiX's (linear C3D8) volume change, mL.
    pub calculix_volume_change_ml: f64,
    /// Ours against CalculiX.
    pub ours_vs_calculix: DisplacementDifference,
}

/// The end-inhale frame, ours against CalculiX.
#[derive(Debug, Clone, Serialize)]
pub struct LungCalculixReport {
    /// Which lungs.
    pub case: String,
    /// Settings used.
    pub settings: LungCalculixSettings,
    /// Lung material.
    pub material: Material,
    /// Elements of both lungs.
    pub elements: usize,
    /// Nodes of both lungs.
    pub nodes: usize,
    /// Nodes held fixed (hilum).
    pub fixed_nodes: usize,
    /// Nodes sliding on a tangent plane (one DOF imposed).
    pub plane_nodes: usize,
    /// Nodes moving along a line (two DOFs imposed: the diaphragm).
    pub line_nodes: usize,
    /// Follower surface pressure both codes solve at, Pa (negative inflates).
    pub pressure_pa: f64,
    /// Rest volume of the lung surface, mL.
    pub rest_volume_ml: f64,
    /// Our solve.
    pub ours: OurRun,
    /// CalculiX solves, in the settings' order.
    pub calculix: Vec<CalculixRun>,
    /// First CalculiX formulation against the second (their own modelling spread), if run.
    pub calculix_cross_check: Option<DisplacementDifference>,
    /// The same comparison at small strain, if asked for.
    pub small_strain: Option<SmallStrainCheck>,
    /// Wall time of the whole comparison, s.
    pub wall_time_s: f64,
}

/// The CIP lungs' end-inhale frame against CalculiX (see the module doc).
pub fn compare_end_inhale_with_calculix(
    settings: &LungCalculixSettings,
) -> Result<LungCalculixReport> {
    let model = crate::datasets::cip_lung_model_of(settings.element_size_mm, settings.material)?;
    compare_model_with_calculix(&model, "CIP chest CT ct-64, expert lung labels", settings)
}

/// `model`'s end-inhale frame (lung scene at the pressure that inhales
/// `settings.target_volume_ml`) solved by us and by CalculiX, compared node by node.
pub fn compare_model_with_calculix(
    model: &LungModel,
    case: &str,
    settings: &LungCalculixSettings,
) -> Result<LungCalculixReport> {
    let start = Instant::now();
    if settings.element_types.is_empty() {
        return Err(Error::argument(
            "CalculiX comparison settings",
            "the CalculiX comparison needs at least one element type",
        ));
    }
    calculix::require_ccx()?;
    let scene = lung_scene(model)?;
    let material = model.mesh.mesh.classes[0].material;
    let rest = &scene.mesh.rest_positions_m;
    let rest_volume_ml = scene.mesh.enclosed_volume_m3(rest) * 1e6;
    let compliance = elastic_compliance_ml_per_pa(rest_volume_ml, &material);

    let groups = &model.node_group;
    let (ours, pressure_pa, ours_u) = solve_ours(&scene, groups, compliance, settings)?;
    let (calculix, fields) = solve_calculix(&scene, groups, pressure_pa, &ours_u, settings)?;
    let calculix_cross_check = match fields.as_slice() {
        [a, b, ..] => Some(displacement_difference(b, a, rest, groups)?),
        _ => None,
    };

    let small_strain = match settings.small_strain_fraction {
        Some(f) => Some(small_strain_check(
            &scene,
            model,
            pressure_pa * f,
            settings,
        )?),
        None => None,
    };

    let [fixed_nodes, plane_nodes, line_nodes] = constraint_counts(&scene);
    Ok(LungCalculixReport {
        case: case.to_string(),
        settings: settings.clone(),
        material,
        elements: scene.mesh.element_count(),
        nodes: scene.node_count(),
        fixed_nodes,
        plane_nodes,
        line_nodes,
        pressure_pa,
        rest_volume_ml,
        ours,
        calculix,
        calculix_cross_check,
        small_strain,
        wall_time_s: start.elapsed().as_secs_f64(),
    })
}

/// Our end-inhale frame: the volume driver finds the pressure that inhales the target
/// volume, then a fresh solve from rest at that pressure does what CalculiX does. Returns
/// our run, the pressure and the displacement field.
fn solve_ours(
    scene: &Scene,
    groups: &[u8],
    compliance: f64,
    settings: &LungCalculixSettings,
) -> Result<(OurRun, f64, Vec<V3>)> {
    let t0 = Instant::now();
    let mut driver = BreathingDriver::new(
        scene,
        REFERENCE_PRESSURE_PA,
        compliance,
        settings.solver.clone(),
    )?;
    let by_volume = driver
        .solve_volume(settings.target_volume_ml, settings.volume_tolerance_ml)
        .map_err(|e| {
            Error::InvalidModel(format!(
                "our solver could not reach {} mL: {e}",
                settings.target_volume_ml
            ))
        })?;
    let volume_solve_wall_time_s = t0.elapsed().as_secs_f64();
    let pressure_pa = by_volume.pressure_pa;

    // A fresh driver from rest at the found pressure: the same problem CalculiX solves.
    let t0 = Instant::now();
    let mut fresh = BreathingDriver::new(
        scene,
        REFERENCE_PRESSURE_PA,
        compliance,
        settings.solver.clone(),
    )?;
    let ours_state = fresh.solve_pressure(pressure_pa)?;
    let pressure_solve_wall_time_s = t0.elapsed().as_secs_f64();
    let ours_u = scene.displacements(&ours_state.positions_m);

    let ours = OurRun {
        field: summarise(scene, groups, &ours_u),
        volume_solve_wall_time_s,
        volume_solves: by_volume.solves,
        pressure_solve_wall_time_s,
        newton_iterations: ours_state.newton_iterations,
        residual: ours_state.residual,
    };
    Ok((ours, pressure_pa, ours_u))
}

/// CalculiX on the scene at `pressure_pa`, once per element type of the settings, each
/// compared with our field `ours_u`; returns the runs and their displacement fields.
fn solve_calculix(
    scene: &Scene,
    groups: &[u8],
    pressure_pa: f64,
    ours_u: &[V3],
    settings: &LungCalculixSettings,
) -> Result<(Vec<CalculixRun>, Vec<Vec<V3>>)> {
    let rest = &scene.mesh.rest_positions_m;
    let mut ccx_scene = scaled_scene(scene, pressure_pa / REFERENCE_PRESSURE_PA);
    if let Some(m) = settings.calculix_material {
        for class in &mut ccx_scene.mesh.classes {
            class.material = m;
        }
    }
    let mut calculix = Vec::with_capacity(settings.element_types.len());
    let mut fields = Vec::with_capacity(settings.element_types.len());
    for &element_type in &settings.element_types {
        let options = CalculixOptions {
            element_type,
            threads: settings.ccx_threads,
            ..CalculixOptions::default()
        };
        let run = calculix::solve(&ccx_scene, &options)
            .map_err(|e| Error::External(format!("CalculiX {element_type:?}: {e}")))?;
        calculix.push(CalculixRun {
            element_type,
            field: summarise(scene, groups, &run.displacements_m),
            wall_time_s: run.wall_time_s,
            peak_memory_mb: run.peak_memory_mb,
            increments: run.increments,
            ours_vs_calculix: displacement_difference(ours_u, &run.displacements_m, rest, groups)?,
        });
        fields.push(run.displacements_m);
    }
    Ok((calculix, fields))
}

/// Nodes held fixed, sliding on a plane and moving along a line.
fn constraint_counts(scene: &Scene) -> [usize; 3] {
    let mut counts = [0usize; 3];
    for (_, c) in &scene.constraints.entries {
        match c {
            NodeConstraint::Fixed { .. } => counts[0] += 1,
            NodeConstraint::Plane { .. } => counts[1] += 1,
            NodeConstraint::Line { .. } => counts[2] += 1,
            NodeConstraint::Surface { .. } => {}
        }
    }
    counts
}

fn small_strain_check(
    scene: &Scene,
    model: &LungModel,
    pressure_pa: f64,
    settings: &LungCalculixSettings,
) -> Result<SmallStrainCheck> {
    if !(pressure_pa.is_finite() && pressure_pa != 0.0) {
        return Err(Error::argument(
            "small-strain check",
            format!("small-strain check pressure {pressure_pa} Pa must be finite and non-zero"),
        ));
    }
    let rest = &scene.mesh.rest_positions_m;
    let mut driver =
        BreathingDriver::new(scene, REFERENCE_PRESSURE_PA, 1.0, settings.solver.clone())?;
    let ours = driver.solve_pressure(pressure_pa)?;
    let ours_u = scene.displacements(&ours.positions_m);
    let options = CalculixOptions {
        threads: settings.ccx_threads,
        ..CalculixOptions::linear()
    };
    let ccx_scene = scaled_scene(scene, pressure_pa / REFERENCE_PRESSURE_PA);
    let run = calculix::solve(&ccx_scene, &options)
        .map_err(|e| Error::External(format!("CalculiX linear C3D8: {e}")))?;
    let groups = &model.node_group;
    Ok(SmallStrainCheck {
        pressure_pa,
        ours_volume_change_ml: ours.volume_change_ml,
        calculix_volume_change_ml: summarise(scene, groups, &run.displacements_m).volume_change_ml,
        ours_vs_calculix: displacement_difference(&ours_u, &run.displacements_m, rest, groups)?,
    })
}

/// A copy of `scene` with every load multiplied by `factor`.
fn scaled_scene(scene: &Scene, factor: f64) -> Scene {
    let mut s = scene.clone();
    for p in &mut s.loads.pressures {
        p.pressure_pa *= factor;
    }
    for (_, f) in &mut s.loads.point_forces_n {
        *f *= factor;
    }
    s.loads.gravity_m_per_s2 *= factor;
    s
}

fn group_name(code: u8) -> &'static str {
    ConstraintGroup::from_code(code).map_or("interior", ConstraintGroup::name)
}

fn summarise(scene: &Scene, groups: &[u8], u: &[V3]) -> FieldSummary {
    let rest = &scene.mesh.rest_positions_m;
    let (max, sum) = u
        .iter()
        .map(|v| v.norm())
        .fold((0.0f64, 0.0), |(m, s), d| (m.max(d), s + d));
    let base = ConstraintGroup::Diaphragmatic.code();
    let (dz, n) = u
        .iter()
        .zip(groups)
        .filter(|(_, &g)| g == base)
        .fold((0.0, 0usize), |(s, n), (v, _)| (s + v.z, n + 1));
    let positions: Vec<V3> = rest.iter().zip(u).map(|(r, v)| r + v).collect();
    let volume = scene.mesh.enclosed_volume_m3(&positions) - scene.mesh.enclosed_volume_m3(rest);
    FieldSummary {
        max_displacement_mm: max * 1e3,
        mean_displacement_mm: sum / u.len().max(1) as f64 * 1e3,
        diaphragm_mean_dz_mm: if n > 0 { dz / n as f64 * 1e3 } else { 0.0 },
        volume_change_ml: volume * 1e6,
    }
}

/// Statistics of |a − b| node by node (b is the reference); `groups` holds each node's
/// [`ConstraintGroup`] code and `rest` its rest position (metres).
pub fn displacement_difference(
    a: &[V3],
    b: &[V3],
    rest: &[V3],
    groups: &[u8],
) -> Result<DisplacementDifference> {
    let n = a.len();
    if n == 0 || b.len() != n || rest.len() != n || groups.len() != n {
        return Err(Error::argument(
            "displacement difference",
            format!(
                "displacement fields of {n}, {} nodes, {} rest positions and {} group codes: \
             they must be the same non-zero count",
                b.len(),
                rest.len(),
                groups.len()
            ),
        ));
    }
    let diff: Vec<f64> = a.iter().zip(b).map(|(x, y)| (x - y).norm()).collect();
    let (max_node, max) =
        diff.iter().copied().enumerate().fold(
            (0, f64::MIN),
            |acc, (i, d)| if d > acc.1 { (i, d) } else { acc },
        );
    let mean = diff.iter().sum::<f64>() / n as f64;
    let ref_mean = b.iter().map(|v| v.norm()).sum::<f64>() / n as f64;
    let mut sorted = diff.clone();
    sorted.sort_unstable_by(f64::total_cmp);
    let quantile = |q: f64| sorted[((q * n as f64).ceil() as usize).clamp(1, n) - 1];

    let mut codes: Vec<u8> = groups.to_vec();
    codes.sort_unstable();
    codes.dedup();
    let per_group = codes
        .into_iter()
        .map(|code| {
            let (mut cnt, mut sum, mut mx, mut usum) = (0usize, 0.0, 0.0f64, 0.0);
            for ((&g, &d), u) in groups.iter().zip(&diff).zip(b) {
                if g == code {
                    cnt += 1;
                    sum += d;
                    mx = mx.max(d);
                    usum += u.norm();
                }
            }
            GroupDifference {
                group: group_name(code).to_string(),
                nodes: cnt,
                mean_mm: sum / cnt as f64 * 1e3,
                max_mm: mx * 1e3,
                reference_mean_displacement_mm: usum / cnt as f64 * 1e3,
            }
        })
        .collect();
    let mm = |v: V3| [v.x * 1e3, v.y * 1e3, v.z * 1e3];
    Ok(DisplacementDifference {
        mean_mm: mean * 1e3,
        median_mm: quantile(0.5) * 1e3,
        p95_mm: quantile(0.95) * 1e3,
        max_mm: max * 1e3,
        mean_relative: if ref_mean > 0.0 { mean / ref_mean } else { 0.0 },
        max_node,
        max_group: group_name(groups[max_node]).to_string(),
        max_position_lps_mm: mm(rest[max_node]),
        max_node_displacement_a_mm: mm(a[max_node]),
        max_node_displacement_b_mm: mm(b[max_node]),
        per_group,
    })
}

fn fmt3(v: [f64; 3]) -> String {
    format!("({:.1}, {:.1}, {:.1})", v[0], v[1], v[2])
}

fn difference_markdown(s: &mut String, d: &DisplacementDifference) {
    use crate::markdown::Table;
    let _ = writeln!(
        s,
        "|Δu| mean {:.3} mm ({:.1} % of the reference's mean displacement), median {:.3} mm, \
         95th percentile {:.3} mm, max {:.3} mm at node {} ({}, rest LPS {} mm; displacements \
         {} vs {} mm).\n",
        d.mean_mm,
        100.0 * d.mean_relative,
        d.median_mm,
        d.p95_mm,
        d.max_mm,
        d.max_node,
        d.max_group,
        fmt3(d.max_position_lps_mm),
        fmt3(d.max_node_displacement_a_mm),
        fmt3(d.max_node_displacement_b_mm)
    );
    // The headings' |Δu| and |u| are not escaped: kept as the published reports have them.
    let mut table = Table::new([
        "Group",
        "Nodes",
        "mean |Δu| (mm)",
        "max |Δu| (mm)",
        "reference mean |u| (mm)",
    ]);
    for g in &d.per_group {
        table.row([
            g.group.clone(),
            g.nodes.to_string(),
            format!("{:.3}", g.mean_mm),
            format!("{:.3}", g.max_mm),
            format!("{:.3}", g.reference_mean_displacement_mm),
        ]);
    }
    table.write_to(s);
    s.push('\n');
}

impl LungCalculixReport {
    /// The report as a markdown section.
    pub fn to_markdown(&self) -> String {
        use crate::markdown::{or_dash, Table};
        let mut s = String::new();
        s.push_str("## End-inhale frame against CalculiX\n\n");
        let _ = writeln!(
            s,
            "{}: {} elements of {} mm, {} nodes ({} fixed at the hilum, {} sliding on tangent \
             planes, {} on the diaphragm's z lines). Material E = {} Pa, ν = {}. Rest volume \
             {:.0} mL; our volume driver found {:.2} Pa for {} mL, and both codes solve at that \
             follower pressure from rest (CalculiX: NLGEOM, {}).\n",
            self.case,
            self.elements,
            self.settings.element_size_mm,
            self.nodes,
            self.fixed_nodes,
            self.plane_nodes,
            self.line_nodes,
            self.material.youngs_modulus_pa,
            self.material.poisson_ratio,
            self.rest_volume_ml,
            self.pressure_pa,
            self.settings.target_volume_ml,
            {
                let card = |law: Option<crate::model::ContinuumLaw>| match law {
                    None => "St Venant–Kirchhoff".to_string(),
                    Some(law) => format!("{law:?}"),
                };
                let ccx = self.settings.calculix_material.unwrap_or(self.material);
                let m = &self.material;
                format!(
                    "{}; ours: {:?} springs, volumetric law {}, continuum correction {}",
                    card(ccx.volumetric_law.or(ccx.continuum_correction)),
                    m.spring_law,
                    m.volumetric_law.map_or("none".into(), |l| format!("{l:?}")),
                    m.continuum_correction
                        .map_or("none".into(), |l| format!("{l:?}"))
                )
            }
        );
        let mut table = Table::new([
            "Solver",
            "max |u| (mm)",
            "mean |u| (mm)",
            "diaphragm mean u_z (mm)",
            "ΔV (mL)",
            "wall time (s)",
            "memory (MB)",
        ]);
        let o = &self.ours;
        table.row([
            "lungmotion (mass–spring)".to_string(),
            format!("{:.2}", o.field.max_displacement_mm),
            format!("{:.2}", o.field.mean_displacement_mm),
            format!("{:.2}", o.field.diaphragm_mean_dz_mm),
            format!("{:.1}", o.field.volume_change_ml),
            format!(
                "{:.2} (volume search: {:.2}, {} solves)",
                o.pressure_solve_wall_time_s, o.volume_solve_wall_time_s, o.volume_solves
            ),
            "–".into(),
        ]);
        for c in &self.calculix {
            table.row([
                format!(
                    "CalculiX {:?} ({} increments)",
                    c.element_type, c.increments
                ),
                format!("{:.2}", c.field.max_displacement_mm),
                format!("{:.2}", c.field.mean_displacement_mm),
                format!("{:.2}", c.field.diaphragm_mean_dz_mm),
                format!("{:.1}", c.field.volume_change_ml),
                format!("{:.2}", c.wall_time_s),
                or_dash(c.peak_memory_mb, |m| format!("{m:.0}")),
            ]);
        }
        table.write_to(&mut s);
        s.push('\n');
        for c in &self.calculix {
            let _ = writeln!(s, "### Ours against CalculiX {:?}\n", c.element_type);
            difference_markdown(&mut s, &c.ours_vs_calculix);
        }
        if let (Some(d), [a, b, ..]) = (&self.calculix_cross_check, self.calculix.as_slice()) {
            let _ = writeln!(
                s,
                "### CalculiX {:?} against {:?} (the reference's own spread)\n",
                b.element_type, a.element_type
            );
            difference_markdown(&mut s, d);
        }
        if let Some(c) = &self.small_strain {
            let _ = writeln!(
                s,
                "### Small strain: ours against linear CalculiX C3D8 at {:.3} Pa\n\nVolume \
                 change {:.3} vs {:.3} mL.",
                c.pressure_pa, c.ours_volume_change_ml, c.calculix_volume_change_ml
            );
            difference_markdown(&mut s, &c.ours_vs_calculix);
        }
        let _ = writeln!(s, "Comparison wall time {:.1} s.", self.wall_time_s);
        s
    }

    /// Writes `lung_calculix.json` and `lung_calculix.md` into `dir` (created if needed),
    /// each atomically.
    pub fn write(&self, dir: &Path) -> Result<()> {
        std::fs::create_dir_all(dir).at(IoOp::CreateDir, dir)?;
        let json = serde_json::to_string_pretty(self)
            .map_err(|e| Error::External(format!("serialising the report: {e}")))?;
        write_atomic(&dir.join("lung_calculix.json"), json.as_bytes())?;
        write_atomic(&dir.join("lung_calculix.md"), self.to_markdown().as_bytes())?;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn difference_statistics_locate_the_worst_node() {
        let rest = vec![V3::zeros(), V3::x(), V3::y(), V3::z()];
        let a = vec![V3::zeros(); 4];
        let b = vec![
            V3::new(0.001, 0.0, 0.0),
            V3::new(0.0, 0.002, 0.0),
            V3::new(0.0, 0.0, 0.004),
            V3::new(0.003, 0.0, 0.0),
        ];
        let groups = vec![0, 1, 4, 4];
        let d = displacement_difference(&a, &b, &rest, &groups).unwrap();
        assert!((d.mean_mm - 2.5).abs() < 1e-12);
        assert!((d.max_mm - 4.0).abs() < 1e-12);
        assert!((d.median_mm - 2.0).abs() < 1e-12);
        assert!((d.p95_mm - 4.0).abs() < 1e-12);
        assert_eq!(d.max_node, 2);
        assert_eq!(d.max_group, "diaphragmatic");
        assert_eq!(d.max_position_lps_mm, [0.0, 1000.0, 0.0]);
        let base = d.per_group.iter().find(|g| g.group == "diaphragmatic");
        let base = base.unwrap();
        assert_eq!(base.nodes, 2);
        assert!((base.mean_mm - 3.5).abs() < 1e-12);
        assert!(d.per_group.iter().any(|g| g.group == "interior"));
        assert!(displacement_difference(&a, &b[..3], &rest, &groups).is_err());
        assert!(displacement_difference(&[], &[], &[], &[]).is_err());
    }
}
