//! Kinematic constraints on nodes: fixed or imposed positions, sliding on a plane, a line,
//! or an implicit surface. Each constraint removes the constrained directions of a node's
//! motion and of its force; the removed force is the reaction (thesis eq. 4.1).

use std::sync::Arc;

use nalgebra::Vector3;

use super::sdf::SignedDistanceField;
use crate::{Error, Result};

/// What a constrained node may do.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum NodeConstraint {
    /// Held at a position in metres (fixed, or an imposed displacement from rest).
    Fixed {
        /// Where the node is held, metres.
        target_m: Vector3<f64>,
    },
    /// Slides freely on a plane.
    Plane {
        /// A point of the plane, metres.
        point_m: Vector3<f64>,
        /// Unit normal of the plane.
        normal: Vector3<f64>,
    },
    /// Slides freely along a line.
    Line {
        /// A point of the line, metres.
        point_m: Vector3<f64>,
        /// Unit direction of the line.
        direction: Vector3<f64>,
    },
    /// Slides on a level set of a signed distance field's cubic B-spline
    /// ([`SignedDistanceField::spline`]): the wall itself, or the wall offset by
    /// the node's rest distance to it, so that a node resting off the wall is not pulled onto
    /// it with no load; `level_m` other than `rest_level_m` is a wall moved along its normal.
    Surface {
        /// Index of the field in [`ConstraintSet::fields`].
        field: u32,
        /// Distance value the node is held at, metres (at load factor 1).
        level_m: f64,
        /// Distance value at load factor 0, metres: the level the node rests on.
        rest_level_m: f64,
    },
}

impl NodeConstraint {
    /// Sliding on level `level_m` of surface `field`, which the node rests on (no imposed
    /// motion; 0 is the surface itself).
    pub fn surface(field: u32, level_m: f64) -> Self {
        NodeConstraint::Surface {
            field,
            level_m,
            rest_level_m: level_m,
        }
    }

    /// Multiplies the displacement this constraint imposes on its node (resting at `rest_m`)
    /// by `factor`: a moved plane, level or target moves `factor` times as far; a line
    /// imposes none.
    pub fn scale_imposed_offset(&mut self, rest_m: Vector3<f64>, factor: f64) {
        match self {
            NodeConstraint::Fixed { target_m } => {
                *target_m = rest_m + (*target_m - rest_m) * factor
            }
            NodeConstraint::Plane { point_m, .. } => {
                *point_m = rest_m + (*point_m - rest_m) * factor
            }
            NodeConstraint::Surface {
                level_m,
                rest_level_m,
                ..
            } => *level_m = *rest_level_m + (*level_m - *rest_level_m) * factor,
            NodeConstraint::Line { .. } => {}
        }
    }
}

/// All constraints of a model: at most one per node, stored sparsely.
#[derive(Debug, Clone, Default)]
pub struct ConstraintSet {
    /// Constrained node and its constraint, in insertion order.
    pub entries: Vec<(u32, NodeConstraint)>,
    /// Implicit surfaces referenced by [`NodeConstraint::Surface`], shared: a CT wall field
    /// is the largest array of a clinical model, and every scene and load step holds the set.
    pub fields: Vec<Arc<SignedDistanceField>>,
    slot: Vec<u32>,
}

const FREE: u32 = u32::MAX;

impl ConstraintSet {
    /// An empty set for a mesh of `node_count` nodes.
    pub fn new(node_count: usize) -> Self {
        ConstraintSet {
            entries: Vec::new(),
            fields: Vec::new(),
            slot: vec![FREE; node_count],
        }
    }

