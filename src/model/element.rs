//! Baudet's parameterised hexahedral mass–spring element (thesis §3.3, extraction §1.6–1.8).
//!
//! A rectangular parallelepiped with a lumped mass at each corner, 12 edge springs of
//! stiffness K_x, K_y, K_z (eq. 3.18), 4 body-diagonal springs K_d (eq. 3.17) and Lagrange
//! correction forces (eq. 3.19) that push each corner along the element's axes in proportion to
//! the axial load the element carries. With the per-corner convention 2·F_ij (F the *total*
//! axial load on a face) the element reproduces E, both Poisson ratios and the bulk modulus
//! exactly at small strain for any admissible brick, and the shear modulus for cubes.
//!
//! Corner numbering follows VTK / CalculiX C3D8: corners 0–3 on the −z face counter-clockwise
//! seen from +z starting at (−,−,−), corners 4–7 above them.

use nalgebra::{Matrix3, SMatrix, Vector3};
use serde::Serialize;

use super::continuum_correction::{self, ContinuumCorrection};
use super::hourglass::HourglassCorrection;
use super::material::Material;
use super::volumetric::VolumetricCorrection;
use crate::{Error, Result};

/// Side of each corner relative to the element centre, along x, y, z.
pub const CORNER_SIGNS: [[f64; 3]; 8] = [
    [-1.0, -1.0, -1.0],
    [1.0, -1.0, -1.0],
    [1.0, 1.0, -1.0],
    [-1.0, 1.0, -1.0],
    [-1.0, -1.0, 1.0],
    [1.0, -1.0, 1.0],
    [1.0, 1.0, 1.0],
    [-1.0, 1.0, 1.0],
];

/// What a spring of the element connects: an edge along an axis, or a body diagonal.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SpringKind {
    /// Edge along axis 0 (x), 1 (y) or 2 (z).
    Edge(usize),
    /// Body diagonal through the element centre.
    Diagonal,
}

/// The 16 springs of the element as (corner a, corner b, kind).
pub const SPRINGS: [(usize, usize, SpringKind); 16] = [
    (0, 1, SpringKind::Edge(0)),
    (3, 2, SpringKind::Edge(0)),
    (4, 5, SpringKind::Edge(0)),
    (7, 6, SpringKind::Edge(0)),
    (0, 3, SpringKind::Edge(1)),
    (1, 2, SpringKind::Edge(1)),
    (4, 7, SpringKind::Edge(1)),
    (5, 6, SpringKind::Edge(1)),
    (0, 4, SpringKind::Edge(2)),
    (1, 5, SpringKind::Edge(2)),
    (2, 6, SpringKind::Edge(2)),
    (3, 7, SpringKind::Edge(2)),
    (0, 6, SpringKind::Diagonal),
    (1, 7, SpringKind::Diagonal),
    (2, 4, SpringKind::Diagonal),
    (3, 5, SpringKind::Diagonal),
];

/// Rest dimensions of a brick element along its own x, y, z axes, in metres.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct BrickShape {
    /// Edge lengths (x0, y0, z0) in metres.
    pub edges_m: [f64; 3],
}

impl BrickShape {
    /// A cube of the given edge length in metres.
    pub fn cube(edge_m: f64) -> Self {
        BrickShape {
            edges_m: [edge_m; 3],
        }
    }

    /// Volume in m³.
    pub fn volume_m3(&self) -> f64 {
        self.edges_m.iter().product()
    }

    /// Length of the body diagonal in metres.
    pub fn diagonal_m(&self) -> f64 {
        self.edges_m.iter().map(|e| e * e).sum::<f64>().sqrt()
    }
}

