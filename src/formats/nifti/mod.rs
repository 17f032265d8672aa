//! NIfTI-1 and NIfTI-2 reader, NIfTI-1 writer: CT volumes, label maps and displacement fields.
//!
//! # Conventions
//!
//! * **World space.** NIfTI world coordinates are RAS (+x right, +y anterior, +z superior);
//!   [`Volume`] is DICOM LPS. Reading negates x and y of the affine (origin and direction
//!   rows); writing stores `RAS affine = diag(−1, −1, 1) · LPS affine`. Voxel order is the
//!   same in both (i fastest), so voxels are copied without reordering.
//! * **Which transform.** Reading uses the sform when `sform_code > 0`, otherwise the qform
//!   when `qform_code > 0` (quaternion per `nifti1.h`, with `qfac = pixdim[0] = −1` reflecting
//!   the k axis of left-handed grids), otherwise the ANALYZE fallback (axes along R, A, S
//!   scaled by `pixdim`, origin 0; a warning is logged). An sform whose axes are not
//!   orthogonal once their lengths are divided out (shear, gantry tilt) is refused: a
//!   [`VolumeGeometry`] holds rotations and reflections only.
//! * **Units.** `xyzt_units` metres and micrometres are converted to millimetres; unknown
//!   (0) is taken as millimetres. `scl_slope`/`scl_inter` are applied when the slope is
//!   non-zero (a NaN slope counts as unset, as in nibabel).
//! * **Writing** produces single-file NIfTI-1 (`n+1`, little-endian), the version every tool
//!   reads. Both the sform and the qform are set, with codes 1 (scanner), `xyzt_units` = mm.
//!   Files whose name ends in `.gz` are gzipped; reading tells gzip from raw by the gzip
//!   magic bytes, never by the name.
//! * **Exact geometry.** NIfTI-1 stores the affine in float32 (≈ 6·10⁻⁸ relative: 3·10⁻⁵ mm
//!   at 500 mm from the origin), so the writer also stores the f64 spacing, LPS origin and
//!   direction as a comment extension (`ecode` 6, text starting
//!   "lungmotion exact geometry, LPS mm"). The reader uses it only when it agrees with the
//!   header's transform within 10⁻³ mm; a file whose affine another tool changed falls back
//!   to the header. Other tools ignore the comment.
//! * **CT** is written as int16 when every value is an integer in the int16 range (CT
//!   numbers from scanners are; the file is half the size and lossless), otherwise float32.
//!   Label maps are uint8 with `intent_code` 1002 (label).
//! * **Displacement fields** follow ITK / elastix / ANTs: `dim = [5, nx, ny, nz, 1, 3, 1, 1]`,
//!   `intent_code` 1007 (vector), float32, component planes stored one after the other
//!   (all x, then all y, then all z), and the **components are LPS millimetres, not flipped
//!   to RAS**, while the affine is RAS as the standard requires. The header description
//!   says so ([`VECTOR_FIELD_CONVENTION`]). NiftyReg fields (RAS components) are not this.
//!
//! # Why hand-written
//!
//! The `nifti` crate (0.18) was measured as a replacement for the NIfTI-1 path and kept
//! out (numbers in the README). It parses NIfTI-1 only (16-bit `dim`, no 540-byte
//! NIfTI-2 header), so the field decoder stays for NIfTI-2 anyway; it rescales in f32 and
//! takes a NaN `scl_slope` as a slope; it reserves the header's whole voxel size before
//! reading, stops before the gzip trailer (no CRC check), fails on a malformed extension
//! and copies in-memory voxels once more; its writer creates the final path in place
//! (no temporary and rename), rewrites the path's extension, and needs the voxels as an
//! ndarray of the stored type (a planar copy of a displacement field). Its affine helpers
//! sit behind a feature built on another nalgebra version and apply no LPS conversion.
//! The tests use the crate as an independent reader of our files.

mod block_gzip;
mod extension;
mod geometry;
mod header;
mod image;
mod nifti2;
mod read;
mod samples;
mod write;

pub use read::{
    read_nifti, read_nifti_bytes, read_nifti_bytes_within, read_nifti_labels,
    read_nifti_labels_bytes, read_nifti_vector_field, read_nifti_vector_field_bytes,
};
pub use write::{
    write_nifti_ct, write_nifti_ct_int16, write_nifti_labels, write_nifti_vector_field,
    CT_INT16_GZIP_LEVEL, FIELD_GZIP_LEVEL,
};

use rayon::prelude::*;

use crate::volume::VolumeGeometry;
use crate::{Error, Result};

/// Header description prefix of written displacement fields: the component convention.
pub const VECTOR_FIELD_CONVENTION: &str = "vectors LPS mm (ITK); affine RAS";
/// Header description of written CT volumes.
pub const CT_DESCRIPTION: &str = "lungmotion CT (HU); LPS->RAS affine";
/// Header description of written label maps.
pub const LABELS_DESCRIPTION: &str = "lungmotion labels; LPS->RAS affine";
/// `intent_code` of a label map (NIFTI_INTENT_LABEL).
pub const INTENT_LABEL: i32 = 1002;
/// `intent_code` of a displacement vector field (NIFTI_INTENT_DISPVECT).
pub const INTENT_DISPLACEMENT: i32 = 1006;
/// `intent_code` of a vector image, as ITK writes displacement fields (NIFTI_INTENT_VECTOR).
pub const INTENT_VECTOR: i32 = 1007;

/// Voxels per parallel work item when converting samples.
const CHUNK_VOXELS: usize = 1 << 16;

/// Refuses NaN or infinite values, naming their count and the first voxel.
fn refuse_non_finite(data: &[f32], geometry: &VolumeGeometry, what: &str) -> Result<()> {
    let Some(first) = first_position(data, |v| !v.is_finite()) else {
        return Ok(());
    };
    let count = data.par_iter().filter(|v| !v.is_finite()).count();
    let [i, j, k] = voxel_ijk(first, geometry);
    Err(Error::scan(
        what,
        format!(
            "{count} voxels are NaN or infinite (first at voxel ({i}, {j}, {k}) = {})",
            data[first]
        ),
    ))
}

/// Index of the first element for which `bad` holds, searched in parallel chunks: rayon's
/// per-element `position_first` costs ~15 ns an element (over half the read time of a CT).
fn first_position<T: Sync>(data: &[T], bad: impl Fn(&T) -> bool + Sync) -> Option<usize> {
    let chunk = data
        .par_chunks(CHUNK_VOXELS)
        .position_first(|values| values.iter().any(&bad))?;
    let start = chunk * CHUNK_VOXELS;
    data[start..].iter().position(&bad).map(|i| start + i)
}

/// (i, j, k) of a voxel index, i fastest.
fn voxel_ijk(index: usize, geometry: &VolumeGeometry) -> [usize; 3] {
    let [nx, ny, _] = geometry.dims;
    [index % nx, (index / nx) % ny, index / (nx * ny)]
}
