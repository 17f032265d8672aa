//! A scene: a mesh with its constraints and loads, and the total force on it.

use super::forces::ForceEvaluator;
use crate::math::V3;
use crate::model::{ConstraintSet, Contact, HexMesh, Loads, OneSidedPlanes};
use crate::{Error, Result};

/// Everything the solvers need: mesh, constraints, loads, and the packed force kernels.
#[derive(Debug, Clone)]
pub struct Scene {
    /// The mesh.
    pub mesh: HexMesh,
    /// Kinematic constraints.
    pub constraints: ConstraintSet,
    /// External loads.
    pub loads: Loads,
    /// `Some(f)`: the imposed motions enclose the lung and make every volume change (a
    /// diaphragm the base slides on, with the rib cage), so the driver scales them to the
    /// breath instead of sharing it with the pressure; `f` is the part of their sweep that is
    /// the chest wall's, which frames report apart.
    pub walls_make_volume: Option<f64>,
    /// Rigid obstacles the nodes are kept out of by penalty contact (none by default); set
    /// with [`Scene::with_contact`].
    contact: Contact,
    /// Nodes that may leave their plane but not cross it (none by default): the lung's
    /// mediastinal face against the heart. They are not in `constraints`: the quasi-static
    /// solver holds on its plane each one that touches.
    pub one_sided: OneSidedPlanes,
    forces: ForceEvaluator,
}

impl Scene {
    /// Checks that constraints and loads fit the mesh.
    pub fn new(mesh: HexMesh, constraints: ConstraintSet, loads: Loads) -> Result<Self> {
        constraints.validate(&mesh.rest_positions_m)?;
        loads.validate(&mesh)?;
        let forces = ForceEvaluator::new(&mesh);
        Ok(Scene {
            mesh,
            constraints,
            loads,
            walls_make_volume: None,
            contact: Contact::default(),
            one_sided: OneSidedPlanes::default(),
            forces,
        })
    }

    /// The same scene with `contact` (checked against the mesh) in place of its obstacles.
    pub fn with_contact(mut self, contact: Contact) -> Result<Self> {
        contact.validate(self.node_count())?;
        self.contact = contact;
        Ok(self)
    }

    /// The scene's obstacles.
    pub fn contact(&self) -> &Contact {
        &self.contact
    }

    /// Adds the contact forces at positions `x`, velocities `v` (dampers off when `None`) and
    /// time `t_s` (where moving obstacles are) to `out`.
    pub fn add_contact_forces(&self, x: &[V3], v: Option<&[V3]>, t_s: f64, out: &mut [V3]) {
        if !self.contact.is_empty() {
            self.contact.accumulate(x, v, t_s, out);
        }
    }

    /// Number of nodes.
    pub fn node_count(&self) -> usize {
        self.mesh.node_count()
    }

    /// Rest positions with every constrained node moved onto its constraint.
    pub fn initial_positions(&self) -> Vec<V3> {
        let mut x = self.mesh.rest_positions_m.clone();
        self.constraints.project_positions(&mut x);
        x
    }

    /// Rest positions projected onto the constraints with every imposed displacement at zero:
    /// where the unloaded scene starts (a moving wall at rest too).
    pub fn unloaded_positions(&self) -> Vec<V3> {
        let rest = &self.mesh.rest_positions_m;
        let mut x = rest.clone();
        self.constraints
            .at_load_factor(rest, 0.0)
            .project_positions(&mut x);
        x
    }

    /// Volume the imposed displacements of the nodes `include` accepts sweep at load factor 1,
    /// mL (central difference of the enclosed volume: first order in the displacements).
    pub fn imposed_sweep_ml(&self, include: impl Fn(u32) -> bool) -> f64 {
        let rest = &self.mesh.rest_positions_m;
        let mut moves = crate::model::constraints::imposed_displacements(&self.constraints, rest);
        moves.retain(|&(n, _)| include(n));
        if moves.is_empty() {
            return 0.0;
        }
        let largest = moves.iter().map(|(_, d)| d.norm()).fold(0.0, f64::max);
        // A step of a micrometre at the largest offset keeps the difference linear.
        let eps = 1e-6 / largest;
        let mut x = rest.clone();
        let mut volume = |t: f64| {
            for &(n, d) in &moves {
                x[n as usize] = rest[n as usize] + d * t;
            }
            self.mesh.enclosed_volume_m3(&x)
        };
        (volume(eps) - volume(-eps)) / (2.0 * eps) * 1e6
    }

    /// Internal forces only, into `out`.
    pub fn internal_forces(&self, x: &[V3], v: Option<&[V3]>, out: &mut [V3]) {
        self.forces.internal_forces(&self.mesh, x, v, out);
    }

    /// Internal plus external force on every node (constraints not applied), into `out`,
    /// with contact against the obstacles where they are at time 0.
    pub fn total_forces(&self, x: &[V3], v: Option<&[V3]>, out: &mut [V3]) {
        self.total_forces_at(x, v, 0.0, out);
    }

