//! Regular grids of brick elements: a box, or the voxels of a mask. Ingest builds lung
//! meshes through [`VoxelGrid`]; validation builds beams and blocks.

use std::collections::HashMap;

use nalgebra::{Matrix3, Vector3};

use super::element::{BrickCoefficients, BrickShape, CORNER_SIGNS};
use super::material::Material;
use super::mesh::HexMesh;
use crate::{Error, Result};

/// A regular lattice of optional brick elements, placed in space by an origin and axes.
#[derive(Debug, Clone)]
pub struct VoxelGrid {
    /// Number of element cells along the grid's i, j, k axes.
    pub cells: [usize; 3],
    /// Cell edge lengths along i, j, k in metres.
    pub cell_size_m: [f64; 3],
    /// World position of the lattice point (0, 0, 0) in metres.
    pub origin_m: Vector3<f64>,
    /// Unit world directions of the grid's i, j, k axes, as columns (a rotation).
    pub axes: Matrix3<f64>,
    /// Whether each cell holds an element, i fastest.
    pub active: Vec<bool>,
}

/// A mesh built from a grid, with the lattice coordinates of its nodes and elements.
#[derive(Debug, Clone)]
pub struct GridMesh {
    /// The mechanical mesh.
    pub mesh: HexMesh,
    /// Lattice point (i, j, k) of each node.
    pub node_lattice: Vec<[u32; 3]>,
    /// Cell (i, j, k) of each element.
    pub element_cell: Vec<[u32; 3]>,
}

impl VoxelGrid {
    /// A full axis-aligned box of `cells` elements of `cell_size_m`, lattice point 0 at `origin_m`.
    pub fn filled_box(cells: [usize; 3], cell_size_m: [f64; 3], origin_m: Vector3<f64>) -> Self {
        VoxelGrid {
            cells,
            cell_size_m,
            origin_m,
            axes: Matrix3::identity(),
            active: vec![true; cells.iter().product()],
        }
    }

    /// Linear index of cell (i, j, k).
    pub fn cell_index(&self, i: usize, j: usize, k: usize) -> usize {
        i + self.cells[0] * (j + self.cells[1] * k)
    }

    /// World position in metres of lattice point (i, j, k).
    pub fn lattice_point_m(&self, i: usize, j: usize, k: usize) -> Vector3<f64> {
        let local = Vector3::new(
            i as f64 * self.cell_size_m[0],
            j as f64 * self.cell_size_m[1],
            k as f64 * self.cell_size_m[2],
        );
        self.origin_m + self.axes * local
    }

    /// Builds the mass–spring mesh of the active cells, all of one material, its nodes
    /// numbered in order of first use by the cells (x fastest).
    pub fn to_mesh(&self, material: Material) -> Result<GridMesh> {
        self.build_mesh(material, false)
    }

    /// [`VoxelGrid::to_mesh`] with the nodes numbered in lattice order (x fastest, then y,
    /// then z): a node's neighbours along x are then consecutive numbers in every row, which
    /// the multigrid's stencil product needs (in first-use order only 60 % of the CIP lungs'
    /// nodes at 4 mm had consecutive rows).
    pub fn to_mesh_in_lattice_order(&self, material: Material) -> Result<GridMesh> {
        self.build_mesh(material, true)
    }

    fn build_mesh(&self, material: Material, lattice_order: bool) -> Result<GridMesh> {
        let n_cells: usize = self.cells.iter().product();
        if self.active.len() != n_cells {
            return Err(Error::InvalidModel(format!(
                "grid of {:?} cells has {} activity flags",
                self.cells,
                self.active.len()
            )));
        }
        if (self.axes.transpose() * self.axes - Matrix3::identity()).norm() > 1e-9
            || self.axes.determinant() <= 0.0
        {
            return Err(Error::InvalidModel(
                "grid axes must be a right-handed orthonormal frame".into(),
            ));
        }
        let coeffs = BrickCoefficients::new(
            BrickShape {
                edges_m: self.cell_size_m,
            },
            material,
        )?;
        let mut node_of: HashMap<[u32; 3], u32> = HashMap::new();
        let mut node_lattice = Vec::new();
        let mut positions = Vec::new();
        let mut elements = Vec::new();
        let mut element_cell = Vec::new();
        for k in 0..self.cells[2] {
            for j in 0..self.cells[1] {
                for i in 0..self.cells[0] {
                    if !self.active[self.cell_index(i, j, k)] {
                        continue;
                    }
                    let corners = CORNER_SIGNS.map(|s| {
                        let l = [
                            (i + (s[0] > 0.0) as usize) as u32,
                            (j + (s[1] > 0.0) as usize) as u32,
                            (k + (s[2] > 0.0) as usize) as u32,
                        ];
                        *node_of.entry(l).or_insert_with(|| {
                            node_lattice.push(l);
                            positions.push(self.lattice_point_m(
                                l[0] as usize,
                                l[1] as usize,
                                l[2] as usize,
                            ));
                            (positions.len() - 1) as u32
                        })
                    });
                    elements.push(corners);
                    element_cell.push([i as u32, j as u32, k as u32]);
                }
            }
        }
        if lattice_order {
            let mut order: Vec<u32> = (0..node_lattice.len() as u32).collect();
            order.sort_unstable_by_key(|&n| {
                let l = node_lattice[n as usize];
                (l[2], l[1], l[0])
            });
            let mut renumber = vec![0u32; order.len()];
            for (new, &old) in order.iter().enumerate() {
                renumber[old as usize] = new as u32;
            }
            for corners in &mut elements {
                *corners = corners.map(|c| renumber[c as usize]);
            }
            positions = order.iter().map(|&o| positions[o as usize]).collect();
            node_lattice = order.iter().map(|&o| node_lattice[o as usize]).collect();
        }
        // Grown by push: release the slack so node arrays cost what they hold.
        positions.shrink_to_fit();
        node_lattice.shrink_to_fit();
        elements.shrink_to_fit();
        element_cell.shrink_to_fit();
        let n_el = elements.len();
        let mesh = HexMesh::new(positions, elements, vec![0; n_el], vec![coeffs])?;
        Ok(GridMesh {
            mesh,
            node_lattice,
            element_cell,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn box_counts_masses_and_faces() {
        let grid = VoxelGrid::filled_box([2, 3, 4], [0.01; 3], Vector3::zeros());
        let gm = grid
            .to_mesh(Material::new(1000.0, 0.3, 1000.0).unwrap())
            .unwrap();
        let m = &gm.mesh;
        assert_eq!(m.element_count(), 24);
        assert_eq!(m.node_count(), 3 * 4 * 5);
        assert_eq!(m.external_faces.len(), 2 * (2 * 3 + 3 * 4 + 2 * 4));
        assert!((m.total_mass_kg() - 1000.0 * 24.0 * 1e-6).abs() < 1e-12);
        assert_eq!(m.colors.len(), 8);
        let vol = m.enclosed_volume_m3(&m.rest_positions_m);
        assert!((vol - 24e-6).abs() < 1e-15, "{vol}");
    }

    #[test]
    fn masked_grid_keeps_only_active_cells() {
        let mut grid = VoxelGrid::filled_box([3, 3, 3], [0.01; 3], Vector3::zeros());
        let centre = grid.cell_index(1, 1, 1);
        grid.active.iter_mut().for_each(|a| *a = false);
        grid.active[centre] = true;
        let gm = grid.to_mesh(Material::LUNG).unwrap();
        assert_eq!(gm.mesh.element_count(), 1);
        assert_eq!(gm.mesh.node_count(), 8);
        assert_eq!(gm.element_cell, vec![[1, 1, 1]]);
    }
}
