//! The lung's mediastinal face against the heart: sliding (held on the wall, the default) or
//! in contact (it may slide along the heart and great vessels or leave them, never enter).
//!
//! The obstacle is the CT's own mediastinum: the soft tissue beyond the lung cavity's wall on
//! the medial side, which the wall's distance field already describes. Each mediastinal node
//! keeps the plane it slides on by default (tangent to the wall at its rest position, the
//! normal pointing out of the cavity into the mediastinum), but only one-sidedly
//! ([`crate::model::OneSidedPlanes`]). The heart is held still: its beat is not modelled.

use serde::{Deserialize, Serialize};

use crate::ingest::lung_model::{ConstraintGroup, LungModel};
use crate::model::{NodeConstraint, OneSidedPlanes};
use crate::simulation::Scene;
use crate::Result;

/// How the mediastinal face meets the heart.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum MediastinumContact {
    /// Held on the wall (its tangent plane or level set), as the costal face is: it may not
    /// leave the heart. The default.
    #[default]
    Sliding,
    /// One-sided: it slides along the heart or leaves it, and never enters it.
    Contact,
}

/// Moves the mediastinal nodes of `model` in `scene` from their sliding constraints to
/// one-sided contact on the same planes (a node on the curved wall gets the wall's tangent
/// plane at its rest position). Returns the number of nodes now held by contact.
pub fn hold_mediastinum_by_contact(scene: &mut Scene, model: &LungModel) -> Result<usize> {
    let rest = &scene.mesh.rest_positions_m;
    let mut on_face = vec![false; rest.len()];
    for n in model.group_nodes(ConstraintGroup::Mediastinal) {
        on_face[n as usize] = matches!(
            scene.constraints.get(n),
            Some(NodeConstraint::Plane { .. } | NodeConstraint::Surface { .. })
        );
    }
    let fields = scene.constraints.fields.clone();
    let taken = scene.constraints.take_where(|n| on_face[n as usize]);
    let planes = taken
        .into_iter()
        .filter_map(|(n, c)| {
            let r = rest[n as usize];
            match c {
                NodeConstraint::Plane { point_m, normal } => Some((n, point_m, normal)),
                NodeConstraint::Surface { field, .. } => {
                    Some((n, r, fields[field as usize].spline_normal(r)))
                }
                _ => None,
            }
        })
        .collect();
    scene.one_sided = OneSidedPlanes::new(scene.node_count(), planes)?;
    Ok(scene.one_sided.len())
}
