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
//! The `nifti` crate (0.18) parses NIfTI-1 only (16-bit `dim`, no 540-byte NIfTI-2 header),
//! applies no LPS conversion, and exposes its affine helpers only behind a feature built
//! on another nalgebra version. Both headers are fixed byte layouts, so this module reads
//! them directly; the tests use the `nifti` crate as an independent reader of our files.

use std::borrow::Cow;
use std::io::{Read, Write};
use std::path::Path;

use nalgebra::{Matrix3, Vector3};
use rayon::prelude::*;

use crate::durable::write_atomic;
use crate::volume::{Volume, VolumeGeometry};
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

const NIFTI1_HEADER_BYTES: usize = 348;
const NIFTI2_HEADER_BYTES: usize = 540;
/// Header plus the 4-byte extension flag: where extensions (or voxels) start.
const NIFTI1_VOX_OFFSET: usize = 352;
const GZIP_MAGIC: [u8; 2] = [0x1f, 0x8b];
const NIFTI2_MAGIC: &[u8; 8] = b"n+2\0\r\n\x1a\n";
/// Largest non-orthogonality of sform axes accepted (as [`VolumeGeometry::validate`]).
const MAX_SHEAR: f64 = 1e-3;
/// Voxels per parallel work item when converting samples.
const CHUNK_VOXELS: usize = 1 << 16;
/// Initial buffer for decompressed voxels: a lying header cannot make us allocate more
/// than what the gzip stream actually delivers.
const MAX_PREALLOCATED_BYTES: usize = 64 << 20;
/// Largest extension area (between header and voxels) searched for the exact geometry.
const MAX_EXTENSION_BYTES: usize = 1 << 20;
/// NIFTI_ECODE_COMMENT: the extension code of the exact-geometry text written here.
const ECODE_COMMENT: i32 = 6;
/// First line of the exact-geometry comment extension.
const GEOMETRY_EXTENSION_TAG: &str = "lungmotion exact geometry, LPS mm";
/// Largest distance (mm) between the header's f32 grid and the extension's exact grid for
/// the extension to be trusted: float32 rounding is far below, any edit by another tool
/// (resampling, re-centring) far above.
const EXTENSION_AGREEMENT_MM: f64 = 1e-3;
/// Decompressed bytes after the voxels read to reach the gzip trailer (extensions of
/// other tools are small).
const MAX_TRAILING_BYTES: u64 = 16 << 20;

/// Reads a 3-D NIfTI-1 or NIfTI-2 file (raw or gzipped) into f32 values (HU for CT).
pub fn read_nifti(path: &Path) -> Result<Volume<f32>> {
    let bytes = read_file(path)?;
    read_nifti_bytes(&bytes, &path.display().to_string())
}

/// Reads NIfTI bytes (an upload); `what` names the source in errors.
pub fn read_nifti_bytes(bytes: &[u8], what: &str) -> Result<Volume<f32>> {
    let image = parse_image(bytes, what, Components::Scalar)?;
    let mut data = vec![0f32; image.geometry.voxel_count()];
    let (slope, inter) = image.scaling;
    decode_samples(&image, &mut data, |v| (v * slope + inter) as f32);
    refuse_non_finite(&data, &image.geometry, what)?;
    Volume::from_data(image.geometry, data)
}

/// Reads a NIfTI label map; values must be integers in 0..=255 after scaling.
pub fn read_nifti_labels(path: &Path) -> Result<Volume<u8>> {
    let bytes = read_file(path)?;
    read_nifti_labels_bytes(&bytes, &path.display().to_string())
}

/// Reads NIfTI label-map bytes; `what` names the source in errors.
pub fn read_nifti_labels_bytes(bytes: &[u8], what: &str) -> Result<Volume<u8>> {
    let image = parse_image(bytes, what, Components::Scalar)?;
    let (slope, inter) = image.scaling;
    // 256 marks a voxel that is no label, so the conversion needs no error path per voxel.
    let mut codes = vec![0u16; image.geometry.voxel_count()];
    decode_samples(&image, &mut codes, |v| {
        let v = v * slope + inter;
        if v.fract() == 0.0 && (0.0..=255.0).contains(&v) {
            v as u16
        } else {
            256
        }
    });
    if let Some(first) = codes.par_iter().position_first(|&c| c > 255) {
        let count = codes.par_iter().filter(|&&c| c > 255).count();
        let value = image.sample(first) * slope + inter;
        let [i, j, k] = voxel_ijk(first, &image.geometry);
        return Err(Error::InvalidScan(format!(
            "{what}: not a label map: {count} voxels are not integers in 0..=255 \
             (first at voxel ({i}, {j}, {k}) = {value})"
        )));
    }
    let labels = codes.par_iter().map(|&c| c as u8).collect();
    Volume::from_data(image.geometry, labels)
}

