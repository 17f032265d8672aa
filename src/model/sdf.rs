//! Signed distance fields sampled on a regular grid: the implicit surfaces (chest wall,
//! diaphragm) that constrained nodes slide on.

use nalgebra::Vector3;

use crate::{Error, Result};

/// Signed distance in metres, negative inside, sampled at the points of an axis-aligned grid
/// and interpolated trilinearly between them.
#[derive(Debug, Clone)]
pub struct SignedDistanceField {
    /// World position of sample (0, 0, 0) in metres.
    pub origin_m: Vector3<f64>,
    /// Sample spacing along x, y, z in metres.
    pub spacing_m: [f64; 3],
    /// Number of samples along x, y, z (at least 2 each).
    pub samples: [usize; 3],
    /// Signed distances, x fastest.
    values: SampleValues,
}

/// How the samples are held: metres as given, or `f32` samples in a unit of `unit_m` metres
/// (a CT wall's distances are computed in samples as `f32`; holding them so, rather than
/// as `f64` metres, halves the largest array of a clinical ingest and reads the same values).
#[derive(Debug, Clone, PartialEq)]
enum SampleValues {
    Metres(Vec<f64>),
    Scaled { values: Vec<f32>, unit_m: f64 },
}

impl SignedDistanceField {
    /// Checks sizes, spacing and that every sample is finite.
    pub fn new(
        origin_m: Vector3<f64>,
        spacing_m: [f64; 3],
        samples: [usize; 3],
        values_m: Vec<f64>,
    ) -> Result<Self> {
        if samples.iter().any(|&n| n < 2) {
            return Err(Error::InvalidModel(format!(
                "a distance field needs at least 2 samples per axis, got {samples:?}"
            )));
        }
        if spacing_m.iter().any(|s| !s.is_finite() || *s <= 0.0) {
            return Err(Error::InvalidModel(format!(
                "distance field spacing must be positive, got {spacing_m:?}"
            )));
        }
        Self::checked(origin_m, spacing_m, samples, SampleValues::Metres(values_m))
    }

    /// A field of `f32` samples, each `unit_m` metres per unit: sample i is
    /// `values[i] as f64 * unit_m` metres, exactly. Checked as [`Self::new`].
    pub fn scaled(
        origin_m: Vector3<f64>,
        spacing_m: [f64; 3],
        samples: [usize; 3],
        values: Vec<f32>,
        unit_m: f64,
    ) -> Result<Self> {
        if !unit_m.is_finite() || unit_m <= 0.0 {
            return Err(Error::InvalidModel(format!(
                "distance field unit must be positive, got {unit_m} m"
            )));
        }
        Self::checked(
            origin_m,
            spacing_m,
            samples,
            SampleValues::Scaled { values, unit_m },
        )
    }

    fn checked(
        origin_m: Vector3<f64>,
        spacing_m: [f64; 3],
        samples: [usize; 3],
        values: SampleValues,
    ) -> Result<Self> {
        if samples.iter().any(|&n| n < 2) {
            return Err(Error::InvalidModel(format!(
                "a distance field needs at least 2 samples per axis, got {samples:?}"
            )));
        }
        if spacing_m.iter().any(|s| !s.is_finite() || *s <= 0.0) {
            return Err(Error::InvalidModel(format!(
                "distance field spacing must be positive, got {spacing_m:?}"
            )));
        }
        let (len, non_finite) = match &values {
            SampleValues::Metres(v) => (v.len(), v.iter().position(|v| !v.is_finite())),
            SampleValues::Scaled { values, .. } => {
                (values.len(), values.iter().position(|v| !v.is_finite()))
            }
        };
        if len != samples.iter().product::<usize>() {
            return Err(Error::InvalidModel(format!(
                "distance field of {samples:?} samples has {len} values"
            )));
        }
        if let Some(i) = non_finite {
            return Err(Error::InvalidModel(format!(
                "distance field sample {i} is not finite"
            )));
        }
        Ok(SignedDistanceField {
            origin_m,
            spacing_m,
            samples,
            values,
        })
    }

    /// Number of samples.
    pub fn len(&self) -> usize {
        match &self.values {
            SampleValues::Metres(v) => v.len(),
            SampleValues::Scaled { values, .. } => values.len(),
        }
    }

    /// Whether the field has no sample (never, once built: at least 2 per axis).
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// Bytes the samples occupy.
    pub fn sample_bytes(&self) -> usize {
        match &self.values {
            SampleValues::Metres(v) => 8 * v.len(),
            SampleValues::Scaled { values, .. } => 4 * values.len(),
        }
    }

