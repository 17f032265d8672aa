//! The thesis's composite cases (§3.3.4: bending of a cantilever, the 3D "L") against
//! CalculiX C3D8 with NLGEOM on identical geometry, constraints and loads, as a refinement
//! study: nodal displacement error against the finest CalculiX solution, per resolution.
//!
//! The thesis's loads are unit-inconsistent (extraction §6 item 9), so loads here are chosen
//! to give strains near 10 %, the element's stated validity limit: ρ = 2 kg/m³ for the beam
//! (linear beam theory: peak bending strain 3ρgL²/(EH) ≈ 9.4 %), and a 100 N total shear on
//! the L's top face (column-root bending strain ≈ 7.5 % by beam theory, more at the
//! re-entrant corner). The report states the strains actually reached.

use std::collections::HashMap;
use std::fmt::Write as _;
use std::time::Instant;

use nalgebra::{Matrix3, SymmetricEigen};
use serde::Serialize;

use super::calculix::{self, CalculixOptions, ElementType};
use crate::math::V3;
use crate::model::element::CORNER_SIGNS;
use crate::model::{ConstraintSet, HexMesh, Loads, Material, VoxelGrid};
use crate::simulation::{QuasiStaticSettings, QuasiStaticSolver, Scene, SolveReport};
use crate::{Error, Result};

/// Gravitational acceleration used for the self-weight case, m/s².
pub const GRAVITY_M_PER_S2: f64 = 9.81;
/// Young's modulus of both cases (thesis), Pa.
pub const YOUNGS_MODULUS_PA: f64 = 1000.0;
/// Poisson's ratio of both cases (thesis).
pub const POISSON_RATIO: f64 = 0.3;
/// Cantilever length along x, m (thesis: 400 mm).
pub const BEAM_LENGTH_M: f64 = 0.4;
/// Cantilever section edge, m (thesis: 100 × 100 mm).
pub const BEAM_SECTION_M: f64 = 0.1;
/// Edge of the cube the L is cut from, m (thesis: 4000 mm).
pub const L_CUBE_M: f64 = 4.0;

/// Which composite case.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
pub enum CompositeCase {
    /// 400 × 100 × 100 mm beam clamped at x = 0, bending under its own weight (−z).
    Cantilever,
    /// 4 m cube minus the quadrant x > 2 m, z > 2 m; base clamped, +x force on the top face.
    L,
}

impl CompositeCase {
    /// Cells of the grid at resolution `n`: n × n × 4n along the beam, n³ for the L's cube.
    pub fn cells(self, n: usize) -> [usize; 3] {
        match self {
            CompositeCase::Cantilever => [4 * n, n, n],
            CompositeCase::L => [n, n, n],
        }
    }

    /// Size the errors are expressed against, m (beam length; cube edge).
    pub fn object_size_m(self) -> f64 {
        match self {
            CompositeCase::Cantilever => BEAM_LENGTH_M,
            CompositeCase::L => L_CUBE_M,
        }
    }

    /// Resolution label as the thesis writes it (1×1×4, 2×2×2, …).
    pub fn label(self, n: usize) -> String {
        match self {
            CompositeCase::Cantilever => format!("{n}×{n}×{}", 4 * n),
            CompositeCase::L => format!("{n}×{n}×{n}"),
        }
    }
}

/// Settings of the composite study.
#[derive(Debug, Clone, Serialize)]
pub struct CompositeOptions {
    /// Cantilever resolutions n (n × n × 4n elements); the largest is the reference. Empty: skip.
    pub cantilever_resolutions: Vec<usize>,
    /// L resolutions n (n³ cells of the cube); the largest is the reference. Empty: skip.
    pub l_resolutions: Vec<usize>,
    /// Cantilever density, kg/m³ (sets the load: self-weight).
    pub cantilever_density_kg_per_m3: f64,
    /// Total +x force on the L's top face, N, shared equally by its nodes.
    pub l_total_force_n: f64,
    /// Density of the L, kg/m³: the mesh needs one, the static answer ignores it (no gravity).
    pub l_density_kg_per_m3: f64,
    /// Mass–spring solver settings.
    pub solver: QuasiStaticSettings,
    /// CalculiX settings (NLGEOM, C3D8 for the study).
    pub calculix: CalculixOptions,
    /// Also solve the finest mesh with C3D8I, to show how far C3D8's own locking moves the
    /// reference.
    pub check_reference_with_c3d8i: bool,
    /// Both codes follow this continuum law: ours through `[material] continuum_correction`,
    /// CalculiX through the law's card (`calculix::material_card`). `None`: Baudet's springs
    /// against CalculiX `*ELASTIC` (St Venant–Kirchhoff under NLGEOM), the thesis's comparison.
    pub continuum_law: Option<crate::model::ContinuumLaw>,
}

