//! From a lung label map to the mechanical model: cubic Baudet elements, anatomical constraint
//! groups, the thoracic-cavity wall the lung slides on, and the constraint set the solvers use.
//!
//! # Conventions
//!
//! * Input masks are on the CT grid (any orientation, oblique and left-handed grids included):
//!   lungs `0` background, `1` right lung, `2` left lung; airways non-zero on the trachea and
//!   main bronchi outside the lungs (may be all zero).
//! * The model lives in DICOM patient space (LPS: +x left, +y posterior, +z superior), in
//!   metres. Elements are cubes of `element_size_mm` on a lattice aligned with the LPS axes and
//!   anchored at the LPS origin (lattice points at integer multiples of the element size), so
//!   the same anatomy on a differently oriented CT grid gives the same lattice.
//! * Group codes ([`ConstraintGroup`]) are the values written in `groups.nii.gz`:
//!   0 interior / no group, 1 hilum, 2 mediastinal, 3 costal, 4 diaphragmatic, 5 apex.
//!
//! # Decisions
//!
//! * **Partial volume.** A lattice cell becomes an element of a lung when at least
//!   `occupancy_threshold` (default ½) of its volume lies in that lung, measured on 4³ points
//!   per cell looked up at the nearest CT voxel. Cells half-in count as in, so the staircase
//!   surface gains about as much volume as it loses: mesh volume ≈ mask volume (both reported).
//! * **Mechanisms.** Baudet's brick has three zero-energy twist modes that only neighbours
//!   suppress, so per lung the element mask is (1) cleared of enclosed cavities (filled: the
//!   lung contains its bronchi and vessels), (2) opened with a 2 × 2 × 2 block, which keeps
//!   exactly the cells lying in some fully occupied 2 × 2 × 2 block and so removes every
//!   one-element-thick sheet, column and face-hanging cube, and (3) reduced to its largest
//!   face-connected component, which drops parts hanging by an edge or a corner. Removed and
//!   filled counts are reported.
//! * **Separate bodies.** Each lung is meshed on the same lattice by its own [`VoxelGrid`] and
//!   the meshes are concatenated, so right and left lungs never share a node even where they
//!   touch (the quasi-static solver still recognises one lattice and uses multigrid).
//! * **Wall.** One signed distance field (metres, negative inside the lungs) sampled on an
//!   LPS-aligned grid that refines the lattice (spacing = element size / m, m ≥ 2, about the
//!   CT resolution, at least 1 mm) with two elements of margin: the Euclidean distance to the
//!   CT lung voxels (lung voxels touching the other lung count as outside, so touching lungs
//!   stay two surfaces), smoothed by a Gaussian of one CT voxel so normals vary continuously.
//! * **Sliding** ([`SlidingMode`]). Bricks must keep their exact rest shape, so surface nodes
//!   stay on the element staircase, up to about half an element off the smooth wall (reported).
//!   The solver projects sliding nodes onto their constraint before solving, so a
//!   [`NodeConstraint::Surface`] on the wall would deform the lung with no load. By default
//!   each sliding node therefore slides on the wall's tangent plane through its rest position
//!   ([`NodeConstraint::Plane`], normal from the wall): exact at rest, smooth normals.
//!   [`SlidingMode::WallSurface`] gives the literal surface constraint. A wall bent to pass
//!   through every staircase node was tried and rejected: between a convex and a concave
//!   corner one element apart the field must vanish twice along the normal, so its gradient
//!   collapsed (|∇| down to 0.006 on the CIP case at 8 mm) and Newton failed even at zero load.
//! * **Groups** (automatic; `group_overrides` replaces them): per lung, with outward normals n
//!   from the CT surface field and the medial direction m (+x for the right lung, −x for the
//!   left), in priority order:
//!   hilum = surface nodes within `hilum_radius_mm` (at least 1.5 elements) of the surface
//!   node nearest to where the airway mask touches that lung (or, without airway contact,
//!   the mediastinal-face node nearest to the face's centre in y and z) → **fixed**;
//!   apex = surface nodes in the top `apex_height_fraction` of the lung's height → **sliding**
//!   (the pleural dome encloses it, so sliding already keeps it nearly still; fixing it as
//!   the thesis did would add a second anchor fighting the hilum);
//!   diaphragmatic = n_z ≤ −0.1 below the hilum (the dome and the costophrenic zone of
//!   apposition, where the lower costal surface faces the diaphragm) → **moves
//!   cranio-caudally** ([`DiaphragmMotion`]): the wall here is the diaphragm, which descends
//!   like a piston in tidal breathing, so sliding on the rest-state wall would forbid the
//!   largest motion. With n_z ≤ −½ only, sliding nodes on the downward-narrowing recess were
//!   pushed inward as they slid down and squeezed the lowest elements (signed volume 0.52 of
//!   rest at 250 mL on the CIP case at 8 mm; Newton failed before 400 mL); with −0.1 the
//!   worst element keeps 0.79 at 500 mL;
//!   mediastinal = n·m ≥ ½ on the medial side of the lung → **sliding**;
//!   costal = every other surface node (lateral, anterior, posterior) → **sliding** on the wall.
//! * `groups_volume` gives every lung-surface voxel of the CT grid (a lung voxel with a
//!   6-neighbour outside its lung) the group of the nearest surface node of the same lung.

use std::collections::{BTreeMap, VecDeque};
use std::time::Instant;

use nalgebra::{Matrix3, Vector3};
use rayon::prelude::*;
use serde::Serialize;

use crate::model::grid::GridMesh;
use crate::model::{
    ConstraintSet, HexMesh, Material, NodeConstraint, SignedDistanceField, VoxelGrid,
};
use crate::volume::Volume;
use crate::{Error, Result};

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
/// Points per cell edge used to measure a cell's lung fraction.
const SUPERSAMPLES: usize = 4;
/// Lattice cells of padding around the lungs' bounding box (keeps the border background).
const LATTICE_PAD_CELLS: i64 = 1;
/// Elements of margin between the lattice box and the wall field's border.
const WALL_MARGIN_CELLS: i64 = 2;

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
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
pub enum SlidingMode {
    /// On the plane through its rest position normal to the wall there
    /// ([`NodeConstraint::Plane`]): exact at rest, so no load-free deformation, and a smooth
    /// normal; it departs from the curved wall by d²/2R after sliding d (0.5 mm for 10 mm on a
    /// 10 cm radius). The default.
    TangentPlane,
    /// On the wall field itself ([`NodeConstraint::Surface`], field 0). The element staircase
    /// puts nodes up to `wall_rest_offset_max_mm` off the smooth wall, and the solver projects
    /// them onto it before solving: that deforms the surface elements with no load.
    WallSurface,
}

