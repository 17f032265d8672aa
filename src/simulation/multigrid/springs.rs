//! The fine level's element operator: the small-strain stiffness of a brick evaluated
//! through its springs and corrections, one element or [`LANES`] elements at a time.

use nalgebra::Matrix3;

use crate::math::V3;
use crate::model::element::CORNER_SIGNS;
use crate::simulation::lanes::{LaneV3, Lanes, LANES};

/// Row-major 3 × 3 matrix times a lane vector, summed left to right like nalgebra's product.
#[inline(always)]
fn mat_vec(m: &[Lanes; 9], v: &LaneV3) -> LaneV3 {
    std::array::from_fn(|r| m[3 * r] * v[0] + m[3 * r + 1] * v[1] + m[3 * r + 2] * v[2])
}

/// Transposed row-major 3 × 3 matrix times a lane vector.
#[inline(always)]
fn mat_t_vec(m: &[Lanes; 9], v: &LaneV3) -> LaneV3 {
    std::array::from_fn(|r| m[r] * v[0] + m[3 + r] * v[1] + m[6 + r] * v[2])
}

/// The small-strain element operator K·u evaluated through the springs and corrections in the
/// lattice frame, where an edge spring couples one displacement component and the diagonals
/// have fixed directions: ≈ 200 flops instead of 1152 for the dense 24 × 24 product.
#[derive(Debug, Clone)]
pub(super) struct LinearSprings {
    edge_k: [f64; 3],
    diag_k: f64,
    /// Unit direction of each body diagonal (corner a → corner b) in the lattice frame.
    diag_dir: [V3; 4],
    /// World → lattice rotation (transpose of the lattice axes), `None` when they coincide.
    pub(super) to_lattice: Option<Matrix3<f64>>,
    correction_map: Matrix3<f64>,
}

/// Body diagonals (a, b) of the element: the last four of `element::SPRINGS`.
const DIAGONALS: [(usize, usize); 4] = {
    let s = &crate::model::element::SPRINGS;
    [
        (s[12].0, s[12].1),
        (s[13].0, s[13].1),
        (s[14].0, s[14].1),
        (s[15].0, s[15].1),
    ]
};

impl LinearSprings {
    /// The springs of class `c` on a lattice with world axes `axes` (as columns).
    pub(super) fn new(c: &crate::model::BrickCoefficients, axes: &Matrix3<f64>) -> Self {
        let offsets = c.corner_offsets_m();
        let to_lattice = if (axes - Matrix3::identity()).amax() < 1e-14 {
            None
        } else {
            Some(axes.transpose())
        };
        LinearSprings {
            edge_k: c.edge_stiffness_n_per_m,
            diag_k: c.diagonal_stiffness_n_per_m,
            diag_dir: DIAGONALS.map(|(a, b)| (offsets[b] - offsets[a]).normalize()),
            to_lattice,
            correction_map: c.correction_map,
        }
    }

    /// K·u for the 8 corner displacements u (K = −∂force/∂u), world frame in and out: the
    /// one-element reference for [`LaneSprings::apply`].
    #[cfg(test)]
    pub(super) fn apply(&self, u_world: &[V3; 8]) -> [V3; 8] {
        let u = match &self.to_lattice {
            Some(r) => u_world.map(|v| r * v),
            None => *u_world,
        };
        // Spring forces of displacement u, lattice frame.
        let mut f = [V3::zeros(); 8];
        for &(a, b, kind) in &crate::model::element::SPRINGS {
            let crate::model::element::SpringKind::Edge(i) = kind else {
                continue;
            };
            let t = self.edge_k[i] * (u[b][i] - u[a][i]);
            f[a][i] += t;
            f[b][i] -= t;
        }
        for (d, &(a, b)) in self.diag_dir.iter().zip(&DIAGONALS) {
            let t = d * (self.diag_k * d.dot(&(u[b] - u[a])));
            f[a] += t;
            f[b] -= t;
        }
        let mut axial = V3::zeros();
        for (n, signs) in CORNER_SIGNS.iter().enumerate() {
            for i in 0..3 {
                axial[i] -= 0.5 * signs[i] * f[n][i];
            }
        }
        let w = self.correction_map * axial;
        for (n, signs) in CORNER_SIGNS.iter().enumerate() {
            for i in 0..3 {
                f[n][i] = -(f[n][i] + signs[i] * w[i]);
            }
        }
        match &self.to_lattice {
            Some(r) => f.map(|v| r.transpose() * v),
            None => f,
        }
    }
}

/// [`LinearSprings`] replicated across lanes (or gathered, for batches mixing classes).
#[derive(Debug, Clone)]
pub(super) struct LaneSprings {
    edge_k: [Lanes; 3],
    diag_k: Lanes,
    diag_dir: [LaneV3; 4],
    /// Row-major correction map W.
    correction_map: [Lanes; 9],
}

impl LaneSprings {
    /// `s` in every lane.
    pub(super) fn splat(s: &LinearSprings) -> Self {
        LaneSprings {
            edge_k: s.edge_k.map(Lanes::splat),
            diag_k: Lanes::splat(s.diag_k),
            diag_dir: s.diag_dir.map(|d| [d.x, d.y, d.z].map(Lanes::splat)),
            correction_map: std::array::from_fn(|r| Lanes::splat(s.correction_map[(r / 3, r % 3)])),
        }
    }

    /// Lane `l` taken from `kernels[classes[l]]`.
    pub(super) fn gather(kernels: &[LaneSprings], classes: &[u32; LANES]) -> Self {
        let pick = |get: &dyn Fn(&LaneSprings) -> Lanes| {
            Lanes(std::array::from_fn(|l| {
                get(&kernels[classes[l] as usize]).0[l]
            }))
        };
        LaneSprings {
            edge_k: std::array::from_fn(|i| pick(&|k| k.edge_k[i])),
            diag_k: pick(&|k| k.diag_k),
            diag_dir: std::array::from_fn(|d| std::array::from_fn(|i| pick(&|k| k.diag_dir[d][i]))),
            correction_map: std::array::from_fn(|r| pick(&|k| k.correction_map[r])),
        }
    }

