//! Penalty contact with Hunt–Crossley damping against rigid obstacles given as signed distance
//! fields (Boux de Casson 2000, §2.2.5.2, eq. 2.4, after Hunt & Crossley 1975).
//!
//! A node inside an obstacle at penetration δ > 0, closing at δ̇ = −n·(v − v_obstacle), is
//! pushed out along the obstacle's outward normal n by
//!
//! F = k·δⁿ·(1 + (3/2)·α·δ̇), clamped at 0 (contact never pulls).
//!
//! The thesis writes the penalty force as (−λx − μẋ)k⃗ and, following Hunt & Crossley,
//! multiplies its viscous term by the penetration so that the force starts and ends at zero
//! (no "sticking", its Fig. 2.12); with n = 1 and μ = (3/2)·α·k it is the law above. Hunt and
//! Crossley's own exponent for Hertzian contact is n = 3/2, and their α is the slope of the
//! coefficient of restitution against impact speed, e ≈ 1 − α·v for small α·v. The thesis
//! gives no numeric λ or μ: every parameter here is the caller's.

use std::sync::Arc;

use serde::Serialize;

use super::sdf::SignedDistanceField;
use crate::math::V3;
use crate::{Error, Result};

/// Hunt–Crossley normal contact law F = k·δⁿ·(1 + (3/2)·α·δ̇), never negative.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct HuntCrossley {
    /// k: penalty stiffness of one node, N/mⁿ (the thesis's λ when n = 1; no value given there).
    pub stiffness_n_per_m_pow_n: f64,
    /// n: exponent of the penetration (1 in the thesis's eq. 2.4, 3/2 for Hertz in Hunt and
    /// Crossley), > 0.
    pub exponent: f64,
    /// α: Hunt and Crossley's damping, s/m; the coefficient of restitution at impact speed v
    /// is ≈ 1 − α·v. 0 is a purely elastic penalty.
    pub damping_s_per_m: f64,
}

impl HuntCrossley {
    /// Checks the parameters: k > 0, n > 0, α ≥ 0, all finite.
    pub fn new(stiffness_n_per_m_pow_n: f64, exponent: f64, damping_s_per_m: f64) -> Result<Self> {
        let law = HuntCrossley {
            stiffness_n_per_m_pow_n,
            exponent,
            damping_s_per_m,
        };
        law.validate()?;
        Ok(law)
    }

    /// Refuses a law that could pull, blow up or is not a number, naming the parameter.
    pub fn validate(&self) -> Result<()> {
        let bad = |key: &str, value: f64, why: &str| Error::Config {
            settings: "contact law",
            file: None,
            key: Some(key.into()),
            reason: format!("{value} is not allowed: {why}"),
        };
        let k = self.stiffness_n_per_m_pow_n;
        if !k.is_finite() || k <= 0.0 {
            return Err(bad(
                "stiffness_n_per_m_pow_n",
                k,
                "the penalty stiffness must be positive and finite (0 is no contact, \
                 a negative one pulls nodes into the obstacle)",
            ));
        }
        let n = self.exponent;
        if !n.is_finite() || n <= 0.0 {
            return Err(bad(
                "exponent",
                n,
                "the exponent of the penetration must be positive and finite (at n ≤ 0 the \
                 force does not vanish at first touch)",
            ));
        }
        let a = self.damping_s_per_m;
        if !a.is_finite() || a < 0.0 {
            return Err(bad(
                "damping_s_per_m",
                a,
                "Hunt–Crossley damping must be finite and at least 0 (a negative one feeds \
                 energy into every impact)",
            ));
        }
        Ok(())
    }

    /// Normal force in newtons at penetration `penetration_m` (≤ 0: no contact) closing at
    /// `rate_m_per_s` (> 0 while entering).
    #[inline]
    pub fn force_n(&self, penetration_m: f64, rate_m_per_s: f64) -> f64 {
        if penetration_m <= 0.0 {
            return 0.0;
        }
        let elastic = self.stiffness_n_per_m_pow_n * penetration_m.powf(self.exponent);
        (elastic * (1.0 + 1.5 * self.damping_s_per_m * rate_m_per_s)).max(0.0)
    }