    /// Adds or replaces the constraint of `node`; checks the node and the geometry.
    pub fn set(&mut self, node: u32, constraint: NodeConstraint) -> Result<()> {
        let n = node as usize;
        if n >= self.slot.len() {
            return Err(Error::InvalidModel(format!(
                "constraint on node {node}, but the mesh has {} nodes",
                self.slot.len()
            )));
        }
        let constraint = match constraint {
            NodeConstraint::Fixed { target_m } => {
                finite(&target_m, node, "target")?;
                constraint
            }
            NodeConstraint::Plane { point_m, normal } => {
                finite(&point_m, node, "plane point")?;
                NodeConstraint::Plane {
                    point_m,
                    normal: unit(normal, node, "plane normal")?,
                }
            }
            NodeConstraint::Line { point_m, direction } => {
                finite(&point_m, node, "line point")?;
                NodeConstraint::Line {
                    point_m,
                    direction: unit(direction, node, "line direction")?,
                }
            }
            NodeConstraint::Surface {
                field,
                level_m,
                rest_level_m,
            } => {
                if field as usize >= self.fields.len() {
                    return Err(Error::InvalidModel(format!(
                        "node {node} slides on surface {field}, but only {} surfaces exist",
                        self.fields.len()
                    )));
                }
                if !level_m.is_finite() || !rest_level_m.is_finite() {
                    return Err(Error::InvalidModel(format!(
                        "node {node} slides on surface {field} at level {level_m} m (rest \
                         {rest_level_m} m): the levels must be finite"
                    )));
                }
                constraint
            }
        };
        match self.slot[n] {
            FREE => {
                self.slot[n] = self.entries.len() as u32;
                self.entries.push((node, constraint));
            }
            s => self.entries[s as usize].1 = constraint,
        }
        Ok(())
    }

    /// Removes the constraints of the nodes `take` accepts and returns them in insertion
    /// order (the rest keep theirs, in their order).
    pub fn take_where(&mut self, mut take: impl FnMut(u32) -> bool) -> Vec<(u32, NodeConstraint)> {
        let (taken, kept): (Vec<_>, Vec<_>) = std::mem::take(&mut self.entries)
            .into_iter()
            .partition(|(n, _)| take(*n));
        self.entries = kept;
        self.slot.iter_mut().for_each(|s| *s = FREE);
        for (i, (n, _)) in self.entries.iter().enumerate() {
            self.slot[*n as usize] = i as u32;
        }
        taken
    }

    /// Fixes `node` at `target_m`.
    pub fn fix(&mut self, node: u32, target_m: Vector3<f64>) -> Result<()> {
        self.set(node, NodeConstraint::Fixed { target_m })
    }

    /// Adds an implicit surface and returns its index for [`NodeConstraint::Surface`].
    pub fn add_surface(&mut self, field: impl Into<Arc<SignedDistanceField>>) -> u32 {
        self.fields.push(field.into());
        (self.fields.len() - 1) as u32
    }

    /// The constraint of `node`, if any.
    pub fn get(&self, node: u32) -> Option<&NodeConstraint> {
        match self.slot.get(node as usize) {
            Some(&s) if s != FREE => Some(&self.entries[s as usize].1),
            _ => None,
        }
    }

    /// Number of nodes the set was built for.
    pub fn node_count(&self) -> usize {
        self.slot.len()
    }

    /// Moves a position onto the constraint's manifold.
    pub fn project_position(&self, c: &NodeConstraint, x: Vector3<f64>) -> Vector3<f64> {
        match *c {
            NodeConstraint::Fixed { target_m } => target_m,
            NodeConstraint::Plane { point_m, normal } => x - normal * (x - point_m).dot(&normal),
            NodeConstraint::Line { point_m, direction } => {
                point_m + direction * (x - point_m).dot(&direction)
            }
            NodeConstraint::Surface { field, level_m, .. } => {
                self.fields[field as usize].project_to_spline_level_m(x, level_m)
            }
        }
    }

    /// Removes from `v` the directions the constraint forbids at position `x`
    /// (the tangent projection of a velocity, force or displacement increment).
    pub fn project_free(
        &self,
        c: &NodeConstraint,
        x: Vector3<f64>,
        v: Vector3<f64>,
    ) -> Vector3<f64> {
        match *c {
            NodeConstraint::Fixed { .. } => Vector3::zeros(),
            NodeConstraint::Plane { normal, .. } => v - normal * v.dot(&normal),
            NodeConstraint::Line { direction, .. } => direction * v.dot(&direction),
            NodeConstraint::Surface { field, .. } => {
                let n = self.fields[field as usize].spline_normal(x);
                v - n * v.dot(&n)
            }
        }
    }

    /// The projector onto the directions the constraint leaves free at position `x`
    /// (for a surface, its tangent plane there).
    pub fn free_projector(&self, c: &NodeConstraint, x: Vector3<f64>) -> nalgebra::Matrix3<f64> {
        use nalgebra::Matrix3;
        match *c {
            NodeConstraint::Fixed { .. } => Matrix3::zeros(),
            NodeConstraint::Plane { normal, .. } => {
                Matrix3::identity() - normal * normal.transpose()
            }
            NodeConstraint::Line { direction, .. } => direction * direction.transpose(),
            NodeConstraint::Surface { field, .. } => {
                let n = self.fields[field as usize].spline_normal(x);
                Matrix3::identity() - n * n.transpose()
            }
        }
    }