/// Reads a displacement field written as ITK does (see the module doc): the grid and one
/// LPS-millimetre vector per voxel, i fastest.
pub fn read_nifti_vector_field(path: &Path) -> Result<(VolumeGeometry, Vec<[f32; 3]>)> {
    let bytes = read_file(path)?;
    read_nifti_vector_field_bytes(&bytes, &path.display().to_string())
}

/// Reads displacement-field bytes; `what` names the source in errors.
pub fn read_nifti_vector_field_bytes(
    bytes: &[u8],
    what: &str,
) -> Result<(VolumeGeometry, Vec<[f32; 3]>)> {
    let image = parse_image(bytes, what, Components::Vector3)?;
    if image.intent_code != INTENT_VECTOR && image.intent_code != INTENT_DISPLACEMENT {
        tracing::warn!(
            "{what}: intent_code {} is not a vector intent (1006/1007); reading the 3 \
             components as LPS millimetres anyway",
            image.intent_code
        );
    }
    let n = image.geometry.voxel_count();
    let (slope, inter) = image.scaling;
    let mut planes = vec![0f32; 3 * n];
    decode_samples(&image, &mut planes, |v| (v * slope + inter) as f32);
    refuse_non_finite(
        &planes[..n],
        &image.geometry,
        &format!("{what} (x component)"),
    )?;
    refuse_non_finite(
        &planes[n..2 * n],
        &image.geometry,
        &format!("{what} (y component)"),
    )?;
    refuse_non_finite(
        &planes[2 * n..],
        &image.geometry,
        &format!("{what} (z component)"),
    )?;
    let (x, rest) = planes.split_at(n);
    let (y, z) = rest.split_at(n);
    let vectors = (0..n).into_par_iter().map(|v| [x[v], y[v], z[v]]).collect();
    Ok((image.geometry, vectors))
}

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
pub fn write_nifti_vector_field(
    path: &Path,
    geometry: &VolumeGeometry,
    vectors_lps_mm: &[[f32; 3]],
    description: &str,
) -> Result<()> {
    let what = path.display().to_string();
    check_volume(geometry, vectors_lps_mm.len(), &what)?;
    if let Some(bad) = vectors_lps_mm
        .par_iter()
        .position_first(|v| v.iter().any(|c| !c.is_finite()))
    {
        let [i, j, k] = voxel_ijk(bad, geometry);
        return Err(Error::InvalidInput(format!(
            "{what}: displacement at voxel ({i}, {j}, {k}) is not finite: {:?}",
            vectors_lps_mm[bad]
        )));
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
    let mut bytes = nifti1_header(&header);
    let start = bytes.len();
    let plane_bytes = vectors_lps_mm.len() * 4;
    bytes.resize(start + 3 * plane_bytes, 0);
    for (component, plane) in bytes[start..].chunks_exact_mut(plane_bytes).enumerate() {
        encode(vectors_lps_mm, plane, |v| v[component].to_le_bytes());
    }
    write_file(path, bytes)
}

// ---------------------------------------------------------------------------------------
// Reading
// ---------------------------------------------------------------------------------------

/// What the caller needs per voxel: checked against dim[4..7] before any voxel is read.
#[derive(Clone, Copy, PartialEq)]
enum Components {
    Scalar,
    Vector3,
}

/// Stored sample types (NIFTI_TYPE_* codes).
#[derive(Clone, Copy, Debug, PartialEq)]
enum DataType {
    U8,
    I8,
    I16,
    U16,
    I32,
    U32,
    I64,
    U64,
    F32,
    F64,
}

impl DataType {
    fn from_code(code: i16) -> Option<Self> {
        Some(match code {
            2 => DataType::U8,
            256 => DataType::I8,
            4 => DataType::I16,
            512 => DataType::U16,
            8 => DataType::I32,
            768 => DataType::U32,
            1024 => DataType::I64,
            1280 => DataType::U64,
            16 => DataType::F32,
            64 => DataType::F64,
            _ => return None,
        })
    }

    fn code(self) -> i16 {
        match self {
            DataType::U8 => 2,
            DataType::I8 => 256,
            DataType::I16 => 4,
            DataType::U16 => 512,
            DataType::I32 => 8,
            DataType::U32 => 768,
            DataType::I64 => 1024,
            DataType::U64 => 1280,
            DataType::F32 => 16,
            DataType::F64 => 64,
        }
    }

    fn bytes(self) -> usize {
        match self {
            DataType::U8 | DataType::I8 => 1,
            DataType::I16 | DataType::U16 => 2,
            DataType::I32 | DataType::U32 | DataType::F32 => 4,
            DataType::I64 | DataType::U64 | DataType::F64 => 8,
        }
    }
}

/// The header fields this module uses, widened to the NIfTI-2 types.
struct Header {
    header_bytes: usize,
    big_endian: bool,
    dim: [i64; 8],
    intent_code: i32,
    datatype: i16,
    bitpix: i16,
    pixdim: [f64; 8],
    vox_offset: f64,
    scl_slope: f64,
    scl_inter: f64,
    xyzt_units: i32,
    qform_code: i32,
    sform_code: i32,
    quatern_bcd: [f64; 3],
    qoffset: [f64; 3],
    srow: [[f64; 4]; 3],
}

/// A parsed image whose voxel bytes are present and sized for its grid.
struct Image<'a> {
    geometry: VolumeGeometry,
    datatype: DataType,
    big_endian: bool,
    scaling: (f64, f64),
    intent_code: i32,
    voxels: Cow<'a, [u8]>,
}

