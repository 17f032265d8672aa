//! The one internal image type: voxels on a grid placed in DICOM patient space (LPS, mm).
//!
//! Every reader (DICOM, NIfTI, NRRD) converts into [`Volume`]; every later stage works in
//! patient millimetres through [`VolumeGeometry`]. Voxel data are stored with the first
//! index fastest (`i + nx·(j + ny·k)`), as NIfTI, NRRD and a DICOM frame's rows store them,
//! so readers and writers copy without reordering. They live in an [`Array3`] of shape
//! `(nk, nj, ni)` in standard (C) layout, which is exactly that order: `[[k, j, i]]` and the
//! flat [`Volume::as_slice`] index `geometry.index(i, j, k)` name the same voxel.

use nalgebra::{Matrix3, Matrix4, Vector3};
use ndarray::{Array3, ArrayView3, ArrayViewMut3, Zip};
use serde::Serialize;

use crate::{Error, Result};

/// Largest number of voxels a volume may hold (2³¹, 8 GiB as f32): refused before allocating.
pub const MAX_VOXELS: usize = 1 << 31;
/// Largest number of voxels along one axis.
pub const MAX_DIM: usize = 16_384;
/// Smallest voxel spacing accepted, in millimetres (micro-CT is 0.01 mm; below is corrupt).
pub const MIN_SPACING_MM: f64 = 1e-3;
/// Largest voxel spacing accepted, in millimetres (no clinical CT has 10 cm voxels).
pub const MAX_SPACING_MM: f64 = 100.0;

/// Where a voxel grid sits in DICOM patient space (LPS: +x left, +y posterior, +z superior).
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct VolumeGeometry {
    /// Voxels along the grid's i, j, k axes.
    pub dims: [usize; 3],
    /// Distance between voxel centres along i, j, k, in millimetres.
    pub spacing_mm: [f64; 3],
    /// LPS position of the centre of voxel (0, 0, 0), in millimetres.
    pub origin_lps_mm: [f64; 3],
    /// Unit LPS directions of the i, j, k axes, as the columns of a rotation
    /// (or a reflection: left-handed grids are legal and kept as they are).
    pub direction_lps: [[f64; 3]; 3],
}

impl VolumeGeometry {
    /// An axis-aligned grid (identity direction).
    pub fn axis_aligned(dims: [usize; 3], spacing_mm: [f64; 3], origin_lps_mm: [f64; 3]) -> Self {
        VolumeGeometry {
            dims,
            spacing_mm,
            origin_lps_mm,
            direction_lps: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
        }
    }

    /// Checks dimensions, spacing and direction before anything is allocated; `what` names
    /// the input in the error (a path, "NIfTI header", …).
    pub fn validate(&self, what: &str) -> Result<()> {
        let bad = |reason: String| Err(Error::scan(what, reason));
        if self.dims.contains(&0) {
            return bad(format!("empty grid {:?}", self.dims));
        }
        if self.dims.iter().any(|&n| n > MAX_DIM) {
            return bad(format!(
                "absurd grid {:?}: at most {MAX_DIM} voxels per axis",
                self.dims
            ));
        }
        let count = self.dims.iter().try_fold(1usize, |a, &n| a.checked_mul(n));
        match count {
            Some(c) if c <= MAX_VOXELS => {}
            _ => {
                return bad(format!(
                    "absurd grid {:?}: more than {MAX_VOXELS} voxels",
                    self.dims
                ))
            }
        }
        for (axis, &s) in self.spacing_mm.iter().enumerate() {
            if !s.is_finite() || s <= 0.0 {
                return bad(format!(
                    "voxel spacing along axis {axis} is {s} mm; it must be positive"
                ));
            }
            if !(MIN_SPACING_MM..=MAX_SPACING_MM).contains(&s) {
                return bad(format!(
                    "voxel spacing along axis {axis} is {s} mm, outside the plausible \
                     {MIN_SPACING_MM}–{MAX_SPACING_MM} mm"
                ));
            }
        }
        if self
            .origin_lps_mm
            .iter()
            .any(|v| !v.is_finite() || v.abs() > 1e6)
        {
            return bad(format!("origin {:?} mm is not finite", self.origin_lps_mm));
        }
        let d = self.direction();
        if d.iter().any(|v| !v.is_finite()) {
            return bad("direction cosines are not finite".into());
        }
        let orthonormality = (d.transpose() * d - Matrix3::identity()).abs().max();
        if orthonormality > 1e-3 {
            return bad(format!(
                "voxel axes are not orthonormal (|DᵀD − I| = {orthonormality:.2e}): \
                 sheared grids (e.g. gantry tilt) are not supported"
            ));
        }
        Ok(())
    }

    /// The sub-grid of `dims` voxels whose voxel (0, 0, 0) is this grid's voxel `start`:
    /// same spacing and direction, origin moved there. Its voxels are this grid's voxels.
    pub fn sub_grid(&self, start: [usize; 3], dims: [usize; 3]) -> VolumeGeometry {
        let start_ijk = Vector3::new(start[0] as f64, start[1] as f64, start[2] as f64);
        VolumeGeometry {
            dims,
            origin_lps_mm: self.voxel_to_lps_mm(start_ijk).into(),
            ..*self
        }
    }

