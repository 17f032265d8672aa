//! The mechanical scene of a patient's lungs: the ingest model's mesh and anatomical
//! constraints, plus the pleural pressure that breathing scales.
//!
//! The load is a follower pressure on the whole lung surface: the pleural pressure acts
//! everywhere, and on constrained nodes the wall or the diaphragm takes its blocked part.

use super::REFERENCE_PRESSURE_PA;
use crate::ingest::lung_model::LungModel;
use crate::model::{Loads, SurfacePressure};
use crate::simulation::Scene;
use crate::Result;

/// The scene of `model`: its mesh and constraints (hilum fixed, wall sliding, diaphragm as
/// the model was built) and a follower pressure of [`REFERENCE_PRESSURE_PA`] on every
/// external face.
pub fn lung_scene(model: &LungModel) -> Result<Scene> {
    let mesh = model.mesh.mesh.clone();
    let loads = Loads {
        pressures: vec![SurfacePressure {
            faces: mesh.external_faces.clone(),
            pressure_pa: REFERENCE_PRESSURE_PA,
            follows_deformation: true,
        }],
        ..Loads::default()
    };
    Scene::new(mesh, model.constraints.clone(), loads)
}

/// The scene a breathing run solves: [`lung_scene`], with the costal wall moving
/// ([`super::move_costal_wall`]) when the rib cage has a share of the breath. A rigid wall
/// leaves the planes where they are, bit for bit.
pub fn run_scene(model: &LungModel, rib_cage_share: f64) -> Result<Scene> {
    let mut scene = lung_scene(model)?;
    if rib_cage_share > 0.0 {
        super::move_costal_wall(&mut scene, model);
    }
    Ok(scene)
}