/// Spring stiffnesses and correction coefficients of one brick shape and material.
///
/// Computed once per distinct (shape, material) and shared by every element of that class.
#[derive(Debug, Clone, Serialize)]
pub struct BrickCoefficients {
    /// Shape the coefficients were built for.
    pub shape: BrickShape,
    /// Material the coefficients were built for.
    pub material: Material,
    /// Edge spring stiffness along x, y, z in N/m (eq. 3.18), per element.
    pub edge_stiffness_n_per_m: [f64; 3],
    /// Body-diagonal spring stiffness in N/m (eq. 3.17).
    pub diagonal_stiffness_n_per_m: f64,
    /// c_ij = F_ij / F_i: correction along j per unit total axial load along i (eq. 3.19).
    pub correction_ratios: [[f64; 3]; 3],
    /// W = 2·Cᵀ·(I + 8·Cᵀ)⁻¹: maps the element's axial spring-force resultants to the
    /// per-corner correction magnitudes (extraction §1.8).
    pub correction_map: Matrix3<f64>,
    /// Voigt damping coefficient of each spring in N·s/m, in [`SPRINGS`] order.
    pub spring_damping_n_s_per_m: [f64; 16],
    /// Lumped mass of each corner, ρ·V/8, in kg.
    pub corner_mass_kg: f64,
    /// c = λ₁/λ₂ of every spring's law T = k·ℓ₀·(d + c·d³), d = (ℓ − ℓ₀)/ℓ₀ the relative
    /// elongation (Boux de Casson's cubic springs); 0 for Baudet's linear springs.
    pub spring_cubic_ratio: f64,
    /// The correction pressure that makes the hydrostatic response follow the material's
    /// volumetric law, if it names one.
    pub volumetric: Option<VolumetricCorrection>,
    /// The corner forces that make the element's homogeneous response follow the material's
    /// continuum correction law, if it names one.
    pub continuum: Option<ContinuumCorrection>,
    /// The hourglass response that replaces the springs', if the material names one.
    pub hourglass: Option<HourglassCorrection>,
}

impl BrickCoefficients {
    /// Builds the coefficients; refuses bricks whose stiffnesses would not be positive.
    ///
    /// Such bricks are refused rather than subdivided here: the core must keep the node set
    /// the caller built. Ingest resamples CT voxels to near-cubes before meshing.
    pub fn new(shape: BrickShape, material: Material) -> Result<Self> {
        material.validate()?;
        let [x0, y0, z0] = shape.edges_m;
        if shape.edges_m.iter().any(|e| !e.is_finite() || *e <= 0.0) {
            return Err(Error::InadmissibleElement(format!(
                "element edges must be positive and finite, got {x0} × {y0} × {z0} m"
            )));
        }
        let e = material.youngs_modulus_pa;
        let nu = material.poisson_ratio;
        let d2 = x0 * x0 + y0 * y0 + z0 * z0;
        let vol = x0 * y0 * z0;
        let kd = e * d2 * d2 / (24.0 * vol * (1.0 + nu));
        let dims = shape.edges_m;
        let mut k_edge = [0.0; 3];
        for (i, k) in k_edge.iter_mut().enumerate() {
            let (i0, j0, k0) = (dims[i], dims[(i + 1) % 3], dims[(i + 2) % 3]);
            *k = e
                * (6.0 * j0 * j0 * k0 * k0 * (1.0 + nu)
                    + (nu * (j0 * j0 + k0 * k0) - i0 * i0) * d2)
                / (24.0 * vol * (1.0 + nu));
        }
        let names = ["x", "y", "z"];
        for (i, k) in k_edge.iter().enumerate() {
            if *k <= 0.0 {
                return Err(Error::InadmissibleElement(format!(
                    "a {:.4} × {:.4} × {:.4} mm brick with ν = {nu} needs a non-positive \
                     {} edge stiffness ({k:.3e} N/m); use near-cubic elements (edge ratios \
                     within about 1:1.4)",
                    x0 * 1e3,
                    y0 * 1e3,
                    z0 * 1e3,
                    names[i]
                )));
            }
        }
        let mut c = [[0.0; 3]; 3];
        for i in 0..3 {
            for j in 0..3 {
                if i == j {
                    continue;
                }
                let k = 3 - i - j;
                let (i0, j0, k0) = (dims[i], dims[j], dims[k]);
                c[i][j] = -(d2 * (nu * (k0 * k0 + i0 * i0) - i0 * i0)
                    + 6.0 * i0 * i0 * k0 * k0 * nu)
                    / (48.0 * i0 * j0 * k0 * k0);
            }
        }
        let cm = Matrix3::from_fn(|i, j| c[i][j]);
        let m = (Matrix3::identity() + 8.0 * cm.transpose())
            .try_inverse()
            .ok_or_else(|| {
                Error::InadmissibleElement(format!(
                    "correction system is singular for a {x0} × {y0} × {z0} m brick, ν = {nu}"
                ))
            })?;
        let w = 2.0 * cm.transpose() * m;
        let corner_mass_kg = material.density_kg_per_m3 * vol / 8.0;
        let spring_cubic_ratio = material.spring_law.cubic_ratio(material.poisson_ratio);
        Ok(BrickCoefficients {
            shape,
            material,
            edge_stiffness_n_per_m: k_edge,
            diagonal_stiffness_n_per_m: kd,
            correction_ratios: c,
            correction_map: w,
            spring_damping_n_s_per_m: [0.0; 16],
            corner_mass_kg,
            spring_cubic_ratio,
            volumetric: VolumetricCorrection::new(&material),
            continuum: ContinuumCorrection::new(&material),
            hourglass: HourglassCorrection::new(&shape, &material),
        })
    }

