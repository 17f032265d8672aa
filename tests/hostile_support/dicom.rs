//! Hostile DICOM: a small valid CT series written element by element, then truncated,
//! flipped, given absurd lengths, deep nesting, wrong VRs, missing tags and inconsistent
//! slices.

use std::collections::BTreeMap;
use std::path::Path;

use super::{flip_bytes, load, write, Case, Expect, Outcome, Rng};

/// Pixels per side of the test slices.
const N: u16 = 16;
/// Slices in the valid series.
const SLICES: usize = 4;
/// Slice spacing of the valid series, mm.
const DZ_MM: f64 = 2.5;
const EXPLICIT_LE: &str = "1.2.840.10008.1.2.1";
const IMPLICIT_LE: &str = "1.2.840.10008.1.2";
const CT_STORAGE: &str = "1.2.840.10008.5.1.4.1.1.2";
const SERIES_UID: &str = "1.2.826.0.1.3680043.2.1125.77.1";

/// VRs whose explicit encoding has a 4-byte length (PS3.5 7.1.2).
const LONG_VRS: [&[u8; 2]; 11] = [
    b"OB", b"OW", b"OF", b"SQ", b"UT", b"UN", b"UC", b"UR", b"OD", b"OL", b"OV",
];

/// A tag as (group, element).
pub type Tag = (u16, u16);

/// One element's VR and raw value (lengths written from the value unless overridden).
#[derive(Clone)]
pub struct Element {
    vr: [u8; 2],
    value: Vec<u8>,
    /// Written instead of the value's length (an absurd or lying length).
    length: Option<u32>,
}

fn el(vr: &[u8; 2], value: impl Into<Vec<u8>>) -> Element {
    Element {
        vr: *vr,
        value: value.into(),
        length: None,
    }
}

fn us(v: u16) -> Element {
    el(b"US", v.to_le_bytes().to_vec())
}

/// One slice of the test series: its data set and how to write it.
#[derive(Clone)]
pub struct Slice {
    /// Data set elements (group ≥ 0008), in tag order.
    pub elements: BTreeMap<Tag, Element>,
    /// Transfer syntax written in the meta header.
    pub transfer_syntax: String,
    /// Written after the last element (raw, e.g. nested sequences).
    pub trailer: Vec<u8>,
    /// Overrides File Meta Information Group Length.
    pub meta_length: Option<u32>,
    /// The whole file as given (a mutated copy), instead of the elements.
    pub raw: Option<Vec<u8>>,
}

impl Slice {
    /// Slice `k` of the valid series: 16 × 16 pixels of body (0 HU), lungs (−800 HU) and
    /// air outside (−1024 HU), at z = k · 2.5 mm.
    pub fn ct(k: usize) -> Slice {
        let mut e = BTreeMap::new();
        let sop = format!("{SERIES_UID}.{}", k + 1);
        e.insert((0x0008, 0x0016), el(b"UI", CT_STORAGE));
        e.insert((0x0008, 0x0018), el(b"UI", sop.as_str()));
        e.insert((0x0008, 0x0060), el(b"CS", "CT"));
        e.insert((0x0018, 0x0050), el(b"DS", "2.5"));
        e.insert((0x0020, 0x000D), el(b"UI", "1.2.826.0.1.3680043.2.1125.77"));
        e.insert((0x0020, 0x000E), el(b"UI", SERIES_UID));
        e.insert((0x0020, 0x0013), el(b"IS", (k + 1).to_string()));
        e.insert(
            (0x0020, 0x0032),
            el(b"DS", format!("-20\\-20\\{}", k as f64 * DZ_MM)),
        );
        e.insert((0x0020, 0x0037), el(b"DS", "1\\0\\0\\0\\1\\0"));
        e.insert((0x0028, 0x0002), us(1));
        e.insert((0x0028, 0x0004), el(b"CS", "MONOCHROME2"));
        e.insert((0x0028, 0x0010), us(N));
        e.insert((0x0028, 0x0011), us(N));
        e.insert((0x0028, 0x0030), el(b"DS", "2.5\\2.5"));
        e.insert((0x0028, 0x0100), us(16));
        e.insert((0x0028, 0x0101), us(16));
        e.insert((0x0028, 0x0102), us(15));
        e.insert((0x0028, 0x0103), us(1));
        e.insert((0x0028, 0x1052), el(b"DS", "-1024"));
        e.insert((0x0028, 0x1053), el(b"DS", "1"));
        e.insert((0x7FE0, 0x0010), el(b"OW", pixels()));
        Slice {
            elements: e,
            transfer_syntax: EXPLICIT_LE.into(),
            trailer: Vec::new(),
            meta_length: None,
            raw: None,
        }
    }

