//! Pixel decoding of one slice (a single-frame file or one frame of a multi-frame file) into
//! HU: native data straight from the parsed values, JPEG-LS and 12-bit JPEG through
//! openreadout-codecs, everything else through dicom-pixeldata.

use std::panic::{catch_unwind, AssertUnwindSafe};

use dicom_core::Tag;
use dicom_dictionary_std::{tags, uids};
use dicom_pixeldata::PixelDecoder;

use super::{FrameLayout, Slice};
use crate::{Error, Result};

/// How stored pixel values are laid out (PS3.3 C.7.6.3.1).
#[derive(Debug, Clone, Copy)]
struct PixelFormat {
    bits_allocated: u16,
    bits_stored: u16,
    high_bit: u16,
    signed: bool,
}

impl PixelFormat {
    fn check(self, name: &str) -> Result<Self> {
        let PixelFormat {
            bits_allocated,
            bits_stored,
            high_bit,
            ..
        } = self;
        if !matches!(bits_allocated, 8 | 16 | 32) {
            return Err(Error::scan(
                name,
                format!("BitsAllocated {bits_allocated} is not supported (8, 16 or 32)"),
            ));
        }
        if bits_stored == 0
            || bits_stored > bits_allocated
            || high_bit + 1 < bits_stored
            || high_bit >= bits_allocated
        {
            return Err(Error::scan(
                name,
                format!(
                    "inconsistent BitsAllocated {bits_allocated}, BitsStored \
                 {bits_stored}, HighBit {high_bit}"
                ),
            ));
        }
        Ok(self)
    }

    /// Converts raw samples to HU; `out.len()` samples are taken from `raw`.
    fn fill_hu(self, raw: impl Iterator<Item = u32>, slope: f64, intercept: f64, out: &mut [f32]) {
        let shift = u32::from(self.high_bit + 1 - self.bits_stored);
        let mask: u64 = (1u64 << self.bits_stored) - 1;
        let sign_bit: u64 = 1u64 << (self.bits_stored - 1);
        let wrap: i64 = 1i64 << self.bits_stored;
        let signed = self.signed;
        for (o, stored) in out.iter_mut().zip(raw) {
            let bits = (u64::from(stored) >> shift) & mask;
            let value = if signed && bits & sign_bit != 0 {
                bits as i64 - wrap
            } else {
                bits as i64
            };
            *o = (value as f64 * slope + intercept) as f32;
        }
    }
}

/// Decodes one slice into `out` (rows × columns HU values, i fastest).
pub(super) fn decode_slice(slice: &Slice, layout: &FrameLayout, out: &mut [f32]) -> Result<()> {
    let name = &slice.name;
    let bad = |m: String| Error::scan(name, m);
    let (slope, intercept) = (slice.rescale_slope, slice.rescale_intercept);
    let object = &slice.file.object;
    if let Some(samples) = tag_u16(slice, tags::SAMPLES_PER_PIXEL) {
        if samples != 1 {
            return Err(bad(format!(
                "{samples} samples per pixel: a CT image has 1"
            )));
        }
    }

    // Native pixel data is converted straight from the parsed values: decoding through
    // dicom-pixeldata would copy every slice twice.
    let native = object
        .get(tags::PIXEL_DATA)
        .and_then(|e| e.value().primitive());
    if let Some(values) = native {
        let format = stored_format(slice)?;
        let n = out.len();
        let first = slice.frame.unwrap_or(0) * n;
        let short = |have: usize| {
            bad(format!(
                "pixel data holds {have} samples, {} expected (truncated?)",
                first + n
            ))
        };
        use dicom_core::PrimitiveValue as V;
        match (values, format.bits_allocated) {
            (V::U16(v), 16) if v.len() < first + n => return Err(short(v.len())),
            (V::I16(v), 16) if v.len() < first + n => return Err(short(v.len())),
            (V::U8(v), 8) if v.len() < first + n => return Err(short(v.len())),
            (V::U16(v), 16) => format.fill_hu(
                v[first..].iter().map(|&x| u32::from(x)),
                slope,
                intercept,
                out,
            ),
            (V::I16(v), 16) => format.fill_hu(
                v[first..].iter().map(|&x| u32::from(x as u16)),
                slope,
                intercept,
                out,
            ),
            (V::U8(v), 8) => format.fill_hu(
                v[first..].iter().map(|&x| u32::from(x)),
                slope,
                intercept,
                out,
            ),
            _ => return decode_with_pixeldata(slice, layout, out),
        }
        return Ok(());
    }
    let syntax = object.meta().transfer_syntax().trim_end_matches('\0');
    match syntax {
        uids::JPEGLS_LOSSLESS | uids::JPEGLS_NEAR_LOSSLESS => {
            decode_with_codec(slice, layout, out, Codec::JpegLs)
        }
        uids::JPEG_EXTENDED12_BIT => decode_with_codec(slice, layout, out, Codec::Jpeg),
        _ => decode_with_pixeldata(slice, layout, out),
    }
}

