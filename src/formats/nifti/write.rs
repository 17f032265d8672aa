//! The NIfTI-1 writer: header with both transforms and the exact-geometry extension, voxels
//! encoded in parallel, gzip by name, atomic replacement.

use std::path::Path;
use std::time::Instant;

use nalgebra::{Matrix3, Vector3};
use rayon::prelude::*;

use super::block_gzip::{gzip_blocks, gzip_blocks_into, BLOCK_BYTES};
use super::extension::{geometry_text, ECODE_COMMENT};
use super::geometry::rotation_to_quaternion;
use super::header::{DataType, NIFTI1_HEADER_BYTES};
use super::{
    first_position, refuse_non_finite, voxel_ijk, CHUNK_VOXELS, CT_DESCRIPTION, INTENT_LABEL,
    INTENT_VECTOR, LABELS_DESCRIPTION, VECTOR_FIELD_CONVENTION,
};
use crate::durable::{temporary_sibling, write_atomic};
use crate::error::{IoContext, IoOp};
use crate::volume::{Volume, VolumeGeometry};
use crate::{Error, Result};

/// Header plus the 4-byte extension flag: where extensions (or voxels) start.
const NIFTI1_VOX_OFFSET: usize = 352;

/// Gzip level of displacement fields (`.nii.gz`). Fields are rounded to 1/64 mm; a POPI
/// end-inhale lung box (117 MB raw) gives 13.1 MB at level 1, 7.7 MB at 2, 6.2 MB at 3 and
/// 5.4 MB at 6, level 2 taking a quarter of level 6's time (README, Outputs).
pub const FIELD_GZIP_LEVEL: u32 = 2;

/// Writes a CT volume (HU) as NIfTI-1: int16 when lossless, float32 otherwise.
pub fn write_nifti_ct(path: &Path, volume: &Volume<f32>) -> Result<()> {
    let what = path.display().to_string();
    check_volume(&volume.geometry, volume.as_slice().len(), &what)?;
    refuse_non_finite(
        volume.as_slice(),
        &volume.geometry,
        &format!("{what}: CT to write"),
    )?;
    let fits_int16 = volume
        .as_slice()
        .par_iter()
        .all(|&v| v.fract() == 0.0 && (i16::MIN as f32..=i16::MAX as f32).contains(&v));
    let datatype = if fits_int16 {
        DataType::I16
    } else {
        DataType::F32
    };
    let header = HeaderSpec {
        geometry: &volume.geometry,
        components: 1,
        datatype,
        intent_code: 0,
        intent_name: "",
        description: CT_DESCRIPTION,
    };
    let mut bytes = nifti1_header(&header);
    let start = bytes.len();
    bytes.resize(start + volume.as_slice().len() * datatype.bytes(), 0);
    if fits_int16 {
        encode(volume.as_slice(), &mut bytes[start..], |v| {
            (v as i16).to_le_bytes()
        });
    } else {
        encode(volume.as_slice(), &mut bytes[start..], |v| v.to_le_bytes());
    }
    write_file(path, bytes)
}

/// Gzip level of the virtual CT's int16 phases: on a POPI phase (74 MB raw) level 1 gives
/// 37.8 MB, level 6 36.8 MB in three times the time (README, Virtual 4D-CT).
pub const CT_INT16_GZIP_LEVEL: u32 = 1;

