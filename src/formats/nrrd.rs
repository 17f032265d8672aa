//! NRRD reader (teem's format, as 3D Slicer and the Chest Imaging Platform write it).
//!
//! Convention: `space directions` columns are the voxel axes scaled by the spacing, in the
//! file's `space`; `space origin` is the centre of the first voxel. LPS files are read as
//! they are; RAS files have x and y negated. Supported: 3-D, attached data, `raw` or `gzip`
//! encoding, integer and float sample types, either endianness. Every size the header
//! declares is checked against a [`ScanBudget`] and the bytes present before the data are
//! inflated or copied.

use std::borrow::Cow;
use std::io::Read;
use std::path::Path;

use nalgebra::{Matrix3, Vector3};

use crate::formats::budget::ScanBudget;
use crate::volume::{Volume, VolumeGeometry};
use crate::{Error, Result};

/// Longest header accepted: teem's own headers are under a kilobyte; a file with no empty
/// line in its first megabyte is not a NRRD header.
const MAX_HEADER_BYTES: usize = 1 << 20;
/// Initial buffer for inflated data: a lying `sizes` cannot reserve more than this before
/// the stream delivers it.
const MAX_PREALLOCATED_BYTES: usize = 64 << 20;

/// Reads a 3-D NRRD file into a volume of f32 values (HU for CT, codes for label maps),
/// within [`ScanBudget::for_this_machine`].
pub fn read_nrrd(path: &Path) -> Result<Volume<f32>> {
    let bytes = std::fs::read(path).map_err(|e| Error::scan(path, format!("cannot read: {e}")))?;
    parse_nrrd(&bytes, &path.display().to_string())
}

/// Parses NRRD bytes within [`ScanBudget::for_this_machine`]; `what` names the source in
/// errors.
pub fn parse_nrrd(bytes: &[u8], what: &str) -> Result<Volume<f32>> {
    parse_nrrd_within(bytes, what, &ScanBudget::for_this_machine())
}

/// Parses NRRD bytes within `budget` (its ratio cap applies to gzip data).
pub fn parse_nrrd_within(bytes: &[u8], what: &str, budget: &ScanBudget) -> Result<Volume<f32>> {
    let header = read_header(bytes, what)?;
    let dims = read_sizes(&header)?;
    let geometry = read_geometry(&header, dims)?;
    geometry.validate(what)?;
    budget.check_volume(what, dims, 1)?;
    let (size, decode) = sample_decoder(header.require("type")?).map_err(|m| header.error(m))?;
    let little = match header.field("endian").unwrap_or("little") {
        "little" => true,
        "big" => false,
        other => return Err(header.error(format!("endian '{other}' is not 'little' or 'big'"))),
    };
    let expected = geometry.voxel_count() * size;
    let raw = read_payload(&header, &bytes[header.data_start..], expected, budget)?;
    let data = raw[..expected]
        .chunks_exact(size)
        .map(|c| {
            let mut b = [0u8; 8];
            b[..size].copy_from_slice(c);
            decode(b, little)
        })
        .collect();
    Volume::from_data(geometry, data)
}

/// The header's `key: value` fields (keys lower-cased) and where the data starts.
struct Header<'a> {
    /// Names the source in errors.
    what: &'a str,
    fields: Vec<(String, String)>,
    /// Offset of the first data byte, just after the empty line ending the header.
    data_start: usize,
}

impl Header<'_> {
    /// The error for this file with message `m`.
    fn error(&self, m: String) -> Error {
        Error::scan(self.what, m)
    }

    /// The value of field `name` (lower case), if present.
    fn field(&self, name: &str) -> Option<&str> {
        self.fields
            .iter()
            .find(|(k, _)| k == name)
            .map(|(_, v)| v.as_str())
    }

    /// The value of field `name`, which the reader cannot do without.
    fn require(&self, name: &str) -> Result<&str> {
        self.field(name)
            .ok_or_else(|| self.error(format!("missing field '{name}'")))
    }
}

/// Checks the magic and reads the header up to its first empty line; comments and the magic
/// line are skipped.
fn read_header<'a>(bytes: &[u8], what: &'a str) -> Result<Header<'a>> {
    let bad = |m: String| Error::scan(what, m);
    if !bytes.starts_with(b"NRRD000") {
        return Err(bad("not a NRRD file (no NRRD000x magic)".into()));
    }
    // The header ends at the first empty line.
    let mut pos = 0;
    let mut fields = Vec::new();
    let searched = &bytes[..bytes.len().min(MAX_HEADER_BYTES)];
    loop {
        let end = searched[pos..]
            .iter()
            .position(|&b| b == b'\n')
            .map(|e| pos + e)
            .ok_or_else(|| {
                if searched.len() < bytes.len() {
                    bad(format!(
                        "no empty line ends the header within its first {MAX_HEADER_BYTES} \
                         bytes: not a NRRD header"
                    ))
                } else {
                    bad("header has no end (truncated file?)".into())
                }
            })?;
        let line = std::str::from_utf8(&bytes[pos..end])
            .map_err(|_| bad("header is not text".into()))?
            .trim_end_matches('\r');
        pos = end + 1;
        if line.is_empty() {
            break;
        }
        if line.starts_with('#') || line.starts_with("NRRD") {
            continue;
        }
        if let Some((k, v)) = line.split_once(": ") {
            fields.push((k.trim().to_ascii_lowercase(), v.trim().to_string()));
        }
    }
    Ok(Header {
        what,
        fields,
        data_start: pos,
    })
}

