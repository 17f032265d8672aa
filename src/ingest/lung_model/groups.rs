//! The anatomical constraint groups of the surface nodes (hilum, mediastinal, costal,
//! diaphragmatic, apex), automatic per lung or from a user label map, and what each group's
//! nodes may do.

use std::collections::BTreeMap;

use nalgebra::Vector3;
use rayon::prelude::*;
use serde::Serialize;

use super::hilum::{hilum_centre, medial_direction};
use super::mesh::LungMeshes;
use super::settings::{lung_name, LungModelSettings, LEFT_LUNG, RIGHT_LUNG};
use crate::model::SignedDistanceField;
use crate::volume::Volume;

/// Anatomical constraint group of a lung surface node; the code is its value in `groups.nii.gz`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize)]
#[repr(u8)]
pub enum ConstraintGroup {
    /// Where bronchi and vessels enter, on the medial face.
    Hilum = 1,
    /// Medial face against the heart and great vessels.
    Mediastinal = 2,
    /// Lateral, anterior and posterior faces against the rib cage.
    Costal = 3,
    /// Base, on the diaphragm dome.
    Diaphragmatic = 4,
    /// Top, under the first ribs.
    Apex = 5,
}

/// What a group's nodes may do in the simulation.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
pub enum BoundaryCondition {
    /// Held at the rest position.
    Fixed,
    /// Slides on the wall field.
    SlidingOnWall,
    /// Moves as [`LungModelSettings::diaphragm`] says.
    FollowsDiaphragm,
}

/// Wall normals with a z component at or below this (facing down) and below the hilum make
/// the diaphragmatic group: the dome and the zone of apposition.
pub const DIAPHRAGM_MAX_NORMAL_Z: f64 = -0.1;

impl ConstraintGroup {
    /// Every group, in code order.
    pub const ALL: [ConstraintGroup; 5] = [
        ConstraintGroup::Hilum,
        ConstraintGroup::Mediastinal,
        ConstraintGroup::Costal,
        ConstraintGroup::Diaphragmatic,
        ConstraintGroup::Apex,
    ];

    /// Code written in label maps (1–5; 0 means no group).
    pub fn code(self) -> u8 {
        self as u8
    }

    /// The group of a label-map code, `None` for 0 and unknown codes.
    pub fn from_code(code: u8) -> Option<Self> {
        Self::ALL.into_iter().find(|g| g.code() == code)
    }

    /// Lower-case name used in reports.
    pub fn name(self) -> &'static str {
        match self {
            ConstraintGroup::Hilum => "hilum",
            ConstraintGroup::Mediastinal => "mediastinal",
            ConstraintGroup::Costal => "costal",
            ConstraintGroup::Diaphragmatic => "diaphragmatic",
            ConstraintGroup::Apex => "apex",
        }
    }

    /// The mechanical role of the group's nodes, as text for reports.
    pub fn mechanical_role(self) -> &'static str {
        match self {
            ConstraintGroup::Hilum => "fixed: bronchi and vessels anchor the lung at the carina",
            ConstraintGroup::Mediastinal => "slides on the wall (pleura against the heart)",
            ConstraintGroup::Costal => "slides on the wall (pleura against the rib cage)",
            ConstraintGroup::Diaphragmatic => {
                "follows the diaphragm: moves cranio-caudally, driven by the pressure"
            }
            ConstraintGroup::Apex => "slides on the wall (pleural dome); moves little",
        }
    }

    /// The boundary condition the model gives this group's nodes.
    pub fn boundary_condition(self) -> BoundaryCondition {
        match self {
            ConstraintGroup::Hilum => BoundaryCondition::Fixed,
            ConstraintGroup::Diaphragmatic => BoundaryCondition::FollowsDiaphragm,
            _ => BoundaryCondition::SlidingOnWall,
        }
    }
}

/// The group of every node and where each lung's hilum was put.
pub(super) struct NodeGroups {
    /// [`ConstraintGroup`] code of each node (0 = interior or no group).
    pub(super) node_group: Vec<u8>,
    /// Whether the groups came from `group_overrides`.
    pub(super) from_overrides: bool,
    /// Where each lung's hilum came from: airway contact or geometry.
    pub(super) hilum_source: BTreeMap<String, String>,
    /// LPS position in millimetres of each lung's hilum centre node.
    pub(super) hilum_centre_mm: BTreeMap<String, [f64; 3]>,
    /// Radius in millimetres actually used for the hilum.
    pub(super) hilum_radius_mm: f64,
}

/// Groups the surface nodes: from `group_overrides` when given, otherwise per lung by the
/// rules of the module doc with normals from the `wall`.
pub(super) fn assign_groups(
    lungs: &Volume<u8>,
    airways: &Volume<u8>,
    settings: &LungModelSettings,
    meshes: &LungMeshes,
    wall: &SignedDistanceField,
) -> NodeGroups {
    let h_mm = settings.element_size_mm;
    let mut groups = NodeGroups {
        node_group: Vec::new(),
        from_overrides: false,
        hilum_source: BTreeMap::new(),
        hilum_centre_mm: BTreeMap::new(),
        hilum_radius_mm: settings.hilum_radius_mm.max(1.5 * h_mm),
    };
    match &settings.group_overrides {
        Some(overrides) => {
            groups.node_group =
                groups_from_labels(overrides, &meshes.positions_mm, &meshes.surface, h_mm);
            groups.from_overrides = true;
        }
        None => {
            groups.node_group = vec![0u8; meshes.grid_mesh.mesh.node_count()];
            for lung in [RIGHT_LUNG, LEFT_LUNG] {
                let apex_fraction = settings.apex_height_fraction;
                group_lung(
                    lungs,
                    airways,
                    lung,
                    meshes,
                    wall,
                    apex_fraction,
                    &mut groups,
                );
            }
        }
    }
    groups
}