impl CompositeOptions {
    /// The thesis's resolutions: cantilever 1×1×4 … 8×8×32, L 2³ … 16³.
    pub fn full() -> Self {
        CompositeOptions {
            cantilever_resolutions: vec![1, 2, 4, 8],
            l_resolutions: vec![2, 4, 8, 16],
            cantilever_density_kg_per_m3: 2.0,
            l_total_force_n: 100.0,
            l_density_kg_per_m3: 1.0,
            solver: QuasiStaticSettings::default(),
            calculix: CalculixOptions::default(),
            check_reference_with_c3d8i: true,
            continuum_law: None,
        }
    }

    /// A quicker study: cantilever up to 4×4×16, L up to 8³ (references at those).
    pub fn quick() -> Self {
        CompositeOptions {
            cantilever_resolutions: vec![1, 2, 4],
            l_resolutions: vec![2, 4, 8],
            ..Self::full()
        }
    }
}

impl Default for CompositeOptions {
    fn default() -> Self {
        Self::full()
    }
}

/// A composite case meshed at one resolution.
#[derive(Debug, Clone)]
pub struct CaseModel {
    /// The case.
    pub case: CompositeCase,
    /// Resolution n.
    pub resolution: usize,
    /// Mesh, constraints and loads.
    pub scene: Scene,
    /// Lattice point (i, j, k) of each node.
    pub node_lattice: Vec<[u32; 3]>,
}

/// Builds `case` at resolution `n` with the loads of `options`.
pub fn build_case(case: CompositeCase, n: usize, options: &CompositeOptions) -> Result<CaseModel> {
    if n == 0 {
        return Err(Error::InvalidModel(
            "composite resolution must be at least 1".into(),
        ));
    }
    let cells = case.cells(n);
    let (gm, loads_of) = match case {
        CompositeCase::Cantilever => {
            let h = BEAM_SECTION_M / n as f64;
            let material = Material::new(
                YOUNGS_MODULUS_PA,
                POISSON_RATIO,
                options.cantilever_density_kg_per_m3,
            )?
            .with_continuum_correction(options.continuum_law)?;
            let gm = VoxelGrid::filled_box(cells, [h; 3], V3::zeros()).to_mesh(material)?;
            (gm, None)
        }
        CompositeCase::L => {
            if !n.is_multiple_of(2) {
                return Err(Error::InvalidModel(format!(
                    "the L needs an even resolution so its notch lies on cell faces, got {n}"
                )));
            }
            let h = L_CUBE_M / n as f64;
            let mut grid = VoxelGrid::filled_box(cells, [h; 3], V3::zeros());
            for k in n / 2..n {
                for j in 0..n {
                    for i in n / 2..n {
                        let c = grid.cell_index(i, j, k);
                        grid.active[c] = false;
                    }
                }
            }
            let material = Material::new(
                YOUNGS_MODULUS_PA,
                POISSON_RATIO,
                options.l_density_kg_per_m3,
            )?
            .with_continuum_correction(options.continuum_law)?;
            (grid.to_mesh(material)?, Some(options.l_total_force_n))
        }
    };
    let mesh = gm.mesh;
    let mut constraints = ConstraintSet::new(mesh.node_count());
    let clamp_axis = match case {
        CompositeCase::Cantilever => 0,
        CompositeCase::L => 2,
    };
    for (node, l) in gm.node_lattice.iter().enumerate() {
        if l[clamp_axis] == 0 {
            constraints.fix(node as u32, mesh.rest_positions_m[node])?;
        }
    }
    let mut loads = Loads::default();
    match loads_of {
        None => loads.gravity_m_per_s2 = V3::new(0.0, 0.0, -GRAVITY_M_PER_S2),
        Some(total) => {
            let top: Vec<u32> = (0..mesh.node_count() as u32)
                .filter(|&i| gm.node_lattice[i as usize][2] as usize == n)
                .collect();
            let each = total / top.len() as f64;
            loads.point_forces_n = top
                .into_iter()
                .map(|i| (i, V3::new(each, 0.0, 0.0)))
                .collect();
        }
    }
    Ok(CaseModel {
        case,
        resolution: n,
        scene: Scene::new(mesh, constraints, loads)?,
        node_lattice: gm.node_lattice,
    })
}

/// Mean, standard deviation and maximum of a set of nodal displacement errors.
#[derive(Debug, Clone, Copy, Serialize, PartialEq)]
pub struct ErrorStats {
    /// Mean of |Δu| over the compared nodes, m.
    pub mean_m: f64,
    /// Population standard deviation of |Δu|, m.
    pub sd_m: f64,
    /// Largest |Δu|, m.
    pub max_m: f64,
    /// Mean as a percentage of the object size.
    pub mean_percent_of_size: f64,
}

