//! Where each lung's hilum is: the surface node nearest to where the airways touch the lung,
//! or without airway contact the centre of the mediastinal face.

use nalgebra::Vector3;
use rayon::prelude::*;

use super::settings::RIGHT_LUNG;
use crate::volume::Volume;

/// The hilum centre node of `lung` and where it came from.
pub(super) fn hilum_centre(
    lungs: &Volume<u8>,
    airways: &Volume<u8>,
    lung: u8,
    lung_surface: &[u32],
    normals: &[Vector3<f64>],
    positions_mm: &[Vector3<f64>],
) -> (u32, String) {
    let (count, sum) = airway_contact(lungs, airways, lung);
    if count > 0 {
        let entry = sum / count as f64;
        let centre = lung_surface
            .iter()
            .copied()
            .min_by(|&a, &b| {
                (positions_mm[a as usize] - entry)
                    .norm_squared()
                    .total_cmp(&(positions_mm[b as usize] - entry).norm_squared())
            })
            .expect("a lung with elements has surface nodes");
        return (
            centre,
            format!(
                "airway contact: {count} voxels centred at ({:.1}, {:.1}, {:.1}) mm",
                entry.x, entry.y, entry.z
            ),
        );
    }
    (
        mediastinal_face_centre(lung, lung_surface, normals, positions_mm),
        "geometric: no airway contact; centre of the mediastinal face".to_string(),
    )
}

/// How many airway voxels have a 26-neighbour in `lung` (where the bronchus enters), and the
/// sum of their LPS positions in millimetres.
fn airway_contact(lungs: &Volume<u8>, airways: &Volume<u8>, lung: u8) -> (usize, Vector3<f64>) {
    let g = &lungs.geometry;
    let [nx, ny, _] = g.dims;
    airways
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
        .reduce(|| (0, Vector3::zeros()), |a, b| (a.0 + b.0, a.1 + b.1))
}

/// The mediastinal face's node nearest to the face's centre in y and z (the whole surface
/// when the lung has no mediastinal face).
fn mediastinal_face_centre(
    lung: u8,
    lung_surface: &[u32],
    normals: &[Vector3<f64>],
    positions_mm: &[Vector3<f64>],
) -> u32 {
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
    face.iter()
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
        .expect("face is not empty")
}

/// Unit vector from a lung towards the midline: the right lung lies at −x (patient right).
pub(super) fn medial_direction(lung: u8) -> Vector3<f64> {
    if lung == RIGHT_LUNG {
        Vector3::x()
    } else {
        -Vector3::x()
    }
}