    /// Sample `index` (x fastest), metres.
    #[inline]
    pub fn value_m(&self, index: usize) -> f64 {
        match &self.values {
            SampleValues::Metres(v) => v[index],
            SampleValues::Scaled { values, unit_m } => values[index] as f64 * unit_m,
        }
    }

    /// The `f32` samples and their unit in metres, when the field is held so.
    pub fn scaled_samples(&self) -> Option<(&[f32], f64)> {
        match &self.values {
            SampleValues::Metres(_) => None,
            SampleValues::Scaled { values, unit_m } => Some((values, *unit_m)),
        }
    }

    /// Whether two fields have the same grid and the same sample values, bit for bit.
    pub fn same_samples(&self, other: &SignedDistanceField) -> bool {
        self.origin_m == other.origin_m
            && self.spacing_m == other.spacing_m
            && self.samples == other.samples
            && (0..self.len()).all(|i| self.value_m(i).to_bits() == other.value_m(i).to_bits())
    }

    /// Samples an analytic signed distance function on a grid covering `min_m`..`max_m`.
    pub fn from_fn(
        min_m: Vector3<f64>,
        max_m: Vector3<f64>,
        spacing_m: f64,
        f: impl Fn(Vector3<f64>) -> f64,
    ) -> Result<Self> {
        let samples: [usize; 3] = std::array::from_fn(|a| {
            (((max_m[a] - min_m[a]) / spacing_m).ceil() as usize + 1).max(2)
        });
        let mut values = Vec::with_capacity(samples.iter().product());
        for k in 0..samples[2] {
            for j in 0..samples[1] {
                for i in 0..samples[0] {
                    values.push(f(
                        min_m + Vector3::new(i as f64, j as f64, k as f64) * spacing_m
                    ));
                }
            }
        }
        Self::new(min_m, [spacing_m; 3], samples, values)
    }

    /// Distance and gradient at `p_m` (trilinear; clamped to the grid's boundary cells).
    pub fn evaluate(&self, p_m: Vector3<f64>) -> (f64, Vector3<f64>) {
        let mut cell = [0usize; 3];
        let mut t = [0.0; 3];
        for a in 0..3 {
            let u = (p_m[a] - self.origin_m[a]) / self.spacing_m[a];
            let c = u.floor().clamp(0.0, (self.samples[a] - 2) as f64);
            cell[a] = c as usize;
            t[a] = u - c;
        }
        let at = |di: usize, dj: usize, dk: usize| {
            let (i, j, k) = (cell[0] + di, cell[1] + dj, cell[2] + dk);
            self.value_m(i + self.samples[0] * (j + self.samples[1] * k))
        };
        let mut value = 0.0;
        let mut grad = Vector3::zeros();
        for dk in 0..2 {
            for dj in 0..2 {
                for di in 0..2 {
                    let v = at(di, dj, dk);
                    let w = [
                        if di == 1 { t[0] } else { 1.0 - t[0] },
                        if dj == 1 { t[1] } else { 1.0 - t[1] },
                        if dk == 1 { t[2] } else { 1.0 - t[2] },
                    ];
                    let dw = [
                        if di == 1 { 1.0 } else { -1.0 },
                        if dj == 1 { 1.0 } else { -1.0 },
                        if dk == 1 { 1.0 } else { -1.0 },
                    ];
                    value += v * w[0] * w[1] * w[2];
                    grad[0] += v * dw[0] * w[1] * w[2] / self.spacing_m[0];
                    grad[1] += v * w[0] * dw[1] * w[2] / self.spacing_m[1];
                    grad[2] += v * w[0] * w[1] * dw[2] / self.spacing_m[2];
                }
            }
        }
        (value, grad)
    }

    /// Gradient by central differences of the interpolant over half a cell: unlike the
    /// trilinear gradient it is continuous across cell faces, so sliding nodes see a normal
    /// that does not jump as they cross cells.
    pub fn smooth_gradient(&self, p_m: Vector3<f64>) -> Vector3<f64> {
        Vector3::from_fn(|a, _| {
            let h = 0.5 * self.spacing_m[a];
            let mut e = Vector3::zeros();
            e[a] = h;
            (self.evaluate(p_m + e).0 - self.evaluate(p_m - e).0) / (2.0 * h)
        })
    }

