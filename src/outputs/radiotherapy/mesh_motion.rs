//! The lung mesh's own motion at one instant as a [`PhaseMotion`]: the elements' trilinear
//! interpolation inside the lungs, zero outside. The exact motion the tracked points follow
//! (`trajectories.csv`), used where the motion over the whole CT is not wanted or not built.

use super::PhaseMotion;
use crate::math::V3;
use crate::model::{CubeLattice, HexMesh};
use crate::outputs::displacement_field::corner_weight;
use crate::Result;

/// Fixed-point iterations of [`MeshMotion::source_lps_mm`] before it gives its best estimate.
const INVERSE_ITERATIONS: usize = 60;
/// Residual |x + u(x) − y| at which the inverse stops, mm.
const INVERSE_TOLERANCE_MM: f64 = 1e-5;

/// Where each element of a cube-lattice mesh sits, to find the element holding a point in
/// O(1). Built once per run (the rest mesh does not change).
#[derive(Debug, Clone)]
pub struct MeshLattice(CubeLattice);

impl MeshLattice {
    /// Recovers the lattice of `mesh`'s equal cubes (the first element of a cell both lungs
    /// claim); refuses a mesh that is not one.
    pub fn of(mesh: &HexMesh) -> Result<Self> {
        CubeLattice::of_cells(mesh).map(MeshLattice)
    }

    /// The element holding `p_m` and the point's place in it (0…1 per axis), if any.
    pub fn locate(&self, p_m: V3) -> Option<(u32, V3)> {
        let (cell, f) = self.0.cell_of(p_m);
        let e = self.0.any_element_at(cell)?;
        Some((
            e,
            f - V3::new(cell[0] as f64, cell[1] as f64, cell[2] as f64),
        ))
    }
}

/// The mesh's motion at one instant: node positions over the rest mesh.
pub struct MeshMotion<'a> {
    lattice: &'a MeshLattice,
    mesh: &'a HexMesh,
    positions_m: &'a [V3],
}

impl<'a> MeshMotion<'a> {
    /// The motion that takes `mesh`'s rest nodes to `positions_m` (metres, LPS).
    pub fn new(lattice: &'a MeshLattice, mesh: &'a HexMesh, positions_m: &'a [V3]) -> Self {
        MeshMotion {
            lattice,
            mesh,
            positions_m,
        }
    }

    /// Displacement of the tissue at rest point `p_m`, metres; zero outside every element.
    fn displacement_m(&self, p_m: V3) -> V3 {
        let Some((e, local)) = self.lattice.locate(p_m) else {
            return V3::zeros();
        };
        let rest = &self.mesh.rest_positions_m;
        let mut u = V3::zeros();
        for (corner, &n) in self.mesh.elements[e as usize].iter().enumerate() {
            let n = n as usize;
            u += (self.positions_m[n] - rest[n]) * corner_weight(local, corner);
        }
        u
    }
}

impl PhaseMotion for MeshMotion<'_> {
    fn moved_lps_mm(&self, rest_lps_mm: [f64; 3]) -> [f64; 3] {
        let p = V3::from(rest_lps_mm);
        (p + self.displacement_m(p * 1e-3) * 1e3).into()
    }

    fn source_lps_mm(&self, moved_lps_mm: [f64; 3]) -> [f64; 3] {
        // x = y − u(x): converges where the motion's gradient stays below 1, as breathing's does.
        let y = V3::from(moved_lps_mm);
        let mut x = y;
        for _ in 0..INVERSE_ITERATIONS {
            let next = y - self.displacement_m(x * 1e-3) * 1e3;
            let step = (next - x).norm();
            x = next;
            if step < INVERSE_TOLERANCE_MM {
                break;
            }
        }
        x.into()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::{HexMesh, Material, VoxelGrid};

    /// A 2 × 1 × 1 block of 10 mm cubes at the origin.
    fn block() -> HexMesh {
        VoxelGrid::filled_box([2, 1, 1], [0.01; 3], V3::zeros())
            .to_mesh(Material::LUNG)
            .unwrap()
            .mesh
    }

    #[test]
    fn a_linear_stretch_is_reproduced_inside_and_is_zero_outside_and_inverts() {
        let mesh = block();
        let lattice = MeshLattice::of(&mesh).unwrap();
        // u = (0.1·x, 0, −0.05·z): linear, so the elements carry it exactly.
        let positions: Vec<V3> = mesh
            .rest_positions_m
            .iter()
            .map(|p| V3::new(p.x * 1.1, p.y, p.z * 0.95))
            .collect();
        let motion = MeshMotion::new(&lattice, &mesh, &positions);
        let p = [13.0, 4.0, 7.0];
        let moved = motion.moved_lps_mm(p);
        assert!(
            (moved[0] - 14.3).abs() < 1e-9 && (moved[2] - 6.65).abs() < 1e-9,
            "{moved:?}"
        );
        assert_eq!(motion.moved_lps_mm([35.0, 4.0, 7.0]), [35.0, 4.0, 7.0]);
        let back = motion.source_lps_mm(moved);
        assert!(
            (0..3).all(|a| (back[a] - p[a]).abs() < 1e-4),
            "{back:?} is not {p:?}"
        );
    }
}