    /// Number of voxels.
    pub fn voxel_count(&self) -> usize {
        self.dims.iter().product()
    }

    /// Volume of one voxel in mm³.
    pub fn voxel_volume_mm3(&self) -> f64 {
        self.spacing_mm.iter().product()
    }

    /// Linear index of voxel (i, j, k), i fastest.
    #[inline]
    pub fn index(&self, i: usize, j: usize, k: usize) -> usize {
        i + self.dims[0] * (j + self.dims[1] * k)
    }

    /// Direction cosines as a matrix whose columns are the i, j, k axes in LPS.
    pub fn direction(&self) -> Matrix3<f64> {
        let c = &self.direction_lps;
        Matrix3::from_columns(&[
            Vector3::from(c[0]),
            Vector3::from(c[1]),
            Vector3::from(c[2]),
        ])
    }

    /// LPS origin as a vector, in millimetres.
    pub fn origin(&self) -> Vector3<f64> {
        Vector3::from(self.origin_lps_mm)
    }

    /// The 4×4 affine taking continuous voxel indices (i, j, k, 1) to LPS millimetres.
    pub fn voxel_to_lps(&self) -> Matrix4<f64> {
        let m = self.direction() * Matrix3::from_diagonal(&Vector3::from(self.spacing_mm));
        let mut a = Matrix4::identity();
        a.fixed_view_mut::<3, 3>(0, 0).copy_from(&m);
        a.fixed_view_mut::<3, 1>(0, 3).copy_from(&self.origin());
        a
    }

    /// LPS position in millimetres of continuous voxel index `ijk`.
    pub fn voxel_to_lps_mm(&self, ijk: Vector3<f64>) -> Vector3<f64> {
        self.origin() + self.direction() * ijk.component_mul(&Vector3::from(self.spacing_mm))
    }

    /// Continuous voxel index of an LPS position in millimetres.
    pub fn lps_mm_to_voxel(&self, p_lps_mm: Vector3<f64>) -> Vector3<f64> {
        (self.direction().transpose() * (p_lps_mm - self.origin()))
            .component_div(&Vector3::from(self.spacing_mm))
    }

    /// Whether two geometries describe the same grid (dims equal, positions within `tol_mm`).
    pub fn same_grid(&self, other: &VolumeGeometry, tol_mm: f64) -> bool {
        if self.dims != other.dims {
            return false;
        }
        let corner = Vector3::from(self.dims.map(|n| (n - 1) as f64));
        let pts = [Vector3::zeros(), corner];
        pts.iter()
            .all(|&p| (self.voxel_to_lps_mm(p) - other.voxel_to_lps_mm(p)).norm() <= tol_mm)
            && (self.direction() - other.direction()).abs().max() <= 1e-4
    }
}

/// Voxel values on a grid in patient space: CT numbers in HU (`Volume<f32>`) or labels
/// (`Volume<u8>`).
///
/// The voxels are private so that their shape always matches `geometry.dims` and their
/// layout stays standard (i fastest): [`Volume::as_slice`] can then hand out the flat
/// buffer without copying.
#[derive(Debug, Clone, PartialEq)]
pub struct Volume<T> {
    /// Placement of the grid in LPS millimetres.
    pub geometry: VolumeGeometry,
    /// Voxel values indexed `[[k, j, i]]`, standard layout (i fastest in memory).
    data: Array3<T>,
}

/// The `(nk, nj, ni)` array shape of a grid: k slowest, i fastest.
fn array_shape(geometry: &VolumeGeometry) -> (usize, usize, usize) {
    let [ni, nj, nk] = geometry.dims;
    (nk, nj, ni)
}

impl<T> Volume<T> {
    /// All voxels as one flat slice, i fastest (`geometry.index(i, j, k)`); no copy.
    #[inline]
    pub fn as_slice(&self) -> &[T] {
        self.data
            .as_slice()
            .expect("Volume voxels are always in standard layout")
    }

    /// All voxels as one flat mutable slice, i fastest (`geometry.index(i, j, k)`); no copy.
    #[inline]
    pub fn as_slice_mut(&mut self) -> &mut [T] {
        self.data
            .as_slice_mut()
            .expect("Volume voxels are always in standard layout")
    }

    /// The voxels as a 3-D view indexed `[[k, j, i]]`.
    pub fn voxels(&self) -> ArrayView3<'_, T> {
        self.data.view()
    }

    /// The voxels as a mutable 3-D view indexed `[[k, j, i]]`.
    pub fn voxels_mut(&mut self) -> ArrayViewMut3<'_, T> {
        self.data.view_mut()
    }

    /// The flat voxel buffer, i fastest, without copying.
    pub fn into_vec(self) -> Vec<T> {
        let (vec, offset) = self.data.into_raw_vec_and_offset();
        debug_assert!(matches!(offset, None | Some(0)));
        vec
    }
}

