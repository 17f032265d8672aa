//! The files `lungmotion ingest` writes, so a physicist can check an ingest at a glance and
//! other tools can script against it:
//!
//! | file | content |
//! | --- | --- |
//! | `lung-mask.nii.gz` | uint8 on the CT's grid and affine: 0 background, 1 right lung, 2 left lung |
//! | `groups.nii.gz` | uint8 on the CT's grid: constraint group of each lung-surface voxel (codes in `ingest.json`) |
//! | `ingest.json` | volumes, element and node counts, group legend and node counts, reports |
//! | `surface.vtp` | the model's outer surface in LPS mm, cell data `group` (ParaView) |
//! | `mesh.vtu` | the cubic elements in LPS mm, cell data `lung` (1 right, 2 left), point data `group` |
//! | `quicklook-{axial,coronal,sagittal}.png` | CT (lung window) with lung outlines and groups |

use std::path::{Path, PathBuf};

use nalgebra::Vector3;

use crate::durable::write_atomic;
use crate::formats::{nifti, vtk};
use crate::ingest::lung_model::ConstraintGroup;
use crate::ingest::pipeline::IngestOutcome;
use crate::outputs::quicklook::{write_overview, Overlay};
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
    let surface = vtk::surface_from_hex_mesh(mesh, &mesh.rest_positions_m, Some(&face_group))?;
    vtk::write_vtp_surface(&path("surface.vtp"), &surface)?;
    let mut volume_mesh = vtk::vtu_from_hex_mesh(mesh, &mesh.rest_positions_m)?;
    volume_mesh.cell_data.push((
        "lung".to_string(),
        vtk::DataArray::ScalarsU8(model.element_lung.clone()),
    ));
    volume_mesh.point_data.push((
        "group".to_string(),
        vtk::DataArray::ScalarsU8(model.node_group.clone()),
    ));
    vtk::write_vtu(&path("mesh.vtu"), &volume_mesh)?;

    let json = serde_json::to_string_pretty(&outcome.summary)
        .map_err(|e| crate::Error::Ingest(format!("cannot serialise ingest.json: {e}")))?;
    write_atomic(&path("ingest.json"), json.as_bytes())?;

    let palette = group_palette();
    let overlays = [
        Overlay {
            labels: &outcome.segmentation.lungs,
            palette: &LUNG_PALETTE,
            opacity: 1.0,
            outline_only: true,
        },
        Overlay {
            labels: &model.groups_volume,
            palette: &palette,
            opacity: 0.9,
            outline_only: false,
        },
    ];
    let centre = lung_centroid_lps_mm(&outcome.segmentation.lungs);
    written.extend(write_overview(ct, &overlays, centre, out_dir, "quicklook")?);
    Ok(written)
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

/// Centre of mass of the lung voxels, in LPS mm (the grid centre if there are none).
pub fn lung_centroid_lps_mm(lungs: &Volume<u8>) -> [f64; 3] {
    let g = &lungs.geometry;
    let [nx, ny, _] = g.dims;
    let (mut sum, mut n) = (Vector3::zeros(), 0usize);
    for (idx, &v) in lungs.as_slice().iter().enumerate() {
        if v != 0 {
            let (i, j, k) = (idx % nx, (idx / nx) % ny, idx / (nx * ny));
            sum += Vector3::new(i as f64, j as f64, k as f64);
            n += 1;
        }
    }
    let ijk = if n > 0 {
        sum / n as f64
    } else {
        Vector3::from(g.dims.map(|d| (d as f64 - 1.0) / 2.0))
    };
    g.voxel_to_lps_mm(ijk).into()
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