impl ErrorStats {
    /// Statistics of |a − b| over paired displacements.
    pub fn between(a: &[V3], b: &[V3], object_size_m: f64) -> Self {
        assert_eq!(a.len(), b.len());
        let d: Vec<f64> = a.iter().zip(b).map(|(x, y)| (x - y).norm()).collect();
        let n = d.len().max(1) as f64;
        let mean = d.iter().sum::<f64>() / n;
        let var = d.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / n;
        ErrorStats {
            mean_m: mean,
            sd_m: var.sqrt(),
            max_m: d.iter().cloned().fold(0.0, f64::max),
            mean_percent_of_size: 100.0 * mean / object_size_m,
        }
    }
}

/// One resolution of a case.
#[derive(Debug, Clone, Serialize)]
pub struct ResolutionRow {
    /// Resolution n.
    pub resolution: usize,
    /// Label (1×1×4, …).
    pub label: String,
    /// Element count.
    pub elements: usize,
    /// Node count.
    pub nodes: usize,
    /// Mass–spring error against the reference.
    pub mass_spring_error: Option<ErrorStats>,
    /// CalculiX on this same mesh against the reference (zero on the reference mesh).
    pub calculix_error: Option<ErrorStats>,
    /// Mass–spring against CalculiX on this same mesh (model error without discretisation).
    pub mass_spring_vs_calculix_same_mesh: Option<ErrorStats>,
    /// Observed order of the mass–spring error from the previous resolution:
    /// log(e_prev / e) / log(n / n_prev).
    pub mass_spring_order: Option<f64>,
    /// Same for CalculiX's own error.
    pub calculix_order: Option<f64>,
    /// Largest element-mean Green strain (absolute principal value) of the mass–spring solution.
    pub mass_spring_max_strain: Option<f64>,
    /// Same for the CalculiX solution.
    pub calculix_max_strain: Option<f64>,
    /// Largest displacement of the mass–spring solution, m.
    pub mass_spring_max_displacement_m: Option<f64>,
    /// Wall time of the mass–spring solve (set-up included), s.
    pub mass_spring_wall_time_s: Option<f64>,
    /// Wall time of ccx, s.
    pub calculix_wall_time_s: Option<f64>,
    /// Quasi-static solver statistics.
    pub solve: Option<SolveReport>,
    /// How the mass–spring equilibrium was found (quasi-static, or the explicit fallback and why).
    pub mass_spring_method: Option<String>,
    /// Why the mass–spring solve failed, if it did.
    pub mass_spring_failure: Option<String>,
    /// Why CalculiX failed on this mesh, if it did.
    pub calculix_failure: Option<String>,
}

/// A value the thesis printed for a case, to set beside ours.
#[derive(Debug, Clone, Serialize)]
pub struct ThesisAnchor {
    /// Resolution n it refers to.
    pub resolution: usize,
    /// Mean displacement error, mm.
    pub mean_error_mm: Option<f64>,
    /// Standard deviation, mm.
    pub sd_mm: Option<f64>,
    /// Mean error as a percentage of the object size.
    pub percent_of_size: Option<f64>,
    /// What the thesis says.
    pub note: String,
}

/// The refinement study of one case.
#[derive(Debug, Clone, Serialize)]
pub struct CaseReport {
    /// The case.
    pub case: CompositeCase,
    /// Human description: geometry, constraints, load.
    pub description: String,
    /// Size errors are expressed against, m.
    pub object_size_m: f64,
    /// Reference: CalculiX C3D8 NLGEOM at this resolution.
    pub reference_resolution: usize,
    /// Largest displacement of the reference, m.
    pub reference_max_displacement_m: f64,
    /// Largest element-mean Green strain of the reference.
    pub reference_max_strain: f64,
    /// Reference C3D8 against C3D8I on the finest mesh (uncertainty of the reference).
    pub reference_c3d8_vs_c3d8i: Option<ErrorStats>,
    /// Least-squares slope of log(mass–spring mean error) against log(n).
    pub mass_spring_fitted_order: Option<f64>,
    /// Least-squares slope of log(CalculiX mean error) against log(n), reference excluded.
    pub calculix_fitted_order: Option<f64>,
    /// One row per resolution, coarse to fine.
    pub rows: Vec<ResolutionRow>,
    /// What the thesis printed for this case.
    pub thesis: Vec<ThesisAnchor>,
}

/// The whole composite study.
#[derive(Debug, Clone, Serialize)]
pub struct CompositeReport {
    /// Options it ran with.
    pub options: CompositeOptions,
    /// One report per case run.
    pub cases: Vec<CaseReport>,
}

/// Runs the composite study (both cases unless their resolution lists are empty).
pub fn run_composite(options: &CompositeOptions) -> Result<CompositeReport> {
    // Fail before the mass–spring solves, not after, when the reference cannot be computed.
    calculix::require_ccx()?;
    let mut cases = Vec::new();
    for (case, res) in [
        (CompositeCase::Cantilever, &options.cantilever_resolutions),
        (CompositeCase::L, &options.l_resolutions),
    ] {
        if !res.is_empty() {
            cases.push(run_case(case, res, options)?);
        }
    }
    Ok(CompositeReport {
        options: options.clone(),
        cases,
    })
}