/// Writes a CT of whole HU held as int16 (the virtual CT's phases) as int16 NIfTI-1; gzipped
/// at `gzip_level` when the name ends in `.gz`, block by block straight from the voxels (the
/// raw file is never held).
pub fn write_nifti_ct_int16(path: &Path, volume: &Volume<i16>, gzip_level: u32) -> Result<()> {
    let what = path.display().to_string();
    check_volume(&volume.geometry, volume.as_slice().len(), &what)?;
    let header = nifti1_header(&HeaderSpec {
        geometry: &volume.geometry,
        components: 1,
        datatype: DataType::I16,
        intent_code: 0,
        intent_name: "",
        description: CT_DESCRIPTION,
    });
    let voxels = volume.as_slice();
    if !is_gzip_name(path) {
        let mut bytes = header;
        let start = bytes.len();
        bytes.resize(start + voxels.len() * 2, 0);
        encode(voxels, &mut bytes[start..], i16::to_le_bytes);
        return write_atomic(path, &bytes);
    }
    let per_block = BLOCK_BYTES / 2;
    let blocks = 1 + voxels.len().div_ceil(per_block);
    let fill = |k: usize, raw: &mut Vec<u8>| {
        if k == 0 {
            raw.extend_from_slice(&header);
            return;
        }
        let first = (k - 1) * per_block;
        let chunk = &voxels[first..(first + per_block).min(voxels.len())];
        raw.extend(chunk.iter().flat_map(|v| v.to_le_bytes()));
    };
    // Streamed into a temporary sibling, renamed when complete (as write_atomic does).
    let tmp = temporary_sibling(path);
    let result = (|| {
        let file = std::fs::File::create(&tmp).at(IoOp::Write, path)?;
        let mut out = std::io::BufWriter::with_capacity(1 << 20, file);
        gzip_blocks_into(blocks, gzip_level.min(9), fill, &mut out).at(IoOp::Write, path)?;
        out.into_inner()
            .map_err(|e| e.into_error())
            .at(IoOp::Write, path)?;
        std::fs::rename(&tmp, path).at(IoOp::Replace, path)
    })();
    if result.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    result
}

/// Writes a label map as uint8 NIfTI-1 with the label intent.
pub fn write_nifti_labels(path: &Path, labels: &Volume<u8>) -> Result<()> {
    let what = path.display().to_string();
    check_volume(&labels.geometry, labels.as_slice().len(), &what)?;
    let header = HeaderSpec {
        geometry: &labels.geometry,
        components: 1,
        datatype: DataType::U8,
        intent_code: INTENT_LABEL,
        intent_name: "labels",
        description: LABELS_DESCRIPTION,
    };
    let mut bytes = nifti1_header(&header);
    bytes.extend_from_slice(labels.as_slice());
    write_file(path, bytes)
}

/// Writes a displacement field with LPS-millimetre components as ITK reads it (see the
/// module doc); `description` follows the convention in the 80-character header text.
///
/// # Examples
///
/// ```
/// use lungmotion::formats::nifti::{read_nifti_vector_field, write_nifti_vector_field};
/// use lungmotion::volume::VolumeGeometry;
///
/// let geometry = VolumeGeometry {
///     dims: [4, 3, 2],
///     spacing_mm: [1.0, 1.0, 2.5],
///     origin_lps_mm: [-10.0, 20.0, -30.0],
///     direction_lps: [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
/// };
/// // Every voxel's tissue moves 5 mm up (LPS +z, superior).
/// let field = vec![[0.0f32, 0.0, 5.0]; 4 * 3 * 2];
/// let path = std::env::temp_dir().join(format!("lm-doc-field-{}.nii.gz", std::process::id()));
/// write_nifti_vector_field(&path, &geometry, &field, "example")?;
/// let (read_geometry, read_field) = read_nifti_vector_field(&path)?;
/// assert_eq!(read_geometry.dims, geometry.dims);
/// assert_eq!(read_field, field);
/// std::fs::remove_file(&path)?;
/// # Ok::<(), Box<dyn std::error::Error>>(())
/// ```
pub fn write_nifti_vector_field(
    path: &Path,
    geometry: &VolumeGeometry,
    vectors_lps_mm: &[[f32; 3]],
    description: &str,
) -> Result<()> {
    let what = path.display().to_string();
    check_volume(geometry, vectors_lps_mm.len(), &what)?;
    if let Some(bad) = first_position(vectors_lps_mm, |v| v.iter().any(|c| !c.is_finite())) {
        let [i, j, k] = voxel_ijk(bad, geometry);
        return Err(Error::format(
            what,
            format!(
                "displacement at voxel ({i}, {j}, {k}) is not finite: {:?}",
                vectors_lps_mm[bad]
            ),
        ));
    }
    let full_description = if description.is_empty() {
        VECTOR_FIELD_CONVENTION.to_string()
    } else {
        format!("{VECTOR_FIELD_CONVENTION}; {description}")
    };
    let header = HeaderSpec {
        geometry,
        components: 3,
        datatype: DataType::F32,
        intent_code: INTENT_VECTOR,
        intent_name: "disp LPS mm",
        description: &full_description,
    };
    let header = nifti1_header(&header);
    if !is_gzip_name(path) {
        let mut bytes = header;
        let start = bytes.len();
        let plane_bytes = vectors_lps_mm.len() * 4;
        bytes.resize(start + 3 * plane_bytes, 0);
        for (component, plane) in bytes[start..].chunks_exact_mut(plane_bytes).enumerate() {
            encode(vectors_lps_mm, plane, |v| v[component].to_le_bytes());
        }
        return write_atomic(path, &bytes);
    }
    // Gzipped: each block encodes its own stretch of the component planes, so the 12 bytes a
    // voxel of raw file never exist at once (117 MB for a POPI lung box).
    let t = Instant::now();
    let values = 3 * vectors_lps_mm.len();
    let values_per_block = BLOCK_BYTES / 4;
    let blocks = 1 + values.div_ceil(values_per_block);
    let gz = gzip_blocks(blocks, FIELD_GZIP_LEVEL, |k, raw| {
        if k == 0 {
            raw.extend_from_slice(&header);
            return;
        }
        let first = (k - 1) * values_per_block;
        let end = (first + values_per_block).min(values);
        encode_planar_values(vectors_lps_mm, first..end, raw);
    })
    .at(IoOp::Write, path)?;
    let compress_s = t.elapsed().as_secs_f64();
    write_atomic(path, &gz)?;
    tracing::debug!(
        path = %path.display(),
        compress_s,
        write_s = t.elapsed().as_secs_f64() - compress_s,
        gzip_bytes = gz.len(),
        "displacement field written"
    );
    Ok(())
}

