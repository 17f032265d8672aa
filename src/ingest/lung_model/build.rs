//! The built model and the pipeline that builds it from the lung and airway masks.

use std::time::Instant;

use super::cells::shape_lung_cells;
use super::constraints::{constrain_nodes, wall_rest_fit};
use super::groups::{assign_groups, ConstraintGroup};
use super::lattice::CellLattice;
use super::mesh::mesh_lungs;
use super::paint::paint_groups;
use super::report::{summarise, LungModelReport, MaskVoxels, StepClock};
use super::settings::{LungModelSettings, LEFT_LUNG};
use super::wall::{build_wall, PrebuiltWall};
use crate::ingest::Cancel;
use crate::model::grid::GridMesh;
use crate::model::{ConstraintSet, SignedDistanceField, VoxelGrid};
use crate::volume::Volume;
use crate::{Error, Result};

#[cfg(doc)]
use super::settings::SlidingMode;

/// The mechanical lung model built from a CT's lung mask.
#[derive(Debug, Clone)]
pub struct LungModel {
    /// The lattice of both lungs (active = element of either lung). Its own
    /// [`VoxelGrid::to_mesh`] would merge nodes where the lungs touch; use `mesh`.
    pub grid: VoxelGrid,
    /// Cubic elements of both lungs in metres, LPS; nodes of the right lung first.
    pub mesh: GridMesh,
    /// Lung of each element: 1 right, 2 left.
    pub element_lung: Vec<u8>,
    /// [`ConstraintGroup`] code of each node (0 = interior or no group).
    pub node_group: Vec<u8>,
    /// The thoracic-cavity wall the sliding nodes stay on (metres, negative inside).
    pub wall: std::sync::Arc<SignedDistanceField>,
    /// Hilum fixed, mediastinal/costal/apex sliding ([`SlidingMode`]; with
    /// [`SlidingMode::WallSurface`] `wall` is field 0, with tangent planes there is no field),
    /// base free.
    pub constraints: ConstraintSet,
    /// Group codes painted on the lung-surface voxels of the CT grid.
    pub groups_volume: Volume<u8>,
    /// What was built and how.
    pub report: LungModelReport,
}

impl LungModel {
    /// Nodes of a group.
    pub fn group_nodes(&self, group: ConstraintGroup) -> Vec<u32> {
        (0..self.node_group.len() as u32)
            .filter(|&n| self.node_group[n as usize] == group.code())
            .collect()
    }

    /// Lung of each node (1 right, 2 left).
    pub fn node_lung(&self) -> Vec<u8> {
        let mut lung = vec![0u8; self.mesh.mesh.node_count()];
        for (corners, &l) in self.mesh.mesh.elements.iter().zip(&self.element_lung) {
            for &c in corners {
                lung[c as usize] = l;
            }
        }
        lung
    }
}

/// Builds the model of the lungs in `lungs` (0 bg, 1 right, 2 left) with the hilum located
/// from `airways` (trachea and main bronchi outside the lungs; may be all zero).
pub fn build_lung_model(
    lungs: &Volume<u8>,
    airways: &Volume<u8>,
    settings: &LungModelSettings,
) -> Result<LungModel> {
    build_lung_model_with(lungs, airways, settings, None, Cancel::NEVER)
}

