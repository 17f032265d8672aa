//! sform / qform / ANALYZE fallback → LPS grid, and the NIfTI quaternion conversions.

use nalgebra::{Matrix3, Vector3};

use super::header::Header;
use crate::volume::VolumeGeometry;
use crate::{Error, Result};

/// Largest non-orthogonality of sform axes accepted (as [`VolumeGeometry::validate`]).
const MAX_SHEAR: f64 = 1e-3;
/// How far b² + c² + d² of a qform quaternion may exceed 1: float32 rounding of a unit
/// quaternion stays below 10⁻⁶; nibabel refuses beyond 3 float32 epsilons, nifti1_io
/// silently renormalises any length, which turns garbage into some rotation.
const QUATERNION_ROUNDING: f64 = 1e-5;
/// Smallest |det| of the sform's axes divided by the product of their lengths: below, the
/// axes are (nearly) coplanar and no grid can be placed.
const MIN_SFORM_VOLUME_RATIO: f64 = 1e-6;

/// The grid in LPS millimetres from the sform, the qform or the ANALYZE fallback.
pub(super) fn geometry(header: &Header, dims: [usize; 3], what: &str) -> Result<VolumeGeometry> {
    let bad = |m: String| Error::scan(what, m);
    let mm_per_unit = match header.xyzt_units & 0x07 {
        0 | 2 => 1.0,
        1 => 1000.0,
        3 => 1e-3,
        other => {
            tracing::warn!("{what}: spatial unit code {other} is undefined; assuming mm");
            1.0
        }
    };
    let rank = header.dim[0].clamp(1, 3) as usize;
    let mut pixdim_mm = [1.0f64; 3];
    for (axis, (spacing, &p)) in pixdim_mm
        .iter_mut()
        .zip(&header.pixdim[1..4])
        .enumerate()
        .take(rank)
    {
        if !p.is_finite() || p <= 0.0 {
            return Err(bad(format!(
                "pixdim[{}] = {p}: voxel spacing must be positive",
                axis + 1
            )));
        }
        *spacing = p * mm_per_unit;
    }
    let (axes_ras_mm, origin_ras_mm) = if header.sform_code > 0 {
        check_sform(header, what)?;
        let s = &header.srow;
        let axes = Matrix3::from_fn(|r, c| s[r][c] * mm_per_unit);
        let origin = Vector3::new(s[0][3], s[1][3], s[2][3]) * mm_per_unit;
        (axes, origin)
    } else if header.qform_code > 0 {
        check_quaternion(header, what)?;
        let qfac = if header.pixdim[0] < 0.0 { -1.0 } else { 1.0 };
        let rotation = quaternion_to_rotation(header.quatern_bcd);
        let scale = Vector3::new(pixdim_mm[0], pixdim_mm[1], qfac * pixdim_mm[2]);
        let origin = Vector3::from(header.qoffset) * mm_per_unit;
        (rotation * Matrix3::from_diagonal(&scale), origin)
    } else {
        tracing::warn!(
            "{what}: sform_code and qform_code are 0 (ANALYZE-style header): placing the \
             grid at the origin with axes along R, A, S scaled by pixdim"
        );
        (
            Matrix3::from_diagonal(&Vector3::from(pixdim_mm)),
            Vector3::zeros(),
        )
    };
    let mut spacing_mm = [0.0; 3];
    let mut direction_ras = Matrix3::zeros();
    for (axis, spacing) in spacing_mm.iter_mut().enumerate() {
        let column = axes_ras_mm.column(axis);
        let length = column.norm();
        if !length.is_finite() || length == 0.0 {
            return Err(bad(format!(
                "the affine's axis {axis} has length {length} mm: no grid can be placed"
            )));
        }
        *spacing = length;
        direction_ras.set_column(axis, &(column / length));
    }
    let shear = (direction_ras.transpose() * direction_ras - Matrix3::identity())
        .abs()
        .max();
    if shear > MAX_SHEAR {
        return Err(bad(format!(
            "sheared affine (sform_code {}, qform_code {}): the voxel axes are not \
             orthogonal (|DᵀD − I| = {shear:.2e}); only rotations and reflections are \
             supported, resample the image first",
            header.sform_code, header.qform_code
        )));
    }
    let ras_to_lps = Matrix3::from_diagonal(&Vector3::new(-1.0, -1.0, 1.0));
    let direction_lps = ras_to_lps * direction_ras;
    let origin_lps = ras_to_lps * origin_ras_mm;
    Ok(VolumeGeometry {
        dims,
        spacing_mm,
        origin_lps_mm: origin_lps.into(),
        direction_lps: std::array::from_fn(|c| direction_lps.column(c).into_owned().into()),
    })
}

/// Refuses an sform with a non-finite entry or coplanar axes, naming the rows.
fn check_sform(header: &Header, what: &str) -> Result<()> {
    let names = ["srow_x", "srow_y", "srow_z"];
    for (row, name) in header.srow.iter().zip(names) {
        if row.iter().any(|v| !v.is_finite()) {
            return Err(Error::scan(
                what,
                format!(
                    "sform (sform_code {}) has a non-finite entry: {name} = {row:?}",
                    header.sform_code
                ),
            ));
        }
    }
    let axes = Matrix3::from_fn(|r, c| header.srow[r][c]);
    let lengths: f64 = (0..3).map(|c| axes.column(c).norm()).product();
    let det = axes.determinant();
    if lengths == 0.0 || (det / lengths).abs() < MIN_SFORM_VOLUME_RATIO {
        return Err(Error::scan(
            what,
            format!(
                "singular sform (sform_code {}): determinant {det:.3e} of srow_x = {:?}, \
                 srow_y = {:?}, srow_z = {:?}; its voxel axes do not span space",
                header.sform_code, header.srow[0], header.srow[1], header.srow[2]
            ),
        ));
    }
    Ok(())
}

