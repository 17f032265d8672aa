//! The hourglass correction: an element's inhomogeneous (bending, twist) response taken from a
//! continuum finite element instead of the springs.
//!
//! Why. The continuum correction ([`super::continuum_correction`]) makes an element's response to
//! any *homogeneous* deformation a continuum law's, and leaves the twelve remaining modes of the
//! brick (the hourglass modes: corner displacements proportional to ξη, ηζ, ζξ and ξηζ along each
//! axis, which bend, twist and warp it) to the springs. On an 8 mm cube at ν = 0.3 the springs
//! resist them unlike any continuum element: 1.47× stiffer than a fully integrated trilinear
//! brick (CalculiX C3D8) in the six bending modes, 5.2× stiffer in the three ξηζ modes, and not at
//! all, to first order, in the three twist modes (u_z ∝ ξη, u_x ∝ ηζ, u_y ∝ ζξ: no spring changes
//! length), which only the springs' tension stiffens once the element is loaded
//! (`docs/studies/ccx_gap/`).
//!
//! How. With h_α (α = 1…4) the corner patterns ξη, ηζ, ζξ, ξηζ (products of the corner signs),
//! which are orthogonal to the constant and linear ones on a rectangular brick, the element's
//! hourglass coordinates are q_α = Σ_a h_α,a x_a: zero under any affine (homogeneous)
//! deformation, rigid motion included. The correction
//! * evaluates the springs and Baudet's (and the continuum) correction at the affine part of
//!   the motion, x_a − Σ_α h_α,a q_α/8, so the hourglass modes no longer reach them;
//! * removes the springs' forces along the hourglass patterns, Σ_α h_α,a g_α/8 with
//!   g_α = Σ_b h_α,b f_b: even under homogeneous deformation a shear γ_xy makes the body
//!   diagonals push the corners along z in the ξηζ pattern (forces that cancel between
//!   neighbours inside a lattice but not on its boundary); and
//! * adds a corotational linear hourglass response, f_a = −R·Σ_α h_α,a (C·q̃)_α with
//!   q̃_α = Rᵀq_α, R the element's current axes (those of Baudet's correction) and C the
//!   hourglass block of the target element's small-strain stiffness (over 64, q = 8d for corner
//!   displacements d·h_α) with the material's E and ν.
//!
//! With the continuum correction the element's forces are then −V₀·P_law(F̄)·∇N_a(centre) plus
//! the hourglass response: a one-point-quadrature element of the law with the target's hourglass
//! stiffness, on the springs' nodes. The homogeneous stress (and the patch tests) are untouched,
//! and the hourglass modes get
//! the target element's stiffness at small strain; beyond it they stay linear in the rotated
//! frame (the target's own change of hourglass stiffness with stress, a few per cent at the lung's
//! end-inhale strains, is not carried).

use nalgebra::{SMatrix, SVector, Vector3};
use serde::{Deserialize, Serialize};

use super::element::{BrickShape, CORNER_SIGNS};
use super::Material;

/// Where an element's hourglass (inhomogeneous) response comes from.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum HourglassLaw {
    /// The springs' own (Baudet's element as it is).
    #[default]
    Springs,
    /// A trilinear brick with incompatible modes (Wilson–Taylor; CalculiX C3D8I): exact in pure
    /// bending of rectangular bricks, no shear locking.
    IncompatibleModes,
    /// A fully integrated trilinear brick (2 × 2 × 2 Gauss points; CalculiX C3D8), which locks
    /// in bending on coarse meshes.
    FullIntegration,
}

/// h_α,a: the corner patterns ξη, ηζ, ζξ, ξηζ.
pub const HOURGLASS_PATTERNS: [[f64; 8]; 4] = {
    let mut h = [[0.0; 8]; 4];
    let mut a = 0;
    while a < 8 {
        let s = CORNER_SIGNS[a];
        h[0][a] = s[0] * s[1];
        h[1][a] = s[1] * s[2];
        h[2][a] = s[2] * s[0];
        h[3][a] = s[0] * s[1] * s[2];
        a += 1;
    }
    h
};

/// One element class's hourglass correction.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct HourglassCorrection {
    /// The target's law.
    pub law: HourglassLaw,
    /// C, 12 × 12 over the rotated hourglass coordinates (index 3α + i), N/m.
    #[serde(skip)]
    pub stiffness: SMatrix<f64, 12, 12>,
}

impl HourglassCorrection {
    /// The correction for `shape` and `material`, if the material names a target element.
    pub fn new(shape: &BrickShape, material: &Material) -> Option<Self> {
        let incompatible = match material.hourglass {
            HourglassLaw::Springs => return None,
            HourglassLaw::IncompatibleModes => true,
            HourglassLaw::FullIntegration => false,
        };
        let k = trilinear_stiffness(
            shape,
            material.youngs_modulus_pa,
            material.poisson_ratio,
            incompatible,
        );
        Some(HourglassCorrection {
            law: material.hourglass,
            stiffness: hourglass_block(&k) / 64.0,
        })
    }

