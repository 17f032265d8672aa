//! A [`PhaseMotion`] from one frame's sampled displacement field (the `displacement.nii.gz`
//! a run writes, on the lung box or the CT grid): forward by trilinear interpolation of u,
//! backward by fixed-point iteration.
//!
//! The field is zero outside the lungs, vessels and airways inside them included, which
//! would tear a target that holds a vessel. So a zero vector counts as "no sample": u is the
//! trilinear interpolation over the nonzero samples only, weights renormalised, and zero
//! where all eight are zero (outside the lungs, at rest). This bridges one-voxel gaps, not
//! wider ones; the motion over the whole CT grid supersedes it.

use nalgebra::Vector3;

use super::PhaseMotion;
use crate::volume::VolumeGeometry;

/// Fixed-point iterations of the inverse at most.
const INVERSE_ITERATIONS: usize = 30;
/// The inverse stops once x + u(x) is this close to the point asked for, mm.
const INVERSE_TOLERANCE_MM: f64 = 1e-4;

/// One instant's displacement field u on a grid: the tissue at x is at x + u(x).
pub struct SampledFieldMotion<'a> {
    geometry: VolumeGeometry,
    field_mm: &'a [[f32; 3]],
}

impl<'a> SampledFieldMotion<'a> {
    /// The motion of `field_mm` (one LPS-mm vector per voxel of `geometry`, i fastest).
    /// `None` when the lengths disagree.
    pub fn new(geometry: VolumeGeometry, field_mm: &'a [[f32; 3]]) -> Option<Self> {
        (field_mm.len() == geometry.voxel_count())
            .then_some(SampledFieldMotion { geometry, field_mm })
    }

    /// u at `p_lps_mm`: trilinear over the nonzero samples (see the module doc), zero
    /// outside the grid and where no sample is nonzero.
    pub fn displacement_mm(&self, p_lps_mm: [f64; 3]) -> [f64; 3] {
        let g = &self.geometry;
        let v = g.lps_mm_to_voxel(Vector3::from(p_lps_mm));
        let base = [v[0].floor(), v[1].floor(), v[2].floor()];
        let mut u = [0.0f64; 3];
        let mut total_weight = 0.0;
        for corner in 0..8usize {
            let offset = [corner & 1, (corner >> 1) & 1, (corner >> 2) & 1];
            let mut weight = 1.0;
            let mut index = [0usize; 3];
            let mut inside = true;
            for a in 0..3 {
                let c = base[a] + offset[a] as f64;
                let f = v[a] - base[a];
                weight *= if offset[a] == 1 { f } else { 1.0 - f };
                inside &= c >= 0.0 && c < g.dims[a] as f64;
                index[a] = c.max(0.0) as usize;
            }
            if inside && weight > 0.0 {
                let d = self.field_mm[g.index(index[0], index[1], index[2])];
                if d != [0.0; 3] {
                    total_weight += weight;
                    for a in 0..3 {
                        u[a] += weight * f64::from(d[a]);
                    }
                }
            }
        }
        if total_weight > 0.0 {
            u.map(|c| c / total_weight)
        } else {
            u
        }
    }
}

impl PhaseMotion for SampledFieldMotion<'_> {
    fn moved_lps_mm(&self, rest_lps_mm: [f64; 3]) -> [f64; 3] {
        let u = self.displacement_mm(rest_lps_mm);
        [0, 1, 2].map(|a| rest_lps_mm[a] + u[a])
    }

    fn source_lps_mm(&self, moved_lps_mm: [f64; 3]) -> [f64; 3] {
        // x = y − u(x), iterated from x = y: converges where the field's gradient is below 1,
        // as a physical (non-folding) breathing motion's is.
        let mut x = moved_lps_mm;
        for _ in 0..INVERSE_ITERATIONS {
            let u = self.displacement_mm(x);
            let next = [0, 1, 2].map(|a| moved_lps_mm[a] - u[a]);
            let step = (0..3).map(|a| (next[a] - x[a]).abs()).fold(0.0, f64::max);
            x = next;
            if step < INVERSE_TOLERANCE_MM {
                break;
            }
        }
        x
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_uniform_field_moves_and_inverts_by_its_vector() {
        let g = VolumeGeometry::axis_aligned([10, 10, 10], [2.0, 2.0, 2.0], [0.0, 0.0, 0.0]);
        let field = vec![[1.0f32, -2.0, 3.0]; g.voxel_count()];
        let m = SampledFieldMotion::new(g, &field).unwrap();
        let p = [7.3, 9.1, 5.5];
        let q = m.moved_lps_mm(p);
        assert!((q[0] - 8.3).abs() < 1e-9 && (q[1] - 7.1).abs() < 1e-9);
        let back = m.source_lps_mm(q);
        assert!((0..3).all(|a| (back[a] - p[a]).abs() < 1e-6), "{back:?}");
    }

    #[test]
    fn a_stretch_inverts_within_the_tolerance() {
        // u = 0.2·(z − 5) along z: moved z = 1.2 z − 1.
        let g = VolumeGeometry::axis_aligned([6, 6, 12], [1.0, 1.0, 1.0], [0.0, 0.0, 0.0]);
        let field: Vec<[f32; 3]> = (0..g.voxel_count())
            .map(|n| [0.0, 0.0, 0.2 * ((n / 36) as f32 - 5.0)])
            .collect();
        let m = SampledFieldMotion::new(g, &field).unwrap();
        let y = [2.0, 2.0, 7.0];
        let x = m.source_lps_mm(y);
        assert!((x[2] - 8.0 / 1.2).abs() < 1e-3, "{x:?}");
    }
}
