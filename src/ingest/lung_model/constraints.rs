//! The constraint set the solvers use, from the groups: hilum fixed, sliding nodes on the
//! wall, the diaphragmatic face as [`DiaphragmMotion`] says (on lines, free, or on the wall
//! like the sliding nodes); and how far the sliding nodes sit off the wall at rest.

use nalgebra::Vector3;

use super::groups::{BoundaryCondition, ConstraintGroup};
use super::mesh::LungMeshes;
use super::settings::{DiaphragmMotion, LungModelSettings, SlidingMode};
use crate::model::{ConstraintSet, HexMesh, NodeConstraint, SignedDistanceField};
use crate::Result;

/// The constraint set and its sliding nodes.
pub(super) struct NodeConstraints {
    /// Every constrained surface node; the wall is field 0.
    pub(super) constraints: ConstraintSet,
    /// Nodes held on the wall, in surface order.
    pub(super) sliding: Vec<u32>,
    /// Sliding nodes held on their tangent plane although the wall surface was asked: the
    /// wall's distance field there has a ridge (|∇| below [`MIN_SURFACE_GRADIENT`]).
    pub(super) on_planes: usize,
}

/// Smallest |∇ wall| at a node's rest position for it to slide on the wall's level set.
/// The distance field has a ridge where two surfaces face each other closely (the anterior
/// junction, where the lungs nearly meet): its level sets there are thin tubes whose normal
/// turns within a fraction of a millimetre, and on the CIP lungs at 6 mm Newton could not
/// converge while 142 nodes with |∇| below 0.5 slid on them. A smoothed distance field away
/// from ridges has |∇| of 0.8–1 (88 % of the sliding nodes on CIP, 95 % on POPI).
pub const MIN_SURFACE_GRADIENT: f64 = 0.7;

/// Constrains each grouped surface node of `meshes` by its group's boundary condition.
pub(super) fn constrain_nodes(
    meshes: &LungMeshes,
    node_group: &[u8],
    wall: &std::sync::Arc<SignedDistanceField>,
    settings: &LungModelSettings,
) -> Result<NodeConstraints> {
    let (mesh, surface) = (&meshes.grid_mesh.mesh, &meshes.surface);
    let mut constraints = ConstraintSet::new(mesh.node_count());
    // Tangent planes carry their normal; the surface constraint shares the model's field
    // (114 MB on a 512 × 512 CT at 6 mm) rather than copying it.
    let surface_field = match settings.sliding {
        SlidingMode::WallSurface => Some(constraints.add_surface(std::sync::Arc::clone(wall))),
        SlidingMode::TangentPlane => None,
    };
    let mut sliding = Vec::new();
    let mut on_planes = 0;
    // A node held on the wall where it rests: its tangent plane, or the wall's level set
    // through it (the level through the rest position: a staircase node half an element off
    // the smooth wall stays there, unloaded, and slides along the wall at that distance).
    let mut on_wall = |n: u32, surface_field: Option<u32>| {
        let rest = mesh.rest_positions_m[n as usize];
        let plane = NodeConstraint::Plane {
            point_m: rest,
            normal: wall.normal(rest),
        };
        match surface_field {
            None => plane,
            Some(field) => {
                let (level_m, gradient) = wall.spline(rest);
                if gradient.norm() >= MIN_SURFACE_GRADIENT {
                    NodeConstraint::surface(field, level_m)
                } else {
                    on_planes += 1;
                    plane
                }
            }
        }
    };
    for &n in surface {
        let Some(group) = ConstraintGroup::from_code(node_group[n as usize]) else {
            continue;
        };
        match group.boundary_condition() {
            BoundaryCondition::Fixed => {
                constraints.fix(n, mesh.rest_positions_m[n as usize])?;
            }
            BoundaryCondition::SlidingOnWall => {
                constraints.set(n, on_wall(n, surface_field))?;
                sliding.push(n);
            }
            BoundaryCondition::FollowsDiaphragm => match settings.diaphragm {
                DiaphragmMotion::CranioCaudal => constraints.set(
                    n,
                    NodeConstraint::Line {
                        point_m: mesh.rest_positions_m[n as usize],
                        direction: Vector3::z(),
                    },
                )?,
                // The diaphragm is the wall here: the run moves it down with the breath. On
                // its tangent plane even where the other faces slide on the curved wall: on
                // the level sets of the dome, whose curvature is tightest in the costophrenic
                // recess, the POPI cycle at 6 mm took 41 s instead of 13 s.
                DiaphragmMotion::Sliding => constraints.set(n, on_wall(n, None))?,
                DiaphragmMotion::Free => {}
            },
        }
    }
    constraints.validate(&mesh.rest_positions_m)?;
    Ok(NodeConstraints {
        constraints,
        sliding,
        on_planes,
    })
}

/// How the sliding nodes' rest positions sit on the wall.
pub(super) struct WallRestFit {
    /// Largest |wall distance| at a sliding node's rest position in mm.
    pub(super) offset_max_mm: f64,
    /// Mean |wall distance| at the sliding nodes' rest positions in mm.
    pub(super) offset_mean_mm: f64,
    /// Smallest |∇ wall| at a sliding node's rest position.
    pub(super) min_gradient_norm: f64,
    /// Sliding nodes kept on tangent planes in the wall-surface mode (ridges).
    pub(super) plane_nodes: usize,
}

/// Measures the wall at the rest positions of the `sliding` nodes of `mesh`.
pub(super) fn wall_rest_fit(
    mesh: &HexMesh,
    nodes: &NodeConstraints,
    wall: &SignedDistanceField,
) -> WallRestFit {
    let sliding = &nodes.sliding;
    let rest_offsets_mm: Vec<f64> = sliding
        .iter()
        .map(|&n| wall.evaluate(mesh.rest_positions_m[n as usize]).0.abs() * 1e3)
        .collect();
    let offset_max_mm = rest_offsets_mm.iter().cloned().fold(0.0, f64::max);
    let offset_mean_mm = rest_offsets_mm.iter().sum::<f64>() / rest_offsets_mm.len().max(1) as f64;
    let min_gradient_norm = sliding
        .iter()
        .map(|&n| {
            wall.smooth_gradient(mesh.rest_positions_m[n as usize])
                .norm()
        })
        .fold(f64::INFINITY, f64::min);
    WallRestFit {
        offset_max_mm,
        offset_mean_mm,
        min_gradient_norm,
        plane_nodes: nodes.on_planes,
    }
}