    /// Sets (or replaces) an element.
    pub fn set(mut self, tag: Tag, vr: &[u8; 2], value: impl Into<Vec<u8>>) -> Slice {
        self.elements.insert(tag, el(vr, value));
        self
    }

    /// Removes an element.
    pub fn without(mut self, tag: Tag) -> Slice {
        self.elements.remove(&tag);
        self
    }

    /// Writes `length` as the element's length, whatever its value holds.
    pub fn lying_length(mut self, tag: Tag, length: u32) -> Slice {
        self.elements
            .get_mut(&tag)
            .expect("element to lie about")
            .length = Some(length);
        self
    }

    /// The file's bytes: preamble, `DICM`, meta group (explicit LE) and the data set.
    pub fn bytes(&self) -> Vec<u8> {
        if let Some(raw) = &self.raw {
            return raw.clone();
        }
        let mut meta = Vec::new();
        write_explicit(&mut meta, (0x0002, 0x0001), &el(b"OB", vec![0u8, 1]));
        write_explicit(&mut meta, (0x0002, 0x0002), &el(b"UI", CT_STORAGE));
        let sop = self
            .elements
            .get(&(0x0008, 0x0018))
            .map(|e| e.value.clone());
        write_explicit(
            &mut meta,
            (0x0002, 0x0003),
            &el(b"UI", sop.unwrap_or_default()),
        );
        write_explicit(
            &mut meta,
            (0x0002, 0x0010),
            &el(b"UI", self.transfer_syntax.as_str()),
        );
        let mut out = vec![0u8; 128];
        out.extend_from_slice(b"DICM");
        let length = self.meta_length.unwrap_or(meta.len() as u32);
        write_explicit(
            &mut out,
            (0x0002, 0x0000),
            &el(b"UL", length.to_le_bytes().to_vec()),
        );
        out.extend_from_slice(&meta);
        let implicit = self.transfer_syntax == IMPLICIT_LE;
        for (&tag, e) in &self.elements {
            if tag.0 == 0x7FE0 {
                out.extend_from_slice(&self.trailer);
            }
            if implicit {
                write_implicit(&mut out, tag, e);
            } else {
                write_explicit(&mut out, tag, e);
            }
        }
        if !self.elements.keys().any(|t| t.0 == 0x7FE0) {
            out.extend_from_slice(&self.trailer);
        }
        out
    }
}

/// Pads a value to even length as PS3.5 requires (space for text, NUL for UI and binary).
fn padded(e: &Element) -> Vec<u8> {
    let mut v = e.value.clone();
    if v.len() % 2 == 1 {
        let text = matches!(
            &e.vr,
            b"CS" | b"DS" | b"IS" | b"LO" | b"SH" | b"LT" | b"ST" | b"UT" | b"PN"
        );
        v.push(if text { b' ' } else { 0 });
    }
    v
}