    /// Puts every constrained node of `positions` onto its manifold.
    pub fn project_positions(&self, positions: &mut [Vector3<f64>]) {
        for (node, c) in &self.entries {
            let x = &mut positions[*node as usize];
            *x = self.project_position(c, *x);
        }
    }

    /// Removes the forbidden directions of a per-node vector field (velocities, forces).
    pub fn project_field(&self, positions: &[Vector3<f64>], field: &mut [Vector3<f64>]) {
        for (node, c) in &self.entries {
            let n = *node as usize;
            field[n] = self.project_free(c, positions[n], field[n]);
        }
    }

    /// Reaction forces (eq. 4.1): for each constrained node, minus the part of its total force
    /// the constraint forbids, so that the constraint is visible as a force.
    pub fn reactions(
        &self,
        positions: &[Vector3<f64>],
        total_force_n: &[Vector3<f64>],
    ) -> Vec<(u32, Vector3<f64>)> {
        self.entries
            .iter()
            .map(|(node, c)| {
                let n = *node as usize;
                let f = total_force_n[n];
                (*node, self.project_free(c, positions[n], f) - f)
            })
            .collect()
    }

    /// Whether a constraint moves its node away from `rest_positions_m`: a fixed target off
    /// the rest position, or a plane that does not pass through it. Such a constraint is an
    /// imposed displacement, applied in proportion to the load factor
    /// ([`ConstraintSet::at_load_factor`]).
    pub fn imposes_motion(&self, rest_positions_m: &[Vector3<f64>]) -> bool {
        self.entries.iter().any(|(node, c)| {
            imposed_offset(c, rest_positions_m[*node as usize], &self.fields).is_some()
        })
    }

    /// The set with every imposed displacement scaled by `factor` (0: every moving constraint
    /// passes through its node's rest position; 1: the set itself). Planes move along their
    /// normal only, so a plane through its node's rest position never moves.
    pub fn at_load_factor<'s>(
        &'s self,
        rest_positions_m: &[Vector3<f64>],
        factor: f64,
    ) -> std::borrow::Cow<'s, ConstraintSet> {
        // Most scenes (a lung on a rigid wall with a fixed hilum) impose no displacement:
        // borrow rather than copy the sliding surfaces' distance fields on every solve.
        if factor == 1.0 || !self.imposes_motion(rest_positions_m) {
            return std::borrow::Cow::Borrowed(self);
        }
        let mut out = self.clone();
        self.write_at_load_factor(rest_positions_m, factor, &mut out);
        std::borrow::Cow::Owned(out)
    }

    /// Writes [`ConstraintSet::at_load_factor`] into `out`, a clone of this set, without
    /// allocating (the explicit integrator moves the wall on every time step).
    pub fn write_at_load_factor(
        &self,
        rest_positions_m: &[Vector3<f64>],
        factor: f64,
        out: &mut ConstraintSet,
    ) {
        for ((node, c), (_, o)) in self.entries.iter().zip(out.entries.iter_mut()) {
            let r = rest_positions_m[*node as usize];
            *o = match *c {
                NodeConstraint::Fixed { target_m } => NodeConstraint::Fixed {
                    target_m: r + (target_m - r) * factor,
                },
                NodeConstraint::Plane { point_m, normal } => NodeConstraint::Plane {
                    point_m: r + normal * ((point_m - r).dot(&normal) * factor),
                    normal,
                },
                NodeConstraint::Surface {
                    field,
                    level_m,
                    rest_level_m,
                } => NodeConstraint::Surface {
                    field,
                    level_m: rest_level_m + (level_m - rest_level_m) * factor,
                    rest_level_m,
                },
                other => other,
            };
        }
    }

    /// Checks that every surface field covers its constrained nodes' rest positions.
    pub fn validate(&self, rest_positions_m: &[Vector3<f64>]) -> Result<()> {
        if rest_positions_m.len() != self.slot.len() {
            return Err(Error::InvalidModel(format!(
                "constraint set built for {} nodes, mesh has {}",
                self.slot.len(),
                rest_positions_m.len()
            )));
        }
        for (node, c) in &self.entries {
            if let NodeConstraint::Surface { field, .. } = c {
                let f = &self.fields[*field as usize];
                let p = rest_positions_m[*node as usize];
                let outside = (0..3).any(|a| {
                    let extent = f.spacing_m[a] * (f.samples[a] - 1) as f64;
                    let t = p[a] - f.origin_m[a];
                    t < -1e-9 * extent || t > extent * (1.0 + 1e-9)
                });
                if outside {
                    return Err(Error::InvalidModel(format!(
                        "node {node} slides on surface {field}, but its rest position \
                         ({:.4}, {:.4}, {:.4}) m lies outside that field's sampled box",
                        p.x, p.y, p.z
                    )));
                }
            }
        }
        Ok(())
    }
}