    /// Distance and exact gradient of the field's cubic B-spline at `p_m` (samples indexed
    /// past the border are clamped). Unlike the trilinear interpolant it is twice
    /// continuously differentiable, so a node held on one of its level sets has a normal
    /// that is the level set's own and turns smoothly: Newton's tangent steps stay on the
    /// surface to second order and the sliding equilibrium has a well-defined Jacobian. A
    /// B-spline reproduces linear functions, so a flat wall's distance is exact.
    pub fn spline(&self, p_m: Vector3<f64>) -> (f64, Vector3<f64>) {
        let mut base = [0i64; 3];
        let mut w = [[0.0; 4]; 3];
        let mut dw = [[0.0; 4]; 3];
        for a in 0..3 {
            let u = (p_m[a] - self.origin_m[a]) / self.spacing_m[a];
            let i = u.floor();
            let t = u - i;
            base[a] = i as i64 - 1;
            let s = 1.0 - t;
            w[a] = [
                s * s * s / 6.0,
                (3.0 * t * t * t - 6.0 * t * t + 4.0) / 6.0,
                (-3.0 * t * t * t + 3.0 * t * t + 3.0 * t + 1.0) / 6.0,
                t * t * t / 6.0,
            ];
            let h = self.spacing_m[a];
            dw[a] = [
                -s * s / (2.0 * h),
                (3.0 * t * t - 4.0 * t) / (2.0 * h),
                (-3.0 * t * t + 2.0 * t + 1.0) / (2.0 * h),
                t * t / (2.0 * h),
            ];
        }
        let index =
            |a: usize, o: usize| (base[a] + o as i64).clamp(0, self.samples[a] as i64 - 1) as usize;
        let (mut value, mut grad) = (0.0, Vector3::zeros());
        for c in 0..4 {
            let k = index(2, c);
            for b in 0..4 {
                let j = index(1, b);
                let row = self.samples[0] * (j + self.samples[1] * k);
                // Sums along x first: 4 samples, their weights and the x derivative.
                let (mut vx, mut gx) = (0.0, 0.0);
                for a in 0..4 {
                    let v = self.value_m(index(0, a) + row);
                    vx += w[0][a] * v;
                    gx += dw[0][a] * v;
                }
                value += w[1][b] * w[2][c] * vx;
                grad.x += w[1][b] * w[2][c] * gx;
                grad.y += dw[1][b] * w[2][c] * vx;
                grad.z += w[1][b] * dw[2][c] * vx;
            }
        }
        (value, grad)
    }

    /// Unit normal of the B-spline's level set at `p_m` ([`Self::spline`]).
    pub fn spline_normal(&self, p_m: Vector3<f64>) -> Vector3<f64> {
        let g = self.spline(p_m).1;
        let n = g.norm();
        if n > 0.0 {
            g / n
        } else {
            Vector3::z()
        }
    }

    /// Closest point on the B-spline's level set {distance = `level_m`}, by Newton steps
    /// along its gradient ([`Self::spline`]).
    pub fn project_to_spline_level_m(&self, mut p_m: Vector3<f64>, level_m: f64) -> Vector3<f64> {
        for _ in 0..8 {
            let (v, g) = self.spline(p_m);
            let d = v - level_m;
            let g2 = g.norm_squared();
            if g2 < 1e-24 || d.abs() < 1e-13 {
                break;
            }
            p_m -= g * (d / g2);
        }
        p_m
    }

    /// Closest point on the zero level set reached by Newton steps along the gradient.
    pub fn project_m(&self, mut p_m: Vector3<f64>) -> Vector3<f64> {
        for _ in 0..8 {
            let d = self.evaluate(p_m).0;
            let g = self.smooth_gradient(p_m);
            let g2 = g.norm_squared();
            if g2 < 1e-24 {
                break;
            }
            p_m -= g * (d / g2);
            if d.abs() < 1e-12 {
                break;
            }
        }
        p_m
    }