impl Image<'_> {
    /// One stored sample as f64, unscaled (for error messages).
    fn sample(&self, index: usize) -> f64 {
        let size = self.datatype.bytes();
        let raw = &self.voxels[index * size..(index + 1) * size];
        let mut out = [0f64];
        decode_typed_dispatch(self.datatype, raw, self.big_endian, &mut out, |v| v);
        out[0]
    }
}

fn read_file(path: &Path) -> Result<Vec<u8>> {
    std::fs::read(path)
        .map_err(|e| Error::InvalidScan(format!("{}: cannot read: {e}", path.display())))
}

/// Parses the header, checks it against the wanted components and the available bytes,
/// and returns the voxel bytes; nothing proportional to the header's dims is allocated
/// before the dims are validated.
fn parse_image<'a>(bytes: &'a [u8], what: &str, wanted: Components) -> Result<Image<'a>> {
    let bad = |m: String| Error::InvalidScan(format!("{what}: {m}"));
    if bytes.starts_with(&GZIP_MAGIC) {
        let mut stream = flate2::read::MultiGzDecoder::new(bytes);
        let mut head = Vec::with_capacity(NIFTI2_HEADER_BYTES);
        read_gz(&mut stream, &mut head, 4, what)?;
        let header_len = header_length(&head, what)?;
        read_gz(&mut stream, &mut head, header_len - 4, what)?;
        let header = parse_header(&head, what)?;
        let (geometry, datatype, data_len) = layout(&header, what, wanted)?;
        let skip = header.vox_offset as usize - header_len;
        let mut extensions = Vec::new();
        let skipped = if skip <= MAX_EXTENSION_BYTES {
            (&mut stream)
                .take(skip as u64)
                .read_to_end(&mut extensions)
                .map_err(|e| gz_error(e, what))? as u64
        } else {
            std::io::copy(&mut (&mut stream).take(skip as u64), &mut std::io::sink())
                .map_err(|e| gz_error(e, what))?
        };
        if skipped < skip as u64 {
            return Err(bad(format!(
                "truncated: the gzip stream ends before the voxel data at byte {}",
                header.vox_offset
            )));
        }
        let mut voxels = Vec::with_capacity(data_len.min(MAX_PREALLOCATED_BYTES));
        (&mut stream)
            .take(data_len as u64)
            .read_to_end(&mut voxels)
            .map_err(|e| gz_error(e, what))?;
        if voxels.len() < data_len {
            return Err(bad(format!(
                "truncated: the header's grid needs {data_len} bytes of voxels, the gzip \
                 stream holds {}",
                voxels.len()
            )));
        }
        // Reading on to the end of the stream checks the gzip CRC and length trailer, so
        // a cut-off file is caught even when its voxels happened to decompress; trailing
        // bytes beyond a bound are not inflated.
        std::io::copy(
            &mut (&mut stream).take(MAX_TRAILING_BYTES),
            &mut std::io::sink(),
        )
        .map_err(|e| gz_error(e, what))?;
        let geometry = refine_geometry(geometry, &extensions, header.big_endian, what);
        return finish_image(header, geometry, datatype, Cow::Owned(voxels), what);
    }
    let header_len = header_length(bytes, what)?;
    let head = bytes.get(..header_len).ok_or_else(|| {
        bad(format!(
            "truncated: {} bytes, shorter than the {header_len}-byte header",
            bytes.len()
        ))
    })?;
    let header = parse_header(head, what)?;
    let (geometry, datatype, data_len) = layout(&header, what, wanted)?;
    let start = header.vox_offset as usize;
    let voxels = start
        .checked_add(data_len)
        .and_then(|end| bytes.get(start..end))
        .ok_or_else(|| {
            bad(format!(
                "truncated: the header's grid {:?} needs {data_len} bytes of voxels from \
                 offset {start}, the file has {} bytes",
                geometry.dims,
                bytes.len()
            ))
        })?;
    let extensions = &bytes[header_len..start];
    let geometry = refine_geometry(geometry, extensions, header.big_endian, what);
    finish_image(header, geometry, datatype, Cow::Borrowed(voxels), what)
}

