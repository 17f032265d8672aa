//! Index-based hexahedral mesh: node arrays, element connectivity, element classes,
//! lumped masses, external faces and a colouring for parallel force assembly.
//!
//! Memory: per node 24 B (rest position) + 8 B (mass); per element 32 B (corners) + 4 B
//! (class) + 4 B (colour slot). Coefficients are shared by all elements of a class.

use std::collections::HashMap;

use nalgebra::Vector3;

use super::element::{BrickCoefficients, CORNER_SIGNS};
use crate::{Error, Result};

/// Corner indices of the six faces of a hexahedron, ordered so that the quad's area vector
/// ½·(c−a)×(d−b) points out of the element.
pub const HEX_FACES: [[usize; 4]; 6] = [
    [0, 3, 2, 1],
    [4, 5, 6, 7],
    [0, 1, 5, 4],
    [3, 7, 6, 2],
    [0, 4, 7, 3],
    [1, 2, 6, 5],
];

/// The 12 edges of a hexahedron in the mesh's corner order (VTK's).
pub const HEX_EDGES: [(usize, usize); 12] = [
    (0, 1),
    (1, 2),
    (2, 3),
    (3, 0),
    (4, 5),
    (5, 6),
    (6, 7),
    (7, 4),
    (0, 4),
    (1, 5),
    (2, 6),
    (3, 7),
];

/// A mesh of Baudet bricks sharing corner nodes.
#[derive(Debug, Clone)]
pub struct HexMesh {
    /// Rest (reference) position of each node in metres.
    pub rest_positions_m: Vec<Vector3<f64>>,
    /// The 8 node indices of each element, VTK / C3D8 corner order.
    pub elements: Vec<[u32; 8]>,
    /// Index into [`HexMesh::classes`] of each element.
    pub element_class: Vec<u32>,
    /// Coefficient sets shared by elements of the same shape and material.
    pub classes: Vec<BrickCoefficients>,
    /// Lumped mass of each node in kg (Σ ρ·V/8 over the elements that share it).
    pub node_mass_kg: Vec<f64>,
    /// External faces (belonging to one element only), outward-ordered corner indices.
    pub external_faces: Vec<[u32; 4]>,
    /// Element indices grouped so that no two elements of a group share a node.
    pub colors: Vec<Vec<u32>>,
}

impl HexMesh {
    /// Builds a mesh after checking indices, finiteness and that each element's rest geometry
    /// is the brick its class describes (edges along the element axes, lengths within 1e-6).
    pub fn new(
        rest_positions_m: Vec<Vector3<f64>>,
        elements: Vec<[u32; 8]>,
        element_class: Vec<u32>,
        classes: Vec<BrickCoefficients>,
    ) -> Result<Self> {
        if elements.len() != element_class.len() {
            return Err(Error::InvalidModel(format!(
                "{} elements but {} class indices",
                elements.len(),
                element_class.len()
            )));
        }
        if elements.is_empty() {
            return Err(Error::InvalidModel("the mesh has no elements".into()));
        }
        if u32::try_from(rest_positions_m.len()).is_err() {
            return Err(Error::InvalidModel("more than 2³² nodes".into()));
        }
        if let Some(n) = rest_positions_m
            .iter()
            .position(|p| !p.iter().all(|v| v.is_finite()))
        {
            return Err(Error::InvalidModel(format!(
                "node {n} has a non-finite position"
            )));
        }
        let n_nodes = rest_positions_m.len();
        let mut node_mass_kg = vec![0.0; n_nodes];
        for (e, (corners, &class)) in elements.iter().zip(&element_class).enumerate() {
            let coeffs = classes.get(class as usize).ok_or_else(|| {
                Error::InvalidModel(format!("element {e} refers to missing class {class}"))
            })?;
            if let Some(&bad) = corners.iter().find(|&&c| c as usize >= n_nodes) {
                return Err(Error::InvalidModel(format!(
                    "element {e} refers to node {bad}, but the mesh has {n_nodes} nodes"
                )));
            }
            check_brick_geometry(e, corners, &rest_positions_m, coeffs)?;
            for &c in corners {
                node_mass_kg[c as usize] += coeffs.corner_mass_kg;
            }
        }
        let external_faces = external_faces(&elements);
        let colors = color_elements(&elements, n_nodes);
        Ok(HexMesh {
            rest_positions_m,
            elements,
            element_class,
            classes,
            node_mass_kg,
            external_faces,
            colors,
        })
    }