/// One resolution of a case solved by both codes (failures kept as messages).
struct Solved {
    model: CaseModel,
    ours: std::result::Result<MassSpringSolution, String>,
    ccx: std::result::Result<(Vec<V3>, f64), String>,
}

/// Runs one case at the given resolutions; the finest is the reference.
pub fn run_case(
    case: CompositeCase,
    resolutions: &[usize],
    options: &CompositeOptions,
) -> Result<CaseReport> {
    let (res, finest) = nested_resolutions(resolutions)?;
    let mut solved = Vec::new();
    for &n in &res {
        let model = build_case(case, n, options)?;
        let ours = solve_mass_spring(&model.scene, options);
        let ccx = calculix::solve(&model.scene, &options.calculix)
            .map(|s| (s.displacements_m, s.wall_time_s))
            .map_err(|e| e.to_string());
        solved.push(Solved { model, ours, ccx });
    }
    let reference = solved.last().expect("at least one resolution");
    let ref_u = match &reference.ccx {
        Ok((u, _)) => u.clone(),
        Err(e) => {
            return Err(Error::External(format!(
                "the CalculiX reference ({}) failed: {e}",
                case.label(finest)
            )))
        }
    };
    let ref_mesh = &reference.model.scene.mesh;
    let size = case.object_size_m();
    let reference_c3d8_vs_c3d8i = if options.check_reference_with_c3d8i {
        reference_uncertainty(&reference.model.scene, &ref_u, size, options)
    } else {
        None
    };

    let reference_at = ReferenceLookup::new(&reference.model, &ref_u, finest);
    let mut rows: Vec<ResolutionRow> = Vec::new();
    for s in &solved {
        let at_ref = reference_at.nodes_of(&s.model);
        let row = resolution_row(case, s, &at_ref, size, rows.last());
        rows.push(row);
    }
    let (mass_spring_fitted_order, calculix_fitted_order) = fitted_orders(&rows, finest);
    Ok(CaseReport {
        case,
        description: describe(case, options),
        object_size_m: size,
        reference_resolution: finest,
        reference_max_displacement_m: ref_u.iter().map(|v| v.norm()).fold(0.0, f64::max),
        reference_max_strain: max_green_strain(ref_mesh, &ref_u),
        reference_c3d8_vs_c3d8i,
        mass_spring_fitted_order,
        calculix_fitted_order,
        rows,
        thesis: thesis_anchors(case),
    })
}

/// The resolutions sorted and deduplicated, and the finest; refuses an empty list and a
/// resolution that does not divide the finest (its nodes would not be reference nodes).
fn nested_resolutions(resolutions: &[usize]) -> Result<(Vec<usize>, usize)> {
    let mut res = resolutions.to_vec();
    res.sort_unstable();
    res.dedup();
    let finest = *res
        .last()
        .ok_or_else(|| Error::InvalidModel("no resolution to run".into()))?;
    if let Some(n) = res.iter().find(|&&n| finest % n != 0) {
        return Err(Error::InvalidModel(format!(
            "resolution {n} does not divide the reference resolution {finest}, so its nodes \
             are not reference nodes"
        )));
    }
    Ok((res, finest))
}

/// The reference C3D8 solution against C3D8I on the same mesh (none if CalculiX fails).
fn reference_uncertainty(
    reference: &Scene,
    ref_u: &[V3],
    size: f64,
    options: &CompositeOptions,
) -> Option<ErrorStats> {
    let opts = CalculixOptions {
        element_type: ElementType::C3D8I,
        ..options.calculix.clone()
    };
    calculix::solve(reference, &opts)
        .ok()
        .map(|s| ErrorStats::between(&s.displacements_m, ref_u, size))
}

/// The reference displacement at each node of a coarser nested mesh.
struct ReferenceLookup<'a> {
    ref_u: &'a [V3],
    /// Reference node at each reference lattice point.
    index: HashMap<[u32; 3], usize>,
    finest: usize,
}

impl<'a> ReferenceLookup<'a> {
    /// Indexes the reference model's nodes by lattice point.
    fn new(reference: &CaseModel, ref_u: &'a [V3], finest: usize) -> Self {
        let index = reference
            .node_lattice
            .iter()
            .enumerate()
            .map(|(i, l)| (*l, i))
            .collect();
        ReferenceLookup {
            ref_u,
            index,
            finest,
        }
    }

    /// The reference displacement at every node of `model`.
    fn nodes_of(&self, model: &CaseModel) -> Vec<V3> {
        let ratio = (self.finest / model.resolution) as u32;
        model
            .node_lattice
            .iter()
            .map(|l| self.ref_u[self.index[&l.map(|c| c * ratio)]])
            .collect()
    }
}

