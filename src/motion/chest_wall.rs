//! A chest wall that moves: the rib cage's share of each breath.
//!
//! In supine quiet breathing roughly a third of the tidal volume comes from the rib cage
//! moving up and out, the rest from the diaphragm's descent (Konno & Mead 1967; see
//! `../shared/docs/domain.md`). A rigid wall puts all of it on the diaphragm, so the costal
//! faces cannot move outward and the base moves too far.
//!
//! Model: each costal node keeps sliding on its tangent plane, and the plane moves outward
//! along its normal in proportion to the load, so the wall moves with the breath and the
//! node still slides freely along it. The wall moves where the ribs do, anteriorly (pump
//! handle) and laterally (bucket handle), and more at the lower ribs: the plane's unit
//! offset is
//!
//! `g = t · (max(0, −n_y) + max(0, ±n_x))` mm, `t = (z_top − z) / (z_top − z_bottom)`,
//!
//! with `n` the wall's outward normal (LPS: −y anterior, −x lateral for the right lung, +x
//! for the left) and `z_top`, `z_bottom` the extent of that lung's costal face: 0 at the
//! apex end, 1 at the lowest costal node. Posterior and medial faces (spine, mediastinum), the
//! apex and the hilum stay where they are; the diaphragm takes the rest of each breath.
//!
//! The wall's motion is continuous where the costal face meets the faces that do not move out
//! (mediastinal, diaphragmatic, apex, hilum): within [`TAPER_MM`] of them, counted in mesh
//! edges along the lung surface, the offset falls linearly to zero. Without the taper, on the
//! CIP lungs at 4 mm a diaphragmatic node between costal nodes moving out made the shape jump
//! near +313 mL (two equilibria), and the anterior junction, where costal meets mediastinal,
//! is where large breaths invert elements.
//!
//! The offsets' overall scale is set per run so that the wall sweeps the asked share of every
//! volume change ([`BreathingDriver::share_volume_with_imposed_motion`]): the lung's pressure
//! slope with the wall held is measured by one small solve, the wall's sweep is geometric.
//!
//! [`BreathingDriver::share_volume_with_imposed_motion`]:
//! crate::simulation::BreathingDriver::share_volume_with_imposed_motion

use serde::Serialize;

use super::moving_wall::move_wall_under;
use crate::ingest::lung_model::{ConstraintGroup, LungModel};
use crate::model::mesh::HEX_EDGES;
use crate::simulation::Scene;
use crate::{Error, Result};

/// The rib cage's share of the tidal volume in supine quiet breathing, about a third
/// (Konno & Mead 1967, and later plethysmography): the default of a run.
pub const PHYSIOLOGICAL_RIB_CAGE_SHARE: f64 = 1.0 / 3.0;

/// Largest rib-cage share accepted: above it the diaphragm would hardly move, which no
/// breathing pattern shows (thoracic breathing reaches about two thirds).
pub const MAX_RIB_CAGE_SHARE: f64 = 0.8;

/// Offset of a costal plane, per unit of the wall's scale, where the ribs move most, metres.
const UNIT_OFFSET_M: f64 = 1e-3;

/// Distance along the lung surface over which the wall's offset falls to zero at the faces
/// that do not move out, mm (at least two element edges).
pub const TAPER_MM: f64 = 16.0;

/// What moving the costal wall did to a scene.
#[derive(Debug, Clone, Serialize)]
pub struct CostalWallMotion {
    /// Costal nodes whose plane moves (the others face backwards or inwards).
    pub moving_nodes: usize,
    /// Costal sliding nodes in all.
    pub costal_nodes: usize,
}

/// Checks a rib-cage share: a fraction in [0, [`MAX_RIB_CAGE_SHARE`]].
pub fn check_rib_cage_share(share: f64) -> Result<()> {
    if share.is_finite() && (0.0..=MAX_RIB_CAGE_SHARE).contains(&share) {
        Ok(())
    } else {
        Err(Error::settings(
            "motion settings",
            format!(
                "rib_cage_share {share} must be a fraction of the tidal volume between 0 (a rigid \
                 chest wall) and {MAX_RIB_CAGE_SHARE} (physiological: about {:.2})",
                PHYSIOLOGICAL_RIB_CAGE_SHARE
            ),
        ))
    }
}

