//! Pixel decoding of one slice into HU: native data straight from the parsed values,
//! everything else through dicom-pixeldata.

use dicom_core::Tag;
use dicom_dictionary_std::tags;
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
    let name = &slice.file.name;
    let bad = |m: String| Error::scan(name, m);
    let (slope, intercept) = (slice.rescale_slope, slice.rescale_intercept);
    let object = &slice.file.object;
    let tag_u16 = |tag: Tag| object.get(tag).and_then(|e| e.to_int::<u16>().ok());
    if let Some(samples) = tag_u16(tags::SAMPLES_PER_PIXEL) {
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
        let format = PixelFormat {
            bits_allocated: tag_u16(tags::BITS_ALLOCATED)
                .ok_or_else(|| bad("BitsAllocated (0028,0100) is missing".into()))?,
            bits_stored: tag_u16(tags::BITS_STORED)
                .ok_or_else(|| bad("BitsStored (0028,0101) is missing".into()))?,
            high_bit: tag_u16(tags::HIGH_BIT)
                .ok_or_else(|| bad("HighBit (0028,0102) is missing".into()))?,
            signed: tag_u16(tags::PIXEL_REPRESENTATION).unwrap_or(0) == 1,
        }
        .check(name)?;
        let short = |have: usize| {
            bad(format!(
                "pixel data holds {have} samples, {} expected (truncated?)",
                out.len()
            ))
        };
        use dicom_core::PrimitiveValue as V;
        let n = out.len();
        match (values, format.bits_allocated) {
            (V::U16(v), 16) if v.len() < n => return Err(short(v.len())),
            (V::I16(v), 16) if v.len() < n => return Err(short(v.len())),
            (V::U8(v), 8) if v.len() < n => return Err(short(v.len())),
            (V::U16(v), 16) => {
                format.fill_hu(v.iter().map(|&x| u32::from(x)), slope, intercept, out)
            }
            (V::I16(v), 16) => format.fill_hu(
                v.iter().map(|&x| u32::from(x as u16)),
                slope,
                intercept,
                out,
            ),
            (V::U8(v), 8) => format.fill_hu(v.iter().map(|&x| u32::from(x)), slope, intercept, out),
            _ => return decode_with_pixeldata(slice, layout, out),
        }
        return Ok(());
    }
    decode_with_pixeldata(slice, layout, out)
}

/// Decodes through dicom-pixeldata (every encapsulated syntax, unusual native layouts).
fn decode_with_pixeldata(slice: &Slice, layout: &FrameLayout, out: &mut [f32]) -> Result<()> {
    let name = &slice.file.name;
    let bad = |m: String| Error::scan(name, m);
    let pixels = slice
        .file
        .object
        .decode_pixel_data()
        .map_err(|e| bad(format!("cannot decode pixel data ({e})")))?;
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