impl Default for LungModelSettings {
    fn default() -> Self {
        LungModelSettings {
            element_size_mm: DEFAULT_ELEMENT_SIZE_MM,
            material: Material::LUNG,
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
            return Err(Error::InvalidInput(format!(
                "element size {h} mm is outside the supported \
                 {MIN_ELEMENT_SIZE_MM}–{MAX_ELEMENT_SIZE_MM} mm"
            )));
        }
        self.material.validate()?;
        let t = self.occupancy_threshold;
        if !(t.is_finite() && t > 0.0 && t <= 1.0) {
            return Err(Error::InvalidInput(format!(
                "occupancy threshold {t} must be in (0, 1]"
            )));
        }
        let r = self.hilum_radius_mm;
        if !(r.is_finite() && r > 0.0) {
            return Err(Error::InvalidInput(format!(
                "hilum radius {r} mm must be positive"
            )));
        }
        let a = self.apex_height_fraction;
        if !(a.is_finite() && (0.0..0.5).contains(&a)) {
            return Err(Error::InvalidInput(format!(
                "apex height fraction {a} must be in [0, 0.5)"
            )));
        }
        Ok(())
    }
}

/// What the model builder did, for the ingest report.
#[derive(Debug, Clone, Serialize)]
pub struct LungModelReport {
    /// Element edge in millimetres.
    pub element_size_mm: f64,
    /// Elements of both lungs.
    pub elements: usize,
    /// Nodes of both lungs (no node is shared between the lungs).
    pub nodes: usize,
    /// Nodes on the external surface.
    pub surface_nodes: usize,
    /// Elements per lung ("right", "left").
    pub elements_per_lung: BTreeMap<String, usize>,
    /// Volume enclosed by the mesh, both lungs, in millilitres.
    pub mesh_volume_ml: f64,
    /// Volume of the lung voxels of the mask, both lungs, in millilitres.
    pub mask_volume_ml: f64,
    /// Mesh volume per lung in millilitres.
    pub mesh_volume_per_lung_ml: BTreeMap<String, f64>,
    /// Mask volume per lung in millilitres.
    pub mask_volume_per_lung_ml: BTreeMap<String, f64>,
    /// How cells partly inside a lung were decided.
    pub partial_volume_policy: String,
    /// Cells added by filling cavities enclosed by a lung's elements.
    pub cavity_cells_filled: usize,
    /// Cells added by the 2 × 2 × 2 closing (one-cell-wide pits and notches of the surface).
    pub notch_cells_filled: usize,
    /// Elements removed by the 2 × 2 × 2 opening (one-element-thick parts).
    pub removed_thin_elements: usize,
    /// Elements removed because they were not face-connected to their lung's largest part.
    pub removed_detached_elements: usize,
    /// Surface nodes per group name (nodes of no group under "none").
    pub group_nodes: BTreeMap<String, usize>,
    /// Where each lung's hilum came from: airway contact or geometry.
    pub hilum_source: BTreeMap<String, String>,
    /// LPS position in millimetres of each lung's hilum centre node.
    pub hilum_centre_mm: BTreeMap<String, [f64; 3]>,
    /// Radius in millimetres actually used for the hilum.
    pub hilum_radius_mm: f64,
    /// Whether the groups came from `group_overrides`.
    pub groups_from_overrides: bool,
    /// Lung voxels of the CT mask touching the other lung (the lungs are meshed apart anyway).
    pub wall_contact_voxels: usize,
    /// Samples of the wall field along x, y, z.
    pub wall_samples: [usize; 3],
    /// Spacing of the wall field in millimetres.
    pub wall_spacing_mm: f64,
    /// How sliding nodes are held ([`SlidingMode`]).
    pub sliding_mode: SlidingMode,
    /// How the diaphragmatic face moves.
    pub diaphragm_motion: DiaphragmMotion,
    /// Largest |wall distance| at a sliding node's rest position in mm: the element staircase
    /// against the smooth CT surface (with [`SlidingMode::WallSurface`], how far the solver
    /// moves a node onto the wall before any load).
    pub wall_rest_offset_max_mm: f64,
    /// Mean |wall distance| at the sliding nodes' rest positions in mm.
    pub wall_rest_offset_mean_mm: f64,
    /// Smallest |∇ wall| at a sliding node's rest position (1 for an exact distance field;
    /// near 0 would make the sliding direction ill-defined).
    pub wall_min_gradient_norm: f64,
    /// Wall time of the whole build in seconds.
    pub wall_time_s: f64,
}

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
    pub wall: SignedDistanceField,
    /// Hilum fixed, mediastinal/costal/apex sliding ([`SlidingMode`]; `wall` is field 0),
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

fn lung_name(lung: u8) -> &'static str {
    if lung == RIGHT_LUNG {
        "right"
    } else {
        "left"
    }
}