/// The grid size, after refusing what this reader does not support: other than 3-D, and
/// detached data files (it reads the data attached to the header only).
fn read_sizes(header: &Header) -> Result<[usize; 3]> {
    let bad = |m: String| header.error(m);
    if header.require("dimension")?.trim() != "3" {
        return Err(bad(format!(
            "only 3-D images are supported, dimension is {}",
            header.require("dimension")?
        )));
    }
    if header
        .field("data file")
        .or(header.field("datafile"))
        .is_some()
    {
        return Err(bad("detached data files are not supported".into()));
    }
    for skip in ["byte skip", "line skip"] {
        if header.field(skip).is_some_and(|v| v.trim() != "0") {
            return Err(bad(format!(
                "'{skip}: {}' is not supported (the data must follow the header)",
                header.field(skip).unwrap_or_default()
            )));
        }
    }
    let sizes: Vec<usize> = header
        .require("sizes")?
        .split_whitespace()
        .map(|s| s.parse().map_err(|_| bad(format!("bad size '{s}'"))))
        .collect::<Result<_>>()?;
    sizes
        .try_into()
        .map_err(|_| bad("'sizes' must have 3 values".into()))
}

/// Spacing, direction and origin from `space directions` and `space origin`, converted to
/// LPS (RAS files have x and y negated).
fn read_geometry(header: &Header, dims: [usize; 3]) -> Result<VolumeGeometry> {
    let bad = |m: String| header.error(m);
    let space = header.field("space").unwrap_or("left-posterior-superior");
    let flip = match space {
        "left-posterior-superior" | "LPS" => Vector3::new(1.0, 1.0, 1.0),
        "right-anterior-superior" | "RAS" => Vector3::new(-1.0, -1.0, 1.0),
        other => return Err(bad(format!("unsupported space '{other}'"))),
    };
    let vectors = parse_vectors(header.require("space directions")?).map_err(bad)?;
    let origin = match header.field("space origin") {
        Some(o) => parse_vectors(o)
            .map_err(bad)?
            .first()
            .copied()
            .unwrap_or_default(),
        None => Vector3::zeros(),
    };
    if vectors.len() != 3 {
        return Err(bad("'space directions' must have 3 vectors".into()));
    }
    let mut spacing = [0.0; 3];
    let mut direction = Matrix3::zeros();
    for (a, v) in vectors.iter().enumerate() {
        let v = v.component_mul(&flip);
        spacing[a] = v.norm();
        if spacing[a] > 0.0 {
            direction.set_column(a, &(v / spacing[a]));
        }
    }
    let origin = origin.component_mul(&flip);
    Ok(VolumeGeometry {
        dims,
        spacing_mm: spacing,
        origin_lps_mm: origin.into(),
        direction_lps: [
            direction.column(0).into_owned().into(),
            direction.column(1).into_owned().into(),
            direction.column(2).into_owned().into(),
        ],
    })
}

/// Bytes per sample and the decoder of NRRD sample type `name` (teem's spellings).
fn sample_decoder(name: &str) -> std::result::Result<(usize, SampleDecoder), String> {
    Ok(match name {
        "short" | "int16" | "signed short" | "short int" | "int16_t" => (2, |b, le| {
            (if le {
                i16::from_le_bytes([b[0], b[1]])
            } else {
                i16::from_be_bytes([b[0], b[1]])
            }) as f32
        }),
        "unsigned short" | "ushort" | "uint16" | "uint16_t" | "unsigned short int" => {
            (2, |b, le| {
                (if le {
                    u16::from_le_bytes([b[0], b[1]])
                } else {
                    u16::from_be_bytes([b[0], b[1]])
                }) as f32
            })
        }
        "uchar" | "unsigned char" | "uint8" | "uint8_t" => (1, |b, _| b[0] as f32),
        "signed char" | "int8" | "int8_t" => (1, |b, _| b[0] as i8 as f32),
        "int" | "int32" | "signed int" | "int32_t" => (4, |b, le| {
            let a = [b[0], b[1], b[2], b[3]];
            (if le {
                i32::from_le_bytes(a)
            } else {
                i32::from_be_bytes(a)
            }) as f32
        }),
        "float" => (4, |b, le| {
            let a = [b[0], b[1], b[2], b[3]];
            if le {
                f32::from_le_bytes(a)
            } else {
                f32::from_be_bytes(a)
            }
        }),
        other => return Err(format!("unsupported sample type '{other}'")),
    })
}