/// The displacement `c` imposes on a node resting at `rest` (at load factor 1), if any.
/// A surface's level moved by δ moves the node by about δ along the wall's normal at rest
/// (`fields` resolves that normal).
fn imposed_offset(
    c: &NodeConstraint,
    rest: Vector3<f64>,
    fields: &[Arc<SignedDistanceField>],
) -> Option<Vector3<f64>> {
    let offset = match *c {
        NodeConstraint::Fixed { target_m } => target_m - rest,
        NodeConstraint::Plane { point_m, normal } => normal * (point_m - rest).dot(&normal),
        NodeConstraint::Surface {
            field,
            level_m,
            rest_level_m,
        } => {
            if level_m == rest_level_m {
                return None;
            }
            fields[field as usize].spline_normal(rest) * (level_m - rest_level_m)
        }
        NodeConstraint::Line { .. } => return None,
    };
    (offset != Vector3::zeros()).then_some(offset)
}

/// Displacement imposed on each constrained node at load factor 1, with its node: what a
/// moving wall or a prescribed motion sweeps per unit of load.
pub fn imposed_displacements(
    constraints: &ConstraintSet,
    rest_positions_m: &[Vector3<f64>],
) -> Vec<(u32, Vector3<f64>)> {
    constraints
        .entries
        .iter()
        .filter_map(|(node, c)| {
            imposed_offset(c, rest_positions_m[*node as usize], &constraints.fields)
                .map(|o| (*node, o))
        })
        .collect()
}

fn finite(v: &Vector3<f64>, node: u32, what: &str) -> Result<()> {
    if v.iter().all(|x| x.is_finite()) {
        Ok(())
    } else {
        Err(Error::InvalidModel(format!(
            "node {node}: {what} is not finite"
        )))
    }
}