fn finish_image<'a>(
    header: Header,
    geometry: VolumeGeometry,
    datatype: DataType,
    voxels: Cow<'a, [u8]>,
    what: &str,
) -> Result<Image<'a>> {
    Ok(Image {
        geometry,
        datatype,
        big_endian: header.big_endian,
        scaling: scaling(&header, what)?,
        intent_code: header.intent_code,
        voxels,
    })
}

/// Appends exactly `count` decompressed bytes to `buf`, or says the stream is truncated.
fn read_gz(stream: &mut impl Read, buf: &mut Vec<u8>, count: usize, what: &str) -> Result<()> {
    let before = buf.len();
    stream
        .take(count as u64)
        .read_to_end(buf)
        .map_err(|e| gz_error(e, what))?;
    if buf.len() - before < count {
        return Err(Error::InvalidScan(format!(
            "{what}: truncated: the gzip stream ends inside the NIfTI header ({} bytes)",
            buf.len()
        )));
    }
    Ok(())
}

fn gz_error(e: std::io::Error, what: &str) -> Error {
    if e.kind() == std::io::ErrorKind::UnexpectedEof {
        Error::InvalidScan(format!("{what}: truncated gzip stream: {e}"))
    } else {
        Error::InvalidScan(format!("{what}: corrupt or truncated gzip stream: {e}"))
    }
}

/// Header size from `sizeof_hdr` (348 or 540, either byte order).
fn header_length(bytes: &[u8], what: &str) -> Result<usize> {
    let first: [u8; 4] = bytes
        .get(..4)
        .and_then(|b| b.try_into().ok())
        .ok_or_else(|| {
            Error::InvalidScan(format!(
                "{what}: not a NIfTI file: {} bytes, too short for a header",
                bytes.len()
            ))
        })?;
    let (le, be) = (i32::from_le_bytes(first), i32::from_be_bytes(first));
    for size in [NIFTI1_HEADER_BYTES, NIFTI2_HEADER_BYTES] {
        if le == size as i32 || be == size as i32 {
            return Ok(size);
        }
    }
    Err(Error::InvalidScan(format!(
        "{what}: not a NIfTI file: sizeof_hdr is {le}, not 348 (NIfTI-1) or 540 (NIfTI-2)"
    )))
}

/// Little- or big-endian field access to a header of known length.
struct Fields<'a> {
    bytes: &'a [u8],
    big_endian: bool,
}

impl Fields<'_> {
    fn array<const N: usize>(&self, offset: usize) -> [u8; N] {
        let mut a = [0u8; N];
        a.copy_from_slice(&self.bytes[offset..offset + N]);
        if self.big_endian {
            a.reverse();
        }
        a
    }
    fn i16(&self, offset: usize) -> i16 {
        i16::from_le_bytes(self.array(offset))
    }
    fn i32(&self, offset: usize) -> i32 {
        i32::from_le_bytes(self.array(offset))
    }
    fn i64(&self, offset: usize) -> i64 {
        i64::from_le_bytes(self.array(offset))
    }
    fn f32(&self, offset: usize) -> f64 {
        f32::from_le_bytes(self.array(offset)) as f64
    }
    fn f64(&self, offset: usize) -> f64 {
        f64::from_le_bytes(self.array(offset))
    }
}