/// Builds the model of the lungs in `lungs` (0 bg, 1 right, 2 left) with the hilum located
/// from `airways` (trachea and main bronchi outside the lungs; may be all zero).
pub fn build_lung_model(
    lungs: &Volume<u8>,
    airways: &Volume<u8>,
    settings: &LungModelSettings,
) -> Result<LungModel> {
    let start = Instant::now();
    settings.validate()?;
    check_inputs(lungs, airways, settings)?;
    let h_mm = settings.element_size_mm;
    let ct = &lungs.geometry;
    let voxel_ml = ct.voxel_volume_mm3() * 1e-3;
    let voxels_per_lung =
        [RIGHT_LUNG, LEFT_LUNG].map(|l| lungs.as_slice().par_iter().filter(|&&v| v == l).count());

    // Cubic lattice over the lungs, and each cell's lung by partial-volume rule.
    let lattice = CellLattice::covering(lungs, h_mm)?;
    let cell_lung = lattice.classify_cells(lungs, settings.occupancy_threshold);
    let mut cavity_cells_filled = 0;
    let mut removed_thin_elements = 0;
    let mut removed_detached_elements = 0;
    let mut lung_masks = Vec::new();
    let mut notch_cells_filled = 0;
    for lung in [RIGHT_LUNG, LEFT_LUNG] {
        let mut mask: Vec<bool> = cell_lung.iter().map(|&l| l == lung).collect();
        cavity_cells_filled += fill_cavities(&mut mask, lattice.cells);
        let free: Vec<bool> = cell_lung.iter().map(|&l| l == 0 || l == lung).collect();
        notch_cells_filled += close_2x2x2(&mut mask, &free, lattice.cells);
        removed_thin_elements += open_2x2x2(&mut mask, lattice.cells);
        removed_detached_elements += keep_largest_face_component(&mut mask, lattice.cells);
        cavity_cells_filled += fill_cavities(&mut mask, lattice.cells);
        lung_masks.push((lung, mask));
    }

    // One mesh per lung on the same lattice, concatenated: the lungs share no node.
    let h_m = h_mm * 1e-3;
    let origin_m = lattice.point_mm([0, 0, 0]) * 1e-3;
    let mut positions = Vec::new();
    let mut elements: Vec<[u32; 8]> = Vec::new();
    let mut node_lattice = Vec::new();
    let mut element_cell = Vec::new();
    let mut element_lung = Vec::new();
    let mut node_lung = Vec::new();
    let mut classes = Vec::new();
    let mut elements_per_lung = BTreeMap::new();
    for (lung, mask) in &lung_masks {
        let count = mask.iter().filter(|&&a| a).count();
        elements_per_lung.insert(lung_name(*lung).to_string(), count);
        if count == 0 {
            if voxels_per_lung[(*lung - 1) as usize] > 0 {
                tracing::warn!(
                    "the {} lung ({} voxels) is too small or thin for {h_mm} mm elements; \
                     it is left out of the model",
                    lung_name(*lung),
                    voxels_per_lung[(*lung - 1) as usize]
                );
            }
            continue;
        }
        let grid = VoxelGrid {
            cells: lattice.cells,
            cell_size_m: [h_m; 3],
            origin_m,
            axes: Matrix3::identity(),
            active: mask.clone(),
        };
        let gm = grid.to_mesh(settings.material)?;
        let offset = positions.len() as u32;
        positions.extend_from_slice(&gm.mesh.rest_positions_m);
        elements.extend(gm.mesh.elements.iter().map(|e| e.map(|n| n + offset)));
        node_lattice.extend_from_slice(&gm.node_lattice);
        element_cell.extend_from_slice(&gm.element_cell);
        element_lung.extend(std::iter::repeat_n(*lung, gm.mesh.element_count()));
        node_lung.extend(std::iter::repeat_n(*lung, gm.mesh.node_count()));
        if classes.is_empty() {
            classes = gm.mesh.classes.clone();
        }
    }
    if elements.is_empty() {
        return Err(Error::Ingest(format!(
            "no element of {h_mm} mm survives in the lung mask ({} right, {} left voxels): \
             the lungs are too small or thin for this element size",
            voxels_per_lung[0], voxels_per_lung[1]
        )));
    }
    let n_elements = elements.len();
    let mesh = HexMesh::new(positions, elements, vec![0; n_elements], classes)?;
    let n_nodes = mesh.node_count();
    let mut on_surface = vec![false; n_nodes];
    for f in &mesh.external_faces {
        for &n in f {
            on_surface[n as usize] = true;
        }
    }
    let surface: Vec<u32> = (0..n_nodes as u32)
        .filter(|&n| on_surface[n as usize])
        .collect();

    // The wall: CT lung surface distance, then fitted through the surface nodes.
    let wall_build = build_wall(lungs, &lattice)?;

    // Constraint groups.
    let positions_mm: Vec<Vector3<f64>> = mesh.rest_positions_m.iter().map(|p| p * 1e3).collect();
    let hilum_radius_mm = settings.hilum_radius_mm.max(1.5 * h_mm);
    let mut hilum_source = BTreeMap::new();
    let mut hilum_centre_mm = BTreeMap::new();
    let (node_group, groups_from_overrides) = match &settings.group_overrides {
        Some(overrides) => (
            groups_from_labels(overrides, &positions_mm, &surface, h_mm),
            true,
        ),
        None => {
            let mut node_group = vec![0u8; n_nodes];
            for lung in [RIGHT_LUNG, LEFT_LUNG] {
                let lung_surface: Vec<u32> = surface
                    .iter()
                    .copied()
                    .filter(|&n| node_lung[n as usize] == lung)
                    .collect();
                if lung_surface.is_empty() {
                    continue;
                }
                let normals: Vec<Vector3<f64>> = lung_surface
                    .iter()
                    .map(|&n| wall_build.wall.normal(mesh.rest_positions_m[n as usize]))
                    .collect();
                let (centre, source) =
                    hilum_centre(lungs, airways, lung, &lung_surface, &normals, &positions_mm);
                hilum_source.insert(lung_name(lung).to_string(), source);
                let c = positions_mm[centre as usize];
                hilum_centre_mm.insert(lung_name(lung).to_string(), [c.x, c.y, c.z]);
                classify_lung_surface(
                    lung,
                    &lung_surface,
                    &normals,
                    &positions_mm,
                    c,
                    hilum_radius_mm,
                    settings.apex_height_fraction,
                    &mut node_group,
                );
            }
            (node_group, false)
        }
    };

    // Constraints: the wall is field 0.
    let mut constraints = ConstraintSet::new(n_nodes);
    let wall_field = constraints.add_surface(wall_build.wall.clone());
    let mut sliding = Vec::new();
    for &n in &surface {
        let Some(group) = ConstraintGroup::from_code(node_group[n as usize]) else {
            continue;
        };
        match group.boundary_condition() {
            BoundaryCondition::Fixed => {
                constraints.fix(n, mesh.rest_positions_m[n as usize])?;
            }
            BoundaryCondition::SlidingOnWall => {
                let rest = mesh.rest_positions_m[n as usize];
                let constraint = match settings.sliding {
                    SlidingMode::TangentPlane => NodeConstraint::Plane {
                        point_m: rest,
                        normal: wall_build.wall.normal(rest),
                    },
                    SlidingMode::WallSurface => NodeConstraint::Surface { field: wall_field },
                };
                constraints.set(n, constraint)?;
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
                DiaphragmMotion::Free => {}
            },
        }
    }
    constraints.validate(&mesh.rest_positions_m)?;
    let rest_offsets_mm: Vec<f64> = sliding
        .iter()
        .map(|&n| {
            wall_build
                .wall
                .evaluate(mesh.rest_positions_m[n as usize])
                .0
                .abs()
                * 1e3
        })
        .collect();
    let wall_rest_offset_max_mm = rest_offsets_mm.iter().cloned().fold(0.0, f64::max);
    let wall_rest_offset_mean_mm =
        rest_offsets_mm.iter().sum::<f64>() / rest_offsets_mm.len().max(1) as f64;
    let wall_min_gradient_norm = sliding
        .iter()
        .map(|&n| {
            wall_build
                .wall
                .smooth_gradient(mesh.rest_positions_m[n as usize])
                .norm()
        })
        .fold(f64::INFINITY, f64::min);
    let groups_volume = paint_groups(
        lungs,
        &lattice,
        &node_lattice,
        &node_lung,
        &surface,
        &node_group,
        &positions_mm,
    )?;

    // Report.
    let mut group_nodes = BTreeMap::new();
    for g in ConstraintGroup::ALL {
        group_nodes.insert(g.name().to_string(), 0usize);
    }
    group_nodes.insert("none".to_string(), 0usize);
    for &n in &surface {
        let name = ConstraintGroup::from_code(node_group[n as usize]).map_or("none", |g| g.name());
        *group_nodes.entry(name.to_string()).or_insert(0) += 1;
    }
    let mut mesh_volume_per_lung_ml = BTreeMap::new();
    let mut mask_volume_per_lung_ml = BTreeMap::new();
    for lung in [RIGHT_LUNG, LEFT_LUNG] {
        let count = element_lung.iter().filter(|&&l| l == lung).count();
        mesh_volume_per_lung_ml.insert(
            lung_name(lung).to_string(),
            count as f64 * h_mm.powi(3) * 1e-3,
        );
        mask_volume_per_lung_ml.insert(
            lung_name(lung).to_string(),
            voxels_per_lung[(lung - 1) as usize] as f64 * voxel_ml,
        );
    }
    let mesh_volume_ml = mesh.enclosed_volume_m3(&mesh.rest_positions_m) * 1e6;
    let report = LungModelReport {
        element_size_mm: h_mm,
        elements: mesh.element_count(),
        nodes: n_nodes,
        surface_nodes: surface.len(),
        elements_per_lung,
        mesh_volume_ml,
        mask_volume_ml: (voxels_per_lung[0] + voxels_per_lung[1]) as f64 * voxel_ml,
        mesh_volume_per_lung_ml,
        mask_volume_per_lung_ml,
        partial_volume_policy: format!(
            "a {h_mm} mm cell is an element of a lung when at least {:.0} % of its {}³ \
             sample points (nearest CT voxel) lie in that lung",
            settings.occupancy_threshold * 100.0,
            SUPERSAMPLES
        ),
        cavity_cells_filled,
        notch_cells_filled,
        removed_thin_elements,
        removed_detached_elements,
        group_nodes,
        hilum_source,
        hilum_centre_mm,
        hilum_radius_mm,
        groups_from_overrides,
        wall_contact_voxels: wall_build.contact_voxels,
        wall_samples: wall_build.wall.samples,
        wall_spacing_mm: wall_build.wall.spacing_m[0] * 1e3,
        sliding_mode: settings.sliding,
        diaphragm_motion: settings.diaphragm,
        wall_rest_offset_max_mm,
        wall_rest_offset_mean_mm,
        wall_min_gradient_norm,
        wall_time_s: start.elapsed().as_secs_f64(),
    };
    tracing::info!(
        elements = report.elements,
        nodes = report.nodes,
        mesh_ml = report.mesh_volume_ml,
        mask_ml = report.mask_volume_ml,
        "lung model built"
    );
    let active = lung_masks
        .iter()
        .fold(vec![false; cell_lung.len()], |mut acc, (_, m)| {
            acc.iter_mut().zip(m).for_each(|(a, &b)| *a |= b);
            acc
        });
    Ok(LungModel {
        grid: VoxelGrid {
            cells: lattice.cells,
            cell_size_m: [h_m; 3],
            origin_m,
            axes: Matrix3::identity(),
            active,
        },
        mesh: GridMesh {
            mesh,
            node_lattice,
            element_cell,
        },
        element_lung,
        node_group,
        wall: wall_build.wall,
        constraints,
        groups_volume,
        report,
    })
}

