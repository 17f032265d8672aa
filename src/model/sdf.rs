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