    /// Number of nodes.
    pub fn node_count(&self) -> usize {
        self.rest_positions_m.len()
    }

    /// Number of elements.
    pub fn element_count(&self) -> usize {
        self.elements.len()
    }

    /// The material of the class most elements have (the lung's, when tissue varies).
    pub fn typical_material(&self) -> Option<super::Material> {
        let mut count = vec![0usize; self.classes.len()];
        for &c in &self.element_class {
            count[c as usize] += 1;
        }
        let most = (0..count.len()).max_by_key(|&c| count[c])?;
        Some(self.classes[most].material)
    }

    /// Total mass in kg.
    pub fn total_mass_kg(&self) -> f64 {
        self.node_mass_kg.iter().sum()
    }

    /// Enclosed volume in m³ of the deformed mesh, from the divergence theorem over the
    /// external faces (exact for the bilinear faces of a closed surface).
    pub fn enclosed_volume_m3(&self, positions_m: &[Vector3<f64>]) -> f64 {
        self.external_faces
            .iter()
            .map(|f| {
                let p = f.map(|i| positions_m[i as usize]);
                let centroid = (p[0] + p[1] + p[2] + p[3]) / 4.0;
                let area = 0.5 * (p[2] - p[0]).cross(&(p[3] - p[1]));
                centroid.dot(&area) / 3.0
            })
            .sum()
    }

    /// Nodes lying on the external surface.
    pub fn surface_nodes(&self) -> Vec<u32> {
        let mut on = vec![false; self.node_count()];
        for f in &self.external_faces {
            for &n in f {
                on[n as usize] = true;
            }
        }
        (0..self.node_count() as u32)
            .filter(|&n| on[n as usize])
            .collect()
    }
}

fn check_brick_geometry(
    e: usize,
    corners: &[u32; 8],
    positions: &[Vector3<f64>],
    coeffs: &BrickCoefficients,
) -> Result<()> {
    let p = corners.map(|c| positions[c as usize]);
    let centre = p.iter().sum::<Vector3<f64>>() / 8.0;
    // Recover the element axes from corner 0's three edges, then check every corner.
    let axes = [p[1] - p[0], p[3] - p[0], p[4] - p[0]];
    let dims = coeffs.shape.edges_m;
    let scale = dims.iter().cloned().fold(0.0, f64::max);
    for (a, axis) in axes.iter().enumerate() {
        if (axis.norm() - dims[a]).abs() > 1e-6 * scale {
            return Err(Error::InvalidModel(format!(
                "element {e}: edge {a} is {:.6e} m long but its class expects {:.6e} m \
                 (corner order must be VTK hexahedron order)",
                axis.norm(),
                dims[a]
            )));
        }
    }
    let units = axes.map(|a| a / a.norm());
    if units[0].cross(&units[1]).dot(&units[2]) <= 0.0 {
        return Err(Error::InvalidModel(format!(
            "element {e} is inverted or has zero volume (corner order must be VTK hexahedron order)"
        )));
    }
    for (n, signs) in CORNER_SIGNS.iter().enumerate() {
        let want = centre
            + (0..3)
                .map(|i| units[i] * 0.5 * signs[i] * dims[i])
                .sum::<Vector3<f64>>();
        if (p[n] - want).norm() > 1e-6 * scale {
            return Err(Error::InvalidModel(format!(
                "element {e}: corner {n} is not where a rectangular brick puts it"
            )));
        }
    }
    Ok(())
}