/// Decodes a complete 348- or 540-byte header.
fn parse_header(bytes: &[u8], what: &str) -> Result<Header> {
    let bad = |m: String| Error::InvalidScan(format!("{what}: {m}"));
    let size = bytes.len() as i32;
    let big_endian = i32::from_le_bytes([bytes[0], bytes[1], bytes[2], bytes[3]]) != size;
    let f = Fields { bytes, big_endian };
    if bytes.len() == NIFTI1_HEADER_BYTES {
        let magic = &bytes[344..348];
        if magic == b"ni1\0" {
            return Err(bad(
                "two-file NIfTI-1 (.hdr/.img pair) is not supported; convert to a single .nii"
                    .into(),
            ));
        }
        if magic != b"n+1\0" {
            return Err(bad(format!(
                "not a NIfTI-1 file: magic is {magic:?}, not \"n+1\" (ANALYZE 7.5 files \
                 are not supported)"
            )));
        }
        Ok(Header {
            header_bytes: bytes.len(),
            big_endian,
            dim: std::array::from_fn(|a| f.i16(40 + 2 * a) as i64),
            intent_code: f.i16(68) as i32,
            datatype: f.i16(70),
            bitpix: f.i16(72),
            pixdim: std::array::from_fn(|a| f.f32(76 + 4 * a)),
            vox_offset: f.f32(108),
            scl_slope: f.f32(112),
            scl_inter: f.f32(116),
            xyzt_units: bytes[123] as i32,
            qform_code: f.i16(252) as i32,
            sform_code: f.i16(254) as i32,
            quatern_bcd: std::array::from_fn(|a| f.f32(256 + 4 * a)),
            qoffset: std::array::from_fn(|a| f.f32(268 + 4 * a)),
            srow: std::array::from_fn(|r| std::array::from_fn(|c| f.f32(280 + 16 * r + 4 * c))),
        })
    } else {
        let magic = &bytes[4..12];
        if magic.starts_with(b"ni2\0") {
            return Err(bad(
                "two-file NIfTI-2 (.hdr/.img pair) is not supported; convert to a single .nii"
                    .into(),
            ));
        }
        if magic != NIFTI2_MAGIC {
            return Err(bad(format!(
                "not a NIfTI-2 file: magic is {magic:?}, not \"n+2\\0\\r\\n\\x1a\\n\""
            )));
        }
        Ok(Header {
            header_bytes: bytes.len(),
            big_endian,
            dim: std::array::from_fn(|a| f.i64(16 + 8 * a)),
            intent_code: f.i32(504),
            datatype: f.i16(12),
            bitpix: f.i16(14),
            pixdim: std::array::from_fn(|a| f.f64(104 + 8 * a)),
            vox_offset: f.i64(168) as f64,
            scl_slope: f.f64(176),
            scl_inter: f.f64(184),
            xyzt_units: f.i32(500),
            qform_code: f.i32(344),
            sform_code: f.i32(348),
            quatern_bcd: std::array::from_fn(|a| f.f64(352 + 8 * a)),
            qoffset: std::array::from_fn(|a| f.f64(376 + 8 * a)),
            srow: std::array::from_fn(|r| std::array::from_fn(|c| f.f64(400 + 32 * r + 8 * c))),
        })
    }
}

