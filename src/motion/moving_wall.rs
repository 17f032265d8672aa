//! Moving the wall under the nodes that slide on it: the rule both the rib cage
//! ([`super::chest_wall`]) and the descending diaphragm ([`super::diaphragm`]) apply, each
//! with its own offset per node.

use crate::ingest::lung_model::{ConstraintGroup, LungModel};
use crate::math::V3;
use crate::model::NodeConstraint;
use crate::simulation::Scene;

/// A node of a face that slides on the wall, as a moving-wall rule sees it.
pub(super) struct WallNode {
    /// Node index.
    pub node: usize,
    /// Rest position, metres (LPS).
    pub rest_m: V3,
    /// The wall's outward unit normal at rest (LPS).
    pub normal: V3,
    /// Lung of the node (1 right, 2 left).
    pub lung: u8,
    /// Lowest and highest rest z of the face's sliding nodes in that lung, metres.
    pub face_z_m: (f64, f64),
}

/// Moves the wall under every node of `group` in `model` that `scene` holds on a plane or a
/// surface outward along its normal by `offset_m(node)` metres per unit of imposed motion
/// (planes move, levels rise; nodes whose offset is 0 stay); returns how many moved and how
/// many slide on that face. The constraints are edited in place: `ConstraintSet::set` would
/// normalise the normal again, and a last-bit change would keep a rigid wall from being the
/// unmoved one exactly.
pub(super) fn move_wall_under(
    scene: &mut Scene,
    model: &LungModel,
    group: ConstraintGroup,
    mut offset_m: impl FnMut(&WallNode) -> f64,
) -> (usize, usize) {
    let rest = &scene.mesh.rest_positions_m;
    let lung = model.node_lung();
    let face = sliding_nodes_of(scene, model, group);
    // The face's height per lung (index 1 right, 2 left).
    let mut extent = [(f64::INFINITY, f64::NEG_INFINITY); 3];
    for &n in &face {
        let (z, l) = (rest[n as usize].z, lung[n as usize] as usize);
        if let Some(e) = extent.get_mut(l) {
            *e = (e.0.min(z), e.1.max(z));
        }
    }
    let mut on_face = vec![false; rest.len()];
    face.iter().for_each(|&n| on_face[n as usize] = true);
    let mut moved = 0;
    let (entries, fields) = (&mut scene.constraints.entries, &scene.constraints.fields);
    for (n, c) in entries.iter_mut() {
        let n = *n as usize;
        if !on_face[n] {
            continue;
        }
        let r = rest[n];
        let normal = match c {
            NodeConstraint::Plane { normal, .. } => *normal,
            NodeConstraint::Surface { field, .. } => fields[*field as usize].spline_normal(r),
            _ => continue,
        };
        let node = WallNode {
            node: n,
            rest_m: r,
            normal,
            lung: lung[n],
            face_z_m: extent.get(lung[n] as usize).copied().unwrap_or((r.z, r.z)),
        };
        let g = offset_m(&node);
        if g == 0.0 {
            continue;
        }
        match c {
            NodeConstraint::Plane { point_m, .. } => *point_m = r + normal * g,
            // The wall moved by g along its normal: the node's level rises by g.
            NodeConstraint::Surface {
                level_m,
                rest_level_m,
                ..
            } => *level_m = *rest_level_m + g,
            _ => continue,
        }
        moved += 1;
    }
    (moved, face.len())
}

/// Nodes of `group` in `model` that `scene` holds on a plane or a surface.
fn sliding_nodes_of(scene: &Scene, model: &LungModel, group: ConstraintGroup) -> Vec<u32> {
    model
        .group_nodes(group)
        .into_iter()
        .filter(|&n| {
            matches!(
                scene.constraints.get(n),
                Some(NodeConstraint::Plane { .. } | NodeConstraint::Surface { .. })
            )
        })
        .collect()
}
