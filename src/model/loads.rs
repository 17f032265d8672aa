//! External loads: gravity, point forces and uniform pressure on surface faces.

use nalgebra::Vector3;

use super::mesh::HexMesh;
use crate::{Error, Result};

/// Uniform pressure on a set of outward-ordered quad faces.
///
/// Positive pressure pushes into the body (against the outward normal), as CalculiX's
/// `*DLOAD … P` does. Each face passes P·A/4 to each of its corners, A its area vector.
/// With `follows_deformation` the area vector is recomputed from the deformed face (a follower
/// load, as lung pressure is); otherwise the rest face is used, as the thesis did.
#[derive(Debug, Clone)]
pub struct SurfacePressure {
    /// Faces the pressure acts on (corner node indices, outward order).
    pub faces: Vec<[u32; 4]>,
    /// Pressure in pascals, positive pushing inward.
    pub pressure_pa: f64,
    /// Whether the load follows the deformed faces.
    pub follows_deformation: bool,
}

/// Every external load on a model.
#[derive(Debug, Clone, Default)]
pub struct Loads {
    /// Gravitational acceleration in m/s² applied to every lumped mass.
    pub gravity_m_per_s2: Vector3<f64>,
    /// Point forces in newtons on nodes.
    pub point_forces_n: Vec<(u32, Vector3<f64>)>,
    /// Surface pressures.
    pub pressures: Vec<SurfacePressure>,
}

impl Loads {
    /// Checks node indices and finiteness against `mesh`.
    pub fn validate(&self, mesh: &HexMesh) -> Result<()> {
        let n = mesh.node_count();
        if !self.gravity_m_per_s2.iter().all(|g| g.is_finite()) {
            return Err(Error::InvalidModel("gravity is not finite".into()));
        }
        for (node, f) in &self.point_forces_n {
            if *node as usize >= n {
                return Err(Error::InvalidModel(format!(
                    "point force on node {node}, but the mesh has {n} nodes"
                )));
            }
            if !f.iter().all(|x| x.is_finite()) {
                return Err(Error::InvalidModel(format!(
                    "point force on node {node} is not finite"
                )));
            }
        }
        for p in &self.pressures {
            if !p.pressure_pa.is_finite() {
                return Err(Error::InvalidModel(format!(
                    "pressure {} Pa is not finite",
                    p.pressure_pa
                )));
            }
            if let Some(f) = p.faces.iter().find(|f| f.iter().any(|&c| c as usize >= n)) {
                return Err(Error::InvalidModel(format!(
                    "pressure face {f:?} refers to a node beyond the mesh's {n}"
                )));
            }
        }
        Ok(())
    }

    /// Adds the external forces at `positions_m` to `out` (newtons).
    pub fn accumulate(
        &self,
        mesh: &HexMesh,
        positions_m: &[Vector3<f64>],
        out: &mut [Vector3<f64>],
    ) {
        if self.gravity_m_per_s2 != Vector3::zeros() {
            for (f, m) in out.iter_mut().zip(&mesh.node_mass_kg) {
                *f += self.gravity_m_per_s2 * *m;
            }
        }
        for (node, f) in &self.point_forces_n {
            out[*node as usize] += f;
        }
        for p in &self.pressures {
            let x = if p.follows_deformation {
                positions_m
            } else {
                &mesh.rest_positions_m[..]
            };
            for face in &p.faces {
                let c = face.map(|i| x[i as usize]);
                let area = 0.5 * (c[2] - c[0]).cross(&(c[3] - c[1]));
                let f = -area * (p.pressure_pa / 4.0);
                for &i in face {
                    out[i as usize] += f;
                }
            }
        }
    }
}