fn unit(v: Vector3<f64>, node: u32, what: &str) -> Result<Vector3<f64>> {
    finite(&v, node, what)?;
    let n = v.norm();
    if n < 1e-12 {
        return Err(Error::InvalidModel(format!(
            "node {node}: {what} has zero length"
        )));
    }
    Ok(v / n)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn plane_keeps_tangent_motion_and_reports_normal_reaction() {
        let mut cs = ConstraintSet::new(2);
        cs.set(
            1,
            NodeConstraint::Plane {
                point_m: Vector3::zeros(),
                normal: Vector3::new(0.0, 0.0, 2.0),
            },
        )
        .unwrap();
        let x = vec![Vector3::zeros(), Vector3::new(1.0, 2.0, 3.0)];
        let mut p = x.clone();
        cs.project_positions(&mut p);
        assert_eq!(p[1], Vector3::new(1.0, 2.0, 0.0));
        let f = vec![Vector3::zeros(), Vector3::new(1.0, 1.0, 5.0)];
        let r = cs.reactions(&p, &f);
        assert_eq!(r, vec![(1, Vector3::new(0.0, 0.0, -5.0))]);
    }

    #[test]
    fn imposed_motion_scales_with_the_load_factor_and_planes_move_along_their_normal() {
        let rest = vec![Vector3::new(1.0, 2.0, 0.0), Vector3::new(0.0, 0.0, 0.0)];
        let mut cs = ConstraintSet::new(2);
        // A plane through node 0's rest position, given by another point: no motion.
        let normal = Vector3::z();
        cs.set(
            0,
            NodeConstraint::Plane {
                point_m: Vector3::new(5.0, -3.0, 0.0),
                normal,
            },
        )
        .unwrap();
        assert!(!cs.imposes_motion(&rest));
        assert!(matches!(
            cs.at_load_factor(&rest, 0.5),
            std::borrow::Cow::Borrowed(_)
        ));
        // Moved 2 along its normal and 7 within itself: only the normal offset is imposed.
        cs.set(
            1,
            NodeConstraint::Plane {
                point_m: Vector3::new(7.0, 0.0, 2.0),
                normal,
            },
        )
        .unwrap();
        assert!(cs.imposes_motion(&rest));
        assert_eq!(
            imposed_displacements(&cs, &rest),
            vec![(1, Vector3::new(0.0, 0.0, 2.0))]
        );
        let half = cs.at_load_factor(&rest, 0.5);
        let mut x = rest.clone();
        half.project_positions(&mut x);
        assert_eq!(x[0], rest[0]);
        assert_eq!(x[1], Vector3::new(0.0, 0.0, 1.0));
        let zero = cs.at_load_factor(&rest, 0.0);
        let mut x = rest.clone();
        zero.project_positions(&mut x);
        assert_eq!(x, rest);
    }

    #[test]
    fn a_surface_level_holds_its_node_at_rest_and_moves_with_the_load_factor() {
        // A flat wall z = 0.5 (distance increasing upwards), a node resting 0.1 above it.
        let field =
            SignedDistanceField::from_fn(Vector3::zeros(), Vector3::repeat(1.0), 0.05, |p| {
                p.z - 0.5
            })
            .unwrap();
        let rest = vec![Vector3::new(0.4, 0.5, 0.6)];
        let mut cs = ConstraintSet::new(1);
        let s = cs.add_surface(field);
        cs.set(0, NodeConstraint::surface(s, 0.1)).unwrap();
        assert!(!cs.imposes_motion(&rest));
        let mut x = rest.clone();
        cs.project_positions(&mut x);
        assert!((x[0] - rest[0]).norm() < 1e-12, "{:?}", x[0]);
        // The wall moved out by 0.2: half of it at load factor 0.5, along the normal only.
        cs.set(
            0,
            NodeConstraint::Surface {
                field: s,
                level_m: 0.3,
                rest_level_m: 0.1,
            },
        )
        .unwrap();
        let moved = imposed_displacements(&cs, &rest);
        assert_eq!(moved.len(), 1);
        assert!((moved[0].1 - Vector3::new(0.0, 0.0, 0.2)).norm() < 1e-9);
        let half = cs.at_load_factor(&rest, 0.5);
        let mut x = vec![Vector3::new(0.3, 0.2, 0.9)];
        half.project_positions(&mut x);
        assert!(
            (x[0] - Vector3::new(0.3, 0.2, 0.7)).norm() < 1e-9,
            "{:?}",
            x[0]
        );
        // Tangent directions pass, the normal one is removed.
        let p = half.free_projector(half.get(0).unwrap(), x[0]);
        assert!((p * Vector3::new(1.0, 2.0, 3.0) - Vector3::new(1.0, 2.0, 0.0)).norm() < 1e-9);
        assert!(cs
            .set(0, NodeConstraint::surface(s, f64::NAN))
            .unwrap_err()
            .to_string()
            .contains("finite"));
    }

    #[test]
    fn refuses_a_sliding_node_outside_its_field() {
        let field =
            SignedDistanceField::from_fn(Vector3::zeros(), Vector3::repeat(1.0), 0.5, |p| {
                p.z - 0.5
            })
            .unwrap();
        let mut cs = ConstraintSet::new(2);
        let s = cs.add_surface(field);
        cs.set(0, NodeConstraint::surface(s, 0.0)).unwrap();
        cs.set(1, NodeConstraint::surface(s, 0.0)).unwrap();
        let inside = Vector3::new(0.5, 0.5, 0.5);
        assert!(cs.validate(&[inside, inside]).is_ok());
        let err = cs
            .validate(&[inside, Vector3::new(2.0, 0.5, 0.5)])
            .unwrap_err();
        assert!(err.to_string().contains("node 1"), "{err}");
    }

    #[test]
    fn refuses_bad_constraints() {
        let mut cs = ConstraintSet::new(1);
        assert!(cs.fix(3, Vector3::zeros()).is_err());
        assert!(cs.fix(0, Vector3::new(f64::NAN, 0.0, 0.0)).is_err());
        assert!(cs
            .set(
                0,
                NodeConstraint::Plane {
                    point_m: Vector3::zeros(),
                    normal: Vector3::zeros()
                }
            )
            .is_err());
        assert!(cs.set(0, NodeConstraint::surface(0, 0.0)).is_err());
    }
}