    /// Sets Voigt dampers (eq. 4.2) on every spring at a fraction of critical damping.
    ///
    /// The critical coefficient of a spring k joining two corner masses m is 2·√(k·m/2), the
    /// value for their relative motion (reduced mass m/2).
    pub fn with_damping_ratio(mut self, ratio: f64) -> Self {
        for (s, (_, _, kind)) in SPRINGS.iter().enumerate() {
            let k = self.spring_stiffness(*kind);
            self.spring_damping_n_s_per_m[s] =
                ratio * critical_damping(k, self.corner_mass_kg / 2.0);
        }
        self
    }

    /// Stiffness of a spring of the given kind in N/m.
    pub fn spring_stiffness(&self, kind: SpringKind) -> f64 {
        match kind {
            SpringKind::Edge(a) => self.edge_stiffness_n_per_m[a],
            SpringKind::Diagonal => self.diagonal_stiffness_n_per_m,
        }
    }

    /// Rest length of a spring of the given kind in metres.
    pub fn rest_length_m(&self, kind: SpringKind) -> f64 {
        match kind {
            SpringKind::Edge(a) => self.shape.edges_m[a],
            SpringKind::Diagonal => self.shape.diagonal_m(),
        }
    }

    /// Cubic coefficient k·c/ℓ₀² of a spring of the given kind in N/m³: the tension is
    /// k·e + this·e³ for an elongation e = ℓ − ℓ₀ in metres.
    pub fn spring_cubic_n_per_m3(&self, kind: SpringKind) -> f64 {
        let l0 = self.rest_length_m(kind);
        self.spring_stiffness(kind) * self.spring_cubic_ratio / (l0 * l0)
    }

