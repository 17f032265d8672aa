//! What the model builder did, for the ingest report: counts, volumes (mesh against mask),
//! what shaping the cells changed, the groups and the wall.

use std::collections::BTreeMap;
use std::time::Instant;

use rayon::prelude::*;
use serde::Serialize;

use super::cells::LungCells;
use super::constraints::WallRestFit;
use super::groups::{ConstraintGroup, NodeGroups};
use super::lattice::SUPERSAMPLES;
use super::mesh::LungMeshes;
use super::settings::{
    lung_name, DiaphragmMotion, LungModelSettings, SlidingMode, LEFT_LUNG, RIGHT_LUNG,
};
use super::wall::WallBuild;
use crate::ingest::Cancel;
use crate::volume::Volume;
use crate::Result;

/// What the model builder did, for the ingest report.
#[derive(Debug, Clone, Serialize)]
pub struct LungModelReport {
    /// Element edge in millimetres.
    pub element_size_mm: f64,
    /// Elements of both lungs.
    pub elements: usize,
    /// Nodes of both lungs (no node is shared between the lungs).
    pub nodes: usize,
    /// Nodes on the external surface.
    pub surface_nodes: usize,
    /// Elements per lung ("right", "left").
    pub elements_per_lung: BTreeMap<String, usize>,
    /// Volume enclosed by the mesh, both lungs, in millilitres.
    pub mesh_volume_ml: f64,
    /// Volume of the lung voxels of the mask, both lungs, in millilitres.
    pub mask_volume_ml: f64,
    /// Mesh volume per lung in millilitres.
    pub mesh_volume_per_lung_ml: BTreeMap<String, f64>,
    /// Mask volume per lung in millilitres.
    pub mask_volume_per_lung_ml: BTreeMap<String, f64>,
    /// How cells partly inside a lung were decided.
    pub partial_volume_policy: String,
    /// Cells added by filling cavities enclosed by a lung's elements.
    pub cavity_cells_filled: usize,
    /// Cells added by the 2 × 2 × 2 closing (one-cell-wide pits and notches of the surface).
    pub notch_cells_filled: usize,
    /// Elements removed by the 2 × 2 × 2 opening (one-element-thick parts).
    pub removed_thin_elements: usize,
    /// Elements removed because they were not face-connected to their lung's largest part.
    pub removed_detached_elements: usize,
    /// Surface nodes per group name (nodes of no group under "none").
    pub group_nodes: BTreeMap<String, usize>,
    /// Where each lung's hilum came from: airway contact or geometry.
    pub hilum_source: BTreeMap<String, String>,
    /// LPS position in millimetres of each lung's hilum centre node.
    pub hilum_centre_mm: BTreeMap<String, [f64; 3]>,
    /// Radius in millimetres actually used for the hilum.
    pub hilum_radius_mm: f64,
    /// Whether the groups came from `group_overrides`.
    pub groups_from_overrides: bool,
    /// Lung voxels of the CT mask touching the other lung (the lungs are meshed apart anyway).
    pub wall_contact_voxels: usize,
    /// Samples of the wall field along x, y, z.
    pub wall_samples: [usize; 3],
    /// Spacing of the wall field in millimetres.
    pub wall_spacing_mm: f64,
    /// How sliding nodes are held ([`SlidingMode`]).
    pub sliding_mode: SlidingMode,
    /// With [`SlidingMode::WallSurface`], sliding nodes kept on their tangent plane because
    /// the wall's distance field has a ridge there (see `MIN_SURFACE_GRADIENT`).
    pub wall_surface_plane_nodes: usize,
    /// How the diaphragmatic face moves.
    pub diaphragm_motion: DiaphragmMotion,
    /// Largest |wall distance| at a sliding node's rest position in mm: the element staircase
    /// against the smooth CT surface (with [`SlidingMode::WallSurface`], how far the solver
    /// moves a node onto the wall before any load).
    pub wall_rest_offset_max_mm: f64,
    /// Mean |wall distance| at the sliding nodes' rest positions in mm.
    pub wall_rest_offset_mean_mm: f64,
    /// Smallest |∇ wall| at a sliding node's rest position (1 for an exact distance field;
    /// near 0 would make the sliding direction ill-defined).
    pub wall_min_gradient_norm: f64,
    /// Wall time of the whole build in seconds.
    pub wall_time_s: f64,
    /// Wall time of each step of the build, in seconds, in order.
    pub step_times_s: Vec<(String, f64)>,
}

/// Step timer of the build: records (step, seconds since the previous mark) and logs each;
/// where a cancelled build stops.
pub(super) struct StepClock<'c> {
    last: Instant,
    /// The steps timed so far.
    pub(super) times: Vec<(String, f64)>,
    /// The flag looked at after each step and inside the long ones.
    pub(super) cancel: Cancel<'c>,
}

impl<'c> StepClock<'c> {
    /// A clock whose first step starts at `start`, stopping when `cancel` is raised.
    pub(super) fn new(start: Instant, cancel: Cancel<'c>) -> Self {
        StepClock {
            last: start,
            times: Vec::new(),
            cancel,
        }
    }