/// Appends the little-endian bytes of values `range` of the planar layout (all x, then all y,
/// then all z) of `vectors` to `raw`.
fn encode_planar_values(vectors: &[[f32; 3]], range: std::ops::Range<usize>, raw: &mut Vec<u8>) {
    let n = vectors.len();
    let mut at = range.start;
    while at < range.end {
        let component = at / n;
        let plane_end = ((component + 1) * n).min(range.end);
        let voxels = &vectors[at - component * n..plane_end - component * n];
        raw.extend(voxels.iter().flat_map(|v| v[component].to_le_bytes()));
        at = plane_end;
    }
}

/// What a written header says beyond the grid.
struct HeaderSpec<'a> {
    geometry: &'a VolumeGeometry,
    components: usize,
    datatype: DataType,
    intent_code: i32,
    intent_name: &'a str,
    description: &'a str,
}

/// Refuses grids NIfTI-1 cannot hold and value counts that do not match the grid.
fn check_volume(geometry: &VolumeGeometry, values: usize, what: &str) -> Result<()> {
    geometry.validate(what)?;
    if geometry.dims.iter().any(|&n| n > i16::MAX as usize) {
        return Err(Error::format(
            what,
            format!(
                "grid {:?} exceeds NIfTI-1's 32767 voxels per axis",
                geometry.dims
            ),
        ));
    }
    if values != geometry.voxel_count() {
        return Err(Error::format(
            what,
            format!(
                "grid {:?} has {} voxels but {values} values were given",
                geometry.dims,
                geometry.voxel_count()
            ),
        ));
    }
    Ok(())
}