    /// The correction's corner forces (newtons) for an element at `x` whose springs exert
    /// `spring_forces` (elastic part) and whose current axes are `axes`.
    pub fn corner_forces(
        &self,
        x: &[Vector3<f64>; 8],
        axes: &[Vector3<f64>; 3],
        spring_forces: &[Vector3<f64>; 8],
    ) -> [Vector3<f64>; 8] {
        let mut q = SVector::<f64, 12>::zeros();
        let mut g = [Vector3::zeros(); 4];
        for (alpha, h) in HOURGLASS_PATTERNS.iter().enumerate() {
            let mut qa = Vector3::zeros();
            for a in 0..8 {
                qa += x[a] * h[a];
                g[alpha] += spring_forces[a] * h[a];
            }
            for i in 0..3 {
                q[3 * alpha + i] = axes[i].dot(&qa);
            }
        }
        let c = self.stiffness * q;
        let per_pattern: [Vector3<f64>; 4] = std::array::from_fn(|alpha| {
            let back =
                axes[0] * c[3 * alpha] + axes[1] * c[3 * alpha + 1] + axes[2] * c[3 * alpha + 2];
            -(g[alpha] * 0.125 + back)
        });
        std::array::from_fn(|a| {
            (0..4).fold(Vector3::zeros(), |s, alpha| {
                s + per_pattern[alpha] * HOURGLASS_PATTERNS[alpha][a]
            })
        })
    }
}

/// The affine part of the corner positions `x`: x minus its hourglass components,
/// x_a − Σ_α h_α,a q_α/8 (the eight patterns 1, s_x, s_y, s_z, h_α are orthogonal).
pub fn affine_part(x: &[Vector3<f64>; 8]) -> [Vector3<f64>; 8] {
    let q: [Vector3<f64>; 4] = std::array::from_fn(|alpha| {
        (0..8).fold(Vector3::zeros(), |s, a| {
            s + x[a] * HOURGLASS_PATTERNS[alpha][a]
        })
    });
    std::array::from_fn(|a| {
        (0..4).fold(x[a], |s, alpha| {
            s - q[alpha] * (HOURGLASS_PATTERNS[alpha][a] / 8.0)
        })
    })
}

/// H (24 × 12): column 3α + i is the pattern h_α along axis i, corner-major.
pub fn pattern_matrix() -> SMatrix<f64, 24, 12> {
    let mut h = SMatrix::<f64, 24, 12>::zeros();
    for (alpha, pattern) in HOURGLASS_PATTERNS.iter().enumerate() {
        for (a, &s) in pattern.iter().enumerate() {
            for i in 0..3 {
                h[(3 * a + i, 3 * alpha + i)] = s;
            }
        }
    }
    h
}

/// The hourglass block Hᵀ·K·H (12 × 12, index 3α + i) of a 24 × 24 corner-major stiffness.
pub fn hourglass_block(k: &SMatrix<f64, 24, 24>) -> SMatrix<f64, 12, 12> {
    let h = pattern_matrix();
    h.transpose() * k * h
}

