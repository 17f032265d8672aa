//! One-sided contact on planes: nodes resting against a rigid obstacle (for the lung's
//! mediastinal face, the heart and the great vessels) may slide along it or leave it, but
//! never cross it.
//!
//! This is the stiff limit of the penalty contact of [`super::contact`]. A penalty force has
//! no stiffness at first touch, so a body held in some direction *only* by contact gives
//! Newton's method a singular tangent there (a block pressed onto a plane by a pressure
//! stalled at a relative residual of 0.93). Here a node pressed against its plane is held on
//! it, exactly like a sliding node, and freed when the plane would have to pull it; a free
//! node that crosses its plane is put back on it. The quasi-static solver repeats its Newton
//! solve until that active set stops changing (Signorini's conditions: no penetration, no
//! pull, and a reaction only where the node touches).

use nalgebra::Vector3;
use serde::Serialize;

use super::NodeConstraint;
use crate::math::V3;
use crate::{Error, Result};

/// Nodes kept on one side of their own plane: the plane through the node's rest position,
/// tangent to the obstacle there.
#[derive(Debug, Clone, Default)]
pub struct OneSidedPlanes {
    nodes: Vec<u32>,
    points_m: Vec<V3>,
    /// Unit normals pointing into the obstacle.
    normals: Vec<V3>,
}

/// How one round of [`OneSidedPlanes::update_active`] changed the active set.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize)]
pub struct ActiveSetChange {
    /// Nodes in contact that the plane would have had to pull, now free.
    pub released: usize,
    /// Free nodes found across their plane, now held on it.
    pub engaged: usize,
}

impl ActiveSetChange {
    /// Whether the set changed.
    pub fn changed(&self) -> bool {
        self.released + self.engaged > 0
    }
}

/// Where the nodes are against their planes (a frame's report).
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct OneSidedState {
    /// Nodes held by contact.
    pub nodes: usize,
    /// Nodes within `touch_m` of their plane.
    pub touching: usize,
    /// Largest distance a node has left its plane by, m.
    pub max_separation_m: f64,
    /// The node that has left its plane farthest (none when every node touches).
    pub farthest_node: Option<u32>,
    /// Largest distance a node is across its plane (into the obstacle), m.
    pub max_penetration_m: f64,
}

impl OneSidedPlanes {
    /// Planes `(node, point on the plane in m, normal into the obstacle)` for a mesh of
    /// `node_count` nodes; refuses an unknown or repeated node, a non-finite point and a
    /// normal that is not a direction.
    pub fn new(node_count: usize, planes: Vec<(u32, V3, V3)>) -> Result<Self> {
        let mut seen = vec![false; node_count];
        let mut out = OneSidedPlanes::default();
        for (node, point_m, normal) in planes {
            let bad = |why: String| Error::InvalidModel(format!("one-sided contact: {why}"));
            let slot = seen
                .get_mut(node as usize)
                .ok_or_else(|| bad(format!("node {node}, but the mesh has {node_count} nodes")))?;
            if std::mem::replace(slot, true) {
                return Err(bad(format!("node {node} is given twice")));
            }
            if !point_m.iter().all(|c| c.is_finite()) {
                return Err(bad(format!(
                    "node {node}'s plane point {point_m:?} is not finite"
                )));
            }
            let length = normal.norm();
            if !(length.is_finite() && length > 1e-12) {
                return Err(bad(format!(
                    "node {node}'s plane normal {normal:?} has no direction"
                )));
            }
            out.nodes.push(node);
            out.points_m.push(point_m);
            out.normals.push(normal / length);
        }
        Ok(out)
    }

    /// Whether no node is held by contact.
    pub fn is_empty(&self) -> bool {
        self.nodes.is_empty()
    }

    /// Number of nodes held by contact.
    pub fn len(&self) -> usize {
        self.nodes.len()
    }

