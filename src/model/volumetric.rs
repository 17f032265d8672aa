//! The volumetric correction: a pressure on each element, a function of its volume ratio J,
//! that makes the element's hydrostatic response follow a continuum law instead of its springs'.
//!
//! Under a uniform stretch s every spring of a brick has the same relative elongation s − 1,
//! so its forces are the small-strain ones scaled by (s − 1)(1 + c(s − 1)²) and its Cauchy
//! pressure is exactly p_springs(J) = 3K(s − 1)(1 + c(s − 1)²)/s², s = J^(1/3) (K the bulk
//! modulus the element reproduces at small strain, c the springs' cubic ratio). The correction
//! p_law(J) − p_springs(J) has zero value and zero slope at J = 1, so E, ν and K at small
//! strain stay Baudet's; at large compression it carries the law's resistance to collapse
//! (J^(−2β) for the foam laws), which linear springs lack: they let an element squeezed against
//! a wall fold through itself at a finite load.

use std::sync::Arc;

use serde::Serialize;

use super::spring_law::ContinuumLaw;
use super::Material;

/// Volume ratios below which the tabulated correction is extended linearly (an element this
/// compressed is reported by the solvers' inversion checks long before).
const TABLE_J_MIN: f64 = 0.02;
/// Volume ratios above which it is extended linearly.
const TABLE_J_MAX: f64 = 4.0;
/// Table points: linear interpolation between them is within 1e-4 of the closed forms (relative
/// to |p| + K) over [0.1, 4] (checked by a test).
const TABLE_POINTS: usize = 8192;

/// The correction pressure p_law(J) − p_springs(J) of one material, tabulated for the force
/// kernel (one lookup instead of two `powf` per element and evaluation).
///
/// The table holds q(J) = correction/(J − 1)², smooth through J = 1, and the pressure is
/// q(J)·(J − 1)²: exactly zero at rest and second order near it whatever the interpolation
/// error, so small-strain E, ν and K keep the patch tests' precision.
#[derive(Debug, Clone, Serialize)]
pub struct VolumetricCorrection {
    /// The law followed.
    pub law: ContinuumLaw,
    #[serde(skip)]
    table_q_pa: Arc<[f64]>,
    #[serde(skip)]
    step: f64,
}

impl VolumetricCorrection {
    /// The correction for `material`'s moduli and spring law, if it names a volumetric law.
    pub fn new(material: &Material) -> Option<Self> {
        let law = material.volumetric_law?;
        let step = (TABLE_J_MAX - TABLE_J_MIN) / (TABLE_POINTS - 1) as f64;
        let q = |j: f64| exact_correction_pa(law, material, j) / ((j - 1.0) * (j - 1.0));
        // Closer to J = 1 the quotient loses digits to cancellation: interpolate across.
        let near = 2e-3;
        let (q_lo, q_hi) = (q(1.0 - near), q(1.0 + near));
        let table_q_pa = (0..TABLE_POINTS)
            .map(|i| {
                let j = TABLE_J_MIN + step * i as f64;
                let q = if (j - 1.0).abs() < near {
                    q_lo + (q_hi - q_lo) * (j - 1.0 + near) / (2.0 * near)
                } else {
                    q(j)
                };
                // Near ν = 0.5 the foam barrier J^(−2β) overflows at the most compressed
                // samples; kept finite, it still stops any solver there, and the table never
                // interpolates infinities into NaN forces.
                q.clamp(-1e300, 1e300)
            })
            .collect();
        Some(VolumetricCorrection {
            law,
            table_q_pa,
            step,
        })
    }

    /// p_law(J) − p_springs(J) in pascals (tension positive), interpolated.
    #[inline(always)]
    pub fn pressure_pa(&self, volume_ratio: f64) -> f64 {
        let t = (volume_ratio - TABLE_J_MIN) / self.step;
        // Clamped to the first or last interval, so outside the table the line extends.
        let i = (t.max(0.0) as usize).min(TABLE_POINTS - 2);
        let w = t - i as f64;
        let q = self.table_q_pa[i] + w * (self.table_q_pa[i + 1] - self.table_q_pa[i]);
        let d = volume_ratio - 1.0;
        q * d * d
    }
}

