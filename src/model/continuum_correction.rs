//! The continuum correction: nodal forces that make an element's response to any homogeneous
//! deformation the first Piola stress of a continuum law, deviatoric part included.
//!
//! Why. Baudet's springs reproduce E, ν, K (and G, for cubes) at small strain, but beyond it
//! their deviatoric response is not any continuum law's: under uniaxial stretch the body
//! diagonals turn towards the load and the cube is 13–34 % stiffer than neo-Hookean with the
//! same moduli. The volumetric correction ([`super::volumetric`]) fixes the hydrostatic part
//! only. This one replaces the element's whole *homogeneous* response.
//!
//! How. F̄ = Σ_a x_a ⊗ ∇N_a(centre) is the trilinear brick's deformation gradient at its centre
//! (one-point quadrature; its columns are the mean edge vectors over the rest edge lengths,
//! ē_i/L_i). Hourglass modes do not change it, so the springs keep resisting them. The element's
//! own response to the homogeneous deformation F̄ is known in closed form: each spring, rest
//! vector e_s, is stretched to F̄e_s, so the springs carry V₀P_s = Σ_s T_s n_s ⊗ e_s, and
//! Baudet's Lagrange correction, fed those spring forces, carries V₀P_c (derivation at
//! [`homogeneous_response`]). The correction adds f_a = −V₀(P_law(F̄) − P_s − P_c)·∇N_a(centre)
//! to each corner, so under any homogeneous F the element's corner forces, projected on the
//! homogeneous modes (−(1/V₀)Σ_a f_a ⊗ X_a, which is the stress a lattice of such elements
//! carries), are exactly P_law(F). At small strain P_s + P_c is Baudet's linear response, exact
//! for cubes, so the correction is second order there and the patch tests are unchanged.
//!
//! The laws are written as P = α·F + γ·cof F (cof F = J·F⁻ᵀ, whose columns are cross products of
//! F's columns), with α, γ functions of I₁ = |F|² and J: one cube root (and for the foam laws a
//! few powers) per element, no eigen-decomposition, and J ≤ 0 stays finite.

use nalgebra::{Matrix3, Vector3};
use serde::Serialize;

use super::element::{BrickCoefficients, SpringKind};
use super::spring_law::ContinuumLaw;
use super::Material;

/// Birzle et al.'s c₁/c and c₃/c (c = G/2), as in [`ContinuumLaw::principal_cauchy_stress_pa`].
const BIRZLE_C1_OVER_C: f64 = 278.2 / 356.7;
/// See [`BIRZLE_C1_OVER_C`].
const BIRZLE_C3_OVER_C: f64 = 5.766 / 356.7;

/// One material's continuum law with its moduli, ready for the force kernels.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct ContinuumCorrection {
    /// The law the elements follow under homogeneous deformation.
    pub law: ContinuumLaw,
    /// Shear modulus G of the law, pascals (the material's small-strain one).
    pub shear_modulus_pa: f64,
    /// Bulk modulus K of the law, pascals (the material's small-strain one).
    pub bulk_modulus_pa: f64,
}

impl ContinuumCorrection {
    /// The correction for `material`'s moduli, if it names a continuum correction law.
    pub fn new(material: &Material) -> Option<Self> {
        Some(ContinuumCorrection {
            law: material.continuum_correction?,
            shear_modulus_pa: material.shear_modulus_pa(),
            bulk_modulus_pa: material.bulk_modulus_pa(),
        })
    }

