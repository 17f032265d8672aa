//! The files `lungmotion ingest` writes, so a physicist can check an ingest at a glance and
//! other tools can script against it:
//!
//! | file | content |
//! | --- | --- |
//! | `lung-mask.nii.gz` | uint8 on the CT's grid and affine: 0 background, 1 right lung, 2 left lung |
//! | `groups.nii.gz` | uint8 on the CT's grid: constraint group of each lung-surface voxel (codes in `ingest.json`) |
//! | `ingest.json` | volumes, element and node counts, group legend and node counts, reports |
//! | `surface.vtp` | the model's outer surface in LPS mm, cell data `group` (each face's group), point data `group`, `node_id`, `displacement_mm` (ParaView) |
//! | `mesh.vtu` | the cubic elements in LPS mm, point data `group` (each node's group) and `displacement_mm`, cell data `lung` (1 right, 2 left) and `material_class` |
//! | `quicklook-{axial,coronal,sagittal}.png` | CT (lung window) with lung outlines and groups, titled, with orientation letters and a legend (see [`ingest_quicklooks`](crate::outputs::ingest_quicklooks)) |

use std::path::{Path, PathBuf};

use nalgebra::Vector3;

use crate::durable::write_atomic;
use crate::formats::{nifti, vtk};
use crate::ingest::lung_model::ConstraintGroup;
use crate::ingest::pipeline::IngestOutcome;
use crate::model::HexMesh;
use crate::outputs::ingest_quicklooks::write_ingest_quicklooks;
use crate::volume::Volume;
use crate::Result;

/// Colours of the lung labels in quick looks: right lung blue, left lung orange.
pub const LUNG_PALETTE: [(u8, [u8; 3]); 2] = [(1, [70, 150, 255]), (2, [255, 150, 40])];

/// Colours of the constraint groups in quick looks.
pub fn group_palette() -> Vec<(u8, [u8; 3])> {
    ConstraintGroup::ALL
        .iter()
        .map(|&g| {
            let rgb = match g {
                ConstraintGroup::Hilum => [230, 30, 30],
                ConstraintGroup::Mediastinal => [250, 220, 40],
                ConstraintGroup::Costal => [40, 200, 80],
                ConstraintGroup::Diaphragmatic => [60, 120, 255],
                ConstraintGroup::Apex => [220, 60, 220],
            };
            (g.code(), rgb)
        })
        .collect()
}

/// Writes every ingest output into `out_dir` (which must exist); returns the paths written.
pub fn write_ingest_outputs(
    out_dir: &Path,
    ct: &Volume<f32>,
    outcome: &IngestOutcome,
) -> Result<Vec<PathBuf>> {
    let mut written = Vec::new();
    let mut path = |name: &str| {
        let p = out_dir.join(name);
        written.push(p.clone());
        p
    };

    nifti::write_nifti_labels(&path("lung-mask.nii.gz"), &outcome.segmentation.lungs)?;
    nifti::write_nifti_labels(&path("groups.nii.gz"), &outcome.model.groups_volume)?;

    let model = &outcome.model;
    let mesh = &model.mesh.mesh;
    let face_group = face_groups(&mesh.external_faces, &model.node_group);
    let mut surface = vtk::surface_from_hex_mesh(mesh, &mesh.rest_positions_m, Some(&face_group))?;
    let surface_node_group = match surface.point_data.iter().find(|(n, _)| n == "node_id") {
        Some((_, vtk::DataArray::ScalarsI32(ids))) => {
            ids.iter().map(|&n| model.node_group[n as usize]).collect()
        }
        _ => Vec::new(),
    };
    surface.point_data.push((
        "group".to_string(),
        vtk::DataArray::ScalarsU8(surface_node_group),
    ));
    vtk::write_vtp_surface(&path("surface.vtp"), &surface)?;
    let volume_mesh = lung_mesh_vtu(
        mesh,
        &mesh.rest_positions_m,
        &model.element_lung,
        &model.node_group,
    )?;
    vtk::write_vtu(&path("mesh.vtu"), &volume_mesh)?;

    let json = serde_json::to_string_pretty(&outcome.summary)
        .map_err(|e| crate::Error::Ingest(format!("cannot serialise ingest.json: {e}")))?;
    write_atomic(&path("ingest.json"), json.as_bytes())?;

    let looks = write_ingest_quicklooks(
        out_dir,
        ct,
        &outcome.segmentation.lungs,
        &model.groups_volume,
    )?;
    written.extend(looks.into_iter().map(|l| l.path));
    Ok(written)
}

/// The lung mesh at `positions_m` for ParaView, as the ingest and every frame write it:
/// point data `displacement_mm` and `group` (the node's constraint group code, 0 interior),
/// cell data `lung` (1 right, 2 left) and `material_class`.
pub fn lung_mesh_vtu(
    mesh: &HexMesh,
    positions_m: &[Vector3<f64>],
    element_lung: &[u8],
    node_group: &[u8],
) -> Result<vtk::VtuMesh> {
    if element_lung.len() != mesh.elements.len() || node_group.len() != mesh.node_count() {
        return Err(crate::Error::argument(
            "lung mesh labels",
            format!(
                "{} lung labels for {} elements and {} group codes for {} nodes",
                element_lung.len(),
                mesh.elements.len(),
                node_group.len(),
                mesh.node_count()
            ),
        ));
    }
    let mut vtu = vtk::vtu_from_hex_mesh(mesh, positions_m)?;
    vtu.point_data.push((
        "group".to_string(),
        vtk::DataArray::ScalarsU8(node_group.to_vec()),
    ));
    vtu.cell_data.insert(
        0,
        (
            "lung".to_string(),
            vtk::DataArray::ScalarsU8(element_lung.to_vec()),
        ),
    );
    Ok(vtu)
}

/// The group of each external face: the most frequent non-zero group of its four nodes
/// (ties to the lower code, so the fixed hilum wins over sliding surfaces).
pub fn face_groups(faces: &[[u32; 4]], node_group: &[u8]) -> Vec<u8> {
    faces
        .iter()
        .map(|f| {
            let mut counts = [0u8; 256];
            for &n in f {
                counts[node_group[n as usize] as usize] += 1;
            }
            (1..=255u8)
                .max_by_key(|&g| (counts[g as usize], std::cmp::Reverse(g)))
                .filter(|&g| counts[g as usize] > 0)
                .unwrap_or(0)
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_face_takes_its_majority_group_and_ties_go_to_the_fixed_hilum() {
        let node_group = [0u8, 1, 3, 3, 3, 2];
        let faces = [[2, 3, 4, 1], [0, 1, 2, 0], [0, 0, 0, 0], [1, 5, 0, 0]];
        assert_eq!(face_groups(&faces, &node_group), vec![3, 1, 0, 1]);
    }
}