/// [`build_lung_model`] with the wall field `prebuilt` for these masks and settings when
/// there is one (refused unless it lies on the grid this build samples), stopped with
/// [`Error::Cancelled`] once `cancel` is raised (looked at after each step and inside the
/// wall's long loops).
pub fn build_lung_model_with(
    lungs: &Volume<u8>,
    airways: &Volume<u8>,
    settings: &LungModelSettings,
    prebuilt: Option<PrebuiltWall>,
    cancel: Cancel<'_>,
) -> Result<LungModel> {
    let start = Instant::now();
    let mut steps = StepClock::new(start, cancel);
    settings.validate()?;
    check_inputs(lungs, airways, settings)?;
    let mask = MaskVoxels::count(lungs);
    steps.mark("checks and voxel counts")?;

    // Cubic lattice over the lungs, and each cell's lung by partial-volume rule.
    let lattice = CellLattice::covering(lungs, settings.element_size_mm)?;
    let cell_lung = lattice.classify_cells(lungs, settings.occupancy_threshold);
    steps.mark("lattice and cell classes")?;
    let cells = shape_lung_cells(&cell_lung, lattice.cells);
    steps.mark("cell shaping")?;
    let meshes = mesh_lungs(&lattice, &cells, settings.material, mask.per_lung)?;
    steps.mark("mesh")?;

    // The wall: distance to the CT lung surface; then groups and constraints on it.
    let wall = build_wall(lungs, &lattice, &mut steps, prebuilt)?;
    let groups = assign_groups(lungs, airways, settings, &meshes, &wall.wall);
    steps.mark("groups and hilum")?;
    let nodes = constrain_nodes(&meshes, &groups.node_group, &wall.wall, settings)?;
    let fit = wall_rest_fit(&meshes.grid_mesh.mesh, &nodes, &wall.wall);
    steps.mark("constraints")?;
    let groups_volume = paint_groups(lungs, &lattice, &meshes, &groups.node_group)?;
    steps.mark("groups painted on the CT grid")?;

    let mut report = summarise(settings, &mask, &cells, &meshes, &wall, &groups, &fit);
    report.wall_time_s = start.elapsed().as_secs_f64();
    report.step_times_s = steps.times;
    tracing::info!(
        elements = report.elements,
        nodes = report.nodes,
        mesh_ml = report.mesh_volume_ml,
        mask_ml = report.mask_volume_ml,
        seconds = report.wall_time_s,
        "lung model built"
    );
    Ok(LungModel {
        grid: lattice.grid(cells.active()),
        mesh: meshes.grid_mesh,
        element_lung: meshes.element_lung,
        node_group: groups.node_group,
        wall: wall.wall,
        constraints: nodes.constraints,
        groups_volume,
        report,
    })
}

/// Refuses masks on another grid than the lung mask, unknown labels and an empty lung mask.
fn check_inputs(
    lungs: &Volume<u8>,
    airways: &Volume<u8>,
    settings: &LungModelSettings,
) -> Result<()> {
    lungs.geometry.validate("lung mask")?;
    if lungs.as_slice().len() != lungs.geometry.voxel_count() {
        return Err(Error::argument(
            "lung mask",
            format!(
                "grid {:?} needs {} voxels, has {}",
                lungs.geometry.dims,
                lungs.geometry.voxel_count(),
                lungs.as_slice().len()
            ),
        ));
    }
    let same = |other: &Volume<u8>, what: &str| -> Result<()> {
        if !lungs.geometry.same_grid(&other.geometry, 1e-3)
            || other.as_slice().len() != lungs.as_slice().len()
        {
            return Err(Error::argument(
                what,
                format!(
                    "{what} is on a different grid than the lung mask ({:?} voxels of {:?} mm at \
                 {:?} vs {:?} voxels of {:?} mm at {:?}); resample it onto the CT grid",
                    other.geometry.dims,
                    other.geometry.spacing_mm,
                    other.geometry.origin_lps_mm,
                    lungs.geometry.dims,
                    lungs.geometry.spacing_mm,
                    lungs.geometry.origin_lps_mm
                ),
            ));
        }
        Ok(())
    };
    same(airways, "airway mask")?;
    if let Some(o) = &settings.group_overrides {
        same(o, "group override map")?;
        if let Some(i) = o
            .as_slice()
            .iter()
            .position(|&v| v > ConstraintGroup::Apex.code())
        {
            return Err(Error::argument(
                "group override map",
                format!(
                    "group override map holds code {} at voxel {i}; codes are 0 (none) and 1–5 \
                 (hilum, mediastinal, costal, diaphragmatic, apex)",
                    o.as_slice()[i]
                ),
            ));
        }
    }
    if let Some(i) = lungs.as_slice().iter().position(|&v| v > LEFT_LUNG) {
        return Err(Error::argument(
            "lung mask",
            format!(
            "lung mask holds label {} at voxel {i}; expected 0 background, 1 right lung, 2 left lung",
            lungs.as_slice()[i]
        )));
    }
    if !lungs.as_slice().iter().any(|&v| v != 0) {
        return Err(Error::argument(
            "lung mask",
            "lung mask is empty: no voxel is labelled 1 (right lung) or 2 (left lung)",
        ));
    }
    Ok(())
}