fn check_inputs(
    lungs: &Volume<u8>,
    airways: &Volume<u8>,
    settings: &LungModelSettings,
) -> Result<()> {
    lungs.geometry.validate("lung mask")?;
    if lungs.as_slice().len() != lungs.geometry.voxel_count() {
        return Err(Error::InvalidInput(format!(
            "lung mask: grid {:?} needs {} voxels, has {}",
            lungs.geometry.dims,
            lungs.geometry.voxel_count(),
            lungs.as_slice().len()
        )));
    }
    let same = |other: &Volume<u8>, what: &str| -> Result<()> {
        if !lungs.geometry.same_grid(&other.geometry, 1e-3)
            || other.as_slice().len() != lungs.as_slice().len()
        {
            return Err(Error::InvalidInput(format!(
                "{what} is on a different grid than the lung mask ({:?} voxels of {:?} mm at \
                 {:?} vs {:?} voxels of {:?} mm at {:?}); resample it onto the CT grid",
                other.geometry.dims,
                other.geometry.spacing_mm,
                other.geometry.origin_lps_mm,
                lungs.geometry.dims,
                lungs.geometry.spacing_mm,
                lungs.geometry.origin_lps_mm
            )));
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
            return Err(Error::InvalidInput(format!(
                "group override map holds code {} at voxel {i}; codes are 0 (none) and 1–5 \
                 (hilum, mediastinal, costal, diaphragmatic, apex)",
                o.as_slice()[i]
            )));
        }
    }
    if let Some(i) = lungs.as_slice().iter().position(|&v| v > LEFT_LUNG) {
        return Err(Error::InvalidInput(format!(
            "lung mask holds label {} at voxel {i}; expected 0 background, 1 right lung, 2 left lung",
            lungs.as_slice()[i]
        )));
    }
    if !lungs.as_slice().iter().any(|&v| v != 0) {
        return Err(Error::InvalidInput(
            "lung mask is empty: no voxel is labelled 1 (right lung) or 2 (left lung)".into(),
        ));
    }
    Ok(())
}

/// The cubic lattice: cells of `h_mm` whose lattice point (0, 0, 0) sits at LPS
/// `first · h_mm`, so cells are fixed in patient space whatever the CT grid.
struct CellLattice {
    first: [i64; 3],
    cells: [usize; 3],
    h_mm: f64,
}

