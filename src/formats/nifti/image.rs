//! From file bytes (raw or gzipped) to a checked image: header, grid, scaling and the
//! voxel bytes, borrowed when the input is raw.

use std::borrow::Cow;
use std::io::Read;
use std::path::Path;

use super::extension::refine_geometry;
use super::header::{header_length, layout, parse_header, scaling, DataType, Header};
use super::nifti2::NIFTI2_HEADER_BYTES;
use super::samples::decode_typed_dispatch;
use crate::formats::budget::ScanBudget;
use crate::volume::VolumeGeometry;
use crate::{Error, Result};

const GZIP_MAGIC: [u8; 2] = [0x1f, 0x8b];
/// Initial buffer for decompressed voxels: a lying header cannot make us allocate more
/// than what the gzip stream actually delivers.
const MAX_PREALLOCATED_BYTES: usize = 64 << 20;
/// Largest extension area (between header and voxels) searched for the exact geometry.
const MAX_EXTENSION_BYTES: usize = 1 << 20;
/// Decompressed bytes after the voxels read to reach the gzip trailer (extensions of
/// other tools are small).
const MAX_TRAILING_BYTES: u64 = 16 << 20;

/// What the caller needs per voxel: checked against dim[4..7] before any voxel is read.
#[derive(Clone, Copy, PartialEq)]
pub(super) enum Components {
    Scalar,
    Vector3,
}

impl Components {
    /// Values per voxel.
    fn count(self) -> usize {
        match self {
            Components::Scalar => 1,
            Components::Vector3 => 3,
        }
    }
}

/// A parsed image whose voxel bytes are present and sized for its grid.
pub(super) struct Image<'a> {
    pub(super) geometry: VolumeGeometry,
    pub(super) datatype: DataType,
    pub(super) big_endian: bool,
    pub(super) scaling: (f64, f64),
    pub(super) intent_code: i32,
    pub(super) voxels: Cow<'a, [u8]>,
}

impl Image<'_> {
    /// One stored sample as f64, unscaled (for error messages).
    pub(super) fn sample(&self, index: usize) -> f64 {
        let size = self.datatype.bytes();
        let raw = &self.voxels[index * size..(index + 1) * size];
        let mut out = [0f64];
        decode_typed_dispatch(self.datatype, raw, self.big_endian, &mut out, |v| v);
        out[0]
    }
}

/// The whole file; a failure names the path.
pub(super) fn read_file(path: &Path) -> Result<Vec<u8>> {
    std::fs::read(path).map_err(|e| Error::scan(path, format!("cannot read: {e}")))
}

/// Parses the header, checks it against the wanted components and the available bytes,
/// and returns the voxel bytes; nothing proportional to the header's dims is allocated or
/// inflated before the dims are validated and checked against `budget`.
pub(super) fn parse_image<'a>(
    bytes: &'a [u8],
    what: &str,
    wanted: Components,
    budget: &ScanBudget,
) -> Result<Image<'a>> {
    if bytes.starts_with(&GZIP_MAGIC) {
        parse_gzipped_image(bytes, what, wanted, budget)
    } else {
        parse_raw_image(bytes, what, wanted, budget)
    }
}

/// A gzipped file: header, extensions and voxels are inflated in turn, the voxels into a
/// buffer that grows with what the stream delivers.
fn parse_gzipped_image(
    bytes: &[u8],
    what: &str,
    wanted: Components,
    budget: &ScanBudget,
) -> Result<Image<'static>> {
    let bad = |m: String| Error::scan(what, m);
    let mut stream = flate2::read::MultiGzDecoder::new(bytes);
    let mut head = Vec::with_capacity(NIFTI2_HEADER_BYTES);
    read_gz(&mut stream, &mut head, 4, what)?;
    let header_len = header_length(&head, what)?;
    read_gz(&mut stream, &mut head, header_len - 4, what)?;
    let header = parse_header(&head, what)?;
    let (geometry, datatype, data_len) = layout(&header, what, wanted)?;
    budget.check_volume(what, geometry.dims, wanted.count())?;
    // vox_offset counts too: skipping a declared 4 GB extension area is as much inflating.
    let declared = header.vox_offset as u64 + data_len as u64;
    budget.check_inflation(what, "gzip stream", bytes.len() as u64, declared)?;
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
    finish_image(header, geometry, datatype, Cow::Owned(voxels), what)
}

/// A raw file: the voxels are borrowed from `bytes`.
fn parse_raw_image<'a>(
    bytes: &'a [u8],
    what: &str,
    wanted: Components,
    budget: &ScanBudget,
) -> Result<Image<'a>> {
    let bad = |m: String| Error::scan(what, m);
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
    budget.check_volume(what, geometry.dims, wanted.count())?;
    let extensions = &bytes[header_len..start];
    let geometry = refine_geometry(geometry, extensions, header.big_endian, what);
    finish_image(header, geometry, datatype, Cow::Borrowed(voxels), what)
}

/// The checked image: scaling validated, header fields the readers need kept.
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
        return Err(Error::scan(
            what,
            format!(
                "truncated: the gzip stream ends inside the NIfTI header ({} bytes)",
                buf.len()
            ),
        ));
    }
    Ok(())
}

/// A gzip failure as a scan error, truncation named as such.
fn gz_error(e: std::io::Error, what: &str) -> Error {
    if e.kind() == std::io::ErrorKind::UnexpectedEof {
        Error::scan(what, format!("truncated gzip stream: {e}"))
    } else {
        Error::scan(what, format!("corrupt or truncated gzip stream: {e}"))
    }
}