    /// Unit normal (direction of increasing distance) at `p_m`.
    pub fn normal(&self, p_m: Vector3<f64>) -> Vector3<f64> {
        let g = self.smooth_gradient(p_m);
        let n = g.norm();
        if n > 0.0 {
            g / n
        } else {
            Vector3::z()
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sphere_projection_lands_on_surface() {
        let r = 0.1;
        let sdf =
            SignedDistanceField::from_fn(Vector3::repeat(-0.2), Vector3::repeat(0.2), 0.005, |p| {
                p.norm() - r
            })
            .unwrap();
        let p = sdf.project_m(Vector3::new(0.09, 0.03, -0.02));
        assert!((p.norm() - r).abs() < 2e-4, "{}", p.norm());
        let n = sdf.normal(Vector3::new(0.1, 0.0, 0.0));
        assert!((n - Vector3::x()).norm() < 1e-2);
    }

    #[test]
    fn the_spline_reproduces_a_plane_and_its_gradient_is_its_own_derivative() {
        // A tilted plane, sampled with anisotropic spacing: a cubic B-spline reproduces
        // linear functions, so distance and gradient are exact away from the border.
        let n = Vector3::new(0.3, -0.5, 0.8).normalize();
        let plane = SignedDistanceField::new(
            Vector3::new(-0.05, -0.04, -0.06),
            [0.004, 0.005, 0.007],
            [26, 17, 18],
            (0..18)
                .flat_map(|k| (0..17).flat_map(move |j| (0..26).map(move |i| (i, j, k))))
                .map(|(i, j, k)| {
                    let p = Vector3::new(
                        -0.05 + 0.004 * i as f64,
                        -0.04 + 0.005 * j as f64,
                        -0.06 + 0.007 * k as f64,
                    );
                    n.dot(&p) - 0.01
                })
                .collect(),
        )
        .unwrap();
        for p in [
            Vector3::new(0.01, 0.0, 0.02),
            Vector3::new(-0.013, 0.021, -0.005),
        ] {
            let (v, g) = plane.spline(p);
            assert!((v - (n.dot(&p) - 0.01)).abs() < 1e-12, "{v}");
            assert!((g - n).norm() < 1e-10, "{g}");
        }
        // On a curved field the gradient is the derivative of the value (what Newton needs).
        let sphere =
            SignedDistanceField::from_fn(Vector3::repeat(-0.2), Vector3::repeat(0.2), 0.01, |p| {
                p.norm() - 0.1
            })
            .unwrap();
        let p = Vector3::new(0.071, -0.043, 0.052);
        let g = sphere.spline(p).1;
        for a in 0..3 {
            let mut e = Vector3::zeros();
            e[a] = 1e-6;
            let fd = (sphere.spline(p + e).0 - sphere.spline(p - e).0) / 2e-6;
            assert!((fd - g[a]).abs() < 1e-7, "axis {a}: {fd} against {}", g[a]);
        }
        // Projection lands on the asked level, along the normal.
        let q = sphere.project_to_spline_level_m(Vector3::new(0.09, 0.03, -0.02), 0.004);
        assert!((sphere.spline(q).0 - 0.004).abs() < 1e-12);
        // The cubic B-spline smooths with variance h²/3 per axis, which moves the level sets
        // of |p| − R inward by (h²/6)·Δ|p| = h²/(3r): 0.32 mm here, at 10 mm samples (a CT
        // wall is sampled at 1–3 mm, where it is 0.003–0.03 mm).
        let expected = 0.104 - 0.01f64.powi(2) / (3.0 * 0.104);
        assert!(
            (q.norm() - expected).abs() < 2e-5,
            "{} against {expected}",
            q.norm()
        );
        assert!((sphere.spline_normal(q) - q.normalize()).norm() < 1e-2);
    }

    #[test]
    fn refuses_bad_fields() {
        assert!(
            SignedDistanceField::new(Vector3::zeros(), [1.0; 3], [1, 2, 2], vec![0.0; 4]).is_err()
        );
        assert!(
            SignedDistanceField::new(Vector3::zeros(), [0.0, 1.0, 1.0], [2; 3], vec![0.0; 8])
                .is_err()
        );
        let mut v = vec![0.0; 8];
        v[3] = f64::NAN;
        assert!(SignedDistanceField::new(Vector3::zeros(), [1.0; 3], [2; 3], v).is_err());
        let mut w = vec![0.0f32; 8];
        assert!(
            SignedDistanceField::scaled(Vector3::zeros(), [1.0; 3], [2; 3], w.clone(), 0.0)
                .is_err()
        );
        w[5] = f32::INFINITY;
        assert!(SignedDistanceField::scaled(Vector3::zeros(), [1.0; 3], [2; 3], w, 1.0).is_err());
    }

    #[test]
    fn scaled_samples_read_as_the_metres_they_stand_for() {
        let values: Vec<f32> = (0..27).map(|i| i as f32 * 0.37 - 4.1).collect();
        let unit_m = 1.2e-3;
        let metres: Vec<f64> = values.iter().map(|&v| v as f64 * unit_m).collect();
        let origin = Vector3::new(0.01, -0.02, 0.003);
        let a = SignedDistanceField::new(origin, [unit_m; 3], [3; 3], metres).unwrap();
        let b = SignedDistanceField::scaled(origin, [unit_m; 3], [3; 3], values, unit_m).unwrap();
        assert!(a.same_samples(&b));
        assert_eq!((a.sample_bytes(), b.sample_bytes()), (216, 108));
        for p in [
            Vector3::new(0.011, -0.019, 0.004),
            Vector3::new(0.0125, -0.0181, 0.0049),
        ] {
            assert_eq!(a.evaluate(p), b.evaluate(p));
        }
    }
}