    /// (α in Pa, γ in Pa) with the law's first Piola stress P = α·F + γ·cof F at I₁ = tr(FᵀF)
    /// and J = det F.
    #[inline(always)]
    pub fn piola_coefficients_pa(&self, i1: f64, j: f64) -> (f64, f64) {
        let (g, k) = (self.shear_modulus_pa, self.bulk_modulus_pa);
        match self.law {
            ContinuumLaw::NeoHookean => {
                // W = (G/2)(J^(−2/3)·I₁ − 3) + (K/2)(J − 1)²:
                // P = G·J^(−2/3)·F + (K(J − 1) − (G/3)·J^(−5/3)·I₁)·cof F.
                let c = j.cbrt();
                let j_m23 = 1.0 / (c * c);
                (g * j_m23, k * (j - 1.0) - g * i1 * j_m23 / (3.0 * j))
            }
            ContinuumLaw::Hyperfoam | ContinuumLaw::LungBirzle => {
                // W(I₁, I₃), I₃ = J²: P = 2·W₁·F + 2·J·W₃·cof F (the same W₁, W₃ as the
                // principal-stress form in `spring_law`).
                let c = g / 2.0;
                let beta = (3.0 * k - 2.0 * g) / (6.0 * g);
                let (c1, c3) = match self.law {
                    ContinuumLaw::LungBirzle => (c * BIRZLE_C1_OVER_C, c * BIRZLE_C3_OVER_C),
                    _ => (0.0, 0.0),
                };
                let i3 = j * j;
                let i3_m13 = 1.0 / i3.cbrt();
                let (w1, w3) = if c1 == 0.0 && c3 == 0.0 {
                    (c, -c * i3.powf(-beta - 1.0))
                } else {
                    let i1_bar = i3_m13 * i1;
                    let shear = 3.0 * c1 * (i1_bar - 3.0).powi(2);
                    (
                        c + shear * i3_m13,
                        -c * i3.powf(-beta - 1.0) - shear * i1 * i3_m13 / (3.0 * i3)
                            + 2.0 * c3 * (i3.cbrt() - 1.0).powi(5) * i3_m13 * i3_m13,
                    )
                };
                (2.0 * w1, 2.0 * j * w3)
            }
        }
    }

    /// The law's first Piola–Kirchhoff stress at deformation gradient `f`, pascals.
    pub fn piola_pa(&self, f: &Matrix3<f64>) -> Matrix3<f64> {
        let (a, g) = self.piola_coefficients_pa(f.norm_squared(), f.determinant());
        a * f + g * cofactor(f)
    }

    /// The law's strain energy density at `f`, J/m³ (for checking [`Self::piola_pa`] by
    /// differentiation; not used by the kernels).
    pub fn energy_density_j_per_m3(&self, f: &Matrix3<f64>) -> f64 {
        let (g, k) = (self.shear_modulus_pa, self.bulk_modulus_pa);
        let (i1, j) = (f.norm_squared(), f.determinant());
        let i1_bar = i1 / (j * j).cbrt();
        match self.law {
            ContinuumLaw::NeoHookean => 0.5 * g * (i1_bar - 3.0) + 0.5 * k * (j - 1.0).powi(2),
            ContinuumLaw::Hyperfoam | ContinuumLaw::LungBirzle => {
                let c = g / 2.0;
                let beta = (3.0 * k - 2.0 * g) / (6.0 * g);
                let mut w = c * (i1 - 3.0) + c / beta * ((j * j).powf(-beta) - 1.0);
                if self.law == ContinuumLaw::LungBirzle {
                    w += c * BIRZLE_C1_OVER_C * (i1_bar - 3.0).powi(3)
                        + c * BIRZLE_C3_OVER_C * ((j * j).cbrt() - 1.0).powi(6);
                }
                w
            }
        }
    }
}

/// cof F = det(F)·F⁻ᵀ: its columns are F₂×F₃, F₃×F₁, F₁×F₂ (Fᵢ the columns of F).
pub fn cofactor(f: &Matrix3<f64>) -> Matrix3<f64> {
    let c = [f.column(0), f.column(1), f.column(2)];
    Matrix3::from_columns(&[c[1].cross(&c[2]), c[2].cross(&c[0]), c[0].cross(&c[1])])
}