fn write_explicit(out: &mut Vec<u8>, tag: Tag, e: &Element) {
    let v = padded(e);
    out.extend_from_slice(&tag.0.to_le_bytes());
    out.extend_from_slice(&tag.1.to_le_bytes());
    out.extend_from_slice(&e.vr);
    let length = e.length.unwrap_or(v.len() as u32);
    if LONG_VRS.contains(&&e.vr) {
        out.extend_from_slice(&[0, 0]);
        out.extend_from_slice(&length.to_le_bytes());
    } else {
        out.extend_from_slice(&(length as u16).to_le_bytes());
    }
    out.extend_from_slice(&v);
}

fn write_implicit(out: &mut Vec<u8>, tag: Tag, e: &Element) {
    let v = padded(e);
    out.extend_from_slice(&tag.0.to_le_bytes());
    out.extend_from_slice(&tag.1.to_le_bytes());
    out.extend_from_slice(&e.length.unwrap_or(v.len() as u32).to_le_bytes());
    out.extend_from_slice(&v);
}

/// The stored values of one slice (HU + 1024): air outside a body disc holding two lungs.
fn pixels() -> Vec<u8> {
    let mut out = Vec::with_capacity(N as usize * N as usize * 2);
    for j in 0..N as i32 {
        for i in 0..N as i32 {
            let (x, y) = (i - 8, j - 8);
            let hu: i16 = if x * x + y * y > 49 {
                -1024
            } else if (2..=5).contains(&x.abs()) && y.abs() <= 3 {
                -800
            } else {
                0
            };
            out.extend_from_slice(&(hu + 1024).to_le_bytes());
        }
    }
    out
}

/// `count` nested undefined-length ContentSequence items (each in an item of the previous
/// one), written between the image attributes and the pixel data, where the tag sorts.
pub fn nested_sequences(count: usize) -> Vec<u8> {
    let mut out = Vec::with_capacity(count * 24);
    for _ in 0..count {
        out.extend_from_slice(&[0x40, 0x00, 0x30, 0xA7, b'S', b'Q', 0, 0]); // (0040,A730) SQ
        out.extend_from_slice(&u32::MAX.to_le_bytes());
        out.extend_from_slice(&[0xFE, 0xFF, 0x00, 0xE0]); // item, undefined length
        out.extend_from_slice(&u32::MAX.to_le_bytes());
    }
    for _ in 0..count {
        out.extend_from_slice(&[0xFE, 0xFF, 0x0D, 0xE0, 0, 0, 0, 0]); // item delimiter
        out.extend_from_slice(&[0xFE, 0xFF, 0xDD, 0xE0, 0, 0, 0, 0]); // sequence delimiter
    }
    out
}

/// Writes the valid series with slice `k` replaced by `edit(slice k)` (or dropped for `None`),
/// plus `extra` files, and loads the folder.
fn series_with(
    dir: &Path,
    edit: impl Fn(usize, Slice) -> Option<Slice>,
    extra: &[(String, Vec<u8>)],
) -> Outcome {
    let folder = dir.join("series");
    std::fs::create_dir_all(&folder).unwrap();
    for k in 0..SLICES {
        if let Some(s) = edit(k, Slice::ct(k)) {
            write(&folder, &format!("IM{k:04}"), &s.bytes());
        }
    }
    for (name, bytes) in extra {
        write(&folder, name, bytes);
    }
    load(&folder)
}

/// One file alone in a folder.
fn single(dir: &Path, bytes: &[u8]) -> Outcome {
    let folder = dir.join("one");
    write(&folder, "IM0001", bytes);
    load(&folder)
}