/// Checks dims, data type and offset; returns the grid, the sample type and the voxel
/// byte count.
fn layout(
    header: &Header,
    what: &str,
    wanted: Components,
) -> Result<(VolumeGeometry, DataType, usize)> {
    let bad = |m: String| Error::InvalidScan(format!("{what}: {m}"));
    let rank = header.dim[0];
    if !(1..=7).contains(&rank) {
        return Err(bad(format!(
            "dim[0] = {rank}: the number of dimensions must be 1 to 7"
        )));
    }
    let mut extent = [1usize; 7];
    for axis in 1..=rank as usize {
        let n = header.dim[axis];
        if n <= 0 {
            return Err(bad(format!("dim[{axis}] = {n}: sizes must be positive")));
        }
        extent[axis - 1] = usize::try_from(n).map_err(|_| bad(format!("dim[{axis}] = {n}")))?;
    }
    let components = match wanted {
        Components::Scalar => {
            if extent[3] > 1 {
                return Err(bad(format!(
                    "4-D series of {} volumes (dim[4] = {}); one 3-D CT is needed",
                    extent[3], extent[3]
                )));
            }
            let extra: usize = extent[4..].iter().product();
            if extra > 1 {
                return Err(bad(format!(
                    "{extra} values per voxel (dim[5..7] = {:?}); a scalar image is needed",
                    &extent[4..]
                )));
            }
            1
        }
        Components::Vector3 => {
            if rank != 5 || extent[3] != 1 || extent[4] != 3 || extent[5..] != [1, 1] {
                return Err(bad(format!(
                    "not a 3-D displacement field: dim = {:?}, expected [5, nx, ny, nz, 1, 3, 1, 1]",
                    header.dim
                )));
            }
            3
        }
    };
    let datatype = DataType::from_code(header.datatype).ok_or_else(|| {
        bad(format!(
            "unsupported datatype code {} (supported: uint8, int8, int16, uint16, int32, \
             uint32, int64, uint64, float32, float64)",
            header.datatype
        ))
    })?;
    if header.bitpix as usize != 8 * datatype.bytes() {
        return Err(bad(format!(
            "bitpix {} contradicts datatype {:?} ({} bits)",
            header.bitpix,
            datatype,
            8 * datatype.bytes()
        )));
    }
    let offset = header.vox_offset;
    if !(offset.is_finite() && offset.fract() == 0.0)
        || offset < header.header_bytes as f64
        || offset > u32::MAX as f64
    {
        return Err(bad(format!(
            "vox_offset {offset} is not a whole byte offset at or after the {}-byte header",
            header.header_bytes
        )));
    }
    let geometry = geometry(header, [extent[0], extent[1], extent[2]], what)?;
    geometry.validate(what)?;
    let data_len = geometry
        .voxel_count()
        .checked_mul(components * datatype.bytes())
        .ok_or_else(|| bad(format!("absurd grid {:?}", geometry.dims)))?;
    Ok((geometry, datatype, data_len))
}

/// The exact (f64) geometry from our comment extension when it agrees with the header's
/// float32 transform; otherwise the header's geometry unchanged.
fn refine_geometry(
    geometry: VolumeGeometry,
    extensions: &[u8],
    big_endian: bool,
    what: &str,
) -> VolumeGeometry {
    // The 4-byte extension flag precedes the extensions; a zero first byte means none.
    if extensions.len() < 4 || extensions[0] == 0 {
        return geometry;
    }
    let read_i32 = |b: &[u8]| {
        let a = [b[0], b[1], b[2], b[3]];
        if big_endian {
            i32::from_be_bytes(a)
        } else {
            i32::from_le_bytes(a)
        }
    };
    let mut offset = 4;
    while offset + 8 <= extensions.len() {
        let size = read_i32(&extensions[offset..]);
        let code = read_i32(&extensions[offset + 4..]);
        let Some(end) = usize::try_from(size)
            .ok()
            .filter(|&n| n >= 8 && n % 16 == 0)
            .map(|n| offset + n)
            .filter(|&end| end <= extensions.len())
        else {
            tracing::warn!("{what}: malformed header extension at byte {offset}; ignored");
            return geometry;
        };
        if code == ECODE_COMMENT {
            if let Some(exact) = parse_geometry_text(&extensions[offset + 8..end], geometry.dims) {
                let agrees = exact.validate(what).is_ok()
                    && exact.same_grid(&geometry, EXTENSION_AGREEMENT_MM)
                    && (0..3).all(|a| {
                        (exact.spacing_mm[a] - geometry.spacing_mm[a]).abs()
                            <= EXTENSION_AGREEMENT_MM
                    });
                if agrees {
                    return exact;
                }
                tracing::warn!(
                    "{what}: the lungmotion geometry extension disagrees with the header's                      transform (the file was edited?); using the header"
                );
            }
        }
        offset = end;
    }
    geometry
}