/// Locates `lung`'s hilum and groups its surface nodes into `groups`.
fn group_lung(
    lungs: &Volume<u8>,
    airways: &Volume<u8>,
    lung: u8,
    meshes: &LungMeshes,
    wall: &SignedDistanceField,
    apex_fraction: f64,
    groups: &mut NodeGroups,
) {
    let positions_mm = &meshes.positions_mm;
    let lung_surface: Vec<u32> = meshes
        .surface
        .iter()
        .copied()
        .filter(|&n| meshes.node_lung[n as usize] == lung)
        .collect();
    if lung_surface.is_empty() {
        return;
    }
    let rest_positions_m = &meshes.grid_mesh.mesh.rest_positions_m;
    let normals: Vec<Vector3<f64>> = lung_surface
        .iter()
        .map(|&n| wall.normal(rest_positions_m[n as usize]))
        .collect();
    let (centre, source) =
        hilum_centre(lungs, airways, lung, &lung_surface, &normals, positions_mm);
    groups
        .hilum_source
        .insert(lung_name(lung).to_string(), source);
    let c = positions_mm[centre as usize];
    groups
        .hilum_centre_mm
        .insert(lung_name(lung).to_string(), [c.x, c.y, c.z]);
    classify_lung_surface(
        lung,
        &lung_surface,
        &normals,
        positions_mm,
        c,
        groups.hilum_radius_mm,
        apex_fraction,
        &mut groups.node_group,
    );
}

#[allow(clippy::too_many_arguments)]
fn classify_lung_surface(
    lung: u8,
    lung_surface: &[u32],
    normals: &[Vector3<f64>],
    positions_mm: &[Vector3<f64>],
    hilum_centre_mm: Vector3<f64>,
    hilum_radius_mm: f64,
    apex_fraction: f64,
    node_group: &mut [u8],
) {
    let medial = medial_direction(lung);
    let (z_min, z_max) =
        lung_surface
            .iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), &n| {
                let z = positions_mm[n as usize].z;
                (lo.min(z), hi.max(z))
            });
    let centroid_x = lung_surface
        .iter()
        .map(|&n| positions_mm[n as usize].x)
        .sum::<f64>()
        / lung_surface.len() as f64;
    let apex_from_z = z_max - apex_fraction * (z_max - z_min);
    for (&n, normal) in lung_surface.iter().zip(normals) {
        let p = positions_mm[n as usize];
        let group = if (p - hilum_centre_mm).norm() <= hilum_radius_mm {
            ConstraintGroup::Hilum
        } else if p.z >= apex_from_z {
            ConstraintGroup::Apex
        } else if normal.z <= DIAPHRAGM_MAX_NORMAL_Z && p.z < hilum_centre_mm.z {
            ConstraintGroup::Diaphragmatic
        } else if normal.dot(&medial) >= 0.5 && (p.x - centroid_x) * medial.x > 0.0 {
            ConstraintGroup::Mediastinal
        } else {
            ConstraintGroup::Costal
        };
        node_group[n as usize] = group.code();
    }
}

/// Groups from a user label map: each surface node takes the code of the nearest labelled
/// voxel within one element.
fn groups_from_labels(
    labels: &Volume<u8>,
    positions_mm: &[Vector3<f64>],
    surface: &[u32],
    h_mm: f64,
) -> Vec<u8> {
    let g = &labels.geometry;
    let reach: [i64; 3] = g.spacing_mm.map(|s| (h_mm / s).ceil() as i64);
    let mut node_group = vec![0u8; positions_mm.len()];
    let found: Vec<(u32, u8)> = surface
        .par_iter()
        .map(|&n| {
            let v = g.lps_mm_to_voxel(positions_mm[n as usize]);
            let c: [i64; 3] = [v.x.round() as i64, v.y.round() as i64, v.z.round() as i64];
            let mut best = (f64::INFINITY, 0u8);
            for dk in -reach[2]..=reach[2] {
                for dj in -reach[1]..=reach[1] {
                    for di in -reach[0]..=reach[0] {
                        let q = [c[0] + di, c[1] + dj, c[2] + dk];
                        if (0..3).any(|a| q[a] < 0 || q[a] >= g.dims[a] as i64) {
                            continue;
                        }
                        let code = labels.get(q[0] as usize, q[1] as usize, q[2] as usize);
                        if code == 0 {
                            continue;
                        }
                        let p =
                            g.voxel_to_lps_mm(Vector3::new(q[0] as f64, q[1] as f64, q[2] as f64));
                        let d = (p - positions_mm[n as usize]).norm();
                        if d <= h_mm && d < best.0 {
                            best = (d, code);
                        }
                    }
                }
            }
            (n, best.1)
        })
        .collect();
    for (n, code) in found {
        node_group[n as usize] = code;
    }
    node_group
}