impl CellLattice {
    /// The lattice covering every lung voxel, padded by one cell.
    fn covering(lungs: &Volume<u8>, h_mm: f64) -> Result<Self> {
        let g = &lungs.geometry;
        let [nx, ny, _] = g.dims;
        // Voxel-index box of the lung voxels, per slab then reduced.
        let (lo, hi) = lungs
            .as_slice()
            .par_chunks(nx * ny)
            .enumerate()
            .map(|(k, slab)| {
                let mut lo = [usize::MAX; 3];
                let mut hi = [0usize; 3];
                for (idx, &v) in slab.iter().enumerate() {
                    if v != 0 {
                        let ijk = [idx % nx, idx / nx, k];
                        for a in 0..3 {
                            lo[a] = lo[a].min(ijk[a]);
                            hi[a] = hi[a].max(ijk[a]);
                        }
                    }
                }
                (lo, hi)
            })
            .reduce(
                || ([usize::MAX; 3], [0usize; 3]),
                |a, b| {
                    (
                        std::array::from_fn(|i| a.0[i].min(b.0[i])),
                        std::array::from_fn(|i| a.1[i].max(b.1[i])),
                    )
                },
            );
        let mut min_mm = Vector3::repeat(f64::INFINITY);
        let mut max_mm = Vector3::repeat(f64::NEG_INFINITY);
        for corner in 0..8 {
            let ijk = Vector3::from_fn(|a, _| {
                if corner >> a & 1 == 1 {
                    hi[a] as f64 + 0.5
                } else {
                    lo[a] as f64 - 0.5
                }
            });
            let p = g.voxel_to_lps_mm(ijk);
            min_mm = min_mm.inf(&p);
            max_mm = max_mm.sup(&p);
        }
        let first: [i64; 3] =
            std::array::from_fn(|a| (min_mm[a] / h_mm).floor() as i64 - LATTICE_PAD_CELLS);
        let last: [i64; 3] =
            std::array::from_fn(|a| (max_mm[a] / h_mm).ceil() as i64 + LATTICE_PAD_CELLS);
        let cells: [usize; 3] = std::array::from_fn(|a| (last[a] - first[a]) as usize);
        if cells.iter().product::<usize>() > u32::MAX as usize / 8 {
            return Err(Error::InvalidInput(format!(
                "{h_mm} mm elements over the lungs' {:.0} × {:.0} × {:.0} mm box make {cells:?} \
                 cells: too many",
                max_mm.x - min_mm.x,
                max_mm.y - min_mm.y,
                max_mm.z - min_mm.z
            )));
        }
        Ok(CellLattice { first, cells, h_mm })
    }

    /// LPS millimetres of lattice point `l` (may lie outside the box).
    fn point_mm(&self, l: [i64; 3]) -> Vector3<f64> {
        Vector3::from_fn(|a, _| (self.first[a] + l[a]) as f64 * self.h_mm)
    }

    /// The lung (0, 1, 2) of each cell by the partial-volume rule.
    fn classify_cells(&self, lungs: &Volume<u8>, threshold: f64) -> Vec<u8> {
        let g = &lungs.geometry;
        let [nx, ny, nz] = self.cells;
        // Continuous voxel index = A · p_mm + b; sample offsets precomputed through A.
        let a = Matrix3::from_diagonal(&Vector3::from(g.spacing_mm.map(|s| 1.0 / s)))
            * g.direction().transpose();
        let b = -(a * g.origin());
        let offsets: Vec<Vector3<f64>> = (0..SUPERSAMPLES.pow(3))
            .map(|s| {
                let f = |q: usize| (q as f64 + 0.5) / SUPERSAMPLES as f64 * self.h_mm;
                a * Vector3::new(
                    f(s % SUPERSAMPLES),
                    f(s / SUPERSAMPLES % SUPERSAMPLES),
                    f(s / (SUPERSAMPLES * SUPERSAMPLES)),
                )
            })
            .collect();
        let needed = (threshold * offsets.len() as f64 - 1e-9).ceil() as usize;
        let dims = g.dims;
        let mut out = vec![0u8; nx * ny * nz];
        out.par_chunks_mut(nx * ny)
            .enumerate()
            .for_each(|(k, slab)| {
                for j in 0..ny {
                    for i in 0..nx {
                        let corner = a * self.point_mm([i as i64, j as i64, k as i64]) + b;
                        let mut count = [0usize; 3];
                        for o in &offsets {
                            let v = corner + o;
                            let idx: [f64; 3] = [v.x.round(), v.y.round(), v.z.round()];
                            if (0..3).all(|q| idx[q] >= 0.0 && idx[q] < dims[q] as f64) {
                                let label =
                                    lungs.get(idx[0] as usize, idx[1] as usize, idx[2] as usize);
                                count[label.min(2) as usize] += 1;
                            }
                        }
                        let (r, l) = (count[1], count[2]);
                        slab[i + nx * j] = if r >= needed && r >= l {
                            RIGHT_LUNG
                        } else if l >= needed && l > r {
                            LEFT_LUNG
                        } else {
                            0
                        };
                    }
                }
            });
        out
    }
}

/// Face neighbours of cell `c` inside `dims`, written into `out`; returns how many.
fn face_neighbours(c: usize, dims: [usize; 3], out: &mut [usize; 6]) -> usize {
    let [nx, ny, nz] = dims;
    let (i, j, k) = (c % nx, c / nx % ny, c / (nx * ny));
    let mut n = 0;
    let mut push = |ok: bool, idx: usize| {
        if ok {
            out[n] = idx;
            n += 1;
        }
    };
    push(i > 0, c.wrapping_sub(1));
    push(i + 1 < nx, c + 1);
    push(j > 0, c.wrapping_sub(nx));
    push(j + 1 < ny, c + nx);
    push(k > 0, c.wrapping_sub(nx * ny));
    push(k + 1 < nz, c + nx * ny);
    n
}

/// Fills background cells not face-connected to the lattice border; returns how many.
fn fill_cavities(mask: &mut [bool], dims: [usize; 3]) -> usize {
    let [nx, ny, nz] = dims;
    let mut outside = vec![false; mask.len()];
    let mut queue = VecDeque::new();
    for k in 0..nz {
        for j in 0..ny {
            for i in 0..nx {
                let border =
                    i == 0 || j == 0 || k == 0 || i + 1 == nx || j + 1 == ny || k + 1 == nz;
                let c = i + nx * (j + ny * k);
                if border && !mask[c] {
                    outside[c] = true;
                    queue.push_back(c);
                }
            }
        }
    }
    let mut nb = [0usize; 6];
    while let Some(c) = queue.pop_front() {
        let n = face_neighbours(c, dims, &mut nb);
        for &d in &nb[..n] {
            if !mask[d] && !outside[d] {
                outside[d] = true;
                queue.push_back(d);
            }
        }
    }
    let mut filled = 0;
    for (m, o) in mask.iter_mut().zip(&outside) {
        if !*m && !*o {
            *m = true;
            filled += 1;
        }
    }
    filled
}

/// Morphological closing by a 2 × 2 × 2 block, restricted to `free` cells away from the
/// lattice border: fills one-cell-wide pits and notches of the surface. Their walls are
/// sliding nodes whose tangent planes lean towards each other, and as the base descends they
/// crush the element at the pit's bottom (CIP at 4 mm: an element inverted before 400 mL).
/// Returns how many cells were added.
fn close_2x2x2(mask: &mut [bool], free: &[bool], dims: [usize; 3]) -> usize {
    let [nx, ny, nz] = dims;
    let mut outside: Vec<bool> = mask.iter().map(|&m| !m).collect();
    open_2x2x2(&mut outside, dims);
    let mut added = 0;
    for k in 1..nz.saturating_sub(1) {
        for j in 1..ny.saturating_sub(1) {
            for i in 1..nx.saturating_sub(1) {
                let c = i + nx * (j + ny * k);
                if !mask[c] && !outside[c] && free[c] {
                    mask[c] = true;
                    added += 1;
                }
            }
        }
    }
    added
}

