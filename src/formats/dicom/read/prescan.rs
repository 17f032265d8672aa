//! Checks one DICOM file's bytes before dicom-rs sees them: the file meta information, the
//! transfer syntax, a bounded inflate of deflated data sets, the element structure (see
//! `walk`), the memory its parse will take, and the VR UN repair.

use std::io::{Read, Write};

use dicom_encoding::Codec;
use dicom_transfer_syntax_registry::{TransferSyntaxIndex, TransferSyntaxRegistry};
use flate2::read::DeflateDecoder;
use flate2::write::DeflateEncoder;

use super::budget::mb;
use super::vr_repair::ExplicitLittleWriter;
use super::walk::{walk, Encoding, Event, Visitor};

/// Implicit VR Little Endian, the one syntax without VRs.
const IMPLICIT_VR_LITTLE_ENDIAN: &str = "1.2.840.10008.1.2";
// A deflated data set may inflate to at most this many times its compressed size: the cap
// every compressed scan stream shares (zip entries, gzip NIfTI and NRRD).
use crate::formats::budget::MAX_INFLATION_RATIO as MAX_INFLATE_RATIO;
/// Memory dicom-rs takes per element, item or sequence beyond its value (tree node,
/// header, small-vector): 226 bytes measured as the peak RSS difference of `lungmotion
/// ingest` (release) on a slice carrying 1 000 000 vs 200 000 extra empty elements.
const PARSED_NODE_BYTES: u64 = 224;
/// Memory per value of a multi-valued text element (one `String` each).
const PARSED_STRING_BYTES: u64 = 32;

/// A file ready for dicom-rs.
pub(super) struct CheckedFile {
    /// The bytes to parse: the file's own, or a repaired copy.
    pub bytes: Vec<u8>,
    /// Memory the parsed object will hold, estimated from its elements.
    pub parsed_bytes: u64,
    /// Repairs made, one sentence each ("VR UN of 52 elements …").
    pub repairs: Vec<String>,
}

/// Where the data set starts and how it is encoded, from the file meta information.
struct Meta {
    dataset_start: usize,
    encoding: Encoding,
    deflated: bool,
}

/// Checks `bytes` (a whole Part 10 file) and returns what dicom-rs may parse, or the reason
/// it must not. `max_parsed_bytes` bounds an inflated data set.
pub(super) fn check_file(mut bytes: Vec<u8>, max_parsed_bytes: u64) -> Result<CheckedFile, String> {
    let mut repairs = Vec::new();
    let meta = read_meta(&mut bytes, &mut repairs)?;
    let inflated;
    let dataset: &[u8] = if meta.deflated {
        inflated = inflate(&bytes[meta.dataset_start..], max_parsed_bytes)?;
        &inflated
    } else {
        &bytes[meta.dataset_start..]
    };
    let mut estimate = ParseEstimate::default();
    let summary = walk(dataset, meta.encoding, &mut estimate)?;
    let mut parsed_bytes = estimate.bytes + dataset.len() as u64;
    if summary.un_to_repair == 0 {
        return Ok(CheckedFile {
            bytes,
            parsed_bytes,
            repairs,
        });
    }
    let mut writer = ExplicitLittleWriter::with_capacity(dataset.len() + dataset.len() / 8);
    walk(dataset, meta.encoding, &mut writer)?;
    // The rewritten data set is what dicom-rs will see: walked again as it will read it.
    let mut estimate = ParseEstimate::default();
    let check = walk(&writer.out, Encoding::ExplicitLittle, &mut estimate)
        .map_err(|e| format!("after re-reading VR UN elements: {e}"))?;
    parsed_bytes = parsed_bytes.max(estimate.bytes + writer.out.len() as u64);
    repairs.push(format!(
        "elements stored with VR UN (unknown) were read with the standard dictionary's VR{}",
        if check.un_to_repair > 0 {
            " (values too long for it kept as bytes)"
        } else {
            ""
        }
    ));
    let mut repaired = bytes[..meta.dataset_start].to_vec();
    if meta.deflated {
        let mut encoder = DeflateEncoder::new(repaired, flate2::Compression::fast());
        encoder
            .write_all(&writer.out)
            .map_err(|e| format!("cannot re-deflate the repaired data set ({e})"))?;
        repaired = encoder
            .finish()
            .map_err(|e| format!("cannot re-deflate the repaired data set ({e})"))?;
    } else {
        repaired.extend_from_slice(&writer.out);
    }
    Ok(CheckedFile {
        bytes: repaired,
        parsed_bytes,
        repairs,
    })
}

