//! `summary.json`: what a run did, frame by frame, with the model and the software version.

use std::collections::BTreeMap;

use serde::Serialize;

use super::{group_name, RunConfig, RunInputs};
use crate::ingest::lung_model::{ConstraintGroup, DiaphragmMotion, LungModel, SlidingMode};
use crate::ingest::pipeline::{IngestOutcome, IngestSummary};
use crate::math::V3;
use crate::model::{Material, NodeConstraint};
use crate::motion::dynamic::DynamicReport;
use crate::motion::{FrameSummary, MotionReport};
use crate::outputs::displacement_field::{FieldGrid, FieldSampler};
use crate::simulation::keyframes::KeyframeReport;
use crate::simulation::Scene;
use crate::volume::VolumeGeometry;

/// The machine-readable record of a run (`summary.json`); scripts rely on its field names.
#[derive(Debug, Clone, Serialize)]
pub struct RunSummary {
    /// `lungmotion`.
    pub software: &'static str,
    /// Version of the software that wrote it.
    pub software_version: &'static str,
    /// Conventions of every output file.
    pub conventions: BTreeMap<&'static str, &'static str>,
    /// The CT input as given.
    pub ct: String,
    /// The loaded CT's fingerprint (grid and voxels), telling a rerun on the same CT apart.
    pub ct_fingerprint: Option<String>,
    /// The breathing trace.
    pub trace: TraceSummary,
    /// The configuration used (file and command line merged).
    pub config: RunConfig,
    /// The mechanical model.
    pub model: ModelSummary,
    /// Ingest results (segmentation, meshing, groups).
    pub ingest: IngestSummary,
    /// Driver, key volumes and accuracy of the motion (frames listed in `frames`).
    pub motion: MotionReport,
    /// The dynamic run (time step, steps, compliance), when the dynamic mode was used.
    pub dynamic: Option<DynamicReport>,
    /// The grid every frame's displacement field is written on.
    pub field_grid: FieldGridSummary,
    /// How the requested output instants were met (phases of one breath, every sample of a
    /// ramp), when not literally.
    pub output_instants_note: Option<String>,
    /// One entry per output frame, in time order.
    pub frames: Vec<FrameRecord>,
    /// The largest inspiration above the scanned volume, with physical checks; `null` when
    /// the trace never rises above it.
    pub end_inhale: Option<BreathExtremeSummary>,
    /// The largest expiration below the scanned volume, with the same checks; `null` when
    /// the trace never falls below it.
    pub deepest_expiration: Option<BreathExtremeSummary>,
    /// Tracked points (also in `trajectories.csv`).
    pub points: Vec<PointTrajectory>,
    /// The treatment target through the frames (`--target`), with its ITV; `null` without one.
    pub target: Option<crate::outputs::radiotherapy::target_motion::TargetSummary>,
    /// How the tissue varied from element to element (`[tissue]`); `null` when homogeneous.
    pub tissue: Option<crate::model::tissue::TissueReport>,
    /// The virtual 4D-CT: motion grid, decay, inverse residual and files per phase; `null`
    /// when not asked for.
    pub virtual_ct: Option<crate::outputs::radiotherapy::virtual_ct::VirtualCtSummary>,
    /// Stage wall times, s.
    pub timings_s: BTreeMap<String, f64>,
    /// Peak resident memory of the process, MiB.
    pub peak_memory_mib: Option<f64>,
    /// The run's budgets and what it used of them.
    pub budget: BudgetUsage,
    /// Everything the user should know.
    pub warnings: Vec<String>,
}

/// The run's budgets beside what it used of them (`summary.json`'s `budget`).
#[derive(Debug, Clone, Copy, Default, Serialize)]
pub struct BudgetUsage {
    /// The limits: `time_s` and `max_equilibria`.
    #[serde(flatten)]
    pub limits: crate::run::BudgetConfig,
    /// Wall-clock seconds from the start of the run to writing the summary.
    pub elapsed_s: f64,
    /// Equilibrium solves reached.
    pub equilibria: usize,
}

/// Where the displacement fields lie on the CT grid.
#[derive(Debug, Clone, Serialize)]
pub struct FieldGridSummary {
    /// `lung_box` (the lungs' box plus a margin) or `ct` (the whole CT grid).
    pub kind: FieldGrid,
    /// The fields' grid (as in their headers): the CT's spacing and direction.
    pub geometry: VolumeGeometry,
    /// The CT voxel that is the field's voxel (0, 0, 0).
    pub start_voxel_in_ct: [usize; 3],
    /// The CT's own grid size, for comparison.
    pub ct_dims: [usize; 3],
}