/// The brick's own first Piola stress (pascals) when its corners follow the homogeneous
/// deformation `f` (columns in the brick's rest axes): springs and Baudet's correction, elastic
/// part, projected on the homogeneous modes.
///
/// Derivation (X_a the rest corner offsets, s_a their signs, L_i the rest edges, V₀ = ΠL_i,
/// ∇N_a(centre) = (s_a,i/(4L_i))_i):
/// * springs: V₀P_s = Σ_s T_s n_s ⊗ e_s; its column i is L_i·R_i with
///   R_i = 4T_i n_i + Σ_m σ_m,i T_m n_m (T_i the four i-edges' common tension, T_m and σ_m the
///   tension and rest signs of diagonal m);
/// * the correction's axial resultants a_i = −½(Σ_n s_n,i f_n)·ê_i are then ê_i·R_i (ê_i the
///   element's current axes, the Gram–Schmidt of F's first two columns, as the kernel uses), its
///   corner forces Σ_i s_n,i w_i ê_i with w = W·a, and V₀P_c's column i is −4L_i·w_i·ê_i.
///
/// So V₀(P_s + P_c) has columns L_i(R_i − 4w_i ê_i). The same numbers come from the element's
/// corner forces, −(1/V₀)Σ_a f_a ⊗ X_a, which a test checks.
pub fn homogeneous_response(coefficients: &BrickCoefficients, f: &Matrix3<f64>) -> Matrix3<f64> {
    let l = coefficients.shape.edges_m;
    let mean_edges: [Vector3<f64>; 3] = std::array::from_fn(|i| f.column(i) * l[i]);
    let (r, w, axes) = spring_resultants(coefficients, &mean_edges);
    let v0 = coefficients.shape.volume_m3();
    Matrix3::from_fn(|row, i| l[i] * (r[i][row] - 4.0 * w[i] * axes[i][row]) / v0)
}

/// Signs σ_m of the four body diagonals' rest vectors, in [`super::element::SPRINGS`] order.
pub const DIAGONAL_SIGNS: [[f64; 3]; 4] = [
    [1.0, 1.0, 1.0],
    [-1.0, 1.0, 1.0],
    [-1.0, -1.0, 1.0],
    [1.0, -1.0, 1.0],
];

/// For the homogeneous deformation whose mean edge vectors are `mean_edges` (ē_i = F̄·L_iê_i):
/// the spring resultants R_i, the correction magnitudes w = W·a and the current axes.
fn spring_resultants(
    c: &BrickCoefficients,
    mean_edges: &[Vector3<f64>; 3],
) -> ([Vector3<f64>; 3], Vector3<f64>, [Vector3<f64>; 3]) {
    let cubic = c.spring_cubic_ratio;
    let tension = |kind: SpringKind, v: &Vector3<f64>| {
        let (k, l0) = (c.spring_stiffness(kind), c.rest_length_m(kind));
        let len = v.norm();
        let e = len - l0;
        let t = e * (k + k * cubic / (l0 * l0) * e * e);
        v * (t / len)
    };
    let mut r: [Vector3<f64>; 3] =
        std::array::from_fn(|i| 4.0 * tension(SpringKind::Edge(i), &mean_edges[i]));
    for sigma in DIAGONAL_SIGNS {
        let d = mean_edges[0] * sigma[0] + mean_edges[1] * sigma[1] + mean_edges[2] * sigma[2];
        let t = tension(SpringKind::Diagonal, &d);
        for i in 0..3 {
            r[i] += t * sigma[i];
        }
    }
    let e1 = mean_edges[0].normalize();
    let e2 = (mean_edges[1] - e1 * mean_edges[1].dot(&e1)).normalize();
    let axes = [e1, e2, e1.cross(&e2)];
    let a = Vector3::from_fn(|i, _| axes[i].dot(&r[i]));
    (r, c.correction_map * a, axes)
}