    /// The law's closed-form response for a point mass `mass_kg` striking a rigid obstacle
    /// at `impact_speed_m_per_s` with no other force acting: the energy integral of
    /// m·v·dv/dδ = −k·δⁿ·(1 + c·v), c = (3/2)·α.
    pub fn point_mass_impact(&self, mass_kg: f64, impact_speed_m_per_s: f64) -> ImpactResponse {
        let (k, n, v0) = (
            self.stiffness_n_per_m_pow_n,
            self.exponent,
            impact_speed_m_per_s,
        );
        let c = 1.5 * self.damping_s_per_m;
        // ∫ v/(1 + c·v) dv = G(v); G(v0) − G(0) = k·δ_max^(n+1) / ((n+1)·m).
        let g = |v: f64| {
            if c * v.abs() < 1e-4 {
                // Series of v/c − ln(1 + c·v)/c²: the closed form loses every digit as c → 0.
                v * v / 2.0 - c * v.powi(3) / 3.0 + c * c * v.powi(4) / 4.0
            } else {
                v / c - (c * v).ln_1p() / (c * c)
            }
        };
        let g0 = g(v0);
        let max_penetration_m = ((n + 1.0) * mass_kg * g0 / k).powf(1.0 / (n + 1.0));
        // Exit speed: G(−v_e) = G(v0), G(−v) increasing on 0 < v < 1/c (∞ at 1/c).
        let upper = if c > 0.0 { v0.min(1.0 / c) } else { v0 };
        let (mut lo, mut hi) = (0.0, upper);
        for _ in 0..200 {
            let mid = 0.5 * (lo + hi);
            if g(-mid) < g0 {
                lo = mid;
            } else {
                hi = mid;
            }
        }
        let exit = 0.5 * (lo + hi);
        ImpactResponse {
            max_penetration_m,
            exit_speed_m_per_s: exit,
            restitution: exit / v0,
            restitution_first_order: 1.0 - self.damping_s_per_m * v0,
        }
    }
}

/// A point mass's impact under a [`HuntCrossley`] law, from the closed form.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct ImpactResponse {
    /// Deepest penetration, m.
    pub max_penetration_m: f64,
    /// Speed at which the mass leaves the obstacle, m/s.
    pub exit_speed_m_per_s: f64,
    /// Coefficient of restitution: exit speed over impact speed (exact integral).
    pub restitution: f64,
    /// Hunt and Crossley's first-order estimate 1 − α·v.
    pub restitution_first_order: f64,
}

/// How an obstacle moves: rigidly translated by a piecewise-linear offset of time.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub enum ObstacleMotion {
    /// Where its field places it, always.
    Static,
    /// Translated by `offsets_m[i]` at `times_s[i]`, linearly between them and held before the
    /// first and after the last.
    Translated {
        /// Ascending instants, s.
        times_s: Vec<f64>,
        /// Offsets at those instants, m.
        offsets_m: Vec<V3>,
    },
}

impl ObstacleMotion {
    /// Refuses mismatched, empty, non-finite or non-ascending paths.
    pub fn validate(&self) -> Result<()> {
        let ObstacleMotion::Translated { times_s, offsets_m } = self else {
            return Ok(());
        };
        let bad = |reason: String| Error::Config {
            settings: "obstacle motion",
            file: None,
            key: Some("times_s".into()),
            reason,
        };
        if times_s.is_empty() || times_s.len() != offsets_m.len() {
            return Err(bad(format!(
                "{} instants for {} offsets: a path needs one offset per instant, at least one",
                times_s.len(),
                offsets_m.len()
            )));
        }
        if let Some(i) = (0..times_s.len()).find(|&i| {
            !times_s[i].is_finite()
                || !offsets_m[i].iter().all(|v| v.is_finite())
                || (i > 0 && times_s[i] <= times_s[i - 1])
        }) {
            return Err(bad(format!(
                "instant {i} ({} s, offset {:?} m) is not finite or does not follow the one \
                 before",
                times_s[i], offsets_m[i]
            )));
        }
        Ok(())
    }