/// Morphological opening by a 2 × 2 × 2 block: keeps the cells lying in some fully occupied
/// block. Returns how many cells were removed.
fn open_2x2x2(mask: &mut [bool], dims: [usize; 3]) -> usize {
    let [nx, ny, nz] = dims;
    if nx < 2 || ny < 2 || nz < 2 {
        let n = mask.iter().filter(|&&m| m).count();
        mask.iter_mut().for_each(|m| *m = false);
        return n;
    }
    let idx = |i: usize, j: usize, k: usize| i + nx * (j + ny * k);
    // A block is named by its lowest cell.
    let mut block_full = vec![false; mask.len()];
    for k in 0..nz - 1 {
        for j in 0..ny - 1 {
            for i in 0..nx - 1 {
                block_full[idx(i, j, k)] =
                    (0..8).all(|o| mask[idx(i + (o & 1), j + (o >> 1 & 1), k + (o >> 2))]);
            }
        }
    }
    let mut removed = 0;
    for k in 0..nz {
        for j in 0..ny {
            for i in 0..nx {
                let c = idx(i, j, k);
                if !mask[c] {
                    continue;
                }
                let kept = (0..8).any(|o| {
                    let (di, dj, dk) = (o & 1, o >> 1 & 1, o >> 2);
                    i >= di && j >= dj && k >= dk && block_full[idx(i - di, j - dj, k - dk)]
                });
                if !kept {
                    mask[c] = false;
                    removed += 1;
                }
            }
        }
    }
    removed
}

/// Keeps the largest face-connected component; returns how many cells were removed.
fn keep_largest_face_component(mask: &mut [bool], dims: [usize; 3]) -> usize {
    let mut component = vec![u32::MAX; mask.len()];
    let mut sizes: Vec<usize> = Vec::new();
    let mut queue = VecDeque::new();
    let mut nb = [0usize; 6];
    for seed in 0..mask.len() {
        if !mask[seed] || component[seed] != u32::MAX {
            continue;
        }
        let id = sizes.len() as u32;
        let mut size = 0;
        component[seed] = id;
        queue.push_back(seed);
        while let Some(c) = queue.pop_front() {
            size += 1;
            let n = face_neighbours(c, dims, &mut nb);
            for &d in &nb[..n] {
                if mask[d] && component[d] == u32::MAX {
                    component[d] = id;
                    queue.push_back(d);
                }
            }
        }
        sizes.push(size);
    }
    let Some(largest) = (0..sizes.len()).max_by_key(|&c| sizes[c]) else {
        return 0;
    };
    let mut removed = 0;
    for (m, &c) in mask.iter_mut().zip(&component) {
        if *m && c != largest as u32 {
            *m = false;
            removed += 1;
        }
    }
    removed
}

/// The wall field and what building it measured.
struct WallBuild {
    /// Smoothed distance to the CT lung surface.
    wall: SignedDistanceField,
    contact_voxels: usize,
}

fn build_wall(lungs: &Volume<u8>, lattice: &CellLattice) -> Result<WallBuild> {
    let g = &lungs.geometry;
    let h_mm = lattice.h_mm;
    let finest_ct_mm = g.spacing_mm.iter().cloned().fold(f64::INFINITY, f64::min);
    let coarsest_ct_mm = g.spacing_mm.iter().cloned().fold(0.0, f64::max);
    // Samples per element edge: about the CT resolution, at least 2, at least 1 mm apart.
    let per_cell = ((h_mm / finest_ct_mm.max(1.0)).ceil() as usize).clamp(2, 8);
    let s_mm = h_mm / per_cell as f64;
    let margin = WALL_MARGIN_CELLS;
    let origin_mm = lattice.point_mm([-margin; 3]);
    let dims: [usize; 3] =
        std::array::from_fn(|a| (lattice.cells[a] + 2 * margin as usize) * per_cell + 1);
    let [nx, ny, _] = dims;
    let n_samples: usize = dims.iter().product();

    // Inside = a lung voxel not touching the other lung (so touching lungs stay two surfaces).
    let a = Matrix3::from_diagonal(&Vector3::from(g.spacing_mm.map(|s| 1.0 / s)))
        * g.direction().transpose();
    let b = -(a * g.origin());
    let ct_dims = g.dims;
    let touches_other = |i: usize, j: usize, k: usize, lung: u8| -> bool {
        let other = 3 - lung;
        for dk in -1i64..=1 {
            for dj in -1i64..=1 {
                for di in -1i64..=1 {
                    let (x, y, z) = (i as i64 + di, j as i64 + dj, k as i64 + dk);
                    if x >= 0
                        && y >= 0
                        && z >= 0
                        && (x as usize) < ct_dims[0]
                        && (y as usize) < ct_dims[1]
                        && (z as usize) < ct_dims[2]
                        && lungs.get(x as usize, y as usize, z as usize) == other
                    {
                        return true;
                    }
                }
            }
        }
        false
    };
    let mut inside = vec![false; n_samples];
    inside
        .par_chunks_mut(nx * ny)
        .enumerate()
        .for_each(|(k, slab)| {
            for j in 0..ny {
                for i in 0..nx {
                    let p = origin_mm + Vector3::new(i as f64, j as f64, k as f64) * s_mm;
                    let v = a * p + b;
                    let idx = [v.x.round(), v.y.round(), v.z.round()];
                    if (0..3).all(|q| idx[q] >= 0.0 && idx[q] < ct_dims[q] as f64) {
                        let (ci, cj, ck) = (idx[0] as usize, idx[1] as usize, idx[2] as usize);
                        let lung = lungs.get(ci, cj, ck);
                        slab[i + nx * j] = lung != 0 && !touches_other(ci, cj, ck, lung);
                    }
                }
            }
        });
    let [cnx, cny, _] = ct_dims;
    let contact_voxels: usize = lungs
        .as_slice()
        .par_chunks(cnx * cny)
        .enumerate()
        .map(|(k, slab)| {
            slab.iter()
                .enumerate()
                .filter(|(idx, &v)| v != 0 && touches_other(idx % cnx, idx / cnx, k, v))
                .count()
        })
        .sum();

    // One CT voxel of Gaussian smoothing rounds the voxel staircase into continuous normals.
    let s_m = s_mm * 1e-3;
    let ct_sigma = (coarsest_ct_mm / s_mm).clamp(0.5, 4.0);
    let anatomy_m: Vec<f64> = smoothed_signed_distance(&inside, dims, ct_sigma)
        .iter()
        .map(|&v| v as f64 * s_m)
        .collect();
    drop(inside);
    let anatomy = SignedDistanceField::new(origin_mm * 1e-3, [s_m; 3], dims, anatomy_m)?;

    Ok(WallBuild {
        wall: anatomy,
        contact_voxels,
    })
}