/// The row of one resolution: both codes against the reference `at_ref`, against each
/// other, and the observed orders from the previous row.
fn resolution_row(
    case: CompositeCase,
    s: &Solved,
    at_ref: &[V3],
    size: f64,
    prev: Option<&ResolutionRow>,
) -> ResolutionRow {
    let mesh = &s.model.scene.mesh;
    let mut row = ResolutionRow {
        resolution: s.model.resolution,
        label: case.label(s.model.resolution),
        elements: mesh.element_count(),
        nodes: mesh.node_count(),
        mass_spring_error: None,
        calculix_error: None,
        mass_spring_vs_calculix_same_mesh: None,
        mass_spring_order: None,
        calculix_order: None,
        mass_spring_max_strain: None,
        calculix_max_strain: None,
        mass_spring_max_displacement_m: None,
        mass_spring_wall_time_s: None,
        calculix_wall_time_s: None,
        solve: None,
        mass_spring_method: None,
        mass_spring_failure: None,
        calculix_failure: None,
    };
    match &s.ours {
        Ok(MassSpringSolution {
            displacements_m: u,
            wall_time_s: t,
            report,
            method,
        }) => {
            row.mass_spring_error = Some(ErrorStats::between(u, at_ref, size));
            row.mass_spring_max_strain = Some(max_green_strain(mesh, u));
            row.mass_spring_max_displacement_m =
                Some(u.iter().map(|v| v.norm()).fold(0.0, f64::max));
            row.mass_spring_wall_time_s = Some(*t);
            row.solve = Some(report.clone());
            row.mass_spring_method = Some(method.clone());
        }
        Err(e) => row.mass_spring_failure = Some(e.clone()),
    }
    match &s.ccx {
        Ok((u, t)) => {
            row.calculix_error = Some(ErrorStats::between(u, at_ref, size));
            row.calculix_max_strain = Some(max_green_strain(mesh, u));
            row.calculix_wall_time_s = Some(*t);
            if let Ok(ours) = &s.ours {
                row.mass_spring_vs_calculix_same_mesh =
                    Some(ErrorStats::between(&ours.displacements_m, u, size));
            }
        }
        Err(e) => row.calculix_failure = Some(e.clone()),
    }
    if let Some(prev) = prev {
        let h = (row.resolution as f64 / prev.resolution as f64).ln();
        let order = |a: Option<ErrorStats>, b: Option<ErrorStats>| match (a, b) {
            (Some(a), Some(b)) if a.mean_m > 0.0 && b.mean_m > 0.0 => {
                Some((a.mean_m / b.mean_m).ln() / h)
            }
            _ => None,
        };
        row.mass_spring_order = order(prev.mass_spring_error, row.mass_spring_error);
        row.calculix_order = order(prev.calculix_error, row.calculix_error);
    }
    row
}

/// Least-squares orders of the mass–spring and the CalculiX mean errors over the rows
/// (the reference excluded from CalculiX's, where its error is zero by construction).
fn fitted_orders(rows: &[ResolutionRow], finest: usize) -> (Option<f64>, Option<f64>) {
    let fit = |pick: &dyn Fn(&ResolutionRow) -> Option<f64>| {
        let pts: Vec<(f64, f64)> = rows
            .iter()
            .filter_map(|r| {
                pick(r)
                    .filter(|e| *e > 0.0)
                    .map(|e| ((r.resolution as f64).ln(), e.ln()))
            })
            .collect();
        fitted_slope(&pts).map(|s| -s)
    };
    let mass_spring_fitted_order = fit(&|r| r.mass_spring_error.map(|e| e.mean_m));
    let calculix_fitted_order = fit(&|r| {
        (r.resolution != finest)
            .then_some(r.calculix_error.map(|e| e.mean_m))
            .flatten()
    });
    (mass_spring_fitted_order, calculix_fitted_order)
}

struct MassSpringSolution {
    displacements_m: Vec<V3>,
    wall_time_s: f64,
    report: SolveReport,
    method: String,
}

/// Errors are strings: a failure is reported in its row.
fn solve_mass_spring(
    scene: &Scene,
    options: &CompositeOptions,
) -> std::result::Result<MassSpringSolution, String> {
    let start = Instant::now();
    let (x, report) = QuasiStaticSolver::new(scene, options.solver.clone())
        .and_then(|mut s| s.solve(None))
        .map_err(|e| e.to_string())?;
    // The solver says how it got there: plain Newton, pseudo-time steps across a mechanism
    // (the element's twist modes on one-element-thick meshes), or damped relaxation.
    let method = match (report.pseudo_time_steps, report.relaxation_steps) {
        (0, 0) => "quasi-static (Newton)".to_string(),
        (p, 0) => format!("quasi-static, {p} pseudo-time steps (mechanism)"),
        (p, r) => format!("quasi-static, {p} pseudo-time steps, then {r} relaxation steps"),
    };
    Ok(MassSpringSolution {
        displacements_m: scene.displacements(&x),
        wall_time_s: start.elapsed().as_secs_f64(),
        report,
        method,
    })
}