/// Small-strain stiffness (24 × 24, corner-major, force = −K·u) of a trilinear brick with
/// edges `shape` along its axes, isotropic E and ν, 2 × 2 × 2 Gauss points; with
/// `incompatible`, Wilson's nine incompatible modes 1 − ξ_i² per component, condensed out.
pub fn trilinear_stiffness(
    shape: &BrickShape,
    youngs_modulus_pa: f64,
    poisson_ratio: f64,
    incompatible: bool,
) -> SMatrix<f64, 24, 24> {
    let (e, nu) = (youngs_modulus_pa, poisson_ratio);
    let lam = e * nu / ((1.0 + nu) * (1.0 - 2.0 * nu));
    let mu = e / (2.0 * (1.0 + nu));
    let mut d = SMatrix::<f64, 6, 6>::zeros();
    for i in 0..3 {
        for j in 0..3 {
            d[(i, j)] = lam;
        }
        d[(i, i)] += 2.0 * mu;
        d[(i + 3, i + 3)] = mu;
    }
    let half = shape.edges_m.map(|l| 0.5 * l);
    let weight = half[0] * half[1] * half[2];
    // Strain rows of a field with gradient `grad` on DOF block `col` (engineering shear).
    fn put(b: &mut [[f64; 3]; 6], grad: [f64; 3]) {
        *b = [[0.0; 3]; 6];
        b[0][0] = grad[0];
        b[1][1] = grad[1];
        b[2][2] = grad[2];
        b[3][0] = grad[1];
        b[3][1] = grad[0];
        b[4][1] = grad[2];
        b[4][2] = grad[1];
        b[5][0] = grad[2];
        b[5][2] = grad[0];
    }
    let g = 1.0 / 3f64.sqrt();
    let mut k = SMatrix::<f64, 24, 24>::zeros();
    let mut kca = SMatrix::<f64, 9, 24>::zeros();
    let mut kaa = SMatrix::<f64, 9, 9>::zeros();
    for point in CORNER_SIGNS {
        let xi = point.map(|s| s * g);
        let mut b = SMatrix::<f64, 6, 24>::zeros();
        let mut rows = [[0.0; 3]; 6];
        for (a, s) in CORNER_SIGNS.iter().enumerate() {
            let grad: [f64; 3] = std::array::from_fn(|i| {
                let (j, l) = ((i + 1) % 3, (i + 2) % 3);
                s[i] * (1.0 + s[j] * xi[j]) * (1.0 + s[l] * xi[l]) / 8.0 / half[i]
            });
            put(&mut rows, grad);
            for r in 0..6 {
                for c in 0..3 {
                    b[(r, 3 * a + c)] = rows[r][c];
                }
            }
        }
        k += b.transpose() * d * b * weight;
        if incompatible {
            let mut ba = SMatrix::<f64, 6, 9>::zeros();
            for m in 0..3 {
                let mut grad = [0.0; 3];
                grad[m] = -2.0 * xi[m] / half[m];
                put(&mut rows, grad);
                for r in 0..6 {
                    for c in 0..3 {
                        ba[(r, 3 * m + c)] = rows[r][c];
                    }
                }
            }
            kca += ba.transpose() * d * b * weight;
            kaa += ba.transpose() * d * ba * weight;
        }
    }
    if incompatible {
        let inv = kaa
            .try_inverse()
            .expect("the incompatible modes' stiffness is positive definite");
        k -= kca.transpose() * inv * kca;
    }
    k
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::BrickCoefficients;

    fn eigenvalues(m: &SMatrix<f64, 12, 12>) -> Vec<f64> {
        let sym = (m + m.transpose()) * 0.5;
        let mut e: Vec<f64> = sym.symmetric_eigenvalues().iter().copied().collect();
        e.sort_by(f64::total_cmp);
        e
    }

    #[test]
    fn the_target_elements_hourglass_stiffness_is_the_textbook_one() {
        // 8 mm cube, E = 390 Pa, ν = 0.3: eigenvalues of Hᵀ·K·H/8 (unit-norm modes), N/m,
        // computed independently (docs/studies/ccx_gap/cube_modes.py).
        let shape = BrickShape::cube(8e-3);
        let full = hourglass_block(&trilinear_stiffness(&shape, 390.0, 0.3, false)) / 8.0;
        let inc = hourglass_block(&trilinear_stiffness(&shape, 390.0, 0.3, true)) / 8.0;
        let want_full = [
            0.2, 0.2, 0.3667, 0.3667, 0.3667, 0.6, 0.6, 0.6, 0.8, 1.2, 1.2, 1.2,
        ];
        let want_inc = [
            0.2, 0.2, 0.3667, 0.3667, 0.3667, 0.4, 0.4, 0.4, 0.7429, 0.7429, 0.7429, 0.8,
        ];
        for (got, want) in [
            (eigenvalues(&full), want_full),
            (eigenvalues(&inc), want_inc),
        ] {
            for (g, w) in got.iter().zip(want) {
                assert!((g - w).abs() < 1e-4, "{got:?}");
            }
        }
        // The springs: three twist modes at zero, the others stiffer than either.
        let m = Material::LUNG;
        let springs = BrickCoefficients::new(shape, m).unwrap().linear_stiffness();
        let s = eigenvalues(&(hourglass_block(&springs) / 8.0));
        assert!(s[..3].iter().all(|v| v.abs() < 1e-9), "{s:?}");
        assert!(
            (s[3] - 1.32).abs() < 1e-9 && (s[11] - 1.92).abs() < 1e-9,
            "{s:?}"
        );
    }

    #[test]
    fn hourglass_and_homogeneous_modes_couple_only_through_the_springs() {
        // The target elements do not couple the two sets on a rectangular brick; the springs
        // do (shear against the ξηζ modes, through the body diagonals), and the corrected
        // element does not.
        let shape = BrickShape {
            edges_m: [8e-3, 9e-3, 7e-3],
        };
        let mut lin = SMatrix::<f64, 24, 12>::zeros();
        for (a, s) in CORNER_SIGNS.iter().enumerate() {
            for i in 0..3 {
                for j in 0..3 {
                    lin[(3 * a + i, 3 * j + i)] = s[j];
                }
                lin[(3 * a + i, 9 + i)] = 1.0;
            }
        }
        let h = pattern_matrix();
        let coupling = |k: &SMatrix<f64, 24, 24>| {
            ((h.transpose() * k * lin).norm() + (lin.transpose() * k * h).norm()) / k.norm()
        };
        let springs = BrickCoefficients::new(shape, Material::LUNG)
            .unwrap()
            .linear_stiffness();
        assert!(coupling(&springs) > 1e-2, "{}", coupling(&springs));
        let corrected = BrickCoefficients::new(
            shape,
            Material::LUNG.with_hourglass(HourglassLaw::IncompatibleModes),
        )
        .unwrap()
        .linear_stiffness();
        for k in [
            trilinear_stiffness(&shape, 390.0, 0.3, false),
            trilinear_stiffness(&shape, 390.0, 0.3, true),
            corrected,
        ] {
            assert!(coupling(&k) < 1e-12, "{}", coupling(&k));
        }
    }
}