fn tag_u16(slice: &Slice, tag: Tag) -> Option<u16> {
    slice
        .file
        .object
        .get(tag)
        .and_then(|e| e.to_int::<u16>().ok())
}

/// The stored-value layout the header declares.
fn stored_format(slice: &Slice) -> Result<PixelFormat> {
    let bad = |m: &str| Error::scan(&slice.name, m);
    PixelFormat {
        bits_allocated: tag_u16(slice, tags::BITS_ALLOCATED)
            .ok_or_else(|| bad("BitsAllocated (0028,0100) is missing"))?,
        bits_stored: tag_u16(slice, tags::BITS_STORED)
            .ok_or_else(|| bad("BitsStored (0028,0101) is missing"))?,
        high_bit: tag_u16(slice, tags::HIGH_BIT)
            .ok_or_else(|| bad("HighBit (0028,0102) is missing"))?,
        signed: tag_u16(slice, tags::PIXEL_REPRESENTATION).unwrap_or(0) == 1,
    }
    .check(&slice.name)
}

/// The codecs decoded here rather than by dicom-pixeldata.
#[derive(Debug, Clone, Copy)]
enum Codec {
    /// JPEG-LS lossless and near-lossless (ITU-T T.87).
    JpegLs,
    /// JPEG, here for the 12-bit extended process (ITU-T T.81 SOF1).
    Jpeg,
}

/// Decodes an encapsulated JPEG-LS or 12-bit JPEG frame through openreadout-codecs.
fn decode_with_codec(
    slice: &Slice,
    layout: &FrameLayout,
    out: &mut [f32],
    codec: Codec,
) -> Result<()> {
    let name = &slice.name;
    let bad = |m: String| Error::scan(name, m);
    let format = stored_format(slice)?;
    let mut stream = frame_stream(slice)?;
    if matches!(codec, Codec::JpegLs) {
        drop_fill_before_end_of_image(&mut stream);
    }
    // A frame decodes to at most 2 bytes a pixel: a stream declaring more is refused before
    // the decoder allocates.
    let max_bytes = layout.rows * layout.columns * 2;
    let decoded = catch_unwind(AssertUnwindSafe(|| match codec {
        Codec::JpegLs => openreadout_codecs::jpegls_decode_limited(&stream, max_bytes),
        Codec::Jpeg => openreadout_codecs::jpeg_decode_limited(&stream, max_bytes),
    }));
    let what = match codec {
        Codec::JpegLs => "JPEG-LS",
        Codec::Jpeg => "JPEG",
    };
    let raster = match decoded {
        Ok(Ok(raster)) => raster,
        Ok(Err(e)) => return Err(bad(format!("cannot decode the {what} pixel data ({e})"))),
        Err(_) => {
            return Err(bad(format!(
                "cannot decode the {what} pixel data (the decoder failed on a malformed stream)"
            )))
        }
    };
    if (raster.width as usize, raster.height as usize) != (layout.columns, layout.rows)
        || raster.channels != 1
    {
        return Err(bad(format!(
            "the {what} stream holds a {}×{} image of {} component(s), the header says {}×{} \
             (rows×columns) of 1",
            raster.height, raster.width, raster.channels, layout.rows, layout.columns
        )));
    }
    // Decoders return samples right-aligned, whatever HighBit says.
    let format = PixelFormat {
        high_bit: format.bits_stored - 1,
        ..format
    };
    let (slope, intercept) = (slice.rescale_slope, slice.rescale_intercept);
    match raster.bits_per_sample {
        8 => format.fill_hu(
            raster.data.iter().map(|&b| u32::from(b)),
            slope,
            intercept,
            out,
        ),
        _ => format.fill_hu(
            raster
                .data
                .chunks_exact(2)
                .map(|b| u32::from(u16::from_le_bytes([b[0], b[1]]))),
            slope,
            intercept,
            out,
        ),
    }
    Ok(())
}

