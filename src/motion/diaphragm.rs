//! A diaphragm the base slides on: the dome descends and flattens with the breath, and the
//! lung's diaphragmatic face slides along it instead of moving on vertical lines.
//!
//! The piston model (`diaphragm = "cranio_caudal"`) holds each base node on the vertical line
//! through its rest position, so the base cannot slide sideways along the dome, and the
//! pressure decides how far each node descends; Petroll's piston model is quoted at 30 %
//! error against 11 % for a model whose diaphragm changes its configuration (Baudet 2006,
//! ch. 1, `../shared/docs/thesis-baudet-2006.md`).
//!
//! Model (`diaphragm = "sliding"`): each diaphragmatic node slides on the wall where it rests
//! (its tangent plane, or the wall's level set in the wall-surface mode), and that surface
//! moves down by the local descent of the dome, `δ = (1 − F) + F·t` per unit of breath, with
//! `t = (z − z_low) / (z_high − z_low)` the node's height on its lung's diaphragmatic face
//! (0 at the deepest point of the costophrenic recess, 1 at its highest node) and `F` the
//! dome's flattening (`[motion] dome_flattening`, 0 – [`MAX_DOME_FLATTENING`]): with F > 0
//! the top descends farther than the rim, which the diaphragm's costal insertions hold near
//! the lower ribs. A surface moved down by δ moves along its normal `n` by `−δ·n_z`.
//!
//! The default is F = 0, a translated dome the base slides on. The diaphragmatic face is
//! every downward face below the hilum, which includes the lung over the heart, higher than
//! the domes: F = 0.5 lowered it most, made the solves snap there and cost 14.1 s instead of
//! 5.5 s on CIP and 13.0 s instead of 2.9 s on POPI (6 mm, 500 mL cycle, one run each).
//!
//! The lung then fills a cavity whose walls all move (or hold): the rib cage sweeps the
//! asked share of each breath and the diaphragm the rest, so the walls make the volume and
//! the pleural pressure only slides the lung along them. [`share_sweep_between_walls`]
//! scales the two motions so one unit of imposed motion sweeps 1 mL in that split.

use serde::Serialize;

use super::moving_wall::move_wall_under;
use crate::ingest::lung_model::{ConstraintGroup, LungModel};
use crate::simulation::Scene;
use crate::{Error, Result};

/// Largest dome flattening accepted: at 1 the rim of the dome would not move at all.
pub const MAX_DOME_FLATTENING: f64 = 0.8;

/// Checks a dome flattening: a fraction in [0, [`MAX_DOME_FLATTENING`]].
pub fn check_dome_flattening(flattening: f64) -> Result<()> {
    if flattening.is_finite() && (0.0..=MAX_DOME_FLATTENING).contains(&flattening) {
        Ok(())
    } else {
        Err(Error::settings(
            "motion settings",
            format!(
                "dome_flattening {flattening} must be a fraction between 0 (the dome translates) \
                 and {MAX_DOME_FLATTENING} (its rim hardly moves)"
            ),
        ))
    }
}

/// Descent of the dome's top per unit of the diaphragm's motion, metres (the run rescales it).
const UNIT_DESCENT_M: f64 = 1e-3;

/// Moves the surface every sliding diaphragmatic node of `scene` (built from `model` with
/// [`crate::ingest::lung_model::DiaphragmMotion::Sliding`]) rests on down by the module's
/// unit descent, the dome flattening by `flattening`; returns how many moved, and of how many.
pub fn lower_diaphragm(scene: &mut Scene, model: &LungModel, flattening: f64) -> (usize, usize) {
    move_wall_under(scene, model, ConstraintGroup::Diaphragmatic, |w| {
        let (low, high) = w.face_z_m;
        let t = if high > low {
            (w.rest_m.z - low) / (high - low)
        } else {
            1.0
        };
        // A surface moved down by δ moves along its outward normal by −δ·n_z.
        -((1.0 - flattening) + flattening * t) * UNIT_DESCENT_M * w.normal.z
    })
}

/// Rescales the imposed motions of `scene` so that one unit sweeps 1 mL, `rib_cage_share` of
/// it from the costal wall and the rest from the diaphragm (both already moved by
/// [`super::move_costal_wall`] and [`lower_diaphragm`]).
pub fn share_sweep_between_walls(
    scene: &mut Scene,
    model: &LungModel,
    rib_cage_share: f64,
) -> Result<()> {
    super::chest_wall::check_rib_cage_share(rib_cage_share)?;
    let sweep_ml = |scene: &Scene, group: ConstraintGroup| {
        let code = group.code();
        scene.imposed_sweep_ml(|n| model.node_group[n as usize] == code)
    };
    let diaphragm_ml = sweep_ml(scene, ConstraintGroup::Diaphragmatic);
    let costal_ml = sweep_ml(scene, ConstraintGroup::Costal);
    let refuse = |what: &str, ml: f64| {
        Err(Error::InvalidModel(format!(
            "the sliding diaphragm cannot make the breath: the {what} sweeps {ml:.4} mL per \
             unit of motion (it must enlarge the lungs); the lung model's diaphragmatic face \
             may be missing or face upwards, so use diaphragm = \"cranio_caudal\""
        )))
    };
    if !(diaphragm_ml.is_finite() && diaphragm_ml > 0.0) {
        return refuse("diaphragm", diaphragm_ml);
    }
    if rib_cage_share > 0.0 && !(costal_ml.is_finite() && costal_ml > 0.0) {
        return refuse("costal wall", costal_ml);
    }
    scale_group(
        scene,
        model,
        ConstraintGroup::Diaphragmatic,
        (1.0 - rib_cage_share) / diaphragm_ml,
    );
    if rib_cage_share > 0.0 {
        scale_group(
            scene,
            model,
            ConstraintGroup::Costal,
            rib_cage_share / costal_ml,
        );
    }
    Ok(())
}