    /// The nodes, in order.
    pub fn nodes(&self) -> &[u32] {
        &self.nodes
    }

    /// The sliding constraint of contact `i` while it touches.
    pub fn constraint(&self, i: usize) -> NodeConstraint {
        NodeConstraint::Plane {
            point_m: self.points_m[i],
            normal: self.normals[i],
        }
    }

    /// How far node `i` is across its plane at positions `x` (negative: off it), m.
    pub fn penetration_m(&self, i: usize, x: &[V3]) -> f64 {
        (x[self.nodes[i] as usize] - self.points_m[i]).dot(&self.normals[i])
    }

    /// The force pressing node `i` into the obstacle, N (negative: pulling it off), from the
    /// node's total force (internal, external and other contact) `total_force_n`.
    pub fn pressing_force_n(&self, i: usize, total_force_n: &[V3]) -> f64 {
        total_force_n[self.nodes[i] as usize].dot(&self.normals[i])
    }

    /// One round of the active set at an equilibrium `x` with total forces `total_force_n`:
    /// releases the held nodes pulled off their plane by more than `pull_tolerance_n` and
    /// engages the free ones across it by more than `penetration_tolerance_m`.
    pub fn update_active(
        &self,
        x: &[V3],
        total_force_n: &[V3],
        active: &mut [bool],
        pull_tolerance_n: f64,
        penetration_tolerance_m: f64,
    ) -> ActiveSetChange {
        let mut change = ActiveSetChange::default();
        for (i, on) in active.iter_mut().enumerate() {
            if *on {
                if self.pressing_force_n(i, total_force_n) < -pull_tolerance_n {
                    *on = false;
                    change.released += 1;
                }
            } else if self.penetration_m(i, x) > penetration_tolerance_m {
                *on = true;
                change.engaged += 1;
            }
        }
        change
    }