/// The data bytes, gunzipped if so encoded; gzip data declaring more than the ratio cap are
/// refused before inflating, output is capped one byte past `expected` so a bomb cannot fill
/// memory, and fewer than `expected` bytes is truncation.
fn read_payload<'a>(
    header: &Header,
    payload: &'a [u8],
    expected: usize,
    budget: &ScanBudget,
) -> Result<Cow<'a, [u8]>> {
    let bad = |m: String| header.error(m);
    let raw: Cow<[u8]> = match header.require("encoding")? {
        "raw" => Cow::Borrowed(payload),
        "gzip" | "gz" => {
            budget.check_inflation(
                header.what,
                "gzip data",
                payload.len() as u64,
                expected as u64,
            )?;
            let mut out = Vec::with_capacity(expected.min(MAX_PREALLOCATED_BYTES));
            flate2::read::MultiGzDecoder::new(payload)
                .take(expected as u64 + 1)
                .read_to_end(&mut out)
                .map_err(|e| {
                    bad(if e.kind() == std::io::ErrorKind::OutOfMemory {
                        format!("not enough memory to inflate the {expected} bytes of gzip data")
                    } else {
                        format!("gzip data is corrupt: {e}")
                    })
                })?;
            Cow::Owned(out)
        }
        other => return Err(bad(format!("unsupported encoding '{other}'"))),
    };
    if raw.len() < expected {
        return Err(bad(format!(
            "data truncated: {} bytes for {expected} expected",
            raw.len()
        )));
    }
    Ok(raw)
}

/// Decodes one sample from its first bytes; the flag says little endian.
type SampleDecoder = fn([u8; 8], bool) -> f32;

/// Parses `(a,b,c) (d,e,f) …`; `none` entries are skipped.
fn parse_vectors(s: &str) -> std::result::Result<Vec<Vector3<f64>>, String> {
    s.split_whitespace()
        .filter(|t| *t != "none")
        .map(|t| {
            let inner = t.trim_start_matches('(').trim_end_matches(')');
            let v: Vec<f64> = inner
                .split(',')
                .map(|x| x.trim().parse::<f64>())
                .collect::<std::result::Result<_, _>>()
                .map_err(|_| format!("bad vector '{t}'"))?;
            if v.len() != 3 {
                return Err(format!("vector '{t}' needs 3 components"));
            }
            Ok(Vector3::new(v[0], v[1], v[2]))
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn header(space: &str, enc: &str) -> String {
        format!(
            "NRRD0004\n# c\ntype: short\ndimension: 3\nspace: {space}\nsizes: 2 3 4\n\
             space directions: (2,0,0) (0,3,0) (0,0,4)\nendian: little\nencoding: {enc}\n\
             space origin: (10,20,30)\n\n"
        )
    }

    #[test]
    fn raw_lps_file_keeps_values_and_geometry() {
        let mut bytes = header("left-posterior-superior", "raw").into_bytes();
        for v in 0..24i16 {
            bytes.extend_from_slice(&(v - 5).to_le_bytes());
        }
        let vol = parse_nrrd(&bytes, "t").unwrap();
        assert_eq!(vol.geometry.dims, [2, 3, 4]);
        assert_eq!(vol.geometry.spacing_mm, [2.0, 3.0, 4.0]);
        assert_eq!(vol.geometry.origin_lps_mm, [10.0, 20.0, 30.0]);
        assert_eq!(vol.get(1, 2, 3), 18.0);
    }

    #[test]
    fn ras_file_is_converted_to_lps() {
        let mut bytes = header("right-anterior-superior", "raw").into_bytes();
        bytes.extend(std::iter::repeat_n(0u8, 48));
        let g = parse_nrrd(&bytes, "t").unwrap().geometry;
        assert_eq!(g.origin_lps_mm, [-10.0, -20.0, 30.0]);
        assert_eq!(g.direction_lps[0], [-1.0, 0.0, 0.0]);
        assert_eq!(g.direction_lps[1], [0.0, -1.0, 0.0]);
    }

    #[test]
    fn truncated_data_is_an_error_naming_the_sizes() {
        let mut bytes = header("left-posterior-superior", "raw").into_bytes();
        bytes.extend(std::iter::repeat_n(0u8, 40));
        let e = parse_nrrd(&bytes, "cut.nrrd").unwrap_err().to_string();
        assert!(e.contains("cut.nrrd") && e.contains("truncated"), "{e}");
    }
}