/// Makes the costal tangent planes of `scene` (built by [`super::lung_scene`] from `model`)
/// move outward with the load, by the unit offsets of the module's rule; the run scales them
/// to its rib-cage share. Costal nodes on the wall surface itself have their level raised
/// instead: the wall moves out along its normal and they keep sliding on it.
pub fn move_costal_wall(scene: &mut Scene, model: &LungModel) -> CostalWallMotion {
    let taper_edges = (TAPER_MM / model.report.element_size_mm).round().max(2.0) as u32;
    let hops = surface_hops_from_still_faces(scene, model, taper_edges);
    let (moving_nodes, costal_nodes) =
        move_wall_under(scene, model, ConstraintGroup::Costal, |w| {
            let normal = w.normal;
            let lateral = match w.lung {
                1 => -normal.x,
                2 => normal.x,
                _ => return 0.0,
            };
            let (bottom, top) = w.face_z_m;
            let t = if top > bottom {
                (top - w.rest_m.z) / (top - bottom)
            } else {
                1.0
            };
            let taper = f64::from(hops[w.node].min(taper_edges)) / f64::from(taper_edges);
            taper * t * ((-normal.y).max(0.0) + lateral.max(0.0)) * UNIT_OFFSET_M
        });
    CostalWallMotion {
        moving_nodes,
        costal_nodes,
    }
}

/// For every node, the number of mesh edges along the lung surface to the nearest node of a
/// face that does not move out (hilum, mediastinal, diaphragmatic, apex), counted up to
/// `limit` (nodes farther away, or off the surface, get `limit`).
fn surface_hops_from_still_faces(scene: &Scene, model: &LungModel, limit: u32) -> Vec<u32> {
    let groups = &model.node_group;
    let on_surface = |n: usize| groups[n] != 0;
    let still = |n: usize| {
        matches!(
            ConstraintGroup::from_code(groups[n]),
            Some(
                ConstraintGroup::Hilum
                    | ConstraintGroup::Mediastinal
                    | ConstraintGroup::Diaphragmatic
                    | ConstraintGroup::Apex
            )
        )
    };
    let count = groups.len();
    // Surface edges as a compressed adjacency (each edge listed from both ends, duplicates
    // from neighbouring elements kept: the search only reads them).
    let mut degree = vec![0u32; count + 1];
    let surface_edges = || {
        scene.mesh.elements.iter().flat_map(|corners| {
            HEX_EDGES.iter().filter_map(move |&(a, b)| {
                let (a, b) = (corners[a] as usize, corners[b] as usize);
                (on_surface(a) && on_surface(b)).then_some((a, b))
            })
        })
    };
    for (a, b) in surface_edges() {
        degree[a + 1] += 1;
        degree[b + 1] += 1;
    }
    for i in 0..count {
        degree[i + 1] += degree[i];
    }
    let mut fill = degree.clone();
    let mut neighbours = vec![0u32; degree[count] as usize];
    for (a, b) in surface_edges() {
        neighbours[fill[a] as usize] = b as u32;
        fill[a] += 1;
        neighbours[fill[b] as usize] = a as u32;
        fill[b] += 1;
    }
    let mut hops = vec![limit; count];
    let mut queue = std::collections::VecDeque::new();
    for n in (0..count).filter(|&n| still(n)) {
        hops[n] = 0;
        queue.push_back(n);
    }
    while let Some(n) = queue.pop_front() {
        let next = hops[n] + 1;
        if next >= limit {
            continue;
        }
        for &m in &neighbours[degree[n] as usize..degree[n + 1] as usize] {
            let m = m as usize;
            if hops[m] > next {
                hops[m] = next;
                queue.push_back(m);
            }
        }
    }
    hops
}