/// The exact geometry as comment text: a tag line, then spacing, origin and the direction
/// columns, each number in Rust's shortest round-tripping decimal form.
fn geometry_text(g: &VolumeGeometry) -> String {
    let numbers = |v: &[f64]| {
        v.iter()
            .map(|x| format!("{x:?}"))
            .collect::<Vec<_>>()
            .join(" ")
    };
    let direction: Vec<f64> = g.direction_lps.iter().flatten().copied().collect();
    format!(
        "{GEOMETRY_EXTENSION_TAG}\nspacing_mm {}\norigin_lps_mm {}\ndirection_lps_columns {}\n",
        numbers(&g.spacing_mm),
        numbers(&g.origin_lps_mm),
        numbers(&direction)
    )
}

fn parse_geometry_text(bytes: &[u8], dims: [usize; 3]) -> Option<VolumeGeometry> {
    let text = std::str::from_utf8(bytes).ok()?.trim_end_matches('\0');
    let mut lines = text.lines();
    if lines.next()? != GEOMETRY_EXTENSION_TAG {
        return None;
    }
    let mut field = |name: &str, count: usize| -> Option<Vec<f64>> {
        let values = lines.next()?.strip_prefix(name)?;
        let parsed: Vec<f64> = values
            .split_whitespace()
            .map(|v| v.parse().ok())
            .collect::<Option<_>>()?;
        (parsed.len() == count).then_some(parsed)
    };
    let spacing = field("spacing_mm ", 3)?;
    let origin = field("origin_lps_mm ", 3)?;
    let direction = field("direction_lps_columns ", 9)?;
    Some(VolumeGeometry {
        dims,
        spacing_mm: [spacing[0], spacing[1], spacing[2]],
        origin_lps_mm: [origin[0], origin[1], origin[2]],
        direction_lps: std::array::from_fn(|c| std::array::from_fn(|r| direction[3 * c + r])),
    })
}

/// The scale applied to stored values: (slope, intercept), identity when unset.
fn scaling(header: &Header, what: &str) -> Result<(f64, f64)> {
    let (slope, inter) = (header.scl_slope, header.scl_inter);
    if slope == 0.0 || slope.is_nan() {
        return Ok((1.0, 0.0));
    }
    let inter = if inter.is_nan() { 0.0 } else { inter };
    if !slope.is_finite() || !inter.is_finite() {
        return Err(Error::InvalidScan(format!(
            "{what}: scl_slope {slope} / scl_inter {inter} are not finite"
        )));
    }
    Ok((slope, inter))
}

