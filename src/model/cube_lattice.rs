//! The cube lattice a voxel mesh's elements fill, recovered from the mesh, with the element of
//! each (cell, lung) in a dense table: finding the element that holds a point is two
//! multiplications and one array read, which the field sampler does for every lung voxel
//! (11 M on a POPI CT) and the registration and target writers for every grid point.

use crate::math::V3;
use crate::model::HexMesh;
use crate::{Error, Result};

/// Which corners of an element (VTK order) sit one edge along the lattice's i, j, k axes.
pub const CORNER_BITS: [[bool; 3]; 8] = [
    [false, false, false],
    [true, false, false],
    [true, true, false],
    [false, true, false],
    [false, false, true],
    [true, false, true],
    [true, true, true],
    [false, true, true],
];

/// Marks a (cell, lung) that no element fills.
const EMPTY: u32 = u32::MAX;

/// The common lattice of a mesh of equal, equally oriented cubes, and which element fills each
/// cell for each lung label.
#[derive(Debug, Clone)]
pub struct CubeLattice {
    /// Rest position of element 0's first corner, metres (LPS).
    pub origin_m: V3,
    /// Unit lattice axes i, j, k (element 0's edges from its first corner).
    pub axes: [V3; 3],
    /// Element edge, metres.
    pub edge_m: f64,
    /// Cell of each element (its first corner, in element edges), in element order.
    pub element_cell: Vec<[i64; 3]>,
    /// First cell of the table.
    lo: [i64; 3],
    /// Cells of the table along i, j, k.
    dims: [usize; 3],
    /// Slot of each lung label in the table (labels absent from the mesh have none).
    slot_of_label: [Option<u8>; 256],
    /// Labels with a slot, in slot order.
    labels: Vec<u8>,
    /// Element of each (slot, cell), slot slowest: [`EMPTY`] where none.
    cells: Vec<u32>,
}

impl CubeLattice {
    /// Recovers the lattice of `mesh`'s elements, `element_lung` the lung label of each; refuses
    /// a mesh whose elements are not cubes of one lattice, or two elements of one lung in one
    /// cell.
    pub fn of(mesh: &HexMesh, element_lung: &[u8]) -> Result<Self> {
        Self::build(mesh, element_lung, false)
    }

    /// The lattice of `mesh`'s elements whatever their lung: each cell holds its
    /// lowest-numbered element (both lungs may claim a cell where they touch).
    pub fn of_cells(mesh: &HexMesh) -> Result<Self> {
        Self::build(mesh, &vec![0; mesh.elements.len()], true)
    }

    /// [`CubeLattice::of`]; with `keep_first` a second element in a cell is passed over.
    fn build(mesh: &HexMesh, element_lung: &[u8], keep_first: bool) -> Result<Self> {
        if element_lung.len() != mesh.elements.len() {
            return Err(Error::InvalidModel(format!(
                "{} lung labels for {} elements",
                element_lung.len(),
                mesh.elements.len()
            )));
        }
        let first = mesh
            .elements
            .first()
            .ok_or_else(|| Error::InvalidModel("the mesh has no elements".into()))?;
        let x = |n: u32| mesh.rest_positions_m[n as usize];
        let edge = x(first[1]) - x(first[0]);
        let edge_m = edge.norm();
        if !(edge_m.is_finite() && edge_m > 0.0) {
            return Err(Error::InvalidModel(format!(
                "element 0 has an edge of {edge_m} m; the lattice needs cubes"
            )));
        }
        let axes = [
            edge / edge_m,
            (x(first[3]) - x(first[0])).normalize(),
            (x(first[4]) - x(first[0])).normalize(),
        ];
        let mut lattice = CubeLattice {
            origin_m: x(first[0]),
            axes,
            edge_m,
            element_cell: Vec::with_capacity(mesh.elements.len()),
            lo: [0; 3],
            dims: [0; 3],
            slot_of_label: [None; 256],
            labels: Vec::new(),
            cells: Vec::new(),
        };
        let mut lo = [i64::MAX; 3];
        let mut hi = [i64::MIN; 3];
        for (e, nodes) in mesh.elements.iter().enumerate() {
            let (c, f) =
                lattice.cell_of(x(nodes[0]) + (axes[0] + axes[1] + axes[2]) * (0.5 * edge_m));
            let off = (f - V3::new(c[0] as f64 + 0.5, c[1] as f64 + 0.5, c[2] as f64 + 0.5)).norm();
            let edges_ok = (1..8).all(|k| {
                let b = CORNER_BITS[k];
                let expected = x(nodes[0])
                    + (0..3)
                        .filter(|&a| b[a])
                        .map(|a| axes[a] * edge_m)
                        .sum::<V3>();
                (x(nodes[k]) - expected).norm() <= 1e-6 * edge_m.max(1e-3)
            });
            if off > 1e-6 || !edges_ok {
                return Err(Error::InvalidModel(format!(
                    "element {e} is not a cube of the mesh's lattice; the lung fields need one \
                     lattice of equal cubes"
                )));
            }
            for a in 0..3 {
                lo[a] = lo[a].min(c[a]);
                hi[a] = hi[a].max(c[a]);
            }
            lattice.element_cell.push(c);
            let label = element_lung[e];
            if lattice.slot_of_label[label as usize].is_none() {
                lattice.slot_of_label[label as usize] = Some(lattice.labels.len() as u8);
                lattice.labels.push(label);
            }
        }
        lattice.lo = lo;
        lattice.dims = [0, 1, 2].map(|a| (hi[a] - lo[a] + 1) as usize);
        let per_slot = lattice.dims.iter().product::<usize>();
        lattice.cells = vec![EMPTY; per_slot * lattice.labels.len()];
        for (e, &c) in lattice.element_cell.iter().enumerate() {
            let slot = lattice.slot_of_label[element_lung[e] as usize].expect("set above");
            let at = lattice
                .table_index(c, slot)
                .expect("within the bounds just taken");
            if lattice.cells[at] != EMPTY {
                if keep_first {
                    continue;
                }
                return Err(Error::InvalidModel(format!(
                    "elements {} and {e} of lung {} fill the same lattice cell",
                    lattice.cells[at], element_lung[e]
                )));
            }
            lattice.cells[at] = e as u32;
        }
        Ok(lattice)
    }

