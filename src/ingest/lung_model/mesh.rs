//! One mesh per lung on the shared lattice, concatenated so the lungs share no node, and the
//! nodes on its external surface.

use std::collections::BTreeMap;

use nalgebra::Vector3;

use super::cells::LungCells;
use super::lattice::CellLattice;
use super::settings::lung_name;
use crate::model::grid::GridMesh;
use crate::model::{HexMesh, Material};
use crate::{Error, Result};

/// Both lungs' elements and nodes, right lung first.
pub(super) struct LungMeshes {
    /// The concatenated mesh in metres with each node's lattice point and element's cell.
    pub(super) grid_mesh: GridMesh,
    /// Lung of each element.
    pub(super) element_lung: Vec<u8>,
    /// Lung of each node.
    pub(super) node_lung: Vec<u8>,
    /// Elements per lung name.
    pub(super) elements_per_lung: BTreeMap<String, usize>,
    /// Nodes on the external surface, ascending.
    pub(super) surface: Vec<u32>,
    /// Rest position of each node in LPS millimetres.
    pub(super) positions_mm: Vec<Vector3<f64>>,
}

/// Meshes each lung's cells on the same lattice and concatenates the meshes: the lungs share
/// no node. Fails when no element survives in either lung.
pub(super) fn mesh_lungs(
    lattice: &CellLattice,
    cells: &LungCells,
    material: Material,
    voxels_per_lung: [usize; 2],
) -> Result<LungMeshes> {
    let h_mm = lattice.h_mm;
    let mut positions = Vec::new();
    let mut elements: Vec<[u32; 8]> = Vec::new();
    let mut node_lattice = Vec::new();
    let mut element_cell = Vec::new();
    let mut element_lung = Vec::new();
    let mut node_lung = Vec::new();
    let mut classes = Vec::new();
    let mut elements_per_lung = BTreeMap::new();
    for (lung, mask) in &cells.masks {
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
        let gm = lattice
            .grid(mask.clone())
            .to_mesh_in_lattice_order(material)?;
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
    let surface = surface_nodes(&mesh);
    let positions_mm: Vec<Vector3<f64>> = mesh.rest_positions_m.iter().map(|p| p * 1e3).collect();
    Ok(LungMeshes {
        grid_mesh: GridMesh {
            mesh,
            node_lattice,
            element_cell,
        },
        element_lung,
        node_lung,
        elements_per_lung,
        surface,
        positions_mm,
    })
}

/// Nodes on an external face, ascending.
fn surface_nodes(mesh: &HexMesh) -> Vec<u32> {
    let n_nodes = mesh.node_count();
    let mut on_surface = vec![false; n_nodes];
    for f in &mesh.external_faces {
        for &n in f {
            on_surface[n as usize] = true;
        }
    }
    (0..n_nodes as u32)
        .filter(|&n| on_surface[n as usize])
        .collect()
}