    /// Internal forces in newtons on the 8 corners at positions `x` (velocities `v` for the
    /// dampers): the reference the vectorised kernels are tested against.
    ///
    /// The corrections act along the element's current axes (edge directions averaged and
    /// orthonormalised), so they rotate with the element and stay objective under large rotation.
    pub fn corner_forces(
        &self,
        x: &[Vector3<f64>; 8],
        v: Option<&[Vector3<f64>; 8]>,
    ) -> [Vector3<f64>; 8] {
        // With an hourglass correction the springs and corrections see only the affine part of
        // the motion; the correction gives the rest its response ([`super::hourglass`]).
        let x_all = x;
        let affine;
        let x = match &self.hourglass {
            Some(_) => {
                affine = super::hourglass::affine_part(x);
                &affine
            }
            None => x,
        };
        // Elastic spring forces in `f`, damper forces apart in `fd`: the corrections are derived
        // for the elastic response (they make E and ν exact), so they act on `f` only. Fed the
        // damper forces too, they would amplify the damping by up to 1/(2 − 4ν) (25× at
        // ν = 0.49) and put the automatic time step above the stability limit.
        let mut f = [Vector3::zeros(); 8];
        let mut fd = [Vector3::zeros(); 8];
        for (s, &(a, b, kind)) in SPRINGS.iter().enumerate() {
            let d = x[b] - x[a];
            let len = d.norm();
            let n = d / len;
            let e = len - self.rest_length_m(kind);
            let tension =
                e * (self.spring_stiffness(kind) + self.spring_cubic_n_per_m3(kind) * e * e);
            let fa = n * tension;
            f[a] += fa;
            f[b] -= fa;
            if let Some(v) = v {
                let fv = n * (self.spring_damping_n_s_per_m[s] * (v[b] - v[a]).dot(&n));
                fd[a] += fv;
                fd[b] -= fv;
            }
        }
        // Current element axes.
        let ex = (x[1] - x[0]) + (x[2] - x[3]) + (x[5] - x[4]) + (x[6] - x[7]);
        let ey = (x[3] - x[0]) + (x[2] - x[1]) + (x[7] - x[4]) + (x[6] - x[5]);
        let e1 = ex.normalize();
        let e2 = (ey - e1 * ey.dot(&e1)).normalize();
        let e3 = e1.cross(&e2);
        let axes = [e1, e2, e3];
        // The hourglass correction from the springs' elastic forces alone (the corrections
        // below act along the linear corner patterns, which it neither sees nor changes) and
        // the whole motion's hourglass coordinates.
        let hourglass = self
            .hourglass
            .as_ref()
            .map(|h| h.corner_forces(x_all, &axes, &f));
        // Axial resultants a_i = −½ Σ_n s_n,i (f_n · e_i).
        let mut a = Vector3::zeros();
        for (n, signs) in CORNER_SIGNS.iter().enumerate() {
            for i in 0..3 {
                a[i] -= 0.5 * signs[i] * f[n].dot(&axes[i]);
            }
        }
        let w = self.correction_map * a;
        let mut wa = [axes[0] * w[0], axes[1] * w[1], axes[2] * w[2]];
        if let Some(cc) = &self.continuum {
            // Same corner pattern Σ_i s_n,i c_i as the Lagrange correction, so it rides along.
            let ez = (x[4] - x[0]) + (x[5] - x[1]) + (x[6] - x[2]) + (x[7] - x[3]);
            let c = continuum_correction::corner_axis_forces_n(self, cc, &[ex, ey, ez]);
            for i in 0..3 {
                wa[i] += c[i];
            }
        }
        for (n, signs) in CORNER_SIGNS.iter().enumerate() {
            f[n] += wa[0] * signs[0] + wa[1] * signs[1] + wa[2] * signs[2] + fd[n];
        }
        if let Some(h) = hourglass {
            for (fn_, hn) in f.iter_mut().zip(h) {
                *fn_ += hn;
            }
        }
        if let Some(vol) = &self.volumetric {
            // J from the mean deformation gradient (ex, ey, ez)/(4·edge); the force is
            // −p·V₀·∂J/∂x_n = −(p/64)·(s_x·ey×ez + s_y·ez×ex + s_z·ex×ey).
            let ez = (x[4] - x[0]) + (x[5] - x[1]) + (x[6] - x[2]) + (x[7] - x[3]);
            let c = [ey.cross(&ez), ez.cross(&ex), ex.cross(&ey)];
            let j = ex.dot(&c[0]) / (64.0 * self.shape.volume_m3());
            let scale = -vol.pressure_pa(j) / 64.0;
            for (n, signs) in CORNER_SIGNS.iter().enumerate() {
                f[n] += (c[0] * signs[0] + c[1] * signs[1] + c[2] * signs[2]) * scale;
            }
        }
        f
    }