impl FieldGridSummary {
    /// The grid of `field`, a sub-grid of a CT of `ct_dims` voxels.
    pub fn of(kind: FieldGrid, field: &FieldSampler, ct_dims: [usize; 3]) -> Self {
        FieldGridSummary {
            kind,
            geometry: *field.geometry(),
            start_voxel_in_ct: field.start(),
            ct_dims,
        }
    }
}

/// The trace as the run used it.
#[derive(Debug, Clone, Serialize)]
pub struct TraceSummary {
    /// File name or "generated: …".
    pub source: String,
    /// Number of samples.
    pub samples: usize,
    /// First and last sample times, s.
    pub time_range_s: [f64; 2],
    /// Smallest and largest volume change from the scan, mL.
    pub volume_range_ml: [f64; 2],
}

/// The mechanical model of the run.
#[derive(Debug, Clone, Serialize)]
pub struct ModelSummary {
    /// Element edge, mm.
    pub element_size_mm: f64,
    /// Elements of both lungs.
    pub elements: usize,
    /// Nodes of both lungs.
    pub nodes: usize,
    /// Lung tissue.
    pub material: Material,
    /// How the diaphragmatic face moves.
    pub diaphragm: DiaphragmMotion,
    /// How sliding nodes follow the wall.
    pub sliding: SlidingMode,
    /// Boundary condition of each group, by name.
    pub groups: BTreeMap<&'static str, &'static str>,
    /// Volume enclosed by the mesh at rest, mL.
    pub rest_volume_ml: f64,
    /// What drives the surface.
    pub load: &'static str,
}

/// Files of one frame, relative to the output directory.
#[derive(Debug, Clone, Serialize)]
pub struct FrameFiles {
    /// NIfTI displacement field.
    pub displacement_nifti: String,
    /// MetaImage copy, when asked for.
    pub displacement_mha: Option<String>,
    /// Deformed mesh, when asked for.
    pub mesh_vtu: Option<String>,
    /// DICOM Deformable Spatial Registration, when asked for.
    pub registration_dicom: Option<String>,
}

/// One output frame in `summary.json`.
#[derive(Debug, Clone, Serialize)]
pub struct FrameRecord {
    /// Time, volumes, pressure, displacement, solver effort.
    #[serde(flatten)]
    pub summary: FrameSummary,
    /// Rest position of the node that moved most, LPS mm.
    pub max_displacement_at_lps_mm: [f64; 3],
    /// Files written for this frame.
    pub files: FrameFiles,
    /// Time to sample and write the frame's files, s.
    pub write_time_s: f64,
}

/// A tracked point's displacement per frame.
#[derive(Debug, Clone, Serialize)]
pub struct PointTrajectory {
    /// The user's name for it.
    pub name: String,
    /// Position at the scanned state, LPS mm.
    pub rest_lps_mm: [f64; 3],
    /// Displacement at each frame, LPS mm.
    pub displacement_mm: Vec<[f64; 3]>,
}

/// Costal nodes whose distance to the chest wall changes by more than the element edge, and
/// at least this, mm, raise a warning: sliding follows the wall's tangent planes, which depart
/// from a curved wall as a node slides far (21 mm was seen at +1 152 mL on POPI at 8 mm).
/// Below one element edge the departure is within the mesh's own approximation of the wall
/// (the phantom's 500 mL breath at 8 mm: at most 7.1 mm).
pub const COSTAL_WALL_GAP_WARNING_MIN_MM: f64 = 5.0;

/// One warning per volume interval where the lung's shape jumps between key volumes: where,
/// which node, by how much, and that the frames there were solved rather than interpolated.
fn jump_warnings(keys: &KeyframeReport) -> impl Iterator<Item = String> + '_ {
    keys.direct_intervals.iter().map(|j| {
        let p = j.rest_position_mm;
        format!(
            "the lung's shape does not follow its volume smoothly between {:.0} and {:.0} mL \
             (node {} at rest LPS ({:.0}, {:.0}, {:.0}) mm is {:.2} mm off the interpolation of \
             its neighbours: the equilibrium jumps); frames there were solved, not interpolated",
            j.from_ml, j.to_ml, j.node, p[0], p[1], p[2], j.error_mm
        )
    })
}