    /// Offset (m) and velocity (m/s) at `t_s`.
    #[inline]
    pub fn at(&self, t_s: f64) -> (V3, V3) {
        match self {
            ObstacleMotion::Static => (V3::zeros(), V3::zeros()),
            ObstacleMotion::Translated { times_s, offsets_m } => {
                let last = times_s.len() - 1;
                if t_s <= times_s[0] {
                    return (offsets_m[0], V3::zeros());
                }
                if t_s >= times_s[last] {
                    return (offsets_m[last], V3::zeros());
                }
                let i = times_s.partition_point(|&t| t <= t_s) - 1;
                let dt = times_s[i + 1] - times_s[i];
                let velocity = (offsets_m[i + 1] - offsets_m[i]) / dt;
                (offsets_m[i] + velocity * (t_s - times_s[i]), velocity)
            }
        }
    }
}

/// A rigid obstacle: a signed distance field (negative inside the obstacle), its motion, its
/// contact law, and the nodes that may touch it.
#[derive(Debug, Clone)]
pub struct Obstacle {
    /// Distance to the obstacle's surface at its rest placement, m, negative inside. Shared:
    /// a CT's field is large and scenes are cloned (damped copies, relaxation).
    pub field: Arc<SignedDistanceField>,
    /// How it moves.
    pub motion: ObstacleMotion,
    /// The normal contact law.
    pub law: HuntCrossley,
    /// Nodes tested against it (e.g. a body's surface nodes), ascending.
    pub nodes: Vec<u32>,
}

/// Every obstacle of a scene (none by default).
#[derive(Debug, Clone, Default)]
pub struct Contact {
    /// The obstacles.
    pub obstacles: Vec<Obstacle>,
}

/// The deepest penetration of any tested node.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Penetration {
    /// Obstacle index.
    pub obstacle: usize,
    /// Node index.
    pub node: u32,
    /// Penetration, m (≤ 0: outside).
    pub depth_m: f64,
}

impl Contact {
    /// Whether there is no obstacle.
    pub fn is_empty(&self) -> bool {
        self.obstacles.is_empty()
    }

    /// Checks each law, each motion and that every tested node exists.
    pub fn validate(&self, node_count: usize) -> Result<()> {
        for (i, o) in self.obstacles.iter().enumerate() {
            o.law.validate()?;
            o.motion.validate()?;
            if let Some(&n) = o.nodes.iter().find(|&&n| n as usize >= node_count) {
                return Err(Error::InvalidModel(format!(
                    "obstacle {i} tests node {n}, but the mesh has {node_count} nodes"
                )));
            }
        }
        Ok(())
    }

    /// The same obstacles held where they are at `t_s`: a static solve or relaxation that
    /// runs its own clock must not move them.
    pub fn frozen_at(&self, t_s: f64) -> Contact {
        Contact {
            obstacles: self
                .obstacles
                .iter()
                .map(|o| Obstacle {
                    motion: match o.motion {
                        ObstacleMotion::Static => ObstacleMotion::Static,
                        _ => ObstacleMotion::Translated {
                            times_s: vec![0.0],
                            offsets_m: vec![o.motion.at(t_s).0],
                        },
                    },
                    ..o.clone()
                })
                .collect(),
        }
    }