    /// The contacts `active` holds on their planes (indices into this set).
    pub fn touching(active: &[bool]) -> impl Iterator<Item = usize> + '_ {
        active
            .iter()
            .enumerate()
            .filter(|(_, on)| **on)
            .map(|(i, _)| i)
    }

    /// Mean |pressing force| over the nodes `active` holds, N (0 when none is held): the
    /// scale of the pull that releases a node.
    pub fn mean_pressing_force_n(&self, total_force_n: &[V3], active: &[bool]) -> f64 {
        let (sum, count) = Self::touching(active).fold((0.0, 0usize), |(s, c), i| {
            (s + self.pressing_force_n(i, total_force_n).abs(), c + 1)
        });
        if count == 0 {
            0.0
        } else {
            sum / count as f64
        }
    }

    /// The explicit integrators' contact: a node across its plane is put back on it and
    /// loses the velocity that carries it further in (a perfectly inelastic impact, the
    /// penalty's stiff limit); a node moving off keeps its velocity. Returns the nodes moved.
    pub fn enforce(&self, x: &mut [V3], v: &mut [V3]) -> usize {
        let mut moved = 0;
        for (i, &node) in self.nodes.iter().enumerate() {
            let n = self.normals[i];
            let depth = (x[node as usize] - self.points_m[i]).dot(&n);
            if depth > 0.0 {
                x[node as usize] -= n * depth;
                moved += 1;
                let inward = v[node as usize].dot(&n);
                if inward > 0.0 {
                    v[node as usize] -= n * inward;
                }
            }
        }
        moved
    }

    /// Where the nodes are at `x`: touching within `touch_m`, the largest separation and the
    /// largest penetration.
    pub fn state(&self, x: &[V3], touch_m: f64) -> OneSidedState {
        let mut s = OneSidedState {
            nodes: self.len(),
            ..OneSidedState::default()
        };
        for i in 0..self.len() {
            let d = self.penetration_m(i, x);
            if d > -touch_m {
                s.touching += 1;
            }
            if -d > s.max_separation_m {
                s.max_separation_m = -d;
                s.farthest_node = Some(self.nodes[i]);
            }
            s.max_penetration_m = s.max_penetration_m.max(d);
        }
        s
    }

    /// The planes' outward normal of node `i` as a plain vector (for reports and tests).
    pub fn normal(&self, i: usize) -> Vector3<f64> {
        self.normals[i]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn planes() -> OneSidedPlanes {
        OneSidedPlanes::new(
            3,
            vec![
                (0, V3::zeros(), V3::new(0.0, 0.0, 2.0)),
                (2, V3::new(1.0, 0.0, 0.0), V3::x()),
            ],
        )
        .unwrap()
    }

    #[test]
    fn releases_a_pulled_node_and_engages_a_crossing_one() {
        let p = planes();
        assert_eq!(p.normal(0), V3::z());
        let x = vec![
            V3::new(0.0, 0.0, -1e-3),
            V3::zeros(),
            V3::new(1.002, 0.0, 0.0),
        ];
        // Node 0 pulled away from the obstacle (−z), node 2 pressed into it.
        let f = vec![V3::new(0.0, 0.0, -1.0), V3::zeros(), V3::x()];
        let mut active = vec![true, false];
        let change = p.update_active(&x, &f, &mut active, 0.1, 1e-3);
        assert_eq!(
            change,
            ActiveSetChange {
                released: 1,
                engaged: 1
            }
        );
        assert_eq!(active, vec![false, true]);
        // Within the tolerances nothing moves.
        let mut active = vec![true, false];
        let f_small = vec![V3::new(0.0, 0.0, -0.05), V3::zeros(), V3::x()];
        let x_near = vec![x[0], x[1], V3::new(1.0005, 0.0, 0.0)];
        assert!(!p
            .update_active(&x_near, &f_small, &mut active, 0.1, 1e-3)
            .changed());
        let s = p.state(&x, 1e-4);
        assert_eq!((s.nodes, s.touching), (2, 1));
        assert!((s.max_separation_m - 1e-3).abs() < 1e-12);
        assert!((s.max_penetration_m - 2e-3).abs() < 1e-12);
    }

    #[test]
    fn explicit_contact_puts_a_crossing_node_back_and_stops_its_inward_velocity() {
        let p = planes();
        let mut x = vec![
            V3::new(0.3, 0.0, 2e-3),
            V3::new(9.0, 9.0, 9.0),
            V3::new(0.5, 0.0, 0.0),
        ];
        let mut v = vec![
            V3::new(1.0, 0.0, 3.0),
            V3::new(0.0, 0.0, 5.0),
            V3::new(-2.0, 0.0, 0.0),
        ];
        assert_eq!(p.enforce(&mut x, &mut v), 1);
        assert_eq!(x[0], V3::new(0.3, 0.0, 0.0));
        assert_eq!(v[0], V3::new(1.0, 0.0, 0.0));
        // Node 1 has no plane; node 2 is off its plane and leaving it.
        assert_eq!(
            (x[1], v[1]),
            (V3::new(9.0, 9.0, 9.0), V3::new(0.0, 0.0, 5.0))
        );
        assert_eq!(
            (x[2], v[2]),
            (V3::new(0.5, 0.0, 0.0), V3::new(-2.0, 0.0, 0.0))
        );
    }

    #[test]
    fn refuses_bad_planes_by_node() {
        let e = |planes| OneSidedPlanes::new(2, planes).unwrap_err().to_string();
        assert!(e(vec![(5, V3::zeros(), V3::z())]).contains("node 5"));
        assert!(e(vec![(1, V3::zeros(), V3::z()), (1, V3::zeros(), V3::z())]).contains("twice"));
        assert!(e(vec![(0, V3::zeros(), V3::zeros())]).contains("no direction"));
        assert!(e(vec![(0, V3::new(f64::NAN, 0.0, 0.0), V3::z())]).contains("not finite"));
    }
}