/// The costal wall-gap warning bound for elements of `element_size_mm`, mm.
pub fn costal_wall_gap_warning_mm(element_size_mm: f64) -> f64 {
    element_size_mm.max(COSTAL_WALL_GAP_WARNING_MIN_MM)
}

/// Volumes within this of the scanned state, mL, count as the scanned state: a frame must
/// leave it by more to be reported as an inspiration or an expiration.
pub const SCANNED_STATE_TOLERANCE_ML: f64 = 1.0;

/// Which extreme of the breathing a [`BreathExtremeSummary`] describes.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum BreathExtreme {
    /// The largest inspiration above the scanned volume.
    EndInhale,
    /// The largest expiration below the scanned volume.
    DeepestExpiration,
}

impl BreathExtreme {
    /// How the console and the quick looks name it.
    pub fn label(self) -> &'static str {
        match self {
            BreathExtreme::EndInhale => "end-inhale",
            BreathExtreme::DeepestExpiration => "deepest expiration",
        }
    }

    /// File-name stem of its quick look.
    pub fn file_stem(self) -> &'static str {
        match self {
            BreathExtreme::EndInhale => "end-inhale",
            BreathExtreme::DeepestExpiration => "deepest-expiration",
        }
    }
}

/// A breathing extreme (end-inhale or deepest expiration) and the physical checks made on
/// it.
#[derive(Debug, Clone, Serialize)]
pub struct BreathExtremeSummary {
    /// Which extreme this is.
    pub kind: BreathExtreme,
    /// Frame index.
    pub frame: usize,
    /// Time, s.
    pub time_s: f64,
    /// The trace's volume change at that frame, mL.
    pub target_volume_ml: f64,
    /// Simulated volume change, mL.
    pub simulated_volume_ml: f64,
    /// Largest node displacement, mm.
    pub max_displacement_mm: f64,
    /// Where it occurs (rest position, LPS mm).
    pub max_displacement_at_lps_mm: [f64; 3],
    /// Constraint group of that node (`interior` if none).
    pub max_displacement_group: &'static str,
    /// Lung of that node.
    pub max_displacement_lung: &'static str,
    /// Mean cranio-caudal displacement of the diaphragmatic nodes, mm (negative = down).
    pub mean_base_dz_mm: f64,
    /// Mean cranio-caudal displacement of the apex nodes, mm.
    pub mean_apex_dz_mm: f64,
    /// Largest displacement of a hilum node, mm.
    pub hilum_max_displacement_mm: f64,
    /// Costal nodes: median, 95th percentile and largest change of distance to the chest
    /// wall, mm (tangent-plane sliding departs from a curved wall as nodes slide).
    pub costal_wall_gap_change_mm: [f64; 3],
    /// 99th percentile of that change, mm.
    pub costal_wall_gap_change_p99_mm: f64,
    /// Largest change among the costal nodes held on the curved wall itself (sliding mode
    /// `wall_surface`; the others stay on tangent planes where the wall's field has a ridge),
    /// mm; absent with tangent planes.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub costal_wall_gap_max_on_surface_mm: Option<f64>,
    /// Costal nodes whose distance to the wall changed by more than
    /// `costal_wall_gap_warning_mm`.
    pub costal_nodes_off_wall: usize,
    /// The bound those nodes exceed, mm: the element edge, at least
    /// [`COSTAL_WALL_GAP_WARNING_MIN_MM`].
    pub costal_wall_gap_warning_mm: f64,
    /// Rest position of the costal node with the largest change, LPS mm.
    pub costal_wall_gap_max_at_lps_mm: [f64; 3],
    /// Mean |displacement| per LPS axis over the lung tissue (node values weighted by the
    /// nodes' mass), mm: the per-axis motion DIR-Lab's landmarks report.
    pub mean_abs_displacement_lps_mm: [f64; 3],
    /// Share of the volume change the moving chest wall made at this frame (0: rigid wall).
    pub chest_wall_share: f64,
    /// The mediastinal face against the heart, with `mediastinum = "contact"`.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub heart_contact: Option<HeartContactSummary>,
}

/// Where the mediastinal nodes are against the heart at one frame (one-sided contact).
#[derive(Debug, Clone, Serialize)]
pub struct HeartContactSummary {
    /// Mediastinal nodes held by contact.
    pub nodes: usize,
    /// Nodes within [`HEART_TOUCH_MM`] of the heart (their rest tangent plane).
    pub touching: usize,
    /// Largest distance a node has left the heart by, mm.
    pub max_separation_mm: f64,
    /// Rest position of that node, LPS mm (absent when every node touches).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub max_separation_at_lps_mm: Option<[f64; 3]>,
    /// Largest distance a node is inside the heart, mm (the solver's tolerance: 0 up to a
    /// thousandth of the shortest element edge).
    pub max_penetration_mm: f64,
}