    /// `LinearSprings::apply` on [`LANES`] elements at once (`rotation`: world → lattice,
    /// row-major). Same operations in the same order, except that the axial resultants are
    /// summed before the exact scaling by −½, which leaves them bit-for-bit unchanged.
    /// `u` (world frame) is rotated in place; `f` is overwritten.
    #[inline(always)]
    pub(super) fn apply(
        &self,
        rotation: Option<&[Lanes; 9]>,
        u: &mut [LaneV3; 8],
        f: &mut [LaneV3; 8],
    ) {
        if let Some(r) = rotation {
            for v in u.iter_mut() {
                *v = mat_vec(r, v);
            }
        }
        // `element::SPRINGS`' edges spelled out with constant indices (a loop over the table indexes
        // memory). Every corner has exactly one edge along each axis, so the edges initialise
        // all of `f` (0 + t and 0 − t, as the accumulating form computes them).
        macro_rules! edge {
            ($(($a:literal, $b:literal, $i:literal)),*) => {$(
                let t = self.edge_k[$i] * (u[$b][$i] - u[$a][$i]);
                f[$a][$i] = Lanes::ZERO + t;
                f[$b][$i] = Lanes::ZERO - t;
            )*};
        }
        edge!(
            (0, 1, 0),
            (3, 2, 0),
            (4, 5, 0),
            (7, 6, 0),
            (0, 3, 1),
            (1, 2, 1),
            (4, 7, 1),
            (5, 6, 1),
            (0, 4, 2),
            (1, 5, 2),
            (2, 6, 2),
            (3, 7, 2)
        );
        macro_rules! diagonal {
            ($(($d:literal, $a:literal, $b:literal)),*) => {$(
                let d = &self.diag_dir[$d];
                let du: LaneV3 = [
                    u[$b][0] - u[$a][0],
                    u[$b][1] - u[$a][1],
                    u[$b][2] - u[$a][2],
                ];
                let s = self.diag_k * (d[0] * du[0] + d[1] * du[1] + d[2] * du[2]);
                for i in 0..3 {
                    let t = d[i] * s;
                    f[$a][i] = f[$a][i] + t;
                    f[$b][i] = f[$b][i] - t;
                }
            )*};
        }
        diagonal!((0, 0, 6), (1, 1, 7), (2, 2, 4), (3, 3, 5));
        // axial_i = −½ Σ_n s_n,i f_n,i (scaling by ±½ is exact, so it can come last).
        let mut g = [Lanes::ZERO; 3];
        for (n, signs) in CORNER_SIGNS.iter().enumerate() {
            for i in 0..3 {
                g[i] = if signs[i] > 0.0 {
                    g[i] + f[n][i]
                } else {
                    g[i] - f[n][i]
                };
            }
        }
        let half = Lanes::splat(-0.5);
        let axial = [half * g[0], half * g[1], half * g[2]];
        let w = mat_vec(&self.correction_map, &axial);
        // f ← −(f + s·w), written as (−f) ∓ w: negation is exact.
        for (n, signs) in CORNER_SIGNS.iter().enumerate() {
            for i in 0..3 {
                let neg = Lanes::ZERO - f[n][i];
                f[n][i] = if signs[i] > 0.0 {
                    neg - w[i]
                } else {
                    neg + w[i]
                };
            }
        }
        if let Some(r) = rotation {
            for v in f.iter_mut() {
                *v = mat_t_vec(r, v);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::super::M24;
    use super::*;
    use crate::model::{BrickCoefficients, BrickShape, Material};
    use nalgebra::{Rotation3, SMatrix};

    #[test]
    fn spring_operator_equals_dense_element_stiffness() {
        let rotated = *Rotation3::from_euler_angles(0.3, -0.7, 1.1).matrix();
        for (edges, axes) in [
            ([1.0, 1.0, 1.0], Matrix3::identity()),
            ([1.0, 1.2, 0.9], Matrix3::identity()),
            ([1.0, 1.2, 0.9], rotated),
        ] {
            let c = BrickCoefficients::new(
                BrickShape { edges_m: edges },
                Material::new(1000.0, 0.3, 1.0).unwrap(),
            )
            .unwrap();
            // The dense matrix is in the element frame; rotate it to the world frame.
            let k_local = c.linear_stiffness();
            let mut r24 = M24::zeros();
            for n in 0..8 {
                r24.fixed_view_mut::<3, 3>(3 * n, 3 * n).copy_from(&axes);
            }
            let k = r24 * k_local * r24.transpose();
            let op = LinearSprings::new(&c, &axes);
            let u: [V3; 8] = std::array::from_fn(|n| {
                V3::new(
                    (n as f64).sin(),
                    (2.0 * n as f64).cos(),
                    0.3 * n as f64 - 1.0,
                )
            });
            let got = op.apply(&u);
            let mut flat_u = SMatrix::<f64, 24, 1>::zeros();
            for (n, un) in u.iter().enumerate() {
                flat_u.fixed_view_mut::<3, 1>(3 * n, 0).copy_from(un);
            }
            let want = k * flat_u;
            for n in 0..8 {
                for i in 0..3 {
                    assert!(
                        (got[n][i] - want[3 * n + i]).abs() < 1e-9 * k.amax(),
                        "edges {edges:?} corner {n} axis {i}: {} vs {}",
                        got[n][i],
                        want[3 * n + i]
                    );
                }
            }
        }
    }
}