/// Slope of the least-squares line through `pts`, if at least two distinct abscissae.
fn fitted_slope(pts: &[(f64, f64)]) -> Option<f64> {
    if pts.len() < 2 {
        return None;
    }
    let n = pts.len() as f64;
    let mx = pts.iter().map(|p| p.0).sum::<f64>() / n;
    let my = pts.iter().map(|p| p.1).sum::<f64>() / n;
    let sxx: f64 = pts.iter().map(|p| (p.0 - mx).powi(2)).sum();
    let sxy: f64 = pts.iter().map(|p| (p.0 - mx) * (p.1 - my)).sum();
    (sxx > 0.0).then(|| sxy / sxx)
}

/// Largest absolute principal value of the element-mean Green–Lagrange strain.
///
/// The mean deformation gradient of a brick is the least-squares fit to its corners:
/// column i = Σ_n s_n,i · x_n / (4 h_i).
pub fn max_green_strain(mesh: &HexMesh, displacements_m: &[V3]) -> f64 {
    mesh.elements
        .iter()
        .zip(&mesh.element_class)
        .map(|(corners, &class)| {
            let h = mesh.classes[class as usize].shape.edges_m;
            let x =
                corners.map(|c| mesh.rest_positions_m[c as usize] + displacements_m[c as usize]);
            let f = Matrix3::from_fn(|r, i| {
                (0..8).map(|n| CORNER_SIGNS[n][i] * x[n][r]).sum::<f64>() / (4.0 * h[i])
            });
            let e = 0.5 * (f.transpose() * f - Matrix3::identity());
            SymmetricEigen::new(e)
                .eigenvalues
                .iter()
                .map(|v| v.abs())
                .fold(0.0, f64::max)
        })
        .fold(0.0, f64::max)
}

fn describe(case: CompositeCase, options: &CompositeOptions) -> String {
    match case {
        CompositeCase::Cantilever => format!(
            "Cantilever 400 × 100 × 100 mm along x, clamped (all DOFs) at x = 0, self-weight along \
             −z (g = {GRAVITY_M_PER_S2} m/s²); E = {YOUNGS_MODULUS_PA} Pa, ν = {POISSON_RATIO}, \
             ρ = {} kg/m³ (linear beam theory: peak bending strain {:.1} %, tip deflection {:.0} mm)",
            options.cantilever_density_kg_per_m3,
            100.0 * 3.0 * options.cantilever_density_kg_per_m3 * GRAVITY_M_PER_S2 * BEAM_LENGTH_M.powi(2)
                / (BEAM_SECTION_M * YOUNGS_MODULUS_PA),
            1e3 * 1.5 * options.cantilever_density_kg_per_m3 * GRAVITY_M_PER_S2 * BEAM_LENGTH_M.powi(4)
                / (YOUNGS_MODULUS_PA * BEAM_SECTION_M.powi(2)),
        ),
        CompositeCase::L => format!(
            "3D L: 4 m cube minus the quadrant x > 2 m, z > 2 m (through y); base z = 0 clamped; \
             total force {} N along +x shared equally by the nodes of the top face z = 4 m; \
             E = {YOUNGS_MODULUS_PA} Pa, ν = {POISSON_RATIO}, no gravity",
            options.l_total_force_n
        ),
    }
}

fn thesis_anchors(case: CompositeCase) -> Vec<ThesisAnchor> {
    match case {
        CompositeCase::Cantilever => vec![
            ThesisAnchor {
                resolution: 4,
                mean_error_mm: None,
                sd_mm: None,
                percent_of_size: None,
                note: "Figs. 3.47–3.49, no numbers: 4×4×16 \"a good approximation\"".into(),
            },
            ThesisAnchor {
                resolution: 8,
                mean_error_mm: None,
                sd_mm: None,
                percent_of_size: None,
                note: "elements crushed near the clamp, leave the validity range, stay stable"
                    .into(),
            },
        ],
        CompositeCase::L => vec![
            ThesisAnchor {
                resolution: 2,
                mean_error_mm: Some(279.8),
                sd_mm: Some(37.8),
                percent_of_size: Some(7.0),
                note: "vs Code Aster 16³".into(),
            },
            ThesisAnchor {
                resolution: 4,
                mean_error_mm: None,
                sd_mm: None,
                percent_of_size: None,
                note: "figure only".into(),
            },
            ThesisAnchor {
                resolution: 8,
                mean_error_mm: None,
                sd_mm: None,
                percent_of_size: None,
                note: "figure only".into(),
            },
            ThesisAnchor {
                resolution: 16,
                mean_error_mm: Some(26.0),
                sd_mm: Some(0.6),
                percent_of_size: Some(0.65),
                note: "vs Code Aster 16³".into(),
            },
        ],
    }
}