/// A mediastinal node closer than this to its plane touches the heart, mm.
pub const HEART_TOUCH_MM: f64 = 0.1;

impl BreathExtremeSummary {
    /// One console line: which extreme, its frame and volume, the largest displacement and
    /// where, and how base and apex move.
    pub fn describe(&self) -> String {
        format!(
            "{} (frame {}, t = {:.2} s, {:+.0} mL): max displacement {:.1} mm at LPS ({:.0}, \
             {:.0}, {:.0}) mm ({} lung, {}); base moves {:+.1} mm, apex {:+.1} mm in z",
            self.kind.label(),
            self.frame,
            self.time_s,
            self.simulated_volume_ml,
            self.max_displacement_mm,
            self.max_displacement_at_lps_mm[0],
            self.max_displacement_at_lps_mm[1],
            self.max_displacement_at_lps_mm[2],
            self.max_displacement_lung,
            self.max_displacement_group,
            self.mean_base_dz_mm,
            self.mean_apex_dz_mm
        )
    }

    /// The warning for costal nodes that left the wall by more than the bound, if any did.
    pub fn wall_gap_warning(&self) -> Option<String> {
        if self.costal_nodes_off_wall == 0 {
            return None;
        }
        let p = self.costal_wall_gap_max_at_lps_mm;
        Some(format!(
            "{} costal node(s) left the chest wall by more than {} mm at {} (frame {}, \
             {:+.0} mL): up to {:.1} mm, at rest position LPS ({:.0}, {:.0}, {:.0}) mm. Costal \
             nodes slide on the wall's tangent planes, which depart from a curved wall as a \
             node slides far: motion near the chest wall is less trustworthy there. Use a \
             smaller volume change, finer elements (--element-size), or read the displacement \
             near the wall with this in mind",
            self.costal_nodes_off_wall,
            self.costal_wall_gap_warning_mm,
            self.kind.label(),
            self.frame,
            self.simulated_volume_ml,
            self.costal_wall_gap_change_mm[2],
            p[0],
            p[1],
            p[2]
        ))
    }
}

/// The physical checks of the frame `frame` (node positions `x`, metres) as the breathing
/// extreme `kind`.
pub(super) fn extreme_summary(
    kind: BreathExtreme,
    model: &LungModel,
    scene: &Scene,
    frame: usize,
    x: &[V3],
    report: &MotionReport,
) -> BreathExtremeSummary {
    let rest = &scene.mesh.rest_positions_m;
    let u_mm = |n: usize| (x[n] - rest[n]) * 1e3;
    let mean_dz = |g: ConstraintGroup| {
        let nodes = model.group_nodes(g);
        nodes.iter().map(|&n| u_mm(n as usize).z).sum::<f64>() / nodes.len().max(1) as f64
    };
    let (node, max_mm) = (0..x.len())
        .map(|n| (n, u_mm(n).norm()))
        .fold((0, 0.0), |b, c| if c.1 > b.1 { c } else { b });
    let node_lung = model.node_lung();
    let hilum_max = model
        .group_nodes(ConstraintGroup::Hilum)
        .iter()
        .map(|&n| u_mm(n as usize).norm())
        .fold(0.0, f64::max);
    let bound_mm = costal_wall_gap_warning_mm(model.report.element_size_mm);
    let f = &report.frames[frame];
    let wall_factor =
        f.pressure_pa / crate::motion::REFERENCE_PRESSURE_PA * report.chest_wall.scale;
    let wall = costal_wall_gaps(model, scene, x, wall_factor, bound_mm);
    let mass = &scene.mesh.node_mass_kg;
    let mut mean_abs = [0.0; 3];
    for (n, &m_kg) in mass.iter().enumerate() {
        let u = u_mm(n);
        for (m, c) in mean_abs.iter_mut().zip(u.iter()) {
            *m += c.abs() * m_kg;
        }
    }
    let total_mass: f64 = mass.iter().sum();
    mean_abs
        .iter_mut()
        .for_each(|m| *m /= total_mass.max(f64::MIN_POSITIVE));
    BreathExtremeSummary {
        kind,
        frame,
        time_s: f.time_s,
        target_volume_ml: f.target_volume_ml,
        simulated_volume_ml: f.simulated_volume_ml,
        max_displacement_mm: max_mm,
        max_displacement_at_lps_mm: (rest[node] * 1e3).into(),
        max_displacement_group: group_name(model.node_group[node]),
        max_displacement_lung: match node_lung[node] {
            1 => "right",
            2 => "left",
            _ => "none",
        },
        mean_base_dz_mm: mean_dz(ConstraintGroup::Diaphragmatic),
        mean_apex_dz_mm: mean_dz(ConstraintGroup::Apex),
        hilum_max_displacement_mm: hilum_max,
        costal_wall_gap_change_mm: wall.quantiles_mm,
        costal_wall_gap_change_p99_mm: wall.p99_mm,
        costal_wall_gap_max_on_surface_mm: wall.max_on_surface_mm,
        costal_nodes_off_wall: wall.beyond_bound,
        costal_wall_gap_warning_mm: bound_mm,
        costal_wall_gap_max_at_lps_mm: wall.max_at_lps_mm,
        mean_abs_displacement_lps_mm: mean_abs,
        chest_wall_share: if f.simulated_volume_ml.abs() > 1e-9 {
            f.chest_wall_volume_ml / f.simulated_volume_ml
        } else {
            0.0
        },
        heart_contact: (!scene.one_sided.is_empty()).then(|| {
            let s = scene.one_sided.state(x, HEART_TOUCH_MM * 1e-3);
            HeartContactSummary {
                nodes: s.nodes,
                touching: s.touching,
                max_separation_mm: s.max_separation_m * 1e3,
                max_separation_at_lps_mm: s.farthest_node.map(|n| (rest[n as usize] * 1e3).into()),
                max_penetration_mm: s.max_penetration_m * 1e3,
            }
        }),
    }
}