    /// Force in newtons that must pull on each positive face (+x, +y, +z) of the element held
    /// as a box stretched by `stretch` along its own axes (and mirrored on the negative faces):
    /// the element's homogeneous response, for fitting and checking its spring law.
    pub fn box_face_forces_n(&self, stretch: [f64; 3]) -> [f64; 3] {
        let x = std::array::from_fn(|n| {
            Vector3::from_fn(|i, _| 0.5 * CORNER_SIGNS[n][i] * self.shape.edges_m[i] * stretch[i])
        });
        let f = self.corner_forces(&x, None);
        std::array::from_fn(|i| {
            -CORNER_SIGNS
                .iter()
                .zip(&f)
                .filter(|(s, _)| s[i] > 0.0)
                .map(|(_, f)| f[i])
                .sum::<f64>()
        })
    }

    /// Corner rest positions relative to the centre, in the element's own axes, in metres.
    pub fn corner_offsets_m(&self) -> [Vector3<f64>; 8] {
        std::array::from_fn(|n| {
            Vector3::from_fn(|i, _| 0.5 * CORNER_SIGNS[n][i] * self.shape.edges_m[i])
        })
    }

    /// The element's small-strain stiffness (24 × 24, force = −K·u, corner-major DOFs),
    /// springs and corrections together: K_eff = (I − Sᵀ·W·S/2)·K_springs.
    ///
    /// Not symmetric for non-cubic bricks: the correction forces are not conservative.
    pub fn linear_stiffness(&self) -> SMatrix<f64, 24, 24> {
        let offsets = self.corner_offsets_m();
        let mut ks = SMatrix::<f64, 24, 24>::zeros();
        for (a, b, kind) in SPRINGS {
            let d = offsets[b] - offsets[a];
            let n = d / d.norm();
            let block = self.spring_stiffness(kind) * n * n.transpose();
            for r in 0..3 {
                for c in 0..3 {
                    let v = block[(r, c)];
                    ks[(3 * a + r, 3 * a + c)] += v;
                    ks[(3 * b + r, 3 * b + c)] += v;
                    ks[(3 * a + r, 3 * b + c)] -= v;
                    ks[(3 * b + r, 3 * a + c)] -= v;
                }
            }
        }
        let mut s = SMatrix::<f64, 3, 24>::zeros();
        for (n, signs) in CORNER_SIGNS.iter().enumerate() {
            for i in 0..3 {
                s[(i, 3 * n + i)] = signs[i];
            }
        }
        let b = -0.5 * s.transpose() * self.correction_map * s;
        let k = (SMatrix::<f64, 24, 24>::identity() + b) * ks;
        match &self.hourglass {
            None => k,
            Some(hg) => {
                // The springs see the affine part of the motion, (I − P)·u, and their forces
                // along the hourglass patterns, P·f, are removed (P = H·Hᵀ/8); the target's
                // H·C·Hᵀ is added (at rest the element's axes are the coordinate axes).
                let h = super::hourglass::pattern_matrix();
                let q = SMatrix::<f64, 24, 24>::identity() - h * h.transpose() / 8.0;
                q * k * q + h * hg.stiffness * h.transpose()
            }
        }
    }
}

