//! Safe zip reading: normal archives, path escapes, bombs, truncated and non-zip input.

use std::io::{Cursor, Write};
use std::time::Instant;

use lungmotion::formats::archive::{read_zip_entries, read_zip_file, ArchiveLimits};
use zip::write::SimpleFileOptions;
use zip::{CompressionMethod, ZipWriter};

fn deflated() -> SimpleFileOptions {
    SimpleFileOptions::default().compression_method(CompressionMethod::Deflated)
}

/// A zip in memory holding `(name, content)` entries (a name ending in `/` is a directory).
fn zip_of(entries: &[(&str, &[u8])]) -> Vec<u8> {
    let mut w = ZipWriter::new(Cursor::new(Vec::new()));
    for (name, data) in entries {
        if name.ends_with('/') {
            w.add_directory(*name, deflated()).unwrap();
        } else {
            w.start_file(*name, deflated()).unwrap();
            w.write_all(data).unwrap();
        }
    }
    w.finish().unwrap().into_inner()
}

fn err_of(bytes: Vec<u8>, limits: &ArchiveLimits) -> String {
    read_zip_entries(Cursor::new(bytes), "upload.zip", limits)
        .unwrap_err()
        .to_string()
}

#[test]
fn a_normal_zip_gives_its_files_in_order_without_directories() {
    let big: Vec<u8> = (0..100_000u32).map(|i| (i * 7 % 251) as u8).collect();
    let bytes = zip_of(&[
        ("series/", b""),
        ("series/IMG0001.dcm", b"first"),
        ("series/IMG0002.dcm", &big),
        ("README", b""),
    ]);
    let entries = read_zip_entries(Cursor::new(bytes), "x.zip", &ArchiveLimits::default()).unwrap();
    let names: Vec<&str> = entries.iter().map(|e| e.name.as_str()).collect();
    assert_eq!(
        names,
        ["series/IMG0001.dcm", "series/IMG0002.dcm", "README"]
    );
    assert_eq!(entries[0].data, b"first");
    assert_eq!(entries[1].data, big);
    assert!(entries[2].data.is_empty());
}

#[test]
fn a_zip_read_from_disk_names_the_file_in_errors() {
    let dir = std::env::temp_dir().join(format!("lungmotion-archive-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let good = dir.join("good.zip");
    std::fs::write(&good, zip_of(&[("a.dcm", b"abc")])).unwrap();
    assert_eq!(
        read_zip_file(&good, &ArchiveLimits::default()).unwrap()[0].data,
        b"abc"
    );
    let junk = dir.join("junk.zip");
    std::fs::write(&junk, b"this is plain text, not an archive").unwrap();
    let e = read_zip_file(&junk, &ArchiveLimits::default())
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("junk.zip") && e.contains("not a readable zip"),
        "{e}"
    );
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn parent_directory_entries_are_refused_by_name() {
    let bytes = zip_of(&[("ok.dcm", b"1"), ("series/../../evil.dcm", b"2")]);
    let e = err_of(bytes, &ArchiveLimits::default());
    assert!(
        e.contains("upload.zip") && e.contains("series/../../evil.dcm") && e.contains(".."),
        "{e}"
    );
}

#[test]
fn absolute_paths_and_drive_letters_are_refused_by_name() {
    let e = err_of(zip_of(&[("/etc/passwd", b"x")]), &ArchiveLimits::default());
    assert!(e.contains("/etc/passwd") && e.contains("absolute"), "{e}");
    let e = err_of(
        zip_of(&[("C:/Windows/x.dcm", b"x")]),
        &ArchiveLimits::default(),
    );
    assert!(e.contains("C:/Windows/x.dcm") && e.contains("drive"), "{e}");
}

#[test]
fn a_decompression_bomb_is_refused_while_decompressing() {
    // 200 MB of zeros compress to about 200 kB; written in chunks so the test stays small.
    let mut w = ZipWriter::new(Cursor::new(Vec::new()));
    w.start_file("bomb.dcm", deflated()).unwrap();
    let chunk = vec![0u8; 1 << 20];
    for _ in 0..200 {
        w.write_all(&chunk).unwrap();
    }
    let bytes = w.finish().unwrap().into_inner();
    assert!(bytes.len() < 2_000_000, "bomb is {} bytes", bytes.len());
    let started = Instant::now();
    let e = err_of(bytes.clone(), &ArchiveLimits::default());
    assert!(
        e.contains("bomb.dcm") && e.contains("decompression bomb"),
        "{e}"
    );
    // Refused after about ratio × compressed bytes, not after inflating everything.
    assert!(started.elapsed().as_secs_f64() < 5.0);

    // With the ratio guard lifted, the total-size guard still refuses it.
    let lenient = ArchiveLimits {
        max_entry_ratio: u64::MAX,
        max_total_uncompressed_bytes: 50 << 20,
        ..ArchiveLimits::default()
    };
    let e = err_of(bytes, &lenient);
    assert!(e.contains("bomb.dcm") && e.contains("52428800"), "{e}");
}

#[test]
fn too_many_entries_are_refused() {
    let names: Vec<String> = (0..20).map(|i| format!("f{i}")).collect();
    let entries: Vec<(&str, &[u8])> = names.iter().map(|n| (n.as_str(), &b"x"[..])).collect();
    let limits = ArchiveLimits {
        max_entries: 10,
        ..ArchiveLimits::default()
    };
    let e = err_of(zip_of(&entries), &limits);
    assert!(e.contains("20 entries") && e.contains("10"), "{e}");
}

#[test]
fn truncated_and_non_zip_input_are_refused() {
    let data: Vec<u8> = (0..50_000u32).map(|i| (i % 13) as u8).collect();
    let bytes = zip_of(&[("a.dcm", &data), ("b.dcm", &data)]);
    let e = err_of(bytes[..bytes.len() / 2].to_vec(), &ArchiveLimits::default());
    assert!(
        e.contains("upload.zip") && e.contains("not a readable zip"),
        "{e}"
    );

    // A corrupted entry body is caught by the CRC while decompressing.
    let mut corrupt = bytes.clone();
    corrupt[60] ^= 0xFF;
    corrupt[61] ^= 0xFF;
    let e = err_of(corrupt, &ArchiveLimits::default());
    assert!(e.contains("upload.zip") && e.contains("a.dcm"), "{e}");

    let e = err_of(b"\x89PNG not a zip".to_vec(), &ArchiveLimits::default());
    assert!(e.contains("not a readable zip"), "{e}");
}