/// How far the sliding costal nodes moved off (or into) the chest wall.
struct CostalWallGaps {
    /// Median, 95th percentile and largest change of distance to the wall, mm.
    quantiles_mm: [f64; 3],
    /// 99th percentile, mm.
    p99_mm: f64,
    /// Largest change among nodes held on the wall surface, mm (none without such nodes).
    max_on_surface_mm: Option<f64>,
    /// Nodes beyond the warning bound.
    beyond_bound: usize,
    /// Rest position of the node with the largest change, LPS mm.
    max_at_lps_mm: [f64; 3],
}

/// `wall_factor` is how far the moving costal planes have gone (load factor times the run's
/// wall scale): a node is measured against the wall moved by its plane's offset.
fn costal_wall_gaps(
    model: &LungModel,
    scene: &Scene,
    x: &[V3],
    wall_factor: f64,
    bound_mm: f64,
) -> CostalWallGaps {
    let rest = &scene.mesh.rest_positions_m;
    let mut max_on_surface_mm: Option<f64> = None;
    let mut gaps: Vec<(f64, usize)> = model
        .group_nodes(ConstraintGroup::Costal)
        .iter()
        .filter_map(|&n| {
            let c = scene.constraints.get(n)?;
            let wall_offset_m = match c {
                NodeConstraint::Plane { point_m, normal } => {
                    (point_m - rest[n as usize]).dot(normal) * wall_factor
                }
                NodeConstraint::Surface {
                    level_m,
                    rest_level_m,
                    ..
                } => (level_m - rest_level_m) * wall_factor,
                _ => return None,
            };
            let n = n as usize;
            let change_m =
                model.wall.evaluate(x[n]).0 - model.wall.evaluate(rest[n]).0 - wall_offset_m;
            let change_mm = change_m.abs() * 1e3;
            if matches!(c, NodeConstraint::Surface { .. }) {
                max_on_surface_mm = Some(max_on_surface_mm.map_or(change_mm, |m| m.max(change_mm)));
            }
            Some((change_mm, n))
        })
        .collect();
    gaps.sort_by(|a, b| a.0.total_cmp(&b.0));
    let at = |i: usize| gaps.get(i).map_or(0.0, |g| g.0);
    CostalWallGaps {
        quantiles_mm: [
            at(gaps.len() / 2),
            at(gaps.len() * 95 / 100),
            gaps.last().map_or(0.0, |g| g.0),
        ],
        p99_mm: at(gaps.len() * 99 / 100),
        max_on_surface_mm,
        beyond_bound: gaps.iter().filter(|g| g.0 > bound_mm).count(),
        max_at_lps_mm: gaps
            .last()
            .map_or([0.0; 3], |&(_, n)| (rest[n] * 1e3).into()),
    }
}