/// The grid in LPS millimetres from the sform, the qform or the ANALYZE fallback.
fn geometry(header: &Header, dims: [usize; 3], what: &str) -> Result<VolumeGeometry> {
    let bad = |m: String| Error::InvalidScan(format!("{what}: {m}"));
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
        let s = &header.srow;
        let axes = Matrix3::from_fn(|r, c| s[r][c] * mm_per_unit);
        let origin = Vector3::new(s[0][3], s[1][3], s[2][3]) * mm_per_unit;
        (axes, origin)
    } else if header.qform_code > 0 {
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
fn rotation_to_quaternion(r: &Matrix3<f64>) -> [f64; 3] {
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

/// A stored sample type: its width and its value as f64.
trait RawSample {
    const BYTES: usize;
    fn value(bytes: &[u8], big_endian: bool) -> f64;
}

macro_rules! raw_sample {
    ($($t:ty),*) => {$(
        impl RawSample for $t {
            const BYTES: usize = std::mem::size_of::<$t>();
            #[inline]
            fn value(bytes: &[u8], big_endian: bool) -> f64 {
                let mut a = [0u8; std::mem::size_of::<$t>()];
                a.copy_from_slice(bytes);
                (if big_endian { <$t>::from_be_bytes(a) } else { <$t>::from_le_bytes(a) }) as f64
            }
        }
    )*};
}
raw_sample!(u8, i8, i16, u16, i32, u32, i64, u64, f32, f64);

/// Converts every stored sample of `image` through `convert` into `out` (same length).
fn decode_samples<T: Send, F: Fn(f64) -> T + Sync>(image: &Image, out: &mut [T], convert: F) {
    decode_typed_dispatch(
        image.datatype,
        &image.voxels,
        image.big_endian,
        out,
        convert,
    );
}

fn decode_typed_dispatch<T: Send, F: Fn(f64) -> T + Sync>(
    datatype: DataType,
    raw: &[u8],
    big_endian: bool,
    out: &mut [T],
    convert: F,
) {
    match datatype {
        DataType::U8 => decode_typed::<u8, _, _>(raw, big_endian, out, convert),
        DataType::I8 => decode_typed::<i8, _, _>(raw, big_endian, out, convert),
        DataType::I16 => decode_typed::<i16, _, _>(raw, big_endian, out, convert),
        DataType::U16 => decode_typed::<u16, _, _>(raw, big_endian, out, convert),
        DataType::I32 => decode_typed::<i32, _, _>(raw, big_endian, out, convert),
        DataType::U32 => decode_typed::<u32, _, _>(raw, big_endian, out, convert),
        DataType::I64 => decode_typed::<i64, _, _>(raw, big_endian, out, convert),
        DataType::U64 => decode_typed::<u64, _, _>(raw, big_endian, out, convert),
        DataType::F32 => decode_typed::<f32, _, _>(raw, big_endian, out, convert),
        DataType::F64 => decode_typed::<f64, _, _>(raw, big_endian, out, convert),
    }
}

fn decode_typed<S: RawSample, T: Send, F: Fn(f64) -> T + Sync>(
    raw: &[u8],
    big_endian: bool,
    out: &mut [T],
    convert: F,
) {
    out.par_chunks_mut(CHUNK_VOXELS)
        .zip(raw.par_chunks(CHUNK_VOXELS * S::BYTES))
        .for_each(|(dst, src)| {
            for (d, s) in dst.iter_mut().zip(src.chunks_exact(S::BYTES)) {
                *d = convert(S::value(s, big_endian));
            }
        });
}

/// Refuses NaN or infinite values, naming their count and the first voxel.
fn refuse_non_finite(data: &[f32], geometry: &VolumeGeometry, what: &str) -> Result<()> {
    let Some(first) = data.par_iter().position_first(|v| !v.is_finite()) else {
        return Ok(());
    };
    let count = data.par_iter().filter(|v| !v.is_finite()).count();
    let [i, j, k] = voxel_ijk(first, geometry);
    Err(Error::InvalidScan(format!(
        "{what}: {count} voxels are NaN or infinite (first at voxel ({i}, {j}, {k}) = {})",
        data[first]
    )))
}

fn voxel_ijk(index: usize, geometry: &VolumeGeometry) -> [usize; 3] {
    let [nx, ny, _] = geometry.dims;
    [index % nx, (index / nx) % ny, index / (nx * ny)]
}

// ---------------------------------------------------------------------------------------
// Writing
// ---------------------------------------------------------------------------------------

/// What a written header says beyond the grid.
struct HeaderSpec<'a> {
    geometry: &'a VolumeGeometry,
    components: usize,
    datatype: DataType,
    intent_code: i32,
    intent_name: &'a str,
    description: &'a str,
}

fn check_volume(geometry: &VolumeGeometry, values: usize, what: &str) -> Result<()> {
    geometry.validate(what)?;
    if geometry.dims.iter().any(|&n| n > i16::MAX as usize) {
        return Err(Error::InvalidInput(format!(
            "{what}: grid {:?} exceeds NIfTI-1's 32767 voxels per axis",
            geometry.dims
        )));
    }
    if values != geometry.voxel_count() {
        return Err(Error::InvalidInput(format!(
            "{what}: grid {:?} has {} voxels but {values} values were given",
            geometry.dims,
            geometry.voxel_count()
        )));
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

/// Writes atomically, gzipped when the name ends in `.gz`.
fn write_file(path: &Path, bytes: Vec<u8>) -> Result<()> {
    let gzip = path
        .file_name()
        .and_then(|n| n.to_str())
        .is_some_and(|n| n.to_ascii_lowercase().ends_with(".gz"));
    let bytes = if gzip {
        // Level 1: outputs are written on request; speed matters more than a few percent.
        let mut encoder = flate2::write::GzEncoder::new(
            Vec::with_capacity(bytes.len() / 2),
            flate2::Compression::fast(),
        );
        encoder.write_all(&bytes)?;
        encoder.finish()?
    } else {
        bytes
    };
    write_atomic(path, &bytes).map_err(|e| match e {
        Error::Io(io) => Error::Io(std::io::Error::new(
            io.kind(),
            format!("{}: cannot write: {io}", path.display()),
        )),
        other => other,
    })
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