/// Critical damping coefficient 2·√(k·m) of a spring k acting on a mass m (thesis §4.1.3).
pub fn critical_damping(stiffness_n_per_m: f64, mass_kg: f64) -> f64 {
    2.0 * (stiffness_n_per_m * mass_kg).sqrt()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn mat(e: f64, nu: f64) -> Material {
        Material::new(e, nu, 1.0).unwrap()
    }

    #[test]
    fn cube_matches_closed_forms() {
        // Extraction §1.6: K_i = E a (1+4ν)/(8(1+ν)), K_d = 3 E a/(8(1+ν)), F_ij/F_i = (1−4ν)/16.
        let c = BrickCoefficients::new(BrickShape::cube(1.0), mat(1000.0, 0.3)).unwrap();
        for k in c.edge_stiffness_n_per_m {
            assert!((k - 211.538_461_538).abs() < 1e-6, "{k}");
        }
        assert!((c.diagonal_stiffness_n_per_m - 288.461_538_46).abs() < 1e-6);
        for i in 0..3 {
            for j in 0..3 {
                let want = if i == j { 0.0 } else { -0.0125 };
                assert!((c.correction_ratios[i][j] - want).abs() < 1e-12);
            }
        }
    }

    #[test]
    fn refuses_flat_bricks() {
        // Raw CT voxels 0.9 × 0.9 × 5 mm give K_z < 0 (extraction §1.6).
        let shape = BrickShape {
            edges_m: [0.9e-3, 0.9e-3, 5e-3],
        };
        let err = BrickCoefficients::new(shape, mat(390.0, 0.3)).unwrap_err();
        assert!(err.to_string().contains("z edge stiffness"), "{err}");
        // Square prism 1 × 1 × a at ν = 0.3 is admissible for a in 0.425 – 1.543.
        for (a, ok) in [(0.42, false), (0.43, true), (1.54, true), (1.55, false)] {
            let shape = BrickShape {
                edges_m: [1.0, 1.0, a],
            };
            assert_eq!(
                BrickCoefficients::new(shape, mat(1.0, 0.3)).is_ok(),
                ok,
                "a = {a}"
            );
        }
    }

    #[test]
    fn refuses_degenerate_shapes() {
        for edges in [[0.0, 1.0, 1.0], [1.0, -1.0, 1.0], [1.0, f64::NAN, 1.0]] {
            let err = BrickCoefficients::new(BrickShape { edges_m: edges }, mat(1.0, 0.3));
            assert!(matches!(err, Err(Error::InadmissibleElement(_))));
        }
    }

    #[test]
    fn linear_stiffness_annihilates_rigid_translation() {
        let c = BrickCoefficients::new(
            BrickShape {
                edges_m: [1.0, 1.2, 0.9],
            },
            mat(1000.0, 0.3),
        )
        .unwrap();
        let k = c.linear_stiffness();
        for axis in 0..3 {
            let u = SMatrix::<f64, 24, 1>::from_fn(|r, _| if r % 3 == axis { 1.0 } else { 0.0 });
            assert!((k * u).norm() < 1e-9);
        }
    }

    #[test]
    fn cubic_springs_scale_a_uniform_stretch_by_one_plus_c_d_squared() {
        // Under a uniform stretch s every spring has d = s − 1, and springs and corrections are
        // linear in the tensions, so the whole response is the linear one times 1 + c·d².
        let shape = BrickShape {
            edges_m: [1.0, 1.2, 0.9],
        };
        let linear = BrickCoefficients::new(shape, mat(1000.0, 0.3)).unwrap();
        let law = crate::model::SpringLaw::Cubic(4.0);
        let cubic =
            BrickCoefficients::new(shape, mat(1000.0, 0.3).with_spring_law(law).unwrap()).unwrap();
        for s in [0.5, 0.9, 1.1, 1.6] {
            let d: f64 = s - 1.0;
            let (fl, fc) = (
                linear.box_face_forces_n([s; 3]),
                cubic.box_face_forces_n([s; 3]),
            );
            for i in 0..3 {
                let want = fl[i] * (1.0 + 4.0 * d * d);
                assert!(
                    (fc[i] - want).abs() < 1e-9 * want.abs(),
                    "s {s}: {} vs {want}",
                    fc[i]
                );
            }
        }
    }
}