/// Removes what T.87 allows after the scan but pure_jpegls does not skip: the DICOM pad byte
/// after EOI and 0xFF fill bytes before it (DCMTK's encoder writes one when the scan ends on
/// a 0xFF byte). A fill byte cannot be data: a data 0xFF is followed by a byte below 0x80.
fn drop_fill_before_end_of_image(stream: &mut Vec<u8>) {
    if stream.ends_with(&[0xFF, 0xD9, 0x00]) {
        stream.pop();
    }
    while stream.len() >= 3 && stream.ends_with(&[0xFF, 0xFF, 0xD9]) {
        let fill = stream.len() - 3;
        stream.remove(fill);
    }
}

/// The compressed bytes of the slice's frame: all fragments of a single-frame file, else the
/// fragment of each frame or the fragments the Basic Offset Table assigns to it.
fn frame_stream(slice: &Slice) -> Result<Vec<u8>> {
    let bad = |m: String| Error::scan(&slice.name, m);
    let value = slice
        .file
        .object
        .get(tags::PIXEL_DATA)
        .map(|e| e.value())
        .ok_or_else(|| bad("no pixel data".into()))?;
    let fragments = value.fragments().ok_or_else(|| {
        bad("pixel data is not encapsulated, as its transfer syntax requires".into())
    })?;
    let Some(frame) = slice.frame else {
        return Ok(fragments.concat());
    };
    let frames = slice.frame_count;
    if fragments.len() == frames {
        return Ok(fragments[frame].clone());
    }
    let offsets = value.offset_table().unwrap_or(&[]);
    if offsets.len() != frames {
        return Err(bad(format!(
            "{} fragments for {frames} frames and no Basic Offset Table with one entry a frame: \
             cannot tell which fragments hold frame {}",
            fragments.len(),
            frame + 1
        )));
    }
    // Offsets count from the first fragment's item tag; each item has an 8-byte header.
    let (begin, end) = (
        u64::from(offsets[frame]),
        offsets.get(frame + 1).map_or(u64::MAX, |&o| u64::from(o)),
    );
    let mut at = 0u64;
    let mut stream = Vec::new();
    for fragment in fragments {
        if (begin..end).contains(&at) {
            stream.extend_from_slice(fragment);
        }
        at += 8 + fragment.len() as u64;
    }
    if stream.is_empty() {
        return Err(bad(format!(
            "the Basic Offset Table points frame {} at byte {begin}, where no fragment starts",
            frame + 1
        )));
    }
    Ok(stream)
}

/// Decodes through dicom-pixeldata (every other encapsulated syntax, unusual native layouts).
fn decode_with_pixeldata(slice: &Slice, layout: &FrameLayout, out: &mut [f32]) -> Result<()> {
    let name = &slice.name;
    let bad = |m: String| Error::scan(name, m);
    let object = &slice.file.object;
    let decoded = match slice.frame {
        None => object.decode_pixel_data(),
        Some(frame) => object.decode_pixel_data_frame(frame as u32),
    };
    let pixels = decoded.map_err(|e| bad(format!("cannot decode pixel data ({e})")))?;
    if pixels.rows() as usize != layout.rows || pixels.columns() as usize != layout.columns {
        return Err(bad(format!(
            "decoded image is {}×{}, header says {}×{}",
            pixels.rows(),
            pixels.columns(),
            layout.rows,
            layout.columns
        )));
    }
    if pixels.samples_per_pixel() != 1 {
        return Err(bad(format!(
            "{} samples per pixel: a CT image has 1",
            pixels.samples_per_pixel()
        )));
    }
    let format = PixelFormat {
        bits_allocated: pixels.bits_allocated(),
        bits_stored: pixels.bits_stored(),
        high_bit: pixels.high_bit(),
        signed: pixels.pixel_representation() == dicom_pixeldata::PixelRepresentation::Signed,
    }
    .check(name)?;
    let bytes_per_sample = usize::from(format.bits_allocated / 8);
    let raw = pixels.data();
    let needed = out.len() * bytes_per_sample;
    if raw.len() < needed {
        return Err(bad(format!(
            "pixel data holds {} bytes, {needed} expected (truncated?)",
            raw.len()
        )));
    }
    let (slope, intercept) = (slice.rescale_slope, slice.rescale_intercept);
    // Decoded samples are in the machine's byte order.
    match bytes_per_sample {
        1 => format.fill_hu(raw.iter().map(|&b| u32::from(b)), slope, intercept, out),
        2 => format.fill_hu(
            raw.chunks_exact(2)
                .map(|b| u32::from(u16::from_ne_bytes([b[0], b[1]]))),
            slope,
            intercept,
            out,
        ),
        _ => format.fill_hu(
            raw.chunks_exact(4)
                .map(|b| u32::from_ne_bytes([b[0], b[1], b[2], b[3]])),
            slope,
            intercept,
            out,
        ),
    }
    Ok(())
}