    /// Lattice coordinates of `p_m`, in element edges.
    pub fn coords(&self, p_m: V3) -> V3 {
        let d = p_m - self.origin_m;
        V3::new(
            d.dot(&self.axes[0]),
            d.dot(&self.axes[1]),
            d.dot(&self.axes[2]),
        ) / self.edge_m
    }

    /// The cell holding `p_m` and the point's lattice coordinates.
    pub fn cell_of(&self, p_m: V3) -> ([i64; 3], V3) {
        let f = self.coords(p_m);
        (
            [f.x.floor() as i64, f.y.floor() as i64, f.z.floor() as i64],
            f,
        )
    }

    /// The lung labels the mesh's elements carry, in the order first met.
    pub fn labels(&self) -> &[u8] {
        &self.labels
    }

    /// The element of lung `label` filling `cell`, if any.
    #[inline]
    pub fn element_at(&self, cell: [i64; 3], label: u8) -> Option<u32> {
        let slot = self.slot_of_label[label as usize]?;
        let e = self.cells[self.table_index(cell, slot)?];
        (e != EMPTY).then_some(e)
    }

    /// The lowest-numbered element of any lung filling `cell`, if any.
    pub fn any_element_at(&self, cell: [i64; 3]) -> Option<u32> {
        self.labels
            .iter()
            .filter_map(|&l| self.element_at(cell, l))
            .min()
    }

    /// Index of (`cell`, `slot`) in the table; `None` outside its bounds.
    #[inline]
    fn table_index(&self, cell: [i64; 3], slot: u8) -> Option<usize> {
        let mut at = slot as usize;
        for a in (0..3).rev() {
            let c = cell[a] - self.lo[a];
            if c < 0 || c as usize >= self.dims[a] {
                return None;
            }
            at = at * self.dims[a] + c as usize;
        }
        Some(at)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::{Material, VoxelGrid};

    #[test]
    fn every_element_is_found_in_its_cell_and_lung_and_nowhere_else() {
        let mesh = VoxelGrid::filled_box([3, 2, 2], [0.01; 3], V3::zeros())
            .to_mesh(Material::LUNG)
            .unwrap()
            .mesh;
        let n = mesh.elements.len();
        // Two lungs: the first half of the elements is lung 1, the rest lung 2.
        let labels: Vec<u8> = (0..n).map(|e| if e < n / 2 { 1 } else { 2 }).collect();
        let lattice = CubeLattice::of(&mesh, &labels).unwrap();
        assert_eq!(lattice.labels(), &[1, 2]);
        for (e, nodes) in mesh.elements.iter().enumerate() {
            let centre = mesh.rest_positions_m[nodes[0] as usize]
                + (lattice.axes[0] + lattice.axes[1] + lattice.axes[2]) * 0.005;
            let (cell, _) = lattice.cell_of(centre);
            assert_eq!(cell, lattice.element_cell[e]);
            assert_eq!(lattice.element_at(cell, labels[e]), Some(e as u32));
            let other = 3 - labels[e];
            assert_eq!(lattice.element_at(cell, other), None);
            assert_eq!(lattice.any_element_at(cell), Some(e as u32));
            assert_eq!(lattice.element_at(cell, 7), None);
        }
        // Whatever the lung: every cell, one element each.
        let cells = CubeLattice::of_cells(&mesh).unwrap();
        for (e, &cell) in lattice.element_cell.iter().enumerate() {
            assert_eq!(cells.any_element_at(cell), Some(e as u32));
        }
        // Outside the table on every side.
        for cell in [
            [-1, 0, 0],
            [0, -1, 0],
            [0, 0, -1],
            [3, 0, 0],
            [0, 2, 0],
            [0, 0, 2],
        ] {
            assert_eq!(lattice.any_element_at(cell), None, "{cell:?}");
        }
    }

    #[test]
    fn a_mesh_that_is_not_one_lattice_of_cubes_is_refused() {
        let mut mesh = VoxelGrid::filled_box([2, 1, 1], [0.01; 3], V3::zeros())
            .to_mesh(Material::LUNG)
            .unwrap()
            .mesh;
        let labels = vec![1u8; mesh.elements.len()];
        let moved = mesh.elements[1][6] as usize;
        mesh.rest_positions_m[moved].x += 0.002;
        let error = CubeLattice::of(&mesh, &labels).unwrap_err().to_string();
        assert!(error.contains("element 1 is not a cube"), "{error}");
        assert!(CubeLattice::of_cells(&mesh).is_err());
        let error = CubeLattice::of(&mesh, &[1]).unwrap_err().to_string();
        assert!(error.contains("1 lung labels for 2 elements"), "{error}");
    }
}