/// Signed Euclidean distance in samples to the boundary of `inside` (negative inside; half
/// a sample puts the surface between samples), smoothed by a Gaussian of `sigma` samples.
fn smoothed_signed_distance(inside: &[bool], dims: [usize; 3], sigma: f64) -> Vec<f32> {
    const FAR: f32 = 1e12;
    let mut to_inside: Vec<f32> = inside.iter().map(|&i| if i { 0.0 } else { FAR }).collect();
    squared_distance_transform(&mut to_inside, dims);
    let mut to_outside: Vec<f32> = inside.iter().map(|&i| if i { FAR } else { 0.0 }).collect();
    squared_distance_transform(&mut to_outside, dims);
    let mut signed: Vec<f32> = inside
        .par_iter()
        .zip(to_inside.par_iter().zip(to_outside.par_iter()))
        .map(|(&i, (&din, &dout))| {
            if i {
                -(dout.sqrt() - 0.5)
            } else {
                din.sqrt() - 0.5
            }
        })
        .collect();
    drop(to_inside);
    drop(to_outside);
    gaussian_smooth(&mut signed, dims, sigma);
    signed
}

/// Per-task buffers of the line transforms.
#[derive(Default)]
struct LineScratch {
    line: Vec<f32>,
    out: Vec<f32>,
    parabola_at: Vec<usize>,
    boundary: Vec<f64>,
}

/// Applies `op` to every line of `values` along `axis`; `op` reads `s.line` and writes `s.out`.
fn transform_lines(
    values: &mut [f32],
    dims: [usize; 3],
    axis: usize,
    op: &(dyn Fn(&mut LineScratch) + Sync),
) {
    let [nx, ny, nz] = dims;
    match axis {
        0 => values
            .par_chunks_mut(nx)
            .for_each_init(LineScratch::default, |s, line| {
                s.line.clear();
                s.line.extend_from_slice(line);
                op(s);
                line.copy_from_slice(&s.out);
            }),
        1 => values
            .par_chunks_mut(nx * ny)
            .for_each_init(LineScratch::default, |s, slab| {
                for i in 0..nx {
                    s.line.clear();
                    s.line.extend((0..ny).map(|j| slab[i + nx * j]));
                    op(s);
                    for j in 0..ny {
                        slab[i + nx * j] = s.out[j];
                    }
                }
            }),
        _ => {
            // Columns along z interleave across slabs: compute per xz-plane, then scatter.
            let src: &[f32] = values;
            let planes: Vec<Vec<f32>> = (0..ny)
                .into_par_iter()
                .map_init(LineScratch::default, |s, j| {
                    let mut plane = vec![0.0f32; nx * nz];
                    for i in 0..nx {
                        s.line.clear();
                        s.line.extend((0..nz).map(|k| src[i + nx * (j + ny * k)]));
                        op(s);
                        plane[i * nz..(i + 1) * nz].copy_from_slice(&s.out);
                    }
                    plane
                })
                .collect();
            for (j, plane) in planes.iter().enumerate() {
                for i in 0..nx {
                    for k in 0..nz {
                        values[i + nx * (j + ny * k)] = plane[i * nz + k];
                    }
                }
            }
        }
    }
}

/// Exact squared Euclidean distance transform in samples (Felzenszwalb & Huttenlocher):
/// zeros are the feature set, large values elsewhere.
fn squared_distance_transform(values: &mut [f32], dims: [usize; 3]) {
    for axis in 0..3 {
        transform_lines(values, dims, axis, &edt_line);
    }
}

/// Lower envelope of parabolas over one line.
fn edt_line(s: &mut LineScratch) {
    let n = s.line.len();
    s.out.resize(n, 0.0);
    s.parabola_at.resize(n, 0);
    s.boundary.resize(n + 1, 0.0);
    let f = &s.line;
    let height = |q: usize| f[q] as f64 + (q * q) as f64;
    let mut k = 0usize;
    s.parabola_at[0] = 0;
    s.boundary[0] = f64::NEG_INFINITY;
    s.boundary[1] = f64::INFINITY;
    for q in 1..n {
        // boundary[0] is −∞, so k never goes below 0.
        let mut cross;
        loop {
            let p = s.parabola_at[k];
            cross = (height(q) - height(p)) / (2.0 * (q - p) as f64);
            if cross > s.boundary[k] {
                break;
            }
            k -= 1;
        }
        k += 1;
        s.parabola_at[k] = q;
        s.boundary[k] = cross;
        s.boundary[k + 1] = f64::INFINITY;
    }
    k = 0;
    for q in 0..n {
        while s.boundary[k + 1] < q as f64 {
            k += 1;
        }
        let p = s.parabola_at[k];
        let d = q as f64 - p as f64;
        s.out[q] = (d * d + f[p] as f64) as f32;
    }
}

/// Separable Gaussian blur of `sigma` samples, edges clamped.
fn gaussian_smooth(values: &mut [f32], dims: [usize; 3], sigma: f64) {
    let radius = (2.5 * sigma).ceil() as usize;
    let weights: Vec<f32> = (0..=radius)
        .map(|r| (-((r * r) as f64) / (2.0 * sigma * sigma)).exp() as f32)
        .collect();
    let total: f32 = weights[0] + 2.0 * weights[1..].iter().sum::<f32>();
    let weights: Vec<f32> = weights.iter().map(|w| w / total).collect();
    let op = |s: &mut LineScratch| {
        let n = s.line.len();
        s.out.resize(n, 0.0);
        for q in 0..n {
            let mut acc = weights[0] * s.line[q];
            for (r, &w) in weights.iter().enumerate().skip(1) {
                let lo = q.saturating_sub(r);
                let hi = (q + r).min(n - 1);
                acc += w * (s.line[lo] + s.line[hi]);
            }
            s.out[q] = acc;
        }
    };
    for axis in 0..3 {
        transform_lines(values, dims, axis, &op);
    }
}

