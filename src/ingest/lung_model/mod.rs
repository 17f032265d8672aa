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
//!   constraint on the wall's zero level would deform the lung with no load. By default
//!   each sliding node therefore slides on the wall's tangent plane through its rest position
//!   ([`NodeConstraint::Plane`], normal from the wall): exact at rest, smooth normals.
//!   [`SlidingMode::WallSurface`] holds it on the curved wall instead, on the level of the
//!   wall's cubic B-spline through its rest position ([`NodeConstraint::Surface`]), except at
//!   ridges of the field ([`MIN_SURFACE_GRADIENT`]), where it keeps its plane. A wall bent to pass
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

#[cfg(doc)]
use crate::model::{NodeConstraint, VoxelGrid};

mod build;
mod cells;
mod constraints;
mod groups;
mod hilum;
mod lattice;
mod mesh;
mod paint;
mod report;
mod settings;
mod tissue;
mod wall;
mod wall_distance;

pub use build::{build_lung_model, build_lung_model_with, LungModel};
pub use constraints::MIN_SURFACE_GRADIENT;
pub use groups::{BoundaryCondition, ConstraintGroup, DIAPHRAGM_MAX_NORMAL_Z};
pub use report::LungModelReport;
pub use settings::{
    DiaphragmMotion, LungModelSettings, SlidingMode, DEFAULT_ELEMENT_SIZE_MM, LEFT_LUNG,
    MAX_ELEMENT_SIZE_MM, MIN_ELEMENT_SIZE_MM, RIGHT_LUNG,
};
pub use tissue::{element_tissue, sample_element_density};
pub use wall::PrebuiltWall;