fn external_faces(elements: &[[u32; 8]]) -> Vec<[u32; 4]> {
    let mut count: HashMap<[u32; 4], (u32, [u32; 4])> = HashMap::with_capacity(elements.len() * 3);
    for corners in elements {
        for face in HEX_FACES {
            let ordered = face.map(|c| corners[c]);
            let mut key = ordered;
            key.sort_unstable();
            count.entry(key).or_insert((0, ordered)).0 += 1;
        }
    }
    let mut faces: Vec<[u32; 4]> = count
        .into_values()
        .filter(|(n, _)| *n == 1)
        .map(|(_, f)| f)
        .collect();
    faces.sort_unstable();
    faces
}

/// Greedy colouring: elements of one colour share no node, so their forces can be
/// scattered in parallel without atomics. A structured grid gets 8 colours.
pub(crate) fn color_elements(elements: &[[u32; 8]], n_nodes: usize) -> Vec<Vec<u32>> {
    // Bit mask per node of the colours already used by elements touching it.
    let mut used = vec![0u64; n_nodes];
    let mut colors: Vec<Vec<u32>> = Vec::new();
    for (e, corners) in elements.iter().enumerate() {
        let taken = corners.iter().fold(0u64, |m, &c| m | used[c as usize]);
        let color = (!taken).trailing_zeros() as usize;
        assert!(color < 64, "a hexahedral mesh never needs 64 colours");
        if color == colors.len() {
            colors.push(Vec::new());
        }
        colors[color].push(e as u32);
        for &c in corners {
            used[c as usize] |= 1 << color;
        }
    }
    colors
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::{BrickShape, Material};

    fn unit_cube() -> (Vec<Vector3<f64>>, [u32; 8], BrickCoefficients) {
        let pos = CORNER_SIGNS
            .iter()
            .map(|s| Vector3::new(s[0], s[1], s[2]) * 0.5)
            .collect();
        let c =
            BrickCoefficients::new(BrickShape::cube(1.0), Material::new(1.0, 0.3, 1.0).unwrap())
                .unwrap();
        (pos, [0, 1, 2, 3, 4, 5, 6, 7], c)
    }

    fn err(r: Result<HexMesh>) -> String {
        match r {
            Err(Error::InvalidModel(m)) => m,
            other => panic!("expected InvalidModel, got {other:?}"),
        }
    }

    #[test]
    fn refuses_malformed_meshes_with_a_reason() {
        let (pos, el, c) = unit_cube();
        assert!(HexMesh::new(pos.clone(), vec![el], vec![0], vec![c.clone()]).is_ok());

        let m = err(HexMesh::new(
            pos.clone(),
            vec![[0, 1, 2, 3, 4, 5, 6, 9]],
            vec![0],
            vec![c.clone()],
        ));
        assert!(m.contains("node 9"), "{m}");

        let mut nan = pos.clone();
        nan[3].y = f64::NAN;
        let m = err(HexMesh::new(nan, vec![el], vec![0], vec![c.clone()]));
        assert!(m.contains("node 3") && m.contains("non-finite"), "{m}");

        // Mirrored corner order: the element is inverted.
        let m = err(HexMesh::new(
            pos.clone(),
            vec![[4, 5, 6, 7, 0, 1, 2, 3]],
            vec![0],
            vec![c.clone()],
        ));
        assert!(m.contains("inverted or has zero volume"), "{m}");

        // Collapsed to zero volume: corners 4–7 on top of 0–3.
        let mut flat = pos.clone();
        for k in 4..8 {
            flat[k] = flat[k - 4];
        }
        let m = err(HexMesh::new(flat, vec![el], vec![0], vec![c.clone()]));
        assert!(m.contains("edge 2"), "{m}");

        let m = err(HexMesh::new(
            pos.clone(),
            vec![el],
            vec![1],
            vec![c.clone()],
        ));
        assert!(m.contains("missing class 1"), "{m}");

        let m = err(HexMesh::new(pos.clone(), vec![], vec![], vec![c.clone()]));
        assert!(m.contains("no elements"), "{m}");

        let bigger = BrickCoefficients::new(BrickShape::cube(2.0), c.material).unwrap();
        let m = err(HexMesh::new(pos, vec![el], vec![0], vec![bigger]));
        assert!(m.contains("class expects"), "{m}");
    }
}
