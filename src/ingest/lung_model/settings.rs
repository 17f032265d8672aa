//! How to build the model: lung labels, element-size limits, and the settings for occupancy,
//! hilum, apex, sliding and the diaphragm.

use serde::Serialize;

use crate::model::Material;
use crate::volume::Volume;
use crate::{Error, Result};

#[cfg(doc)]
use super::{ConstraintGroup, LungModel};
#[cfg(doc)]
use crate::model::NodeConstraint;

/// Label of the right lung in the lung mask and in [`LungModel::element_lung`].
pub const RIGHT_LUNG: u8 = 1;
/// Label of the left lung in the lung mask and in [`LungModel::element_lung`].
pub const LEFT_LUNG: u8 = 2;
/// Smallest element edge accepted, in millimetres (finer meshes cost more than clinical CT resolves).
pub const MIN_ELEMENT_SIZE_MM: f64 = 2.0;
/// Largest element edge accepted, in millimetres (coarser loses the lung's thin parts).
pub const MAX_ELEMENT_SIZE_MM: f64 = 16.0;
/// Default element edge in millimetres: about 20 000 elements for a 4.5 L lung pair, the size
/// Baudet used, and at least two elements across the thin anterior and basal edges.
pub const DEFAULT_ELEMENT_SIZE_MM: f64 = 6.0;

/// How the nodes of the diaphragmatic face may move.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, serde::Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum DiaphragmMotion {
    /// Along LPS z only ([`NodeConstraint::Line`] through the rest position): the dome
    /// descends like a piston in tidal breathing and the costophrenic recess holds the base
    /// laterally. The default.
    #[default]
    CranioCaudal,
    /// Free in every direction, driven by the pressure alone (the base bulges; large volumes
    /// crush the costophrenic elements).
    Free,
    /// Sliding on the diaphragm's surface, which descends and flattens with the breath (a
    /// configuration change rather than a piston, `crate::motion::diaphragm`): each node keeps
    /// to the wall's tangent plane (or, with [`SlidingMode::WallSurface`], the wall's level
    /// set) through its rest position, moved down as the dome descends, and slides on it.
    Sliding,
}

/// How to build the model.
#[derive(Debug, Clone)]
pub struct LungModelSettings {
    /// Edge of the cubic elements in millimetres, within 2–16.
    pub element_size_mm: f64,
    /// Material of both lungs.
    pub material: Material,
    /// User label map with [`ConstraintGroup`] codes on the CT grid; replaces the automatic
    /// groups (each surface node takes the code of the nearest labelled voxel within one
    /// element; unlabelled nodes are free).
    pub group_overrides: Option<Volume<u8>>,
    /// Fraction of a cell's volume that must lie in a lung for the cell to be an element.
    pub occupancy_threshold: f64,
    /// Radius in millimetres around the bronchus entry within which surface nodes are fixed.
    pub hilum_radius_mm: f64,
    /// Top fraction of each lung's height whose surface nodes form the apex group.
    pub apex_height_fraction: f64,
    /// How sliding nodes are held on the wall.
    pub sliding: SlidingMode,
    /// How the diaphragmatic face moves.
    pub diaphragm: DiaphragmMotion,
}

/// How a sliding node (mediastinal, costal, apex) is held on the thoracic wall.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SlidingMode {
    /// On the plane through its rest position normal to the wall there
    /// ([`NodeConstraint::Plane`]): exact at rest and linear, so cheap; it departs from the
    /// curved wall by d²/2R after sliding d (0.5 mm for 10 mm on a 10 cm radius). The default.
    #[default]
    TangentPlane,
    /// On the curved wall itself: the level set of the wall's distance field through the
    /// node's rest position ([`NodeConstraint::Surface`], field 0), so a staircase node half
    /// an element off the smooth wall keeps that distance as it slides, with no load-free
    /// deformation at rest.
    WallSurface,
}

impl Default for LungModelSettings {
    fn default() -> Self {
        LungModelSettings {
            element_size_mm: DEFAULT_ELEMENT_SIZE_MM,
            material: Material::default(),
            group_overrides: None,
            occupancy_threshold: 0.5,
            hilum_radius_mm: 20.0,
            apex_height_fraction: 0.1,
            sliding: SlidingMode::TangentPlane,
            diaphragm: DiaphragmMotion::CranioCaudal,
        }
    }
}

impl LungModelSettings {
    /// Refuses element sizes outside 2–16 mm and meaningless thresholds.
    pub fn validate(&self) -> Result<()> {
        let h = self.element_size_mm;
        if !h.is_finite() || !(MIN_ELEMENT_SIZE_MM..=MAX_ELEMENT_SIZE_MM).contains(&h) {
            return Err(Error::settings(
                "lung model settings",
                format!(
                    "element size {h} mm is outside the supported \
                 {MIN_ELEMENT_SIZE_MM}–{MAX_ELEMENT_SIZE_MM} mm"
                ),
            ));
        }
        self.material.validate()?;
        let t = self.occupancy_threshold;
        if !(t.is_finite() && t > 0.0 && t <= 1.0) {
            return Err(Error::settings(
                "lung model settings",
                format!("occupancy threshold {t} must be in (0, 1]"),
            ));
        }
        let r = self.hilum_radius_mm;
        if !(r.is_finite() && r > 0.0) {
            return Err(Error::settings(
                "lung model settings",
                format!("hilum radius {r} mm must be positive"),
            ));
        }
        let a = self.apex_height_fraction;
        if !(a.is_finite() && (0.0..0.5).contains(&a)) {
            return Err(Error::settings(
                "lung model settings",
                format!("apex height fraction {a} must be in [0, 0.5)"),
            ));
        }
        Ok(())
    }
}

/// Name of a lung label in reports: "right" or "left".
pub(super) fn lung_name(lung: u8) -> &'static str {
    if lung == RIGHT_LUNG {
        "right"
    } else {
        "left"
    }
}