/// Refuses a qform quaternion that is not finite or longer than a unit quaternion.
fn check_quaternion(header: &Header, what: &str) -> Result<()> {
    let [b, c, d] = header.quatern_bcd;
    let squares = b * b + c * c + d * d;
    let offset_finite = header.qoffset.iter().all(|v| v.is_finite());
    if squares.is_finite() && squares <= 1.0 + QUATERNION_ROUNDING && offset_finite {
        return Ok(());
    }
    let reason = if !offset_finite {
        format!("qoffset {:?} is not finite", header.qoffset)
    } else if !squares.is_finite() {
        format!("quatern_b, c, d = ({b}, {c}, {d}) are not finite")
    } else {
        format!(
            "quatern_b, c, d = ({b}, {c}, {d}) give b²+c²+d² = {squares}, more than 1: \
             not a rotation quaternion"
        )
    };
    Err(Error::scan(
        what,
        format!(
            "degenerate qform (qform_code {}, sform_code 0): {reason}",
            header.qform_code
        ),
    ))
}

/// Rotation of the NIfTI quaternion (b, c, d), a ≥ 0 implied (nifti1.h, method 2).
fn quaternion_to_rotation([b, c, d]: [f64; 3]) -> Matrix3<f64> {
    let squares = b * b + c * c + d * d;
    let (a, b, c, d) = if 1.0 - squares < 1e-7 {
        // A 180° rotation: a is 0 and (b, c, d) is renormalised, as nifti1_io does.
        let norm = squares.sqrt();
        (0.0, b / norm, c / norm, d / norm)
    } else {
        ((1.0 - squares).sqrt(), b, c, d)
    };
    Matrix3::new(
        a * a + b * b - c * c - d * d,
        2.0 * (b * c - a * d),
        2.0 * (b * d + a * c),
        2.0 * (b * c + a * d),
        a * a + c * c - b * b - d * d,
        2.0 * (c * d - a * b),
        2.0 * (b * d - a * c),
        2.0 * (c * d + a * b),
        a * a + d * d - c * c - b * b,
    )
}

/// Quaternion (b, c, d) with a ≥ 0 of a proper rotation (nifti_mat44_to_quatern).
pub(super) fn rotation_to_quaternion(r: &Matrix3<f64>) -> [f64; 3] {
    let trace_plus_one = r[(0, 0)] + r[(1, 1)] + r[(2, 2)] + 1.0;
    let (a, b, c, d) = if trace_plus_one > 0.5 {
        let a = 0.5 * trace_plus_one.sqrt();
        (
            a,
            0.25 * (r[(2, 1)] - r[(1, 2)]) / a,
            0.25 * (r[(0, 2)] - r[(2, 0)]) / a,
            0.25 * (r[(1, 0)] - r[(0, 1)]) / a,
        )
    } else {
        let xd = 1.0 + r[(0, 0)] - (r[(1, 1)] + r[(2, 2)]);
        let yd = 1.0 + r[(1, 1)] - (r[(0, 0)] + r[(2, 2)]);
        let zd = 1.0 + r[(2, 2)] - (r[(0, 0)] + r[(1, 1)]);
        if xd > 1.0 {
            let b = 0.5 * xd.sqrt();
            (
                0.25 * (r[(2, 1)] - r[(1, 2)]) / b,
                b,
                0.25 * (r[(0, 1)] + r[(1, 0)]) / b,
                0.25 * (r[(0, 2)] + r[(2, 0)]) / b,
            )
        } else if yd > 1.0 {
            let c = 0.5 * yd.sqrt();
            (
                0.25 * (r[(0, 2)] - r[(2, 0)]) / c,
                0.25 * (r[(0, 1)] + r[(1, 0)]) / c,
                c,
                0.25 * (r[(1, 2)] + r[(2, 1)]) / c,
            )
        } else {
            let d = 0.5 * zd.sqrt();
            (
                0.25 * (r[(1, 0)] - r[(0, 1)]) / d,
                0.25 * (r[(0, 2)] + r[(2, 0)]) / d,
                0.25 * (r[(1, 2)] + r[(2, 1)]) / d,
                d,
            )
        }
    };
    if a < 0.0 {
        [-b, -c, -d]
    } else {
        [b, c, d]
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn quaternion_conversion_round_trips_including_half_turns() {
        let (s, c) = (0.4f64.sin(), 0.4f64.cos());
        let rotations = [
            Matrix3::new(c, -s, 0.0, s, c, 0.0, 0.0, 0.0, 1.0),
            Matrix3::new(1.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0, -1.0),
            Matrix3::new(-1.0, 0.0, 0.0, 0.0, -1.0, 0.0, 0.0, 0.0, 1.0),
            Matrix3::new(-1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, -1.0),
            nalgebra::Rotation3::from_euler_angles(0.3, -1.2, 2.9).into_inner(),
        ];
        for r in rotations {
            let q = rotation_to_quaternion(&r);
            let back = quaternion_to_rotation(q);
            assert!((back - r).abs().max() < 1e-12, "{r} -> {q:?} -> {back}");
        }
    }
}