impl RunSummary {
    #[allow(clippy::too_many_arguments)]
    pub(super) fn new(
        inputs: &RunInputs,
        config: &RunConfig,
        outcome: &IngestOutcome,
        mut motion: MotionReport,
        mut dynamic: Option<DynamicReport>,
        frames: Vec<FrameRecord>,
        points: Vec<PointTrajectory>,
        extremes: Vec<BreathExtremeSummary>,
        field_grid: FieldGridSummary,
        timings_s: BTreeMap<String, f64>,
    ) -> Self {
        motion.frames.clear();
        if let Some(d) = dynamic.as_mut() {
            d.frames.clear();
        }
        let trace = &inputs.trace;
        let (vmin, vmax) = trace
            .volume_change_ml
            .iter()
            .fold((f64::MAX, f64::MIN), |(a, b), &v| (a.min(v), b.max(v)));
        let model = &outcome.model;
        let mut warnings = outcome.summary.warnings.clone();
        warnings.extend(extremes.iter().filter_map(|e| e.wall_gap_warning()));
        warnings.extend(motion.keyframes.iter().flat_map(jump_warnings));
        let extreme = |kind| extremes.iter().find(|e| e.kind == kind).cloned();
        let groups = ConstraintGroup::ALL
            .iter()
            .map(|g| (g.name(), g.mechanical_role()))
            .collect();
        RunSummary {
            software: "lungmotion",
            software_version: env!("CARGO_PKG_VERSION"),
            conventions: conventions(),
            ct: inputs.ct_path.display().to_string(),
            ct_fingerprint: None,
            trace: TraceSummary {
                source: inputs.trace_source.clone(),
                samples: trace.time_s.len(),
                time_range_s: [trace.time_s[0], *trace.time_s.last().unwrap_or(&0.0)],
                volume_range_ml: [vmin, vmax],
            },
            config: config.clone(),
            model: ModelSummary {
                element_size_mm: model.report.element_size_mm,
                elements: model.report.elements,
                nodes: model.report.nodes,
                material: config.material,
                diaphragm: model.report.diaphragm_motion,
                sliding: model.report.sliding_mode,
                groups,
                rest_volume_ml: motion.rest_volume_ml,
                load: "follower pressure on the whole lung surface (negative inflates); \
                       constrained directions taken by the wall, the diaphragm line or the \
                       fixed hilum",
            },
            ingest: outcome.summary.clone(),
            motion,
            dynamic,
            field_grid,
            frames,
            end_inhale: extreme(BreathExtreme::EndInhale),
            deepest_expiration: extreme(BreathExtreme::DeepestExpiration),
            points,
            target: None,
            tissue: None,
            virtual_ct: None,
            timings_s,
            peak_memory_mib: None,
            budget: BudgetUsage::default(),
            output_instants_note: None,
            warnings,
        }
    }
}

impl RunSummary {
    /// The breathing extremes the trace reaches: end-inhale, then the deepest expiration.
    pub fn extremes(&self) -> impl Iterator<Item = &BreathExtremeSummary> {
        self.end_inhale.iter().chain(&self.deepest_expiration)
    }
}

fn conventions() -> BTreeMap<&'static str, &'static str> {
    BTreeMap::from([
        (
            "coordinates",
            "DICOM patient space LPS, millimetres (+x patient left, +y posterior, +z superior)",
        ),
        (
            "displacement_nifti",
            "NIfTI-1 vector image, intent 1007, 3 float32 components in LPS millimetres (ITK / \
             elastix convention, not RAS), on the input CT's voxels (spacing and direction; by \
             default only the box around the lungs plus 2 voxels, its origin that box's first \
             voxel: see field_grid), values rounded to 1/64 mm, zero outside the lungs; the tissue at \
             voxel x is at x + u(x), as ITK's DisplacementFieldTransform maps it (SimpleITK \
             lands every lung voxel there, on either grid); one gzip member, level 2",
        ),
        (
            "volumes",
            "volume change from the scanned state, millilitres (positive = more air)",
        ),
        (
            "pressure",
            "surface pressure on the lung, pascals, positive pushing inward (inhalation is \
             negative)",
        ),
        (
            "phases",
            "phase 0 is end-inhale; N phases split one cycle into equal time steps",
        ),
        (
            "extremes",
            "end_inhale is the output frame with the largest volume above the scanned state, \
             deepest_expiration the one with the largest volume change below it (more than 1 mL \
             either way); null when the trace never goes that way",
        ),
    ])
}