/// The hilum centre node of `lung` and where it came from.
fn hilum_centre(
    lungs: &Volume<u8>,
    airways: &Volume<u8>,
    lung: u8,
    lung_surface: &[u32],
    normals: &[Vector3<f64>],
    positions_mm: &[Vector3<f64>],
) -> (u32, String) {
    let g = &lungs.geometry;
    let [nx, ny, _] = g.dims;
    // Airway voxels with a 26-neighbour in this lung: where the bronchus enters.
    let (count, sum) = airways
        .as_slice()
        .par_chunks(nx * ny)
        .enumerate()
        .map(|(k, slab)| {
            let mut count = 0usize;
            let mut sum = Vector3::zeros();
            for (idx, &v) in slab.iter().enumerate() {
                if v == 0 {
                    continue;
                }
                let (i, j) = (idx % nx, idx / nx);
                let touches = (0..27).any(|o| {
                    let d = [o % 3, o / 3 % 3, o / 9];
                    let q = [i + d[0], j + d[1], k + d[2]];
                    q.iter().zip(g.dims).all(|(&c, n)| c >= 1 && c <= n)
                        && lungs.get(q[0] - 1, q[1] - 1, q[2] - 1) == lung
                });
                if touches {
                    count += 1;
                    sum += g.voxel_to_lps_mm(Vector3::new(i as f64, j as f64, k as f64));
                }
            }
            (count, sum)
        })
        .reduce(|| (0, Vector3::zeros()), |a, b| (a.0 + b.0, a.1 + b.1));
    let nearest_to = |target: Vector3<f64>, candidates: &mut dyn Iterator<Item = u32>| {
        candidates
            .min_by(|&a, &b| {
                (positions_mm[a as usize] - target)
                    .norm_squared()
                    .total_cmp(&(positions_mm[b as usize] - target).norm_squared())
            })
            .expect("a lung with elements has surface nodes")
    };
    if count > 0 {
        let entry = sum / count as f64;
        let centre = nearest_to(entry, &mut lung_surface.iter().copied());
        return (
            centre,
            format!(
                "airway contact: {count} voxels centred at ({:.1}, {:.1}, {:.1}) mm",
                entry.x, entry.y, entry.z
            ),
        );
    }
    // Geometric: the mediastinal face's node nearest to the face's centre in y and z.
    let medial = medial_direction(lung);
    let face: Vec<u32> = lung_surface
        .iter()
        .zip(normals)
        .filter(|(_, n)| n.dot(&medial) >= 0.5)
        .map(|(&n, _)| n)
        .collect();
    let face = if face.is_empty() {
        lung_surface.to_vec()
    } else {
        face
    };
    let centre_yz = face
        .iter()
        .map(|&n| positions_mm[n as usize])
        .sum::<Vector3<f64>>()
        / face.len() as f64;
    let centre = face
        .iter()
        .copied()
        .min_by(|&a, &b| {
            let key = |n: u32| {
                let p = positions_mm[n as usize];
                let yz = (p.y - centre_yz.y).powi(2) + (p.z - centre_yz.z).powi(2);
                // Ties (same y, z) go to the most medial node.
                (yz, -p.dot(&medial))
            };
            let (ka, kb) = (key(a), key(b));
            ka.0.total_cmp(&kb.0).then(ka.1.total_cmp(&kb.1))
        })
        .expect("face is not empty");
    (
        centre,
        "geometric: no airway contact; centre of the mediastinal face".to_string(),
    )
}

/// Unit vector from a lung towards the midline: the right lung lies at −x (patient right).
fn medial_direction(lung: u8) -> Vector3<f64> {
    if lung == RIGHT_LUNG {
        Vector3::x()
    } else {
        -Vector3::x()
    }
}

/// Assigns groups to one lung's surface nodes (see the module doc for the rules).
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

/// Paints each lung-surface voxel of the CT grid with the group of the nearest surface node
/// of the same lung.
#[allow(clippy::too_many_arguments)]
fn paint_groups(
    lungs: &Volume<u8>,
    lattice: &CellLattice,
    node_lattice: &[[u32; 3]],
    node_lung: &[u8],
    surface: &[u32],
    node_group: &[u8],
    positions_mm: &[Vector3<f64>],
) -> Result<Volume<u8>> {
    // Surface node at each lattice point, one slot per lung.
    let pdims = lattice.cells.map(|c| c + 1);
    let mut at = vec![[u32::MAX; 2]; pdims.iter().product()];
    for &n in surface {
        let l = node_lattice[n as usize];
        let idx = l[0] as usize + pdims[0] * (l[1] as usize + pdims[1] * l[2] as usize);
        at[idx][(node_lung[n as usize] - 1) as usize] = n;
    }
    let g = &lungs.geometry;
    let [nx, ny, nz] = g.dims;
    let mut out = vec![0u8; lungs.as_slice().len()];
    let origin = lattice.point_mm([0, 0, 0]);
    out.par_chunks_mut(nx * ny)
        .enumerate()
        .for_each(|(k, slab)| {
            for j in 0..ny {
                for i in 0..nx {
                    let lung = lungs.get(i, j, k);
                    if lung == 0 {
                        continue;
                    }
                    let boundary = (0..6).any(|f| {
                        let d: [i64; 3] = match f {
                            0 => [-1, 0, 0],
                            1 => [1, 0, 0],
                            2 => [0, -1, 0],
                            3 => [0, 1, 0],
                            4 => [0, 0, -1],
                            _ => [0, 0, 1],
                        };
                        let q = [i as i64 + d[0], j as i64 + d[1], k as i64 + d[2]];
                        q[0] < 0
                            || q[1] < 0
                            || q[2] < 0
                            || q[0] >= nx as i64
                            || q[1] >= ny as i64
                            || q[2] >= nz as i64
                            || lungs.get(q[0] as usize, q[1] as usize, q[2] as usize) != lung
                    });
                    if !boundary {
                        continue;
                    }
                    let p = g.voxel_to_lps_mm(Vector3::new(i as f64, j as f64, k as f64));
                    let u = (p - origin) / lattice.h_mm;
                    let slot = (lung - 1) as usize;
                    let mut best = (f64::INFINITY, u32::MAX);
                    for reach in [2i64, 4, 8] {
                        let c = [u.x.round() as i64, u.y.round() as i64, u.z.round() as i64];
                        for dk in -reach..=reach {
                            for dj in -reach..=reach {
                                for di in -reach..=reach {
                                    let q = [c[0] + di, c[1] + dj, c[2] + dk];
                                    if (0..3).any(|a| q[a] < 0 || q[a] >= pdims[a] as i64) {
                                        continue;
                                    }
                                    let idx = q[0] as usize
                                        + pdims[0] * (q[1] as usize + pdims[1] * q[2] as usize);
                                    let n = at[idx][slot];
                                    if n == u32::MAX {
                                        continue;
                                    }
                                    let d = (positions_mm[n as usize] - p).norm_squared();
                                    if d < best.0 {
                                        best = (d, n);
                                    }
                                }
                            }
                        }
                        if best.1 != u32::MAX {
                            break;
                        }
                    }
                    if best.1 != u32::MAX {
                        slab[i + nx * j] = node_group[best.1 as usize];
                    }
                }
            }
        });
    Volume::from_data(lungs.geometry, out)
}