/// What the walls make of a breath, measured in the linear range, and the split of their
/// motion that gives the rib cage its share of the volume ([`calibrate_wall_split`]).
#[derive(Debug, Clone, Copy, Serialize)]
pub struct WallSplit {
    /// The rib-cage share of the volume asked.
    pub share: f64,
    /// Volume the pleural pressure makes per unit load with the walls held, mL.
    pub pressure_ml: f64,
    /// Volume the costal wall makes per millilitre it sweeps (the lung also slides along it).
    pub costal_ratio: f64,
    /// Volume the diaphragm makes per millilitre it sweeps.
    pub diaphragm_ratio: f64,
    /// The costal wall's part of the walls' geometric sweep after calibration.
    pub costal_sweep_fraction: f64,
}

/// Re-splits the walls' unit of motion (from [`share_sweep_between_walls`]) so that the rib
/// cage's sweep is `rib_cage_share` of the lung's volume change, not only of the walls'
/// sweep: the lung also slides along the walls and the pleural pressure swells it a little,
/// which neither wall sweeps. Three solves of about 5 mL measure, in the linear range, the
/// pressure's volume `a` with the walls held and each wall's volume per millilitre it sweeps
/// (`ρ_c`, `ρ_d`); with the driver's imposed-motion scale `s` (the compliance's volume per
/// unit load) the costal fraction `x` of the unit sweep solves
/// `s·x = share·(a + s·(x·ρ_c + (1 − x)·ρ_d))`.
pub fn calibrate_wall_split(
    scene: &mut Scene,
    model: &LungModel,
    rib_cage_share: f64,
    compliance_ml_per_pa: f64,
) -> Result<WallSplit> {
    use crate::simulation::{BreathingDriver, QuasiStaticSettings};
    let settings = QuasiStaticSettings {
        tolerance: super::BREATHING_SOLVER_TOLERANCE,
        ..QuasiStaticSettings::default()
    };
    let p_ref = super::REFERENCE_PRESSURE_PA;
    let slopes = |scene: &Scene| -> Result<(f64, f64)> {
        let mut driver =
            BreathingDriver::new(scene, p_ref, compliance_ml_per_pa, settings.clone())?;
        let pressure = driver.linear_volume_slope_ml(0.0)?;
        Ok((pressure, driver.linear_volume_slope_ml(1.0)? - pressure))
    };
    let x0 = rib_cage_share;
    let (a, both) = slopes(scene)?;
    let kept = scene.constraints.clone();
    scale_group(scene, model, ConstraintGroup::Diaphragmatic, 0.0);
    let costal = slopes(scene).map(|(_, b)| b);
    scene.constraints = kept;
    let costal = costal?;
    let costal_ratio = costal / x0;
    let diaphragm_ratio = (both - costal) / (1.0 - x0);
    let s = -compliance_ml_per_pa * p_ref;
    let x = x0 * (a / s + diaphragm_ratio) / (1.0 - x0 * (costal_ratio - diaphragm_ratio));
    if !(x.is_finite() && x > 0.0 && x < 1.0) {
        return Err(Error::InvalidModel(format!(
            "the rib cage cannot make {x0} of the volume with a sliding diaphragm: the walls \
             make {costal_ratio:.3} (costal) and {diaphragm_ratio:.3} (diaphragm) mL per mL \
             they sweep and the pressure {a:.3} mL per unit load, so the costal wall would need \
             {x:.3} of their sweep"
        )));
    }
    scale_group(scene, model, ConstraintGroup::Costal, x / x0);
    scale_group(
        scene,
        model,
        ConstraintGroup::Diaphragmatic,
        (1.0 - x) / (1.0 - x0),
    );
    Ok(WallSplit {
        share: x0,
        pressure_ml: a,
        costal_ratio,
        diaphragm_ratio,
        costal_sweep_fraction: x,
    })
}

/// Multiplies the imposed offsets of the nodes of `group` (in `model`) in `scene` by `factor`.
fn scale_group(scene: &mut Scene, model: &LungModel, group: ConstraintGroup, factor: f64) {
    let rest = &scene.mesh.rest_positions_m;
    let code = group.code();
    for (n, c) in scene.constraints.entries.iter_mut() {
        if model.node_group[*n as usize] == code {
            c.scale_imposed_offset(rest[*n as usize], factor);
        }
    }
}
