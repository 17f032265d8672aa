//! Hostile zip uploads: bombs, escaping names, too many entries, nested zips, lying
//! directories and truncation.

use std::io::{Cursor, Write};
use std::path::Path;

use lungmotion::formats::archive::{read_zip_entries, ArchiveLimits};
use zip::write::SimpleFileOptions;
use zip::{CompressionMethod, ZipWriter};

use super::dicom::Slice;
use super::{flip_bytes, load, write, Case, Expect, Outcome, Rng};

fn deflated() -> SimpleFileOptions {
    SimpleFileOptions::default().compression_method(CompressionMethod::Deflated)
}

/// A zip of `(name, content)` entries.
pub fn zip_of(entries: &[(String, Vec<u8>)]) -> Vec<u8> {
    let mut w = ZipWriter::new(Cursor::new(Vec::new()));
    for (name, data) in entries {
        w.start_file(name.as_str(), deflated()).unwrap();
        w.write_all(data).unwrap();
    }
    w.finish().unwrap().into_inner()
}

/// The valid 4-slice test series as zip entries `series/IMk`.
pub fn series_entries() -> Vec<(String, Vec<u8>)> {
    (0..4)
        .map(|k| (format!("series/IM{k}"), Slice::ct(k).bytes()))
        .collect()
}

/// The series plus `extra` entries, zipped and loaded as `upload.zip`.
fn series_plus(extra: Vec<(String, Vec<u8>)>) -> impl Fn(&Path) -> Outcome + 'static {
    move |dir| {
        let mut entries = series_entries();
        entries.extend(extra.iter().cloned());
        load(&write(dir, "upload.zip", &zip_of(&entries)))
    }
}

fn load_zip(dir: &Path, bytes: &[u8]) -> Outcome {
    load(&write(dir, "upload.zip", bytes))
}

/// An end-of-central-directory record pointing to a zip64 one that declares `entries`.
fn zip64_declaring(entries: u64) -> Vec<u8> {
    let mut out = Vec::new();
    // zip64 end of central directory record at offset 0.
    out.extend_from_slice(&0x0606_4b50u32.to_le_bytes());
    out.extend_from_slice(&44u64.to_le_bytes());
    out.extend_from_slice(&[45, 0, 45, 0]);
    out.extend_from_slice(&[0u8; 8]); // this disk, disk of the central directory
    out.extend_from_slice(&entries.to_le_bytes());
    out.extend_from_slice(&entries.to_le_bytes());
    out.extend_from_slice(&0u64.to_le_bytes()); // central directory size
    out.extend_from_slice(&0u64.to_le_bytes()); // central directory offset
                                                // zip64 locator.
    out.extend_from_slice(&0x0706_4b50u32.to_le_bytes());
    out.extend_from_slice(&0u32.to_le_bytes());
    out.extend_from_slice(&0u64.to_le_bytes());
    out.extend_from_slice(&1u32.to_le_bytes());
    // End of central directory, every field saying "see zip64".
    out.extend_from_slice(&0x0605_4b50u32.to_le_bytes());
    out.extend_from_slice(&[0xFF; 16]);
    out.extend_from_slice(&[0, 0]);
    out
}

/// The zip cases.
pub fn cases() -> Vec<Case> {
    use Expect::*;
    let mut c = vec![
        Case::new(
            "valid series zip",
            Accepted(&["DicomZip", "grid [16, 16, 4]"]),
            series_plus(vec![]),
        ),
        Case::new("empty zip", Refused(&["no files"]), |dir| {
            load_zip(dir, &zip_of(&[]))
        }),
        Case::new("zip cut in half", Refused(&["upload.zip"]), |dir| {
            let z = zip_of(&series_entries());
            load_zip(dir, &z[..z.len() / 2])
        }),
        Case::new(
            "zip of text files",
            Refused(&["no readable DICOM"]),
            |dir| {
                load_zip(
                    dir,
                    &zip_of(&[
                        ("a.txt".into(), b"hello".to_vec()),
                        ("b.csv".into(), b"1,2".to_vec()),
                    ]),
                )
            },
        ),
        Case::new("zip in a zip", Refused(&["no readable DICOM"]), |dir| {
            load_zip(
                dir,
                &zip_of(&[("inner.zip".into(), zip_of(&series_entries()))]),
            )
        }),
        Case::new(
            "64 MiB of zeros in one entry (bomb)",
            Refused(&["decompression bomb"]),
            series_plus(vec![("bomb.dcm".into(), vec![0u8; 64 << 20])]),
        ),
        Case::new(
            "100 001 empty entries",
            Refused(&["100001 entries"]),
            |dir| {
                let mut w = ZipWriter::new(Cursor::new(Vec::new()));
                let stored =
                    SimpleFileOptions::default().compression_method(CompressionMethod::Stored);
                for i in 0..100_001 {
                    w.start_file(format!("{i}"), stored).unwrap();
                }
                load_zip(dir, &w.finish().unwrap().into_inner())
            },
        ),
        Case::new(
            "zip64 directory declaring 2^60 entries",
            Refused(&["upload.zip"]),
            |dir| load_zip(dir, &zip64_declaring(1 << 60)),
        ),
        Case::new(
            "zip64 directory declaring 100 000 entries in 98 bytes",
            Refused(&["upload.zip"]),
            |dir| load_zip(dir, &zip64_declaring(100_000)),
        ),
        Case::new(
            "entries over a 1 MiB total limit",
            Refused(&["limit"]),
            |dir| {
                let entries: Vec<(String, Vec<u8>)> = (0..3)
                    .map(|i| {
                        (
                            format!("e{i}"),
                            (0..600_000u32).map(|x| (x * 31 % 251) as u8).collect(),
                        )
                    })
                    .collect();
                let limits = ArchiveLimits {
                    max_total_uncompressed_bytes: 1 << 20,
                    ..ArchiveLimits::default()
                };
                let _ = dir;
                read_zip_entries(Cursor::new(zip_of(&entries)), "upload.zip", &limits)
                    .map(|e| format!("{} entries", e.len()))
                    .map_err(|e| e.to_string())
            },
        ),
        Case::new("a DICOMDIR only", Refused(&["no files"]), |dir| {
            load_zip(dir, &zip_of(&[("DICOMDIR".into(), vec![0u8; 200])]))
        }),
        Case::new(
            "series plus a DICOMDIR",
            Accepted(&["grid [16, 16, 4]"]),
            series_plus(vec![("DICOMDIR".into(), vec![0u8; 200])]),
        ),
        Case::new(
            "an entry name of 60 000 characters",
            Accepted(&["grid [16, 16, 4]"]),
            series_plus(vec![(format!("{}.txt", "n".repeat(60_000)), b"x".to_vec())]),
        ),
    ];
    for name in [
        "../evil.dcm",
        "/etc/evil.dcm",
        "C:\\evil.dcm",
        "series/../../evil.dcm",
        "nul\0byte.dcm",
    ] {
        let shown = name.replace('\0', "\\0");
        c.push(Case::new(
            format!("entry named {shown}"),
            Refused(&["refused"]),
            series_plus(vec![(name.to_string(), Slice::ct(0).bytes())]),
        ));
    }
    for seed in 0..8u64 {
        c.push(Case::new(
            format!("series zip with bytes flipped (seed {seed})"),
            Either("upload.zip"),
            move |dir| {
                let mut z = zip_of(&series_entries());
                let mut rng = Rng::new(3000 + seed);
                let count = 1 + rng.below(8);
                let n = z.len();
                flip_bytes(&mut z, 0..n, count, &mut rng);
                load_zip(dir, &z)
            },
        ));
    }
    c
}
