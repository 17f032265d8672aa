//! Hostile NIfTI, NRRD and MetaImage: absurd dims, bad spacing, bad offsets, truncation,
//! gzip bombs, unknown types.

use std::io::Write;
use std::path::Path;

use super::{flip_bytes, load, write, Case, Expect, Outcome, Rng};

/// The test volume's grid.
const DIMS: [usize; 3] = [16, 16, 4];

/// HU values of a small CT (air outside a body with two lungs), i fastest.
fn ct_values() -> Vec<i16> {
    let mut v = Vec::new();
    for _k in 0..DIMS[2] {
        for j in 0..16i32 {
            for i in 0..16i32 {
                let (x, y) = (i - 8, j - 8);
                v.push(if x * x + y * y > 49 {
                    -1024
                } else if (2..=5).contains(&x.abs()) && y.abs() <= 3 {
                    -800
                } else {
                    0
                });
            }
        }
    }
    v
}

fn gzip(bytes: &[u8]) -> Vec<u8> {
    let mut e = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::fast());
    e.write_all(bytes).unwrap();
    e.finish().unwrap()
}

/// A NIfTI-1 header for the test volume (int16, 2.5 mm, sform and qform), to edit.
pub struct Nifti {
    /// The 348 header bytes plus the 4-byte extension flag.
    pub header: Vec<u8>,
    /// Voxel bytes after the header.
    pub data: Vec<u8>,
}

impl Nifti {
    /// The valid test CT.
    pub fn ct() -> Nifti {
        let mut h = vec![0u8; 352];
        put_i32(&mut h, 0, 348);
        for (n, d) in [3i16, 16, 16, 4, 1, 1, 1, 1].iter().enumerate() {
            put_i16(&mut h, 40 + 2 * n, *d);
        }
        put_i16(&mut h, 70, 4); // int16
        put_i16(&mut h, 72, 16);
        for (n, p) in [1.0f32, 2.5, 2.5, 2.5, 0.0, 0.0, 0.0, 0.0]
            .iter()
            .enumerate()
        {
            put_f32(&mut h, 76 + 4 * n, *p);
        }
        put_f32(&mut h, 108, 352.0);
        put_f32(&mut h, 112, 1.0);
        put_i16(&mut h, 252, 1); // qform_code
        put_i16(&mut h, 254, 1); // sform_code
        put_f32(&mut h, 268, 20.0);
        put_f32(&mut h, 272, 20.0);
        for (row, values) in [
            [-2.5f32, 0.0, 0.0, 20.0],
            [0.0, -2.5, 0.0, 20.0],
            [0.0, 0.0, 2.5, 0.0],
        ]
        .iter()
        .enumerate()
        {
            for (n, v) in values.iter().enumerate() {
                put_f32(&mut h, 280 + 16 * row + 4 * n, *v);
            }
        }
        h[344..348].copy_from_slice(b"n+1\0");
        let data = ct_values().iter().flat_map(|v| v.to_le_bytes()).collect();
        Nifti { header: h, data }
    }

    /// Sets a little-endian i16 field.
    pub fn i16(mut self, offset: usize, v: i16) -> Nifti {
        put_i16(&mut self.header, offset, v);
        self
    }

    /// Sets a little-endian f32 field.
    pub fn f32(mut self, offset: usize, v: f32) -> Nifti {
        put_f32(&mut self.header, offset, v);
        self
    }

    /// Header and data.
    pub fn bytes(&self) -> Vec<u8> {
        [self.header.clone(), self.data.clone()].concat()
    }
}

fn put_i16(h: &mut [u8], at: usize, v: i16) {
    h[at..at + 2].copy_from_slice(&v.to_le_bytes());
}
fn put_i32(h: &mut [u8], at: usize, v: i32) {
    h[at..at + 4].copy_from_slice(&v.to_le_bytes());
}
fn put_f32(h: &mut [u8], at: usize, v: f32) {
    h[at..at + 4].copy_from_slice(&v.to_le_bytes());
}