/// The per-axis vectors c_i whose signed sums Σ_i s_n,i c_i are the correction's force on
/// corner n, for the element whose four-edge sums along its axes are `edge_sums` (4ē_i), in
/// newtons: c_i = (R_i/4 − w_i ê_i) − V₀·P_law(F̄)·ê_i/(4L_i).
///
/// The scalar reference of the batched kernel in `simulation::forces`.
pub fn corner_axis_forces_n(
    coefficients: &BrickCoefficients,
    correction: &ContinuumCorrection,
    edge_sums: &[Vector3<f64>; 3],
) -> [Vector3<f64>; 3] {
    let l = coefficients.shape.edges_m;
    let mean_edges = edge_sums.map(|e| e * 0.25);
    let (r, w, axes) = spring_resultants(coefficients, &mean_edges);
    let f = Matrix3::from_fn(|row, i| mean_edges[i][row] / l[i]);
    let p = correction.piola_pa(&f);
    let v0 = coefficients.shape.volume_m3();
    std::array::from_fn(|i| r[i] * 0.25 - axes[i] * w[i] - p.column(i) * (v0 / (4.0 * l[i])))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::element::BrickShape;
    use crate::model::{HourglassLaw, SpringLaw};

    fn laws() -> [ContinuumLaw; 3] {
        [
            ContinuumLaw::NeoHookean,
            ContinuumLaw::Hyperfoam,
            ContinuumLaw::LungBirzle,
        ]
    }

    /// A deterministic pseudo-random deformation gradient near the identity (|F − I| ≲ `amp`).
    fn random_f(seed: u64, amp: f64) -> Matrix3<f64> {
        let mut s = seed
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        let mut next = || {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((s >> 11) as f64 / (1u64 << 53) as f64) * 2.0 - 1.0
        };
        Matrix3::identity() + Matrix3::from_fn(|_, _| amp * next())
    }

    /// The stress a brick's corner forces carry: −(1/V₀)Σ_a f_a ⊗ X_a.
    fn projected_stress(c: &BrickCoefficients, f: &Matrix3<f64>) -> Matrix3<f64> {
        let offsets = c.corner_offsets_m();
        // A rotation and a translation of the whole element change nothing (objectivity is
        // checked separately); keep the rest frame here.
        let x = offsets.map(|o| f * o);
        let forces = c.corner_forces(&x, None);
        let mut p = Matrix3::zeros();
        for (fa, xa) in forces.iter().zip(&offsets) {
            p -= fa * xa.transpose();
        }
        p / c.shape.volume_m3()
    }

    #[test]
    fn piola_stress_is_the_derivative_of_the_energy_and_matches_the_principal_form() {
        for law in laws() {
            let m = Material::new(390.0, 0.3, 700.0).unwrap();
            let cc = ContinuumCorrection {
                law,
                shear_modulus_pa: m.shear_modulus_pa(),
                bulk_modulus_pa: m.bulk_modulus_pa(),
            };
            for seed in 0..5 {
                let f = random_f(seed, 0.3);
                let p = cc.piola_pa(&f);
                let h = 1e-6;
                for r in 0..3 {
                    for c in 0..3 {
                        let mut fp = f;
                        fp[(r, c)] += h;
                        let mut fm = f;
                        fm[(r, c)] -= h;
                        let d = (cc.energy_density_j_per_m3(&fp) - cc.energy_density_j_per_m3(&fm))
                            / (2.0 * h);
                        assert!(
                            (d - p[(r, c)]).abs() < 1e-6 * p.norm().max(1.0),
                            "{law:?} seed {seed} ({r},{c}): {d} vs {}",
                            p[(r, c)]
                        );
                    }
                }
            }
            let stretch = [1.2, 0.9, 1.05];
            let p = cc.piola_pa(&Matrix3::from_diagonal(&Vector3::from(stretch)));
            let want = law.nominal_stress_pa(stretch, cc.shear_modulus_pa, cc.bulk_modulus_pa);
            for i in 0..3 {
                assert!((p[(i, i)] - want[i]).abs() < 1e-9 * want[i].abs().max(1.0));
            }
        }
    }

    #[test]
    fn the_closed_form_homogeneous_response_is_the_elements_own() {
        for law in [SpringLaw::Linear, SpringLaw::Cubic(3.0)] {
            for edges_m in [[1.0, 1.0, 1.0], [1.0, 1.2, 0.9]] {
                let m = Material::new(1000.0, 0.3, 1.0)
                    .unwrap()
                    .with_spring_law(law)
                    .unwrap();
                let c = BrickCoefficients::new(BrickShape { edges_m }, m).unwrap();
                for seed in 0..10 {
                    let f = random_f(seed, 0.3);
                    let want = projected_stress(&c, &f);
                    let got = homogeneous_response(&c, &f);
                    assert!(
                        (got - want).norm() < 1e-10 * want.norm(),
                        "{law:?} {edges_m:?} seed {seed}:\n{got}\n{want}"
                    );
                }
            }
        }
    }

    #[test]
    fn a_corrected_brick_under_any_homogeneous_deformation_carries_the_laws_stress() {
        for law in laws() {
            for spring_law in [SpringLaw::Linear, SpringLaw::Cubic(3.0)] {
                for (edges_m, hourglass) in [
                    ([1e-3, 1e-3, 1e-3], HourglassLaw::Springs),
                    ([4e-3, 4.5e-3, 5e-3], HourglassLaw::Springs),
                    ([1e-3, 1e-3, 1e-3], HourglassLaw::IncompatibleModes),
                    ([4e-3, 4.5e-3, 5e-3], HourglassLaw::FullIntegration),
                ] {
                    let m = Material::new(390.0, 0.3, 700.0)
                        .unwrap()
                        .with_spring_law(spring_law)
                        .unwrap()
                        .with_continuum_correction(Some(law))
                        .unwrap()
                        .with_hourglass(hourglass);
                    let c = BrickCoefficients::new(BrickShape { edges_m }, m).unwrap();
                    let cc = ContinuumCorrection::new(&m).unwrap();
                    for seed in 0..20 {
                        let f = random_f(seed, 0.35);
                        let want = cc.piola_pa(&f);
                        let got = projected_stress(&c, &f);
                        assert!(
                            (got - want).norm() < 1e-6 * want.norm(),
                            "{law:?} {spring_law:?} {edges_m:?} seed {seed}:\n{got}\n{want}"
                        );
                    }
                }
            }
        }
    }

    #[test]
    fn the_correction_is_second_order_at_small_strain_on_cubes() {
        // Baudet's cube is exact in E, ν, K and G at small strain, so the law and the element
        // agree to first order and the correction force is O(|F − I|²).
        let m = Material::new(390.0, 0.3, 700.0)
            .unwrap()
            .with_continuum_correction(Some(ContinuumLaw::NeoHookean))
            .unwrap();
        let c = BrickCoefficients::new(BrickShape::cube(8e-3), m).unwrap();
        let cc = ContinuumCorrection::new(&m).unwrap();
        let l = c.shape.edges_m;
        let size = |amp: f64| {
            let f = random_f(7, 1.0);
            let f = Matrix3::identity() + (f - Matrix3::identity()) * amp;
            let sums: [Vector3<f64>; 3] = std::array::from_fn(|i| f.column(i) * (4.0 * l[i]));
            let v = corner_axis_forces_n(&c, &cc, &sums);
            v.iter().map(|v| v.norm()).sum::<f64>()
        };
        let (a, b) = (size(1e-3), size(2e-3));
        // Quadratic: doubling the strain quadruples the force (a linear term would double it).
        assert!((b / a - 4.0).abs() < 0.05, "{a} {b}");
        // And small beside the element's own forces at that strain, E·L²·|F − I| (about
        // 2.5e-5 N here): measured 1.3e-3 of it, the size of the strain itself.
        assert!(a < 1e-2 * m.youngs_modulus_pa * l[0] * l[0] * 1e-3, "{a}");
        // At rest, nothing.
        let rest: [Vector3<f64>; 3] = std::array::from_fn(|i| Vector3::ith(i, 4.0 * l[i]));
        let v = corner_axis_forces_n(&c, &cc, &rest);
        assert!(v
            .iter()
            .all(|v| v.norm() < 1e-12 * m.youngs_modulus_pa * l[0] * l[0]));
    }
}