impl<T: Copy> Volume<T> {
    /// A volume of `value` everywhere; the geometry is validated first.
    pub fn filled(geometry: VolumeGeometry, value: T) -> Result<Self> {
        geometry.validate("volume")?;
        Ok(Volume {
            geometry,
            data: Array3::from_elem(array_shape(&geometry), value),
        })
    }

    /// Wraps data, checking its length against the geometry.
    pub fn from_data(geometry: VolumeGeometry, data: Vec<T>) -> Result<Self> {
        geometry.validate("volume")?;
        if data.len() != geometry.voxel_count() {
            return Err(Error::scan(
                "volume",
                format!(
                    "grid {:?} needs {} voxels, got {}",
                    geometry.dims,
                    geometry.voxel_count(),
                    data.len()
                ),
            ));
        }
        let data = Array3::from_shape_vec(array_shape(&geometry), data)
            .expect("length checked against the grid above");
        Ok(Volume { geometry, data })
    }

    /// The voxels of the sub-grid `start`, `dims` (see [`VolumeGeometry::sub_grid`]), copied;
    /// refused when it leaves the grid.
    pub fn crop(&self, start: [usize; 3], dims: [usize; 3]) -> Result<Volume<T>> {
        if (0..3).any(|a| dims[a] == 0 || start[a] + dims[a] > self.geometry.dims[a]) {
            return Err(Error::argument(
                "volume crop",
                format!(
                    "{dims:?} voxels from {start:?} leave the grid {:?}",
                    self.geometry.dims
                ),
            ));
        }
        let view = self.data.slice(ndarray::s![
            start[2]..start[2] + dims[2],
            start[1]..start[1] + dims[1],
            start[0]..start[0] + dims[0]
        ]);
        Volume::from_data(
            self.geometry.sub_grid(start, dims),
            view.iter().copied().collect(),
        )
    }

    /// Value at voxel (i, j, k).
    #[inline]
    pub fn get(&self, i: usize, j: usize, k: usize) -> T {
        self.data[[k, j, i]]
    }

    /// Dimensions of the grid.
    pub fn dims(&self) -> [usize; 3] {
        self.geometry.dims
    }

    /// A volume of the same grid with each voxel mapped through `f`.
    pub fn map<U: Copy + Send, F: Fn(T) -> U + Sync>(&self, f: F) -> Volume<U>
    where
        T: Sync,
    {
        // A standard-layout input gives a standard-layout output, so the i-fastest order holds.
        Volume {
            geometry: self.geometry,
            data: Zip::from(&self.data).par_map_collect(|&v| f(v)),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn voxel_to_lps_round_trips_through_an_oblique_grid() {
        let (s, c) = (0.3f64.sin(), 0.3f64.cos());
        let g = VolumeGeometry {
            dims: [10, 12, 14],
            spacing_mm: [0.8, 0.9, 2.5],
            origin_lps_mm: [-100.0, 20.0, 300.0],
            direction_lps: [[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]],
        };
        g.validate("test").unwrap();
        let ijk = Vector3::new(3.5, 7.0, 11.25);
        let p = g.voxel_to_lps_mm(ijk);
        assert!((g.lps_mm_to_voxel(p) - ijk).norm() < 1e-12);
        let a = g.voxel_to_lps() * ijk.push(1.0);
        assert!((a.xyz() - p).norm() < 1e-12);
        // Voxel (1,0,0) lies one spacing along the first direction column.
        let step = g.voxel_to_lps_mm(Vector3::x()) - g.origin();
        assert!((step - Vector3::new(c, s, 0.0) * 0.8).norm() < 1e-12);
    }

    #[test]
    fn absurd_geometries_are_refused_with_the_reason() {
        let ok = VolumeGeometry::axis_aligned([4, 4, 4], [1.0; 3], [0.0; 3]);
        ok.validate("x").unwrap();
        let cases = [
            (
                VolumeGeometry {
                    dims: [0, 4, 4],
                    ..ok
                },
                "empty",
            ),
            (
                VolumeGeometry {
                    dims: [100_000, 4, 4],
                    ..ok
                },
                "absurd",
            ),
            (
                VolumeGeometry {
                    dims: [16_000, 16_000, 16_000],
                    ..ok
                },
                "absurd",
            ),
            (
                VolumeGeometry {
                    spacing_mm: [0.0, 1.0, 1.0],
                    ..ok
                },
                "positive",
            ),
            (
                VolumeGeometry {
                    spacing_mm: [-1.0, 1.0, 1.0],
                    ..ok
                },
                "positive",
            ),
            (
                VolumeGeometry {
                    spacing_mm: [f64::NAN, 1.0, 1.0],
                    ..ok
                },
                "positive",
            ),
            (
                VolumeGeometry {
                    spacing_mm: [1e4, 1.0, 1.0],
                    ..ok
                },
                "plausible",
            ),
            (
                VolumeGeometry {
                    direction_lps: [[1.0, 0.0, 0.0], [0.5, 1.0, 0.0], [0.0, 0.0, 1.0]],
                    ..ok
                },
                "orthonormal",
            ),
        ];
        for (g, word) in cases {
            let e = g.validate("scan.nii").unwrap_err().to_string();
            assert!(e.contains("scan.nii") && e.contains(word), "{e}");
        }
    }
}
