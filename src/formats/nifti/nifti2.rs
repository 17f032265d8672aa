//! The 540-byte NIfTI-2 header (64-bit dims, double-precision geometry).

use super::header::{Fields, Header};
use crate::{Error, Result};

pub(super) const NIFTI2_HEADER_BYTES: usize = 540;
const NIFTI2_MAGIC: &[u8; 8] = b"n+2\0\r\n\x1a\n";

/// The 540-byte NIfTI-2 header's fields, after its magic is checked.
pub(super) fn parse_nifti2_header(f: &Fields, what: &str) -> Result<Header> {
    let bad = |m: String| Error::scan(what, m);
    let (bytes, big_endian) = (f.bytes, f.big_endian);
    let magic = &bytes[4..12];
    if magic.starts_with(b"ni2\0") {
        return Err(bad(
            "two-file NIfTI-2 (.hdr/.img pair) is not supported; convert to a single .nii".into(),
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
