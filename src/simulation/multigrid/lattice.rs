//! Lattice coordinates and bodies of a voxel-lattice mesh, the keys of every level's cells
//! and nodes.

use nalgebra::Matrix3;

use crate::model::element::CORNER_SIGNS;
use crate::model::HexMesh;

/// Lattice coordinates of a mesh whose elements are equal bricks on one regular grid.
///
/// The mesh may hold several bodies (connected components through shared element nodes)
/// that touch on the lattice without sharing nodes, such as the two lungs: two nodes may then
/// sit at one lattice point, and every level of the hierarchy keeps the bodies apart.
#[derive(Debug, Clone)]
pub struct Lattice {
    /// Lattice point of each node.
    pub node: Vec<[u32; 3]>,
    /// Lattice cell of each element.
    pub cell: Vec<[u32; 3]>,
    /// Body (connected component, numbered from 0 in node order) of each node.
    pub body: Vec<u32>,
    /// World directions of the lattice axes, as columns.
    pub axes: Matrix3<f64>,
}

impl Lattice {
    /// Recovers the lattice from geometry, or `None` if the elements are not equal bricks
    /// aligned on one grid, or two nodes of one body share a lattice point (the solver then
    /// falls back to block Jacobi).
    pub fn infer(mesh: &HexMesh) -> Option<Lattice> {
        let shape = mesh.classes.first()?.shape;
        if mesh.classes.iter().any(|c| c.shape != shape) {
            return None;
        }
        let p = &mesh.rest_positions_m;
        let e0 = mesh.elements[0];
        let axes = [
            (p[e0[1] as usize] - p[e0[0] as usize]).normalize(),
            (p[e0[3] as usize] - p[e0[0] as usize]).normalize(),
            (p[e0[4] as usize] - p[e0[0] as usize]).normalize(),
        ];
        let origin = p[e0[0] as usize];
        let h = shape.edges_m;
        let mut raw = Vec::with_capacity(p.len());
        for x in p {
            let mut c = [0i64; 3];
            for a in 0..3 {
                let t = (x - origin).dot(&axes[a]) / h[a];
                let r = t.round();
                if (t - r).abs() > 1e-6 {
                    return None;
                }
                c[a] = r as i64;
            }
            raw.push(c);
        }
        let min: [i64; 3] = std::array::from_fn(|a| raw.iter().map(|c| c[a]).min().unwrap_or(0));
        let node: Vec<[u32; 3]> = raw
            .iter()
            .map(|c| std::array::from_fn(|a| (c[a] - min[a]) as u32))
            .collect();
        let mut cell = Vec::with_capacity(mesh.elements.len());
        for corners in &mesh.elements {
            let base = node[corners[0] as usize];
            for (k, signs) in CORNER_SIGNS.iter().enumerate() {
                let want: [u32; 3] = std::array::from_fn(|a| base[a] + (signs[a] > 0.0) as u32);
                if node[corners[k] as usize] != want {
                    return None;
                }
            }
            cell.push(base);
        }
        // Coarse levels identify nodes by (body, lattice point): two bodies touching on the
        // lattice (the two lungs, meshed without shared nodes) must not be glued there, where
        // their sliding surfaces face opposite ways. Within one body a lattice point is one node.
        let body = node_bodies(mesh);
        let mut seen = std::collections::HashSet::with_capacity(node.len());
        if !node.iter().zip(&body).all(|(c, &b)| seen.insert((*c, b))) {
            return None;
        }
        Some(Lattice {
            node,
            cell,
            body,
            axes: Matrix3::from_columns(&axes),
        })
    }
}

/// Connected component of each node through shared element nodes, numbered in order of
/// first node; a node in no element is a body of its own.
fn node_bodies(mesh: &HexMesh) -> Vec<u32> {
    fn root(parent: &mut [u32], mut n: u32) -> u32 {
        while parent[n as usize] != n {
            // Path halving keeps the trees shallow without recursion.
            let up = parent[parent[n as usize] as usize];
            parent[n as usize] = up;
            n = up;
        }
        n
    }
    let mut parent: Vec<u32> = (0..mesh.node_count() as u32).collect();
    for corners in &mesh.elements {
        let a = root(&mut parent, corners[0]);
        for &c in &corners[1..] {
            let b = root(&mut parent, c);
            if b != a {
                parent[b as usize] = a;
            }
        }
    }
    let mut number = vec![u32::MAX; parent.len()];
    let mut next = 0;
    (0..parent.len() as u32)
        .map(|n| {
            let r = root(&mut parent, n) as usize;
            if number[r] == u32::MAX {
                number[r] = next;
                next += 1;
            }
            number[r]
        })
        .collect()
}