/// Loads `bytes` written as `name`.
fn load_as(dir: &Path, name: &str, bytes: &[u8]) -> Outcome {
    load(&write(dir, name, bytes))
}

fn nii(edit: impl Fn(Nifti) -> Nifti + 'static) -> impl Fn(&Path) -> Outcome + 'static {
    move |dir| load_as(dir, "ct.nii", &edit(Nifti::ct()).bytes())
}

fn nii_gz(edit: impl Fn(Nifti) -> Nifti + 'static) -> impl Fn(&Path) -> Outcome + 'static {
    move |dir| load_as(dir, "ct.nii.gz", &gzip(&edit(Nifti::ct()).bytes()))
}

/// A gzip of `header` followed by `zero_bytes` zeros, as concatenated members of 64 MiB
/// (cheap to make; MultiGz readers inflate them all).
fn gzip_bomb(header: &[u8], zero_bytes: u64) -> Vec<u8> {
    const MEMBER: usize = 64 << 20;
    let member = gzip(&vec![0u8; MEMBER]);
    let mut out = gzip(header);
    for _ in 0..zero_bytes.div_ceil(MEMBER as u64) {
        out.extend_from_slice(&member);
    }
    out
}

/// The NIfTI cases.
pub fn nifti_cases() -> Vec<Case> {
    use Expect::*;
    let mut c = vec![
        Case::new("valid .nii", Accepted(&["grid [16, 16, 4]"]), nii(|n| n)),
        Case::new(
            "valid .nii.gz",
            Accepted(&["grid [16, 16, 4]"]),
            nii_gz(|n| n),
        ),
        Case::new("dim[0] 0", Refused(&["dim"]), nii(|n| n.i16(40, 0))),
        Case::new("dim[0] 8", Refused(&["dim"]), nii(|n| n.i16(40, 8))),
        Case::new("dim[1] 0", Refused(&["dim[1] = 0"]), nii(|n| n.i16(42, 0))),
        Case::new("dim[2] −5", Refused(&["-5"]), nii(|n| n.i16(44, -5))),
        Case::new(
            "dims 32767³ over 2 kB",
            Refused(&["32767"]),
            nii(|n| n.i16(42, 32767).i16(44, 32767).i16(46, 32767)),
        ),
        Case::new(
            "dims 16 384 × 16 384 × 8 over 2 kB",
            Refused(&["ct.nii"]),
            nii(|n| n.i16(42, 16384).i16(44, 16384).i16(46, 8)),
        ),
        Case::new(
            "5 components per voxel",
            Refused(&["ct.nii"]),
            nii(|n| n.i16(40, 5).i16(50, 5)),
        ),
        Case::new(
            "pixdim NaN",
            Refused(&["spacing"]),
            nii(|n| n.f32(80, f32::NAN)),
        ),
        Case::new("pixdim 0", Refused(&["spacing"]), nii(|n| n.f32(84, 0.0))),
        Case::new(
            "pixdim 1e9",
            Refused(&["spacing"]),
            nii(|n| n.f32(88, 1e9).f32(280 + 40, 1e9)),
        ),
        Case::new("vox_offset 0", Either("ct.nii"), nii(|n| n.f32(108, 0.0))),
        Case::new(
            "vox_offset 1e9",
            Refused(&["ct.nii"]),
            nii(|n| n.f32(108, 1e9)),
        ),
        Case::new(
            "vox_offset NaN",
            Refused(&["vox_offset"]),
            nii(|n| n.f32(108, f32::NAN)),
        ),
        Case::new(
            "vox_offset −352",
            Refused(&["vox_offset"]),
            nii(|n| n.f32(108, -352.0)),
        ),
        Case::new("datatype 0", Refused(&["datatype"]), nii(|n| n.i16(70, 0))),
        Case::new("datatype 999", Refused(&["999"]), nii(|n| n.i16(70, 999))),
        Case::new(
            "datatype complex64",
            Refused(&["datatype"]),
            nii(|n| n.i16(70, 32).i16(72, 64)),
        ),
        Case::new(
            "datatype RGB24",
            Refused(&["datatype"]),
            nii(|n| n.i16(70, 128).i16(72, 24)),
        ),
        Case::new(
            "bitpix 8 for int16",
            Either("ct.nii"),
            nii(|n| n.i16(72, 8)),
        ),
        Case::new(
            "scl_slope NaN (unset, as nibabel)",
            Accepted(&["grid [16, 16, 4]"]),
            nii(|n| n.f32(112, f32::NAN)),
        ),
        Case::new(
            "scl_inter infinite",
            Refused(&["ct.nii"]),
            nii(|n| n.f32(112, 2.0).f32(116, f32::INFINITY)),
        ),
        Case::new(
            "qform quaternion b = c = d = 5",
            Refused(&["quaternion"]),
            nii(|n| n.i16(254, 0).f32(256, 5.0).f32(260, 5.0).f32(264, 5.0)),
        ),
        Case::new(
            "singular sform",
            Refused(&["singular sform", "srow_x"]),
            nii(|n| {
                n.i16(252, 0)
                    .f32(280, 0.0)
                    .f32(296 + 4, 0.0)
                    .f32(312 + 8, 0.0)
            }),
        ),
        Case::new(
            "sform with NaN",
            Refused(&["non-finite", "srow_x"]),
            nii(|n| n.i16(252, 0).f32(284, f32::NAN)),
        ),
        Case::new(
            "40 mm slices",
            Refused(&["40 mm"]),
            nii(|n| n.f32(88, 40.0).f32(312 + 8, 40.0)),
        ),
        Case::new(
            "magic 'xyz'",
            Refused(&["magic"]),
            nii(|n| {
                let mut n = n;
                n.header[344..348].copy_from_slice(b"xyz\0");
                n
            }),
        ),
        Case::new("header cut at 100 bytes", Refused(&["ct.nii"]), |dir| {
            load_as(dir, "ct.nii", &Nifti::ct().bytes()[..100])
        }),
        Case::new("data cut in half", Refused(&["ct.nii"]), |dir| {
            let b = Nifti::ct().bytes();
            load_as(dir, "ct.nii", &b[..b.len() - 1024])
        }),
        Case::new("empty file", Refused(&["ct.nii"]), |dir| {
            load_as(dir, "ct.nii", b"")
        }),
        Case::new("gzip cut in half", Refused(&["ct.nii.gz"]), |dir| {
            let g = gzip(&Nifti::ct().bytes());
            load_as(dir, "ct.nii.gz", &g[..g.len() / 2])
        }),
        Case::new("gzip with a wrong CRC", Refused(&["ct.nii.gz"]), |dir| {
            let mut g = gzip(&Nifti::ct().bytes());
            let n = g.len();
            g[n - 8] ^= 0xFF;
            load_as(dir, "ct.nii.gz", &g)
        }),
        Case::new(
            "gzip bomb: 4 MB inflating to 2048 × 1024 × 1024 int16 zeros",
            Refused(&["budget"]),
            |dir| {
                let header = Nifti::ct().i16(42, 2048).i16(44, 1024).i16(46, 1024).header;
                load_as(
                    dir,
                    "ct.nii.gz",
                    &gzip_bomb(&header, 2048 * 1024 * 1024 * 2),
                )
            },
        ),
        Case::new(
            "gzip stream 64 MiB longer than the volume",
            Either("ct.nii.gz"),
            |dir| {
                let mut bytes = Nifti::ct().bytes();
                bytes.extend(std::iter::repeat_n(0u8, 64 << 20));
                load_as(dir, "ct.nii.gz", &gzip(&bytes))
            },
        ),
        Case::new("extension with esize 0x7FFFFFF0", Either("ct.nii"), |dir| {
            let mut n = Nifti::ct().f32(108, 368.0);
            n.header[348] = 1;
            n.header.extend_from_slice(&0x7FFF_FFF0i32.to_le_bytes());
            n.header.extend_from_slice(&[0u8; 12]);
            load_as(dir, "ct.nii", &n.bytes())
        }),
    ];
    for seed in 0..12u64 {
        c.push(Case::new(
            format!("header bytes flipped (seed {seed})"),
            Either("ct.nii"),
            move |dir| {
                let mut b = Nifti::ct().bytes();
                let mut rng = Rng::new(1000 + seed);
                let count = 1 + rng.below(6);
                flip_bytes(&mut b, 0..348, count, &mut rng);
                load_as(dir, "ct.nii", &b)
            },
        ));
    }
    c
}

/// A NRRD of the test volume with `fields` (`key: value` lines) after the type line.
fn nrrd(fields: &str, payload: &[u8]) -> Vec<u8> {
    let head = format!("NRRD0004\ntype: short\ndimension: 3\n{fields}\n\n");
    [head.as_bytes(), payload].concat()
}

const NRRD_GEOMETRY: &str = "space: left-posterior-superior\nsizes: 16 16 4\nspace directions: (2.5,0,0) (0,2.5,0) (0,0,2.5)\nspace origin: (0,0,0)\nendian: little";

fn raw_payload() -> Vec<u8> {
    ct_values().iter().flat_map(|v| v.to_le_bytes()).collect()
}

fn nrrd_case(name: &str, expect: Expect, fields: String, payload: Vec<u8>) -> Case {
    Case::new(name, expect, move |dir| {
        load_as(dir, "ct.nrrd", &nrrd(&fields, &payload))
    })
}

/// The NRRD cases.
pub fn nrrd_cases() -> Vec<Case> {
    use Expect::*;
    let raw = raw_payload();
    let with = |replace: &str, by: &str| NRRD_GEOMETRY.replace(replace, by) + "\nencoding: raw";
    let mut c = vec![
        nrrd_case(
            "valid raw",
            Accepted(&["grid [16, 16, 4]"]),
            format!("{NRRD_GEOMETRY}\nencoding: raw"),
            raw.clone(),
        ),
        nrrd_case(
            "valid gzip",
            Accepted(&["grid [16, 16, 4]"]),
            format!("{NRRD_GEOMETRY}\nencoding: gzip"),
            gzip(&raw),
        ),
        nrrd_case(
            "sizes 100000³",
            Refused(&["absurd"]),
            with("sizes: 16 16 4", "sizes: 100000 100000 100000"),
            raw.clone(),
        ),
        nrrd_case(
            "sizes 16384 × 16384 × 8 over 2 kB",
            Refused(&["ct.nrrd"]),
            with("sizes: 16 16 4", "sizes: 16384 16384 8"),
            raw.clone(),
        ),
        nrrd_case(
            "sizes −16",
            Refused(&["size '-16'"]),
            with("sizes: 16 16 4", "sizes: -16 16 4"),
            raw.clone(),
        ),
        nrrd_case(
            "sizes with 2 values",
            Refused(&["sizes"]),
            with("sizes: 16 16 4", "sizes: 16 16"),
            raw.clone(),
        ),
        nrrd_case(
            "sizes 2^64",
            Refused(&["size '18446744073709551616'"]),
            with("sizes: 16 16 4", "sizes: 18446744073709551616 1 1"),
            raw.clone(),
        ),
        nrrd_case(
            "no sizes",
            Refused(&["sizes"]),
            with("sizes: 16 16 4\n", ""),
            raw.clone(),
        ),
        nrrd_case(
            "space directions NaN",
            Refused(&["ct.nrrd"]),
            with("(2.5,0,0)", "(nan,0,0)"),
            raw.clone(),
        ),
        nrrd_case(
            "space directions zero vector",
            Refused(&["ct.nrrd"]),
            with("(2.5,0,0)", "(0,0,0)"),
            raw.clone(),
        ),
        nrrd_case(
            "space directions none",
            Refused(&["ct.nrrd"]),
            with("(2.5,0,0)", "none"),
            raw.clone(),
        ),
        nrrd_case(
            "space origin infinite",
            Refused(&["origin"]),
            with("space origin: (0,0,0)", "space origin: (inf,0,0)"),
            raw.clone(),
        ),
        nrrd_whole(
            "type quaternion",
            Refused(&["type"]),
            format!("NRRD0004\ntype: quaternion\ndimension: 3\n{NRRD_GEOMETRY}\nencoding: raw\n\n"),
            raw.clone(),
        ),
        nrrd_case(
            "encoding bzip2",
            Refused(&["bzip2"]),
            format!("{NRRD_GEOMETRY}\nencoding: bzip2"),
            raw.clone(),
        ),
        nrrd_case(
            "raw data cut in half",
            Refused(&["ct.nrrd"]),
            format!("{NRRD_GEOMETRY}\nencoding: raw"),
            raw[..raw.len() / 2].to_vec(),
        ),
        nrrd_case(
            "gzip data cut in half",
            Refused(&["ct.nrrd"]),
            format!("{NRRD_GEOMETRY}\nencoding: gzip"),
            {
                let g = gzip(&raw);
                g[..g.len() / 2].to_vec()
            },
        ),
        nrrd_case(
            "detached data file /etc/passwd",
            Refused(&["ct.nrrd"]),
            format!("{NRRD_GEOMETRY}\nencoding: raw\ndata file: /etc/passwd"),
            Vec::new(),
        ),
        nrrd_whole(
            "header without its blank line",
            Refused(&["header has no end"]),
            format!("NRRD0004\ntype: short\ndimension: 3\n{NRRD_GEOMETRY}\nencoding: raw\n"),
            Vec::new(),
        ),
        nrrd_case(
            "a 4 MB content line",
            Refused(&["first 1048576 bytes", "not a NRRD header"]),
            format!(
                "{NRRD_GEOMETRY}\nencoding: raw\ncontent: {}",
                "x".repeat(4 << 20)
            ),
            raw.clone(),
        ),
        nrrd_case(
            "gzip stream 1 GiB longer than the data (not inflated)",
            Accepted(&["grid [16, 16, 4]"]),
            format!("{NRRD_GEOMETRY}\nencoding: gzip"),
            gzip_bomb(&raw, 1 << 30),
        ),
        nrrd_case(
            "gzip bomb: 1 MB inflating to 1024 × 1024 × 512 zeros",
            Refused(&["budget"]),
            with("sizes: 16 16 4", "sizes: 1024 1024 512")
                .replace("encoding: raw", "encoding: gzip"),
            gzip_bomb(&[], 1 << 30),
        ),
        nrrd_whole(
            "dimension 7",
            Refused(&["dimension"]),
            format!("NRRD0004\ntype: short\ndimension: 7\n{NRRD_GEOMETRY}\nencoding: raw\n\n"),
            raw.clone(),
        ),
    ];
    for seed in 0..6u64 {
        let file = nrrd(&format!("{NRRD_GEOMETRY}\nencoding: raw"), &raw);
        c.push(Case::new(
            format!("header bytes flipped (seed {seed})"),
            Either("ct.nrrd"),
            move |dir| {
                let mut b = file.clone();
                let mut rng = Rng::new(2000 + seed);
                let count = 1 + rng.below(6);
                flip_bytes(&mut b, 0..200, count, &mut rng);
                load_as(dir, "ct.nrrd", &b)
            },
        ));
    }
    c
}

/// A NRRD case whose whole header is given.
fn nrrd_whole(name: &str, expect: Expect, header: String, payload: Vec<u8>) -> Case {
    Case::new(name, expect, move |dir| {
        load_as(dir, "ct.nrrd", &[header.as_bytes(), &payload].concat())
    })
}

/// A MetaImage of the test volume (float, LPS) with `fields` replacing the defaults.
fn mha(replace: &[(&str, &str)], data: Option<Vec<u8>>) -> Vec<u8> {
    let mut head = String::from(
        "ObjectType = Image\nNDims = 3\nBinaryData = True\nBinaryDataByteOrderMSB = False\nCompressedData = False\nTransformMatrix = 1 0 0 0 1 0 0 0 1\nOffset = 0 0 0\nElementSpacing = 2.5 2.5 2.5\nDimSize = 16 16 4\nElementType = MET_FLOAT\nElementDataFile = LOCAL\n",
    );
    for (from, to) in replace {
        head = head.replace(from, to);
    }
    let data = data.unwrap_or_else(|| {
        ct_values()
            .iter()
            .flat_map(|&v| (v as f32).to_le_bytes())
            .collect()
    });
    [head.into_bytes(), data].concat()
}

fn read_mha(dir: &Path, bytes: &[u8]) -> Outcome {
    let path = write(dir, "field.mha", bytes);
    lungmotion::formats::metaimage::read_mha(&path)
        .map(|(g, channels, values)| {
            format!(
                "grid {:?} channels {channels} values {}",
                g.dims,
                values.len()
            )
        })
        .map_err(|e| e.to_string())
}

fn mha_case(name: &str, expect: Expect, replace: &'static [(&'static str, &'static str)]) -> Case {
    Case::new(name, expect, move |dir| read_mha(dir, &mha(replace, None)))
}

/// The MetaImage cases.
pub fn metaimage_cases() -> Vec<Case> {
    use Expect::*;
    vec![
        mha_case("valid", Accepted(&["grid [16, 16, 4]"]), &[]),
        mha_case(
            "DimSize 2.5",
            Refused(&["DimSize"]),
            &[("DimSize = 16 16 4", "DimSize = 16 16 4.5")],
        ),
        mha_case(
            "DimSize −16",
            Refused(&["DimSize"]),
            &[("DimSize = 16 16 4", "DimSize = -16 16 4")],
        ),
        mha_case(
            "DimSize 1e30",
            Refused(&["field.mha"]),
            &[("DimSize = 16 16 4", "DimSize = 1e30 16 4")],
        ),
        mha_case(
            "DimSize with 2 values",
            Refused(&["DimSize"]),
            &[("DimSize = 16 16 4", "DimSize = 16 16")],
        ),
        mha_case(
            "ElementNumberOfChannels 2^62",
            Refused(&["ElementNumberOfChannels"]),
            &[(
                "ElementType",
                "ElementNumberOfChannels = 4611686018427387904\nElementType",
            )],
        ),
        mha_case(
            "ElementNumberOfChannels 0",
            Refused(&["ElementNumberOfChannels"]),
            &[("ElementType", "ElementNumberOfChannels = 0\nElementType")],
        ),
        mha_case(
            "ElementSpacing negative",
            Refused(&["spacing"]),
            &[("2.5 2.5 2.5", "2.5 -2.5 2.5")],
        ),
        mha_case(
            "ElementSpacing NaN",
            Refused(&["spacing"]),
            &[("2.5 2.5 2.5", "2.5 NaN 2.5")],
        ),
        mha_case(
            "Offset infinite",
            Refused(&["origin"]),
            &[("Offset = 0 0 0", "Offset = inf 0 0")],
        ),
        mha_case(
            "ElementType MET_SHORT",
            Refused(&["MET_FLOAT"]),
            &[("MET_FLOAT", "MET_SHORT")],
        ),
        mha_case(
            "compressed data",
            Refused(&["compressed"]),
            &[("CompressedData = False", "CompressedData = True")],
        ),
        mha_case(
            "detached data file",
            Refused(&["LOCAL"]),
            &[("= LOCAL", "= /etc/passwd")],
        ),
        mha_case(
            "no ElementDataFile",
            Refused(&["ElementDataFile"]),
            &[("ElementDataFile = LOCAL\n", "")],
        ),
        Case::new("data cut short", Refused(&["truncated"]), |dir| {
            let b = mha(&[], None);
            read_mha(dir, &b[..b.len() - 6])
        }),
        Case::new(
            "a 4 MB header line without '='",
            Refused(&["field.mha"]),
            |dir| {
                read_mha(
                    dir,
                    &[vec![b'x'; 4 << 20], b"\n".to_vec(), mha(&[], None)].concat(),
                )
            },
        ),
        Case::new(
            "16 MB of header without a newline",
            Refused(&["ElementDataFile"]),
            |dir| read_mha(dir, &vec![b'x'; 16 << 20]),
        ),
    ]
}