    /// Internal, external and contact force on every node at time `t_s` (constraints not
    /// applied), into `out`.
    pub fn total_forces_at(&self, x: &[V3], v: Option<&[V3]>, t_s: f64, out: &mut [V3]) {
        self.forces.internal_forces(&self.mesh, x, v, out);
        self.loads.accumulate(&self.mesh, x, out);
        self.add_contact_forces(x, v, t_s, out);
    }

    /// External forces only, into `out`.
    pub fn external_forces(&self, x: &[V3], out: &mut [V3]) {
        out.iter_mut().for_each(|f| *f = V3::zeros());
        self.loads.accumulate(&self.mesh, x, out);
    }

    /// Relative force residual ‖free part of total force‖ / max(‖external‖, ‖internal‖).
    ///
    /// `scratch` must hold two node-sized buffers; returns the residual and fills
    /// `scratch.0` with the free part of the total force. Obstacles are where they are at
    /// time 0.
    pub fn relative_residual(&self, x: &[V3], scratch: (&mut [V3], &mut [V3])) -> f64 {
        self.relative_residual_at(x, 0.0, scratch)
    }

    /// [`Scene::relative_residual`] with the obstacles where they are at `t_s`; contact
    /// forces count with the internal ones (they are reactions, as the springs' are).
    pub fn relative_residual_at(&self, x: &[V3], t_s: f64, scratch: (&mut [V3], &mut [V3])) -> f64 {
        let (total, ext) = scratch;
        self.forces.internal_forces(&self.mesh, x, None, total);
        self.add_contact_forces(x, None, t_s, total);
        let internal_norm = norm(total);
        self.external_forces(x, ext);
        let external_norm = norm(ext);
        total.iter_mut().zip(ext.iter()).for_each(|(t, e)| *t += e);
        self.constraints.project_field(x, total);
        let scale = internal_norm.max(external_norm);
        if scale == 0.0 {
            0.0
        } else {
            norm(total) / scale
        }
    }

    /// Refuses positions with a non-finite coordinate, naming the node.
    pub fn check_finite(&self, x: &[V3], step: usize) -> Result<()> {
        if let Some(n) = x.iter().position(|p| !p.iter().all(|v| v.is_finite())) {
            return Err(Error::Diverged {
                step,
                cause: format!("node {n} has a non-finite position"),
            });
        }
        Ok(())
    }

    /// The element with the smallest signed volume over its rest volume, if that ratio is at or
    /// below `threshold` (0 finds inverted elements). The volume is the triple product of the
    /// averaged edge vectors, exact for parallelepipeds.
    pub fn most_compressed_element(&self, x: &[V3], threshold: f64) -> Option<(usize, f64)> {
        use rayon::prelude::*;
        let mesh = &self.mesh;
        let ratio = |e: usize| {
            let c = mesh.elements[e].map(|n| x[n as usize]);
            let ex = (c[1] - c[0]) + (c[2] - c[3]) + (c[5] - c[4]) + (c[6] - c[7]);
            let ey = (c[3] - c[0]) + (c[2] - c[1]) + (c[7] - c[4]) + (c[6] - c[5]);
            let ez = (c[4] - c[0]) + (c[5] - c[1]) + (c[6] - c[2]) + (c[7] - c[3]);
            let v = ex.dot(&ey.cross(&ez)) / 64.0;
            v / mesh.classes[mesh.element_class[e] as usize]
                .shape
                .volume_m3()
        };
        (0..mesh.element_count())
            .into_par_iter()
            .map(|e| (e, ratio(e)))
            .filter(|(_, r)| *r <= threshold || !r.is_finite())
            .min_by(|a, b| a.1.total_cmp(&b.1))
    }

    /// Refuses states with an inverted element: no valid equilibrium or motion has one, and an
    /// unstable run can settle into such a state with a small residual.
    /// `likely_cause` ends the message: what the caller's method makes likely (a time step above
    /// the stability limit for explicit integration, a load step too large for a static solve).
    pub fn check_not_inverted(&self, x: &[V3], step: usize, likely_cause: &str) -> Result<()> {
        match self.most_compressed_element(x, 0.0) {
            Some((e, r)) => Err(Error::Diverged {
                step,
                cause: format!(
                    "element {e} is inverted (signed volume {r:.3} × its rest volume): {likely_cause}"
                ),
            }),
            None => Ok(()),
        }
    }

    /// Displacements (positions − rest) in metres.
    pub fn displacements(&self, x: &[V3]) -> Vec<V3> {
        x.iter()
            .zip(&self.mesh.rest_positions_m)
            .map(|(p, r)| p - r)
            .collect()
    }

    /// Reaction force on every constrained node at positions `x` (thesis eq. 4.1).
    pub fn reactions(&self, x: &[V3]) -> Vec<(u32, V3)> {
        let mut f = vec![V3::zeros(); self.node_count()];
        self.total_forces(x, None, &mut f);
        self.constraints.reactions(x, &f)
    }
}

/// Euclidean norm of a node field.
pub fn norm(v: &[V3]) -> f64 {
    v.iter().map(|x| x.norm_squared()).sum::<f64>().sqrt()
}