/// Slice 1 of the series replaced by `slice`.
fn second_is(slice: impl Fn() -> Slice + 'static) -> impl Fn(&Path) -> Outcome + 'static {
    move |dir| series_with(dir, |k, s| Some(if k == 1 { slice() } else { s }), &[])
}

/// Every slice edited by `edit`.
fn every(edit: impl Fn(Slice) -> Slice + 'static) -> impl Fn(&Path) -> Outcome + 'static {
    move |dir| series_with(dir, |_, s| Some(edit(s)), &[])
}

/// The DICOM cases.
pub fn cases() -> Vec<Case> {
    use Expect::*;
    let mut c = vec![
        Case::new(
            "valid series (explicit VR)",
            Accepted(&["grid [16, 16, 4]"]),
            every(|s| s),
        ),
        Case::new(
            "valid series (implicit VR)",
            Accepted(&["grid [16, 16, 4]"]),
            every(|mut s| {
                s.transfer_syntax = IMPLICIT_LE.into();
                s
            }),
        ),
    ];
    let full = Slice::ct(0).bytes();
    let pixel_start = full.len() - (N as usize * N as usize * 2);
    for cut in [
        0,
        1,
        64,
        128,
        131,
        132,
        140,
        160,
        200,
        300,
        pixel_start - 4,
        pixel_start + 10,
        full.len() - 1,
    ] {
        let bytes = full[..cut].to_vec();
        c.push(Case::new(
            format!("single file truncated to {cut} bytes"),
            Refused(&["IM0001"]),
            move |dir| single(dir, &bytes),
        ));
    }
    for cut in [132, 300, pixel_start + 100] {
        let bytes = full[..cut].to_vec();
        c.push(Case::new(
            format!("a file truncated to {cut} bytes beside the series"),
            Accepted(&["grid [16, 16, 4]", "junk.dcm"]),
            move |dir| series_with(dir, |_, s| Some(s), &[("junk.dcm".into(), bytes.clone())]),
        ));
    }
    for seed in 0..24u64 {
        let case = Case::new(
            format!("slice 2 with header bytes flipped (seed {seed})"),
            Either("series"),
            move |dir| {
                series_with(
                    dir,
                    |k, s| {
                        let mut bytes = s.bytes();
                        if k == 2 {
                            let mut rng = Rng::new(seed);
                            let count = 1 + rng.below(8);
                            flip_bytes(&mut bytes, 128..pixel_start, count, &mut rng);
                        }
                        // Flipped bytes are written as they are: no re-encoding.
                        Some(Slice::raw(bytes))
                    },
                    &[],
                )
            },
        );
        // Seeds 2, 8, 12, 17, 19, 21 and 23 made dicom-rs allocate 745–905 MiB for this 2 kB
        // file before the bounded pre-scan.
        c.push(case);
    }
    c.extend(length_cases());
    c.extend(vr_and_tag_cases());
    c.extend(series_cases());
    c
}

impl Slice {
    /// A slice whose bytes are given as they are (written by [`series_with`] unchanged).
    fn raw(bytes: Vec<u8>) -> Slice {
        let mut s = Slice::ct(0);
        s.raw = Some(bytes);
        s
    }
}

/// Absurd and lying lengths, and deep nesting.
fn length_cases() -> Vec<Case> {
    use Expect::*;
    let mut c = vec![
        Case::new(
            "private OB element declaring 0xFFFFFFF0 bytes",
            Refused(&["IM0001", "declares 4294967280 bytes"]),
            |dir| {
                single(
                    dir,
                    &Slice::ct(0)
                        .set((0x0009, 0x0010), b"OB", vec![0u8; 4])
                        .lying_length((0x0009, 0x0010), 0xFFFF_FFF0)
                        .bytes(),
                )
            },
        ),
        Case::new(
            "pixel data declaring 0xFFFFFFF0 bytes",
            Refused(&["IM0001", "declares 4294967280 bytes"]),
            |dir| {
                single(
                    dir,
                    &Slice::ct(0)
                        .lying_length((0x7FE0, 0x0010), 0xFFFF_FFF0)
                        .bytes(),
                )
            },
        ),
        Case::new(
            "20 files declaring 0xFFFFFFF0 bytes beside the series",
            Accepted(&["grid [16, 16, 4]", "bad19.dcm"]),
            |dir| {
                let bad = Slice::ct(0)
                    .set((0x0009, 0x0010), b"OB", vec![0u8; 4])
                    .lying_length((0x0009, 0x0010), 0xFFFF_FFF0)
                    .bytes();
                let extra: Vec<(String, Vec<u8>)> = (0..20)
                    .map(|i| (format!("bad{i}.dcm"), bad.clone()))
                    .collect();
                series_with(dir, |_, s| Some(s), &extra)
            },
        ),
        Case::new(
            "UN element declaring 0x7FFFFFFF bytes",
            Refused(&["IM0001"]),
            |dir| {
                single(
                    dir,
                    &Slice::ct(0)
                        .set((0x0009, 0x0011), b"UN", vec![0u8; 8])
                        .lying_length((0x0009, 0x0011), 0x7FFF_FFFF)
                        .bytes(),
                )
            },
        ),
        Case::new(
            "text element declaring 0xFFFE bytes past the end",
            Refused(&["IM0001"]),
            |dir| {
                single(
                    dir,
                    &Slice::ct(0)
                        .without((0x7FE0, 0x0010))
                        .set((0x0008, 0x0070), b"LO", "GE")
                        .lying_length((0x0008, 0x0070), 0xFFFE)
                        .bytes(),
                )
            },
        ),
        Case::new(
            "pixel data 2 bytes short of Rows × Columns",
            // The short file is skipped; the refusal names the gap it leaves and the file
            // with its reason.
            Refused(&[
                "missing slice",
                "skipped and may be the missing part",
                "IM0001",
            ]),
            second_is(|| Slice::ct(1).set((0x7FE0, 0x0010), b"OW", pixels()[..510].to_vec())),
        ),
        Case::new(
            "Rows and Columns 65535 over 512 bytes of pixels",
            Refused(&["65535×65535", "IM0001"]),
            second_is(|| {
                Slice::ct(1)
                    .set((0x0028, 0x0010), b"US", 65535u16.to_le_bytes().to_vec())
                    .set((0x0028, 0x0011), b"US", 65535u16.to_le_bytes().to_vec())
            }),
        ),
        Case::new(
            "200 000 nested undefined-length sequences",
            Refused(&["IM0001", "nest"]),
            |dir| {
                let mut s = Slice::ct(0);
                s.trailer = nested_sequences(200_000);
                single(dir, &s.bytes())
            },
        ),
        Case::new(
            "200 000 nested sequences in one file beside the series",
            Accepted(&["grid [16, 16, 4]", "deep.dcm"]),
            |dir| {
                let mut s = Slice::ct(0);
                s.trailer = nested_sequences(200_000);
                series_with(dir, |_, s| Some(s), &[("deep.dcm".into(), s.bytes())])
            },
        ),
        Case::new(
            "8 nested sequences (allowed)",
            Accepted(&["grid [16, 16, 4]"]),
            second_is(|| {
                let mut s = Slice::ct(1);
                s.trailer = nested_sequences(8);
                s
            }),
        ),
    ];
    for (name, length) in [
        ("0", 0u32),
        ("0xFFFFFFFF", u32::MAX),
        ("2 too many", 0),
        ("2 too few", 0),
    ] {
        let lie = name.starts_with('2');
        let more = name.contains("many");
        c.push(Case::new(
            format!("meta group length {name}"),
            Either("series"),
            move |dir| {
                series_with(
                    dir,
                    |k, mut s| {
                        if k == 1 {
                            let true_length = {
                                let b = s.bytes();
                                u32::from_le_bytes([b[140], b[141], b[142], b[143]])
                            };
                            s.meta_length = Some(if lie {
                                if more {
                                    true_length + 2
                                } else {
                                    true_length - 2
                                }
                            } else {
                                length
                            });
                        }
                        Some(s)
                    },
                    &[],
                )
            },
        ));
    }
    c
}

/// Wrong VRs, nonsense values and missing tags.
fn vr_and_tag_cases() -> Vec<Case> {
    use Expect::*;
    let mut c = vec![
        Case::new(
            "Modality MR",
            Refused(&["MR"]),
            every(|s| s.set((0x0008, 0x0060), b"CS", "MR")),
        ),
        Case::new(
            "Modality written as UN",
            Accepted(&["grid [16, 16, 4]"]),
            every(|s| s.set((0x0008, 0x0060), b"UN", "CT")),
        ),
        Case::new(
            "Rows and Columns written as UN",
            Accepted(&["grid [16, 16, 4]"]),
            every(|s| {
                s.set((0x0028, 0x0010), b"UN", N.to_le_bytes().to_vec())
                    .set((0x0028, 0x0011), b"UN", N.to_le_bytes().to_vec())
            }),
        ),
        Case::new(
            "geometry written as UN",
            Accepted(&["grid [16, 16, 4]"]),
            every(|s| {
                let ipp = s.elements[&(0x0020, 0x0032)].value.clone();
                s.set((0x0020, 0x0032), b"UN", ipp)
                    .set((0x0020, 0x0037), b"UN", "1\\0\\0\\0\\1\\0")
                    .set((0x0028, 0x0030), b"UN", "2.5\\2.5")
            }),
        ),
        Case::new(
            "Rows written as DS text",
            Either("series"),
            second_is(|| Slice::ct(1).set((0x0028, 0x0010), b"DS", "16")),
        ),
        Case::new(
            "PixelSpacing 'abc\\def'",
            Refused(&["PixelSpacing"]),
            every(|s| s.set((0x0028, 0x0030), b"DS", "abc\\def")),
        ),
        Case::new(
            "PixelSpacing 0",
            Refused(&["spacing"]),
            every(|s| s.set((0x0028, 0x0030), b"DS", "0\\0")),
        ),
        Case::new(
            "PixelSpacing negative",
            Refused(&["spacing"]),
            every(|s| s.set((0x0028, 0x0030), b"DS", "-2.5\\2.5")),
        ),
        Case::new(
            "PixelSpacing NaN",
            Refused(&["spacing"]),
            every(|s| s.set((0x0028, 0x0030), b"DS", "NaN\\2.5")),
        ),
        Case::new(
            "ImagePositionPatient NaN",
            Refused(&["ImagePositionPatient"]),
            second_is(|| Slice::ct(1).set((0x0020, 0x0032), b"DS", "nan\\0\\2.5")),
        ),
        Case::new(
            "ImagePositionPatient with 2 values",
            Refused(&["ImagePositionPatient"]),
            second_is(|| Slice::ct(1).set((0x0020, 0x0032), b"DS", "0\\2.5")),
        ),
        Case::new(
            "ImageOrientationPatient all zero",
            Refused(&["orientation"]),
            every(|s| s.set((0x0020, 0x0037), b"DS", "0\\0\\0\\0\\0\\0")),
        ),
        Case::new(
            "ImageOrientationPatient rows parallel",
            Refused(&["orientation"]),
            every(|s| s.set((0x0020, 0x0037), b"DS", "1\\0\\0\\1\\0\\0")),
        ),
        Case::new(
            "RescaleSlope 'abc'",
            Refused(&["RescaleSlope"]),
            every(|s| s.set((0x0028, 0x1053), b"DS", "abc")),
        ),
        Case::new(
            "RescaleSlope infinite",
            Refused(&["slope"]),
            every(|s| s.set((0x0028, 0x1053), b"DS", "1e999")),
        ),
        Case::new(
            "BitsAllocated 12",
            Refused(&["BitsAllocated"]),
            every(|s| s.set((0x0028, 0x0100), b"US", 12u16.to_le_bytes().to_vec())),
        ),
        Case::new(
            "BitsAllocated 64 over 16-bit data",
            Refused(&["IM0001"]),
            every(|s| s.set((0x0028, 0x0100), b"US", 64u16.to_le_bytes().to_vec())),
        ),
        Case::new(
            "SamplesPerPixel 3 (RGB)",
            Refused(&["3 samples per pixel", "IM0000"]),
            every(|s| {
                s.set((0x0028, 0x0002), b"US", 3u16.to_le_bytes().to_vec())
                    .set((0x0028, 0x0004), b"CS", "RGB")
                    .set((0x0028, 0x0006), b"US", 0u16.to_le_bytes().to_vec())
                    .set((0x7FE0, 0x0010), b"OW", pixels().repeat(3))
            }),
        ),
        Case::new(
            "float pixel data instead of pixel data",
            Refused(&["float"]),
            every(|s| {
                let v = s.elements[&(0x7FE0, 0x0010)].value.clone();
                s.without((0x7FE0, 0x0010))
                    .set((0x7FE0, 0x0008), b"OF", [v.clone(), v].concat())
            }),
        ),
        Case::new(
            "unknown transfer syntax",
            Refused(&["1.2.3.4.5"]),
            every(|mut s| {
                s.transfer_syntax = "1.2.3.4.5".into();
                s
            }),
        ),
        // Native pixel data under an encapsulated syntax: read as native, leniently.
        Case::new(
            "JPEG baseline declared over native pixels",
            Accepted(&["grid [16, 16, 4]"]),
            every(|mut s| {
                s.transfer_syntax = "1.2.840.10008.1.2.4.50".into();
                s
            }),
        ),
    ];
    for (tag, name, want) in [
        ((0x0028, 0x0010), "Rows", "Rows"),
        ((0x0028, 0x0011), "Columns", "Columns"),
        ((0x7FE0, 0x0010), "PixelData", "pixel data"),
        (
            (0x0020, 0x0032),
            "ImagePositionPatient",
            "ImagePositionPatient",
        ),
        (
            (0x0020, 0x0037),
            "ImageOrientationPatient",
            "ImageOrientationPatient",
        ),
        ((0x0028, 0x0030), "PixelSpacing", "PixelSpacing"),
        ((0x0008, 0x0060), "Modality", "Modality"),
        ((0x0028, 0x0100), "BitsAllocated", "BitsAllocated"),
    ] {
        let words: &'static [&'static str] = Box::leak(Box::new([want]));
        let case = Case::new(
            format!("every slice without {name}"),
            Refused(words),
            every(move |s| s.without(tag)),
        );
        // Rows is the "Rows deleted" row: once "found modality CT … (CT, 79 files)".
        c.push(case);
    }
    c
}

/// Inconsistent slices of one series.
fn series_cases() -> Vec<Case> {
    use Expect::*;
    vec![
        // Files without a series UID are one series, as long as their geometry agrees.
        Case::new(
            "every slice without SeriesInstanceUID",
            Accepted(&["grid [16, 16, 4]"]),
            every(|s| s.without((0x0020, 0x000E))),
        ),
        Case::new(
            "a missing slice in the middle",
            Refused(&["missing"]),
            |dir| series_with(dir, |k, s| (k != 2).then_some(s), &[]),
        ),
        Case::new(
            "a duplicate slice",
            Accepted(&["grid [16, 16, 4]", "duplicate"]),
            |dir| {
                series_with(
                    dir,
                    |_, s| Some(s),
                    &[("copy.dcm".into(), Slice::ct(1).bytes())],
                )
            },
        ),
        Case::new(
            "two slices at one position with different pixels",
            Refused(&["position"]),
            |dir| {
                let mut other = Slice::ct(1).set((0x0008, 0x0018), b"UI", "1.2.3.99");
                other.elements.get_mut(&(0x7FE0, 0x0010)).unwrap().value[0] ^= 0x40;
                series_with(dir, |_, s| Some(s), &[("other.dcm".into(), other.bytes())])
            },
        ),
        Case::new(
            "gantry tilt (slices sheared along y)",
            Refused(&["tilt"]),
            |dir| {
                series_with(
                    dir,
                    |k, s| {
                        let ipp = format!("-20\\{}\\{}", -20.0 + k as f64 * 1.5, k as f64 * DZ_MM);
                        Some(s.set((0x0020, 0x0032), b"DS", ipp))
                    },
                    &[],
                )
            },
        ),
        Case::new(
            "slice 3 with 8 rows",
            Refused(&["rows"]),
            second_is(|| {
                Slice::ct(1)
                    .set((0x0028, 0x0010), b"US", 8u16.to_le_bytes().to_vec())
                    .set((0x7FE0, 0x0010), b"OW", pixels()[..256].to_vec())
            }),
        ),
        Case::new(
            "slice 3 with another orientation",
            Refused(&["orientation"]),
            second_is(|| Slice::ct(1).set((0x0020, 0x0037), b"DS", "0\\1\\0\\1\\0\\0")),
        ),
        Case::new(
            "slice 3 with another pixel spacing",
            Refused(&["spacing"]),
            second_is(|| Slice::ct(1).set((0x0028, 0x0030), b"DS", "2\\2")),
        ),
        Case::new(
            "every slice at the same position",
            Refused(&["position"]),
            |dir| {
                series_with(
                    dir,
                    |k, s| {
                        Some(s.set((0x0020, 0x0032), b"DS", "-20\\-20\\0").set(
                            (0x0008, 0x0018),
                            b"UI",
                            format!("1.2.3.{k}"),
                        ))
                    },
                    &[],
                )
            },
        ),
        Case::new("two CT series", Refused(&["series"]), |dir| {
            let other: Vec<(String, Vec<u8>)> = (0..SLICES)
                .map(|k| {
                    (
                        format!("B{k}"),
                        Slice::ct(k)
                            .set((0x0020, 0x000E), b"UI", "1.2.3.4.2")
                            .bytes(),
                    )
                })
                .collect();
            series_with(dir, |_, s| Some(s), &other)
        }),
        Case::new(
            "a folder of non-DICOM files",
            Refused(&["no readable DICOM"]),
            |dir| {
                let folder = dir.join("junk");
                write(&folder, "a.txt", b"hello");
                write(&folder, "b.bin", &[0u8; 1000]);
                load(&folder)
            },
        ),
        Case::new("an empty folder", Refused(&["no files"]), |dir| {
            let folder = dir.join("empty");
            std::fs::create_dir_all(&folder).unwrap();
            load(&folder)
        }),
    ]
}

/// The fuzzer's findings (`tests/data/fuzz/dicom_series/`, see its README), each read as the
/// `dicom_series` target reads it: alone in a folder. Each must be refused, naming the file,
/// within the time and memory limits (under the 2 GiB address space: a reader that still
/// asked for the gigabytes a finding declares would abort the child).
pub fn fuzz_finding_cases() -> Vec<Case> {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/fuzz/dicom_series");
    let mut files: Vec<_> = std::fs::read_dir(&dir)
        .map(|rd| rd.map(|e| e.unwrap().path()).collect())
        .unwrap_or_default();
    files.retain(|p| p.extension().is_some_and(|x| x == "dcm"));
    files.sort();
    files
        .into_iter()
        .map(|path| {
            let name = path.file_name().unwrap().to_string_lossy().into_owned();
            // These once passed the pre-scan and had dicom-rs ask for 4 GB (refused under
            // `ulimit -v` only because the allocation failed): now the pre-scan names them.
            let words: &'static [&'static str] = if name.starts_with("oom-odd-length") {
                &["IM0001", "not a whole number of its VR"]
            } else {
                &["IM0001"]
            };
            Case::new(
                format!("fuzz finding {name}"),
                Expect::Refused(words),
                move |dir| single(dir, &std::fs::read(&path).unwrap()),
            )
        })
        .collect()
}
