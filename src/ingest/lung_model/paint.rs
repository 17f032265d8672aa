//! The groups painted on the CT grid: each lung-surface voxel takes the group of the nearest
//! surface node of the same lung (`groups.nii.gz`).

use nalgebra::Vector3;
use rayon::prelude::*;

use super::lattice::CellLattice;
use super::mesh::LungMeshes;
use crate::volume::Volume;
use crate::Result;

/// Paints each lung-surface voxel of the CT grid with the group of the nearest surface node
/// of the same lung.
pub(super) fn paint_groups(
    lungs: &Volume<u8>,
    lattice: &CellLattice,
    meshes: &LungMeshes,
    node_group: &[u8],
) -> Result<Volume<u8>> {
    let index = SurfaceNodeIndex::new(lattice, meshes);
    let g = &lungs.geometry;
    let [nx, ny, _] = g.dims;
    let mut out = vec![0u8; lungs.as_slice().len()];
    let origin = lattice.point_mm([0, 0, 0]);
    out.par_chunks_mut(nx * ny)
        .enumerate()
        .for_each(|(k, slab)| {
            for j in 0..ny {
                for i in 0..nx {
                    let lung = lungs.get(i, j, k);
                    if lung == 0 || !is_surface_voxel(lungs, [i, j, k], lung) {
                        continue;
                    }
                    let p = g.voxel_to_lps_mm(Vector3::new(i as f64, j as f64, k as f64));
                    let u = (p - origin) / lattice.h_mm;
                    let slot = (lung - 1) as usize;
                    if let Some(n) = index.nearest(u, p, slot, &meshes.positions_mm) {
                        slab[i + nx * j] = node_group[n as usize];
                    }
                }
            }
        });
    Volume::from_data(lungs.geometry, out)
}

/// Whether voxel `ijk` of `lung` has a 6-neighbour outside its lung (or outside the grid).
fn is_surface_voxel(lungs: &Volume<u8>, ijk: [usize; 3], lung: u8) -> bool {
    let [nx, ny, nz] = lungs.geometry.dims;
    let [i, j, k] = ijk;
    (0..6).any(|f| {
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
    })
}

/// The surface node at each lattice point, one slot per lung (`u32::MAX` for none).
struct SurfaceNodeIndex {
    /// Lattice points along x, y, z.
    pdims: [usize; 3],
    /// Right- and left-lung surface node per lattice point.
    at: Vec<[u32; 2]>,
}

impl SurfaceNodeIndex {
    /// Indexes the surface nodes of `meshes` on `lattice`.
    fn new(lattice: &CellLattice, meshes: &LungMeshes) -> Self {
        let pdims = lattice.cells.map(|c| c + 1);
        let mut at = vec![[u32::MAX; 2]; pdims.iter().product()];
        for &n in &meshes.surface {
            let l = meshes.grid_mesh.node_lattice[n as usize];
            let idx = l[0] as usize + pdims[0] * (l[1] as usize + pdims[1] * l[2] as usize);
            at[idx][(meshes.node_lung[n as usize] - 1) as usize] = n;
        }
        SurfaceNodeIndex { pdims, at }
    }

    /// The `slot` lung's surface node nearest to `p_mm` (at lattice coordinates `u`), searched
    /// in growing boxes of 2, 4 and 8 lattice points around `u`.
    fn nearest(
        &self,
        u: Vector3<f64>,
        p_mm: Vector3<f64>,
        slot: usize,
        positions_mm: &[Vector3<f64>],
    ) -> Option<u32> {
        let pdims = self.pdims;
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
                        let idx =
                            q[0] as usize + pdims[0] * (q[1] as usize + pdims[1] * q[2] as usize);
                        let n = self.at[idx][slot];
                        if n == u32::MAX {
                            continue;
                        }
                        let d = (positions_mm[n as usize] - p_mm).norm_squared();
                        if d < best.0 {
                            best = (d, n);
                        }
                    }
                }
            }
            if best.1 != u32::MAX {
                return Some(best.1);
            }
        }
        None
    }
}