/// Reads the file meta information (always Explicit VR Little Endian, group 0002): its
/// elements must fit in the file; a wrong group length is corrected in `bytes`, as DCMTK
/// and pydicom read past it.
fn read_meta(bytes: &mut [u8], repairs: &mut Vec<String>) -> Result<Meta, String> {
    let start = if bytes.get(128..132) == Some(b"DICM") {
        132
    } else if bytes.starts_with(b"DICM") {
        4
    } else {
        return Err("no DICM marker at byte 128: not a DICOM file".into());
    };
    let header = bytes
        .get(start..start + 12)
        .ok_or("the file ends inside its meta information")?;
    if header[0..4] != [2, 0, 0, 0] || &header[4..6] != b"UL" || header[6..8] != [4, 0] {
        return Err(
            "the file meta information does not start with its Group Length (0002,0000)".into(),
        );
    }
    let declared = u32::from_le_bytes([header[8], header[9], header[10], header[11]]);
    let first = start + 12;
    let mut pos = first;
    let mut transfer_syntax = None;
    while bytes.len() - pos >= 8 && bytes[pos..pos + 2] == [2, 0] {
        let element = u16::from_le_bytes([bytes[pos + 2], bytes[pos + 3]]);
        let vr = [bytes[pos + 4], bytes[pos + 5]];
        let short = dicom_core::VR::from_binary(vr).is_some_and(super::walk::has_short_length);
        let (header_len, length) = if short {
            (
                8,
                u32::from(u16::from_le_bytes([bytes[pos + 6], bytes[pos + 7]])),
            )
        } else {
            let field = bytes
                .get(pos + 8..pos + 12)
                .ok_or("the file ends inside its meta information")?;
            (
                12,
                u32::from_le_bytes([field[0], field[1], field[2], field[3]]),
            )
        };
        let left = bytes.len() - pos - header_len;
        if length as usize > left {
            return Err(format!(
                "meta element (0002,{element:04X}) declares {} bytes but only {left} remain in \
                 the file",
                if length == u32::MAX {
                    "an undefined number of".to_string()
                } else {
                    length.to_string()
                }
            ));
        }
        let value = &bytes[pos + header_len..pos + header_len + length as usize];
        if element == 0x0010 {
            transfer_syntax = Some(
                String::from_utf8_lossy(value)
                    .trim_end_matches(['\0', ' '])
                    .to_string(),
            );
        }
        pos += header_len + length as usize;
    }
    let actual = (pos - first) as u32;
    if actual != declared {
        bytes[start + 8..start + 12].copy_from_slice(&actual.to_le_bytes());
        repairs.push(format!(
            "its File Meta Information Group Length (0002,0000) said {declared} bytes, its \
             elements take {actual}: corrected"
        ));
    }
    let uid = transfer_syntax.ok_or("the Transfer Syntax UID (0002,0010) is missing")?;
    let syntax = TransferSyntaxRegistry.get(&uid).ok_or_else(|| {
        format!("Transfer Syntax UID (0002,0010) \"{uid}\" is not a known transfer syntax")
    })?;
    let encoding = if uid == IMPLICIT_VR_LITTLE_ENDIAN {
        Encoding::ImplicitLittle
    } else if syntax.endianness() == dicom_encoding::Endianness::Big {
        Encoding::ExplicitBig
    } else {
        Encoding::ExplicitLittle
    };
    Ok(Meta {
        dataset_start: pos,
        deflated: matches!(syntax.codec(), Codec::Dataset(_)),
        encoding,
    })
}

/// Inflates a deflated data set, refusing it past `MAX_INFLATE_RATIO` times its size or
/// `max_bytes`, whichever is smaller, from the bytes actually produced.
fn inflate(compressed: &[u8], max_bytes: u64) -> Result<Vec<u8>, String> {
    let cap = (compressed.len() as u64)
        .saturating_mul(MAX_INFLATE_RATIO)
        .min(max_bytes);
    let mut out = Vec::new();
    DeflateDecoder::new(compressed)
        .take(cap + 1)
        .read_to_end(&mut out)
        .map_err(|e| format!("its deflated data set cannot be inflated ({e})"))?;
    if out.len() as u64 > cap {
        return Err(format!(
            "its deflated data set ({}) inflates past {} ({MAX_INFLATE_RATIO}× its size or the \
             memory budget): refused as a decompression bomb",
            mb(compressed.len() as u64),
            mb(cap)
        ));
    }
    Ok(out)
}

/// Sums the memory dicom-rs will take for the walked elements beyond their value bytes.
#[derive(Default)]
struct ParseEstimate {
    bytes: u64,
}

impl Visitor for ParseEstimate {
    fn visit(&mut self, event: Event<'_>) -> Result<(), String> {
        use dicom_core::VR::*;
        self.bytes += PARSED_NODE_BYTES;
        if let Event::Element { vr, value, .. } = event {
            if matches!(
                vr,
                AE | AS | CS | DA | DS | DT | IS | LO | LT | PN | SH | ST | TM | UC | UI | UR | UT
            ) {
                let values = 1 + value.iter().filter(|&&b| b == b'\\').count() as u64;
                self.bytes += values * PARSED_STRING_BYTES;
            }
        }
        Ok(())
    }
}
