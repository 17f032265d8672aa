//! The mechanical scene of a patient's lungs: the ingest model's mesh and anatomical
//! constraints, plus the pleural pressure that breathing scales.
//!
//! The load is a follower pressure on the whole lung surface: the pleural pressure acts
//! everywhere, and on constrained nodes the wall or the diaphragm takes its blocked part.

use super::REFERENCE_PRESSURE_PA;
use crate::ingest::lung_model::{DiaphragmMotion, LungModel};
use crate::model::tissue::{with_element_tissue, ElementTissue};
use crate::model::{HexMesh, Loads, SurfacePressure};
use crate::simulation::Scene;
use crate::Result;

/// The scene of `model`: its mesh and constraints (hilum fixed, wall sliding, diaphragm as
/// the model was built) and a follower pressure of [`REFERENCE_PRESSURE_PA`] on every
/// external face.
pub fn lung_scene(model: &LungModel) -> Result<Scene> {
    lung_scene_on(model, model.mesh.mesh.clone())
}

/// [`lung_scene`] on `mesh`, the model's mesh with its own element classes.
fn lung_scene_on(model: &LungModel, mesh: HexMesh) -> Result<Scene> {
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

/// How a run's walls move with the breath.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct WallMotion {
    /// Share of each breath the rib cage makes ([`super::move_costal_wall`]; 0 a rigid wall).
    pub rib_cage_share: f64,
    /// How much less the dome's rim descends than its top, with a sliding diaphragm
    /// ([`super::diaphragm`]; 0 a translated dome).
    pub dome_flattening: f64,
    /// How the mediastinal face meets the heart ([`super::heart_contact`]).
    pub mediastinum: super::MediastinumContact,
}

impl Default for WallMotion {
    /// As a run has them by default: the rib cage makes a third of each breath.
    fn default() -> Self {
        WallMotion {
            rib_cage_share: super::PHYSIOLOGICAL_RIB_CAGE_SHARE,
            dome_flattening: 0.0,
            mediastinum: super::MediastinumContact::Sliding,
        }
    }
}

/// The scene a breathing run solves: [`lung_scene`], with the costal wall moving
/// ([`super::move_costal_wall`]) when the rib cage has a share of the breath, and the
/// diaphragm descending ([`super::diaphragm`]) when the model's base slides on it. A rigid
/// wall over a piston diaphragm leaves the planes where they are, bit for bit.
pub fn run_scene(model: &LungModel, walls: &WallMotion) -> Result<Scene> {
    run_scene_on(model, walls, model.mesh.mesh.clone())
}

/// [`run_scene`] with each element's modulus and density scaled as `tissue` says (ratios
/// rounded to steps of `step`, [`crate::model::tissue::with_element_tissue`]). The walls are
/// calibrated on these elements.
pub fn run_scene_with_tissue(
    model: &LungModel,
    walls: &WallMotion,
    tissue: &ElementTissue,
    step: f64,
) -> Result<Scene> {
    let mesh = with_element_tissue(&model.mesh.mesh, tissue, step)?;
    run_scene_on(model, walls, mesh)
}

/// [`run_scene`] on `mesh`.
fn run_scene_on(model: &LungModel, walls: &WallMotion, mesh: HexMesh) -> Result<Scene> {
    let mut scene = lung_scene_on(model, mesh)?;
    if walls.mediastinum == super::MediastinumContact::Contact {
        // First: the walls' calibration below solves the scene as the run will.
        let held = super::hold_mediastinum_by_contact(&mut scene, model)?;
        tracing::debug!(held, "mediastinal face in one-sided contact with the heart");
    }
    if walls.rib_cage_share > 0.0 {
        super::move_costal_wall(&mut scene, model);
    }
    if model.report.diaphragm_motion == DiaphragmMotion::Sliding {
        use super::diaphragm::{check_dome_flattening, lower_diaphragm, share_sweep_between_walls};
        check_dome_flattening(walls.dome_flattening)?;
        let (moved, face) = lower_diaphragm(&mut scene, model, walls.dome_flattening);
        tracing::debug!(moved, face, "diaphragm descends with the breath");
        share_sweep_between_walls(&mut scene, model, walls.rib_cage_share)?;
        let mut chest_wall_part = walls.rib_cage_share;
        if walls.rib_cage_share > 0.0 {
            // The driver's compliance when the run does not give one: the elastic one.
            let rest_ml = scene.mesh.enclosed_volume_m3(&scene.mesh.rest_positions_m) * 1e6;
            let material = scene.mesh.typical_material();
            let compliance =
                material.map_or(1.0, |m| super::elastic_compliance_ml_per_pa(rest_ml, &m));
            let split = super::diaphragm::calibrate_wall_split(
                &mut scene,
                model,
                walls.rib_cage_share,
                compliance,
            )?;
            tracing::debug!(?split, "walls' sweep split for the rib cage's share");
            chest_wall_part = split.costal_sweep_fraction;
        }
        scene.walls_make_volume = Some(chest_wall_part);
    }
    Ok(scene)
}