fn mm(v: f64) -> String {
    let v = v * 1e3;
    if v == 0.0 {
        "0".into()
    } else if v.abs() >= 100.0 {
        format!("{v:.0}")
    } else if v.abs() >= 1.0 {
        format!("{v:.2}")
    } else {
        format!("{v:.3}")
    }
}

fn stats_cell(s: &Option<ErrorStats>, failure: &Option<String>) -> String {
    match (s, failure) {
        (Some(s), _) => format!(
            "{} ± {} ({:.2} %)",
            mm(s.mean_m),
            mm(s.sd_m),
            s.mean_percent_of_size
        ),
        (None, Some(_)) => "failed".into(),
        (None, None) => "–".into(),
    }
}

impl CompositeReport {
    /// Markdown: one table per case, thesis anchors beside our numbers, then notes.
    pub fn to_markdown(&self) -> String {
        use crate::markdown::{first_line, or_dash, Table};
        let mut s = String::new();
        s.push_str("## Composite cases against CalculiX C3D8 NLGEOM\n\n");
        s.push_str(
            "Errors are |u_ours − u_ref| over every node of the coarse mesh (each is a node of the \
             reference mesh): mean ± population SD in mm, (mean as % of object size). The \
             reference is CalculiX C3D8 with NLGEOM on the finest mesh. \"Order\" is the observed \
             convergence order of the mean error from the previous row.\n\n",
        );
        for c in &self.cases {
            let _ = writeln!(s, "### {:?}\n\n{}.\n", c.case, c.description);
            let _ = writeln!(
                s,
                "Reference: CalculiX {} ({} mm largest displacement, largest element-mean Green \
                 strain {:.1} %).{}\n",
                c.case.label(c.reference_resolution),
                mm(c.reference_max_displacement_m),
                100.0 * c.reference_max_strain,
                c.reference_c3d8_vs_c3d8i
                    .map(|e| format!(
                        " C3D8 vs C3D8I on that mesh: {} ± {} mm (max {} mm), the reference's own \
                         uncertainty.",
                        mm(e.mean_m),
                        mm(e.sd_m),
                        mm(e.max_m)
                    ))
                    .unwrap_or_default()
            );
            let mut table = Table::new([
                "Resolution",
                "Elements",
                "Ours vs ref (mm)",
                "max (mm)",
                "order",
                "CalculiX same mesh vs ref (mm)",
                "order",
                "Ours vs CalculiX same mesh (mm)",
                "max strain ours / ccx",
                "t ours (s)",
                "t ccx (s)",
                "Thesis",
            ]);
            let strain = |v: f64| format!("{:.1} %", 100.0 * v);
            let two_places = |v: f64| format!("{v:.2}");
            for r in &c.rows {
                let thesis = c
                    .thesis
                    .iter()
                    .find(|a| a.resolution == r.resolution)
                    .map(|a| match (a.mean_error_mm, a.sd_mm, a.percent_of_size) {
                        (Some(m), Some(sd), Some(p)) => format!("{m} ± {sd} ({p} %)"),
                        _ => a.note.clone(),
                    })
                    .unwrap_or_else(|| "–".into());
                table.row([
                    r.label.clone(),
                    r.elements.to_string(),
                    stats_cell(&r.mass_spring_error, &r.mass_spring_failure),
                    or_dash(r.mass_spring_error.map(|e| e.max_m), mm),
                    or_dash(r.mass_spring_order, two_places),
                    stats_cell(&r.calculix_error, &r.calculix_failure),
                    or_dash(r.calculix_order, two_places),
                    or_dash(r.mass_spring_vs_calculix_same_mesh.map(|e| e.mean_m), mm),
                    format!(
                        "{} / {}",
                        or_dash(r.mass_spring_max_strain, strain),
                        or_dash(r.calculix_max_strain, strain)
                    ),
                    or_dash(r.mass_spring_wall_time_s, two_places),
                    or_dash(r.calculix_wall_time_s, two_places),
                    thesis,
                ]);
            }
            table.write_to(&mut s);
            let _ = writeln!(
                s,
                "\nFitted order of the mean error: ours {}, CalculiX {}.",
                or_dash(c.mass_spring_fitted_order, two_places),
                or_dash(c.calculix_fitted_order, two_places)
            );
            for r in &c.rows {
                if let Some(m) = r
                    .mass_spring_method
                    .as_deref()
                    .filter(|m| *m != "quasi-static")
                {
                    let _ = writeln!(
                        s,
                        "\n* {}: mass–spring equilibrium by {}",
                        r.label,
                        first_line(m)
                    );
                }
                if let Some(f) = &r.mass_spring_failure {
                    let _ = writeln!(
                        s,
                        "\n* {}: mass–spring solve failed: {}",
                        r.label,
                        first_line(f)
                    );
                }
                if let Some(f) = &r.calculix_failure {
                    let _ = writeln!(s, "\n* {}: CalculiX failed: {}", r.label, first_line(f));
                }
            }
            s.push('\n');
        }
        s
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cases_have_the_thesis_geometry() {
        let o = CompositeOptions::full();
        let beam = build_case(CompositeCase::Cantilever, 2, &o).unwrap();
        assert_eq!(beam.scene.mesh.element_count(), 2 * 2 * 8);
        let clamped = beam.scene.constraints.entries.len();
        assert_eq!(clamped, 3 * 3);
        let mass = beam.scene.mesh.total_mass_kg();
        assert!((mass - 2.0 * 0.4 * 0.01).abs() < 1e-12);

        let l = build_case(CompositeCase::L, 4, &o).unwrap();
        assert_eq!(l.scene.mesh.element_count(), 64 - 16);
        assert_eq!(l.scene.constraints.entries.len(), 25);
        let total: V3 = l.scene.loads.point_forces_n.iter().map(|(_, f)| f).sum();
        assert!((total - V3::new(100.0, 0.0, 0.0)).norm() < 1e-9);
        assert_eq!(l.scene.loads.point_forces_n.len(), 3 * 5);
        assert!(build_case(CompositeCase::L, 3, &o).is_err());
    }

    #[test]
    fn green_strain_of_a_stretch() {
        let o = CompositeOptions::full();
        let beam = build_case(CompositeCase::Cantilever, 1, &o).unwrap();
        let u: Vec<V3> = beam
            .scene
            .mesh
            .rest_positions_m
            .iter()
            .map(|p| V3::new(0.1 * p.x, 0.0, 0.0))
            .collect();
        let e = max_green_strain(&beam.scene.mesh, &u);
        assert!((e - 0.5 * (1.1f64.powi(2) - 1.0)).abs() < 1e-12, "{e}");
    }

    #[test]
    fn markdown_sets_thesis_anchors_beside_ours() {
        let stats = ErrorStats {
            mean_m: 0.28,
            sd_m: 0.03,
            max_m: 0.4,
            mean_percent_of_size: 7.0,
        };
        let row = ResolutionRow {
            resolution: 2,
            label: CompositeCase::L.label(2),
            elements: 6,
            nodes: 27,
            mass_spring_error: Some(stats),
            calculix_error: None,
            mass_spring_vs_calculix_same_mesh: None,
            mass_spring_order: None,
            calculix_order: None,
            mass_spring_max_strain: Some(0.05),
            calculix_max_strain: None,
            mass_spring_max_displacement_m: Some(0.3),
            mass_spring_wall_time_s: Some(0.01),
            calculix_wall_time_s: None,
            solve: None,
            mass_spring_method: Some("quasi-static".into()),
            mass_spring_failure: None,
            calculix_failure: Some("ccx crashed\ndetails".into()),
        };
        let report = CompositeReport {
            options: CompositeOptions::quick(),
            cases: vec![CaseReport {
                case: CompositeCase::L,
                description: describe(CompositeCase::L, &CompositeOptions::quick()),
                object_size_m: 4.0,
                reference_resolution: 8,
                reference_max_displacement_m: 0.5,
                reference_max_strain: 0.09,
                reference_c3d8_vs_c3d8i: None,
                mass_spring_fitted_order: Some(1.5),
                calculix_fitted_order: None,
                rows: vec![row],
                thesis: thesis_anchors(CompositeCase::L),
            }],
        };
        let md = report.to_markdown();
        assert!(md.contains("| 2×2×2 | 6 | 280 ± 30.00 (7.00 %)"), "{md}");
        assert!(md.contains("279.8 ± 37.8 (7 %)"), "{md}");
        assert!(md.contains("CalculiX failed: ccx crashed\n"), "{md}");
        assert!(!md.contains("details"), "{md}");
        serde_json::to_string(&report).unwrap();
    }

    #[test]
    fn error_stats_and_slope() {
        let a = vec![V3::new(1.0, 0.0, 0.0), V3::new(3.0, 0.0, 0.0)];
        let b = vec![V3::zeros(); 2];
        let s = ErrorStats::between(&a, &b, 10.0);
        assert_eq!(
            (s.mean_m, s.sd_m, s.max_m, s.mean_percent_of_size),
            (2.0, 1.0, 3.0, 20.0)
        );
        let pts = [(0.0, 1.0), (1.0, -1.0), (2.0, -3.0)];
        assert!((fitted_slope(&pts).unwrap() + 2.0).abs() < 1e-12);
    }
}