    /// Adds the contact force on every penetrating node at positions `x` (m), velocities `v`
    /// (m/s; `None`: at rest, no damping) and time `t_s` to `out` (N).
    pub fn accumulate(&self, x: &[V3], v: Option<&[V3]>, t_s: f64, out: &mut [V3]) {
        for o in &self.obstacles {
            let (offset, velocity) = o.motion.at(t_s);
            for &n in &o.nodes {
                let n = n as usize;
                let p = x[n] - offset;
                let (d, _) = o.field.evaluate(p);
                if d >= 0.0 {
                    continue;
                }
                // The half-cell central gradient is continuous across cells: the force's
                // direction does not jump as a node slides, which Newton's finite-difference
                // Jacobian needs.
                let normal = o.field.normal(p);
                let rate = match v {
                    Some(v) => -normal.dot(&(v[n] - velocity)),
                    None => 0.0,
                };
                out[n] += normal * o.law.force_n(-d, rate);
            }
        }
    }

    /// The deepest penetration over every obstacle's tested nodes at `x` and `t_s` (`None`
    /// without obstacles or tested nodes).
    pub fn deepest(&self, x: &[V3], t_s: f64) -> Option<Penetration> {
        let mut best: Option<Penetration> = None;
        for (i, o) in self.obstacles.iter().enumerate() {
            let (offset, _) = o.motion.at(t_s);
            for &n in &o.nodes {
                let depth_m = -o.field.evaluate(x[n as usize] - offset).0;
                if best.is_none_or(|b| depth_m > b.depth_m) {
                    best = Some(Penetration {
                        obstacle: i,
                        node: n,
                        depth_m,
                    });
                }
            }
        }
        best
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn half_space(z0: f64) -> Arc<SignedDistanceField> {
        Arc::new(
            SignedDistanceField::from_fn(V3::repeat(-0.1), V3::repeat(0.1), 0.01, |p| p.z - z0)
                .unwrap(),
        )
    }

    #[test]
    fn bad_laws_are_refused_with_the_parameter_and_value() {
        for (k, n, a, key, value) in [
            (-1.0, 1.0, 0.0, "stiffness_n_per_m_pow_n", "-1"),
            (0.0, 1.0, 0.0, "stiffness_n_per_m_pow_n", "0"),
            (f64::INFINITY, 1.0, 0.0, "stiffness_n_per_m_pow_n", "inf"),
            (1.0, 0.0, 0.0, "exponent", "0"),
            (1.0, -1.5, 0.0, "exponent", "-1.5"),
            (1.0, f64::NAN, 0.0, "exponent", "NaN"),
            (1.0, 1.0, -0.2, "damping_s_per_m", "-0.2"),
            (1.0, 1.0, f64::NAN, "damping_s_per_m", "NaN"),
        ] {
            let e = HuntCrossley::new(k, n, a).unwrap_err();
            let Error::Config { key: Some(got), .. } = &e else {
                panic!("{e:?}");
            };
            assert_eq!(got, key);
            let text = e.to_string();
            assert!(text.contains(value) && text.contains(key), "{text}");
        }
        assert!(HuntCrossley::new(1.0, 1.5, 0.0).is_ok());
    }

    #[test]
    fn force_is_zero_outside_never_pulls_and_follows_the_law() {
        let law = HuntCrossley::new(200.0, 1.5, 0.4).unwrap();
        assert_eq!(law.force_n(0.0, 10.0), 0.0);
        assert_eq!(law.force_n(-1e-3, 10.0), 0.0);
        let d: f64 = 2e-3;
        let expected = 200.0 * d.powf(1.5) * (1.0 + 0.6 * 0.5);
        assert!((law.force_n(d, 0.5) - expected).abs() < 1e-12 * expected);
        // Leaving fast: the damping term exceeds the elastic one; the force stops at 0.
        assert_eq!(law.force_n(d, -5.0), 0.0);
    }

    #[test]
    fn nodes_inside_are_pushed_out_along_the_normal_and_outside_untouched() {
        let contact = Contact {
            obstacles: vec![Obstacle {
                field: half_space(0.0),
                motion: ObstacleMotion::Static,
                law: HuntCrossley::new(100.0, 1.0, 0.0).unwrap(),
                nodes: vec![0, 1],
            }],
        };
        let x = [V3::new(0.01, 0.02, 0.003), V3::new(0.0, 0.0, -0.004)];
        let mut f = [V3::zeros(); 2];
        contact.accumulate(&x, None, 0.0, &mut f);
        assert_eq!(f[0], V3::zeros());
        // The obstacle fills z < 0 (the field is z): its outward normal, and the push, are +z.
        assert!((f[1] - V3::new(0.0, 0.0, 0.4)).norm() < 1e-9, "{:?}", f[1]);
        let deepest = contact.deepest(&x, 0.0).unwrap();
        assert_eq!(deepest.node, 1);
        assert!((deepest.depth_m - 0.004).abs() < 1e-12);
    }

    #[test]
    fn a_moving_obstacle_is_where_its_path_puts_it() {
        let motion = ObstacleMotion::Translated {
            times_s: vec![0.0, 2.0],
            offsets_m: vec![V3::zeros(), V3::new(0.0, 0.0, 0.02)],
        };
        motion.validate().unwrap();
        let (o, v) = motion.at(0.5);
        assert!((o.z - 0.005).abs() < 1e-15 && (v.z - 0.01).abs() < 1e-15);
        assert_eq!(motion.at(3.0), (V3::new(0.0, 0.0, 0.02), V3::zeros()));
        let contact = Contact {
            obstacles: vec![Obstacle {
                field: half_space(0.0),
                motion,
                law: HuntCrossley::new(100.0, 1.0, 1.0).unwrap(),
                nodes: vec![0],
            }],
        };
        // At rest at z = 0.004: outside at t = 0, 6 mm inside at t = 2 s.
        let x = [V3::new(0.0, 0.0, 0.004)];
        assert!(contact.deepest(&x, 0.0).unwrap().depth_m < 0.0);
        assert!((contact.deepest(&x, 2.0).unwrap().depth_m - 0.016).abs() < 1e-12);
        // The obstacle moving into a still node closes the contact: damping adds force.
        let mut moving = [V3::zeros()];
        contact.accumulate(&x, Some(&[V3::zeros()]), 1.0, &mut moving);
        let mut frozen = [V3::zeros()];
        contact
            .frozen_at(1.0)
            .accumulate(&x, Some(&[V3::zeros()]), 7.0, &mut frozen);
        assert!((frozen[0].z - 100.0 * 0.006).abs() < 1e-9, "{frozen:?}");
        assert!((moving[0].z - frozen[0].z * (1.0 + 1.5 * 0.01)).abs() < 1e-9);
        let bad = ObstacleMotion::Translated {
            times_s: vec![0.0, 0.0],
            offsets_m: vec![V3::zeros(); 2],
        };
        assert!(bad
            .validate()
            .unwrap_err()
            .to_string()
            .contains("instant 1"));
    }

    #[test]
    fn closed_form_matches_its_limits() {
        // Undamped: all energy returns and ½mv² = kδ^(n+1)/(n+1).
        let law = HuntCrossley::new(5e3, 1.5, 0.0).unwrap();
        let r = law.point_mass_impact(0.2, 0.3);
        let expected = (2.5 * 0.5 * 0.2 * 0.09 / 5e3_f64).powf(1.0 / 2.5);
        assert!((r.max_penetration_m - expected).abs() < 1e-12 * expected);
        assert!((r.restitution - 1.0).abs() < 1e-9, "{}", r.restitution);
        // Small α·v: Hunt and Crossley's e ≈ 1 − α·v to first order.
        let law = HuntCrossley::new(5e3, 1.0, 0.05).unwrap();
        let r = law.point_mass_impact(0.2, 0.3);
        assert!(
            (r.restitution - (1.0 - 0.015)).abs() < 1e-3,
            "{}",
            r.restitution
        );
        assert!(r.max_penetration_m < (0.2 * 0.09 / 5e3_f64).sqrt());
    }
}