    /// Records the time since the previous mark under `step`; [`crate::Error::Cancelled`]
    /// when the flag was raised meanwhile.
    pub(super) fn mark(&mut self, step: &str) -> Result<()> {
        let now = Instant::now();
        let seconds = (now - self.last).as_secs_f64();
        tracing::debug!(step, seconds, "lung model step");
        self.times.push((step.to_string(), seconds));
        self.last = now;
        self.cancel.check("the lung model's construction")
    }
}

/// The lung voxels of the CT mask.
pub(super) struct MaskVoxels {
    /// Voxels of the right and of the left lung.
    pub(super) per_lung: [usize; 2],
    /// Volume of one voxel in millilitres.
    pub(super) voxel_ml: f64,
}

impl MaskVoxels {
    /// Counts the voxels of each lung in `lungs`.
    pub(super) fn count(lungs: &Volume<u8>) -> Self {
        MaskVoxels {
            per_lung: [RIGHT_LUNG, LEFT_LUNG]
                .map(|l| lungs.as_slice().par_iter().filter(|&&v| v == l).count()),
            voxel_ml: lungs.geometry.voxel_volume_mm3() * 1e-3,
        }
    }
}

/// The report of a finished build; `wall_time_s` and `step_times_s` are left for the caller.
pub(super) fn summarise(
    settings: &LungModelSettings,
    mask: &MaskVoxels,
    cells: &LungCells,
    meshes: &LungMeshes,
    wall: &WallBuild,
    groups: &NodeGroups,
    fit: &WallRestFit,
) -> LungModelReport {
    let h_mm = settings.element_size_mm;
    let mesh = &meshes.grid_mesh.mesh;
    let group_nodes = count_group_nodes(&meshes.surface, &groups.node_group);
    let mut mesh_volume_per_lung_ml = BTreeMap::new();
    let mut mask_volume_per_lung_ml = BTreeMap::new();
    for lung in [RIGHT_LUNG, LEFT_LUNG] {
        let count = meshes.element_lung.iter().filter(|&&l| l == lung).count();
        mesh_volume_per_lung_ml.insert(
            lung_name(lung).to_string(),
            count as f64 * h_mm.powi(3) * 1e-3,
        );
        mask_volume_per_lung_ml.insert(
            lung_name(lung).to_string(),
            mask.per_lung[(lung - 1) as usize] as f64 * mask.voxel_ml,
        );
    }
    let mesh_volume_ml = mesh.enclosed_volume_m3(&mesh.rest_positions_m) * 1e6;
    LungModelReport {
        element_size_mm: h_mm,
        elements: mesh.element_count(),
        nodes: mesh.node_count(),
        surface_nodes: meshes.surface.len(),
        elements_per_lung: meshes.elements_per_lung.clone(),
        mesh_volume_ml,
        mask_volume_ml: (mask.per_lung[0] + mask.per_lung[1]) as f64 * mask.voxel_ml,
        mesh_volume_per_lung_ml,
        mask_volume_per_lung_ml,
        partial_volume_policy: format!(
            "a {h_mm} mm cell is an element of a lung when at least {:.0} % of its {}³ \
             sample points (nearest CT voxel) lie in that lung",
            settings.occupancy_threshold * 100.0,
            SUPERSAMPLES
        ),
        cavity_cells_filled: cells.cavity_cells_filled,
        notch_cells_filled: cells.notch_cells_filled,
        removed_thin_elements: cells.removed_thin_elements,
        removed_detached_elements: cells.removed_detached_elements,
        group_nodes,
        hilum_source: groups.hilum_source.clone(),
        hilum_centre_mm: groups.hilum_centre_mm.clone(),
        hilum_radius_mm: groups.hilum_radius_mm,
        groups_from_overrides: groups.from_overrides,
        wall_contact_voxels: wall.contact_voxels,
        wall_samples: wall.wall.samples,
        wall_spacing_mm: wall.wall.spacing_m[0] * 1e3,
        sliding_mode: settings.sliding,
        wall_surface_plane_nodes: fit.plane_nodes,
        diaphragm_motion: settings.diaphragm,
        wall_rest_offset_max_mm: fit.offset_max_mm,
        wall_rest_offset_mean_mm: fit.offset_mean_mm,
        wall_min_gradient_norm: fit.min_gradient_norm,
        wall_time_s: 0.0,
        step_times_s: Vec::new(),
    }
}

/// Surface nodes per group name, every group listed, nodes of no group under "none".
fn count_group_nodes(surface: &[u32], node_group: &[u8]) -> BTreeMap<String, usize> {
    let mut group_nodes = BTreeMap::new();
    for g in ConstraintGroup::ALL {
        group_nodes.insert(g.name().to_string(), 0usize);
    }
    group_nodes.insert("none".to_string(), 0usize);
    for &n in surface {
        let name = ConstraintGroup::from_code(node_group[n as usize]).map_or("none", |g| g.name());
        *group_nodes.entry(name.to_string()).or_insert(0) += 1;
    }
    group_nodes
}