/// The springs' own hydrostatic Cauchy pressure at volume ratio `j` (tension positive).
pub fn springs_pressure_pa(material: &Material, j: f64) -> f64 {
    let s = j.cbrt();
    let d = s - 1.0;
    3.0 * material.bulk_modulus_pa()
        * d
        * (1.0 + material.spring_law.cubic_ratio(material.poisson_ratio) * d * d)
        / (s * s)
}

/// p_law(J) − p_springs(J) from the closed forms, pascals.
pub fn exact_correction_pa(law: ContinuumLaw, material: &Material, j: f64) -> f64 {
    let (g, k) = (material.shear_modulus_pa(), material.bulk_modulus_pa());
    let s = j.cbrt();
    law.principal_cauchy_stress_pa([s; 3], g, k)[0] - springs_pressure_pa(material, j)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::element::{BrickCoefficients, BrickShape};
    use crate::model::SpringLaw;

    fn material(law: SpringLaw) -> Material {
        Material::new(390.0, 0.3, 700.0)
            .unwrap()
            .with_spring_law(law)
            .unwrap()
    }

    #[test]
    fn springs_pressure_is_the_elements_hydrostatic_response() {
        for law in [SpringLaw::Linear, SpringLaw::Cubic(3.0)] {
            let m = material(law);
            let brick = BrickCoefficients::new(
                BrickShape {
                    edges_m: [4e-3, 4.5e-3, 5e-3],
                },
                m,
            )
            .unwrap();
            for j in [0.3f64, 0.8, 0.99, 1.2, 2.0] {
                let s = j.cbrt();
                let f = brick.box_face_forces_n([s; 3]);
                let e = brick.shape.edges_m;
                let want = springs_pressure_pa(&m, j);
                for i in 0..3 {
                    let area = e[(i + 1) % 3] * e[(i + 2) % 3] * s * s;
                    let got = f[i] / area;
                    assert!(
                        (got - want).abs() < 1e-9 * want.abs().max(1.0),
                        "{law:?} J {j}: {got} vs {want}"
                    );
                }
            }
        }
    }

    #[test]
    fn the_table_stays_finite_near_incompressibility() {
        let mut m = Material::new(390.0, 0.499, 700.0).unwrap();
        m.volumetric_law = Some(ContinuumLaw::Hyperfoam);
        let table = VolumetricCorrection::new(&m).unwrap();
        for j in [0.001, 0.02, 0.05, 0.5, 1.0, 2.0, 5.0] {
            assert!(table.pressure_pa(j).is_finite(), "J {j}");
        }
        // Stiffer than anything the springs give, in compression.
        assert!(table.pressure_pa(0.05) < -1e6 * m.bulk_modulus_pa());
    }

    #[test]
    fn correction_vanishes_to_second_order_and_the_table_follows_the_closed_form() {
        let mut m = material(SpringLaw::Linear);
        for law in [
            ContinuumLaw::NeoHookean,
            ContinuumLaw::Hyperfoam,
            ContinuumLaw::LungBirzle,
        ] {
            m.volumetric_law = Some(law);
            let (h, k) = (1e-3, m.bulk_modulus_pa());
            // Zero value and slope at J = 1: what is left over ±h is O(h²), against K·h for the
            // pressures themselves.
            for j in [1.0 - h, 1.0 + h] {
                let c = exact_correction_pa(law, &m, j);
                assert!(c.abs() < 10.0 * k * h * h, "{law:?} J {j}: {c}");
            }
            let table = VolumetricCorrection::new(&m).unwrap();
            for i in 0..2000 {
                let j = 0.1 + 3.9 * i as f64 / 1999.0;
                let exact = exact_correction_pa(law, &m, j);
                let err = (table.pressure_pa(j) - exact).abs();
                assert!(err < 1e-4 * (exact.abs() + k), "{law:?} J {j}: {err}");
            }
        }
    }
}
