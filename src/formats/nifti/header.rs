//! The header fields this module uses (NIfTI-1 and NIfTI-2 widened to one type), their
//! byte-level decoding, and the checks of dims, data type, offset and scaling.

use super::geometry::geometry;
use super::image::Components;
use super::nifti2::{parse_nifti2_header, NIFTI2_HEADER_BYTES};
use crate::volume::VolumeGeometry;
use crate::{Error, Result};

pub(super) const NIFTI1_HEADER_BYTES: usize = 348;

/// Stored sample types (NIFTI_TYPE_* codes).
#[derive(Clone, Copy, Debug, PartialEq)]
pub(super) enum DataType {
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
    /// The type of a `datatype` code, if supported.
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

    /// The `datatype` code written for this type.
    pub(super) fn code(self) -> i16 {
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

    /// Bytes per stored sample.
    pub(super) fn bytes(self) -> usize {
        match self {
            DataType::U8 | DataType::I8 => 1,
            DataType::I16 | DataType::U16 => 2,
            DataType::I32 | DataType::U32 | DataType::F32 => 4,
            DataType::I64 | DataType::U64 | DataType::F64 => 8,
        }
    }
}

/// The header fields this module uses, widened to the NIfTI-2 types.
pub(super) struct Header {
    pub(super) header_bytes: usize,
    pub(super) big_endian: bool,
    pub(super) dim: [i64; 8],
    pub(super) intent_code: i32,
    pub(super) datatype: i16,
    pub(super) bitpix: i16,
    pub(super) pixdim: [f64; 8],
    pub(super) vox_offset: f64,
    pub(super) scl_slope: f64,
    pub(super) scl_inter: f64,
    pub(super) xyzt_units: i32,
    pub(super) qform_code: i32,
    pub(super) sform_code: i32,
    pub(super) quatern_bcd: [f64; 3],
    pub(super) qoffset: [f64; 3],
    pub(super) srow: [[f64; 4]; 3],
}

/// Header size from `sizeof_hdr` (348 or 540, either byte order).
pub(super) fn header_length(bytes: &[u8], what: &str) -> Result<usize> {
    let first: [u8; 4] = bytes
        .get(..4)
        .and_then(|b| b.try_into().ok())
        .ok_or_else(|| {
            Error::scan(
                what,
                format!(
                    "not a NIfTI file: {} bytes, too short for a header",
                    bytes.len()
                ),
            )
        })?;
    let (le, be) = (i32::from_le_bytes(first), i32::from_be_bytes(first));
    for size in [NIFTI1_HEADER_BYTES, NIFTI2_HEADER_BYTES] {
        if le == size as i32 || be == size as i32 {
            return Ok(size);
        }
    }
    Err(Error::scan(
        what,
        format!("not a NIfTI file: sizeof_hdr is {le}, not 348 (NIfTI-1) or 540 (NIfTI-2)"),
    ))
}

/// Little- or big-endian field access to a header of known length.
pub(super) struct Fields<'a> {
    pub(super) bytes: &'a [u8],
    pub(super) big_endian: bool,
}

impl Fields<'_> {
    pub(super) fn array<const N: usize>(&self, offset: usize) -> [u8; N] {
        let mut a = [0u8; N];
        a.copy_from_slice(&self.bytes[offset..offset + N]);
        if self.big_endian {
            a.reverse();
        }
        a
    }
    pub(super) fn i16(&self, offset: usize) -> i16 {
        i16::from_le_bytes(self.array(offset))
    }
    pub(super) fn i32(&self, offset: usize) -> i32 {
        i32::from_le_bytes(self.array(offset))
    }
    pub(super) fn i64(&self, offset: usize) -> i64 {
        i64::from_le_bytes(self.array(offset))
    }
    pub(super) fn f32(&self, offset: usize) -> f64 {
        f32::from_le_bytes(self.array(offset)) as f64
    }
    pub(super) fn f64(&self, offset: usize) -> f64 {
        f64::from_le_bytes(self.array(offset))
    }
}

/// Decodes a complete 348- or 540-byte header.
pub(super) fn parse_header(bytes: &[u8], what: &str) -> Result<Header> {
    let size = bytes.len() as i32;
    let big_endian = i32::from_le_bytes([bytes[0], bytes[1], bytes[2], bytes[3]]) != size;
    let f = Fields { bytes, big_endian };
    if bytes.len() == NIFTI1_HEADER_BYTES {
        parse_nifti1_header(&f, what)
    } else {
        parse_nifti2_header(&f, what)
    }
}

/// The 348-byte NIfTI-1 header's fields, after its magic is checked.
fn parse_nifti1_header(f: &Fields, what: &str) -> Result<Header> {
    let bad = |m: String| Error::scan(what, m);
    let (bytes, big_endian) = (f.bytes, f.big_endian);
    let magic = &bytes[344..348];
    if magic == b"ni1\0" {
        return Err(bad(
            "two-file NIfTI-1 (.hdr/.img pair) is not supported; convert to a single .nii".into(),
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
}

/// Checks dims, data type and offset; returns the grid, the sample type and the voxel
/// byte count.
pub(super) fn layout(
    header: &Header,
    what: &str,
    wanted: Components,
) -> Result<(VolumeGeometry, DataType, usize)> {
    let bad = |m: String| Error::scan(what, m);
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

/// The scale applied to stored values: (slope, intercept), identity when unset.
pub(super) fn scaling(header: &Header, what: &str) -> Result<(f64, f64)> {
    let (slope, inter) = (header.scl_slope, header.scl_inter);
    if slope == 0.0 || slope.is_nan() {
        return Ok((1.0, 0.0));
    }
    let inter = if inter.is_nan() { 0.0 } else { inter };
    if !slope.is_finite() || !inter.is_finite() {
        return Err(Error::scan(
            what,
            format!("scl_slope {slope} / scl_inter {inter} are not finite"),
        ));
    }
    Ok((slope, inter))
}