/// The 348-byte NIfTI-1 header, the extension flag and the exact-geometry comment
/// extension (the float32 affine alone loses up to 3·10⁻⁵ mm), little-endian; voxels
/// follow at the returned length.
fn nifti1_header(spec: &HeaderSpec) -> Vec<u8> {
    let mut comment = geometry_text(spec.geometry).into_bytes();
    let extension_bytes = (8 + comment.len()).div_ceil(16) * 16;
    comment.resize(extension_bytes - 8, 0);
    let vox_offset = NIFTI1_VOX_OFFSET + extension_bytes;
    let mut h = vec![0u8; vox_offset];
    let put = |h: &mut [u8], offset: usize, bytes: &[u8]| {
        h[offset..offset + bytes.len()].copy_from_slice(bytes)
    };
    let g = spec.geometry;
    put(&mut h, 0, &(NIFTI1_HEADER_BYTES as i32).to_le_bytes());
    let mut dim = [1i16; 8];
    dim[0] = if spec.components > 1 { 5 } else { 3 };
    for axis in 0..3 {
        dim[axis + 1] = g.dims[axis] as i16;
    }
    dim[5] = spec.components as i16;
    for (a, d) in dim.iter().enumerate() {
        put(&mut h, 40 + 2 * a, &d.to_le_bytes());
    }
    put(&mut h, 68, &(spec.intent_code as i16).to_le_bytes());
    put(&mut h, 70, &spec.datatype.code().to_le_bytes());
    put(
        &mut h,
        72,
        &(8 * spec.datatype.bytes() as i16).to_le_bytes(),
    );

    let ras_to_lps = Matrix3::from_diagonal(&Vector3::new(-1.0, -1.0, 1.0));
    let mut rotation_ras = ras_to_lps * g.direction();
    // A left-handed grid is stored as a proper rotation with the k axis reflected (qfac).
    let qfac = if rotation_ras.determinant() < 0.0 {
        let k = -rotation_ras.column(2);
        rotation_ras.set_column(2, &k);
        -1.0f32
    } else {
        1.0
    };
    let mut pixdim = [1.0f32; 8];
    pixdim[0] = qfac;
    for axis in 0..3 {
        pixdim[axis + 1] = g.spacing_mm[axis] as f32;
    }
    for (a, p) in pixdim.iter().enumerate() {
        put(&mut h, 76 + 4 * a, &p.to_le_bytes());
    }
    put(&mut h, 108, &(vox_offset as f32).to_le_bytes());
    put(&mut h, 112, &1.0f32.to_le_bytes());
    h[123] = 2; // NIFTI_UNITS_MM
    let description = truncate_utf8(spec.description, 79);
    put(&mut h, 148, description.as_bytes());
    put(&mut h, 252, &1i16.to_le_bytes());
    put(&mut h, 254, &1i16.to_le_bytes());
    let origin_ras = ras_to_lps * g.origin();
    let quaternion = rotation_to_quaternion(&rotation_ras);
    for (a, v) in quaternion.iter().chain(origin_ras.iter()).enumerate() {
        put(&mut h, 256 + 4 * a, &(*v as f32).to_le_bytes());
    }
    let affine_ras = ras_to_lps.to_homogeneous() * g.voxel_to_lps();
    for row in 0..3 {
        for col in 0..4 {
            let v = affine_ras[(row, col)] as f32;
            put(&mut h, 280 + 16 * row + 4 * col, &v.to_le_bytes());
        }
    }
    put(&mut h, 328, truncate_utf8(spec.intent_name, 15).as_bytes());
    put(&mut h, 344, b"n+1\0");
    h[NIFTI1_HEADER_BYTES] = 1; // extensions follow
    put(
        &mut h,
        NIFTI1_VOX_OFFSET,
        &(extension_bytes as i32).to_le_bytes(),
    );
    put(&mut h, NIFTI1_VOX_OFFSET + 4, &ECODE_COMMENT.to_le_bytes());
    put(&mut h, NIFTI1_VOX_OFFSET + 8, &comment);
    h
}

/// `text` cut to at most `max_bytes` on a character boundary (fixed-width header text).
fn truncate_utf8(text: &str, max_bytes: usize) -> &str {
    let mut end = text.len().min(max_bytes);
    while !text.is_char_boundary(end) {
        end -= 1;
    }
    &text[..end]
}

/// Encodes `values` into `out` (exactly `values.len() · N` bytes) in parallel.
fn encode<T: Sync + Copy, const N: usize, F: Fn(T) -> [u8; N] + Sync>(
    values: &[T],
    out: &mut [u8],
    to_bytes: F,
) {
    out.par_chunks_mut(CHUNK_VOXELS * N)
        .zip(values.par_chunks(CHUNK_VOXELS))
        .for_each(|(dst, src)| {
            for (d, &v) in dst.chunks_exact_mut(N).zip(src) {
                d.copy_from_slice(&to_bytes(v));
            }
        });
}

/// Whether `path` names a gzipped file (`.gz`, any case).
fn is_gzip_name(path: &Path) -> bool {
    path.file_name()
        .and_then(|n| n.to_str())
        .is_some_and(|n| n.to_ascii_lowercase().ends_with(".gz"))
}

/// Writes atomically, gzipped (in parallel blocks, level 6) when the name ends in `.gz`.
fn write_file(path: &Path, bytes: Vec<u8>) -> Result<()> {
    if !is_gzip_name(path) {
        return write_atomic(path, &bytes);
    }
    let blocks: Vec<&[u8]> = bytes.chunks(BLOCK_BYTES).collect();
    let gz = gzip_blocks(blocks.len(), 6, |k, raw| raw.extend_from_slice(blocks[k]))
        .at(IoOp::Write, path)?;
    write_atomic(path, &gz)
}
