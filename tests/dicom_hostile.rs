//! Hostile and damaged DICOM input: nesting and declared lengths that must not take the
//! process down, damaged file meta information, decompression bombs, the memory budget,
//! elements stored as VR UN (made by pydicom), and refusals that name the actual fault.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};

use dicom_core::{DataElement, PrimitiveValue, VR};
use dicom_dictionary_std::tags;
use dicom_object::{open_file, DefaultDicomObject};
use lungmotion::datasets::cip_chest_ct64;
use lungmotion::formats::dicom::{
    read_dicom_series, read_dicom_series_with, write_ct_series, CtSeriesMetadata, DicomReadOptions,
};
use lungmotion::volume::{Volume, VolumeGeometry};

const EXPLICIT_LE: &str = "1.2.840.10008.1.2.1";
const DEFLATED_EXPLICIT_LE: &str = "1.2.840.10008.1.2.1.99";

/// A fresh, empty directory for one test.
fn scratch(name: &str) -> PathBuf {
    let dir =
        std::env::temp_dir().join(format!("lungmotion-hostile-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// A small valid CT series (6 × 5 × 4, HU values on a ramp) written by the project's writer.
fn write_small_series(dir: &Path) -> (Vec<PathBuf>, Volume<f32>) {
    let geometry = VolumeGeometry::axis_aligned([6, 5, 4], [0.8, 0.7, 2.5], [-10.0, 5.0, -40.0]);
    let data = (0..geometry.voxel_count())
        .map(|n| -1000.0 + (n * 37 % 1500) as f32)
        .collect();
    let volume = Volume::from_data(geometry, data).unwrap();
    let paths = write_ct_series(&volume, dir, &CtSeriesMetadata::default()).unwrap();
    (paths, volume)
}

fn edit(path: &Path, change: impl FnOnce(&mut DefaultDicomObject)) {
    let mut obj = open_file(path).unwrap();
    change(&mut obj);
    obj.write_to_file(path).unwrap();
}

/// One explicit VR little endian element (long length form for OB, OW, SQ, UN, UT …).
fn element(group: u16, number: u16, vr: &[u8; 2], length: u32, value: &[u8]) -> Vec<u8> {
    let mut out = Vec::new();
    out.extend_from_slice(&group.to_le_bytes());
    out.extend_from_slice(&number.to_le_bytes());
    out.extend_from_slice(vr);
    if matches!(vr, b"OB" | b"OW" | b"SQ" | b"UN" | b"UT" | b"OF") {
        out.extend_from_slice(&[0, 0]);
        out.extend_from_slice(&length.to_le_bytes());
    } else {
        out.extend_from_slice(&(length as u16).to_le_bytes());
    }
    out.extend_from_slice(value);
    out
}

/// An item-level header: (FFFE,`number`) and a 32-bit length.
fn item(number: u16, length: u32) -> Vec<u8> {
    let mut out = vec![0xFE, 0xFF];
    out.extend_from_slice(&number.to_le_bytes());
    out.extend_from_slice(&length.to_le_bytes());
    out
}

/// A Part 10 file: preamble, DICM, meta information for a CT image in `syntax`, `dataset`.
fn part10(syntax: &str, dataset: &[u8]) -> Vec<u8> {
    let uid = |s: &str| {
        let mut v = s.as_bytes().to_vec();
        if v.len() % 2 == 1 {
            v.push(0);
        }
        v
    };
    let mut meta = element(2, 1, b"OB", 2, &[0, 1]);
    let sop = uid("1.2.840.10008.5.1.4.1.1.2");
    meta.extend(element(2, 2, b"UI", sop.len() as u32, &sop));
    let instance = uid("1.2.3.4");
    meta.extend(element(2, 3, b"UI", instance.len() as u32, &instance));
    let ts = uid(syntax);
    meta.extend(element(2, 0x10, b"UI", ts.len() as u32, &ts));
    let mut out = vec![0u8; 128];
    out.extend_from_slice(b"DICM");
    out.extend(element(2, 0, b"UL", 4, &(meta.len() as u32).to_le_bytes()));
    out.extend(meta);
    out.extend_from_slice(dataset);
    out
}

/// `levels` sequences of undefined length, each holding one item of undefined length
/// holding the next, closed properly.
fn nested_sequences(levels: usize) -> Vec<u8> {
    let mut out = Vec::with_capacity(levels * 32);
    for _ in 0..levels {
        out.extend(element(0x0008, 0x1140, b"SQ", u32::MAX, &[]));
        out.extend(item(0xE000, u32::MAX));
    }
    for _ in 0..levels {
        out.extend(item(0xE00D, 0));
        out.extend(item(0xE0DD, 0));
    }
    out
}

/// The 412-byte file of the issue: one element declaring 0xFFFFFFF0 bytes.
fn four_gib_declaration() -> Vec<u8> {
    let mut file = part10(
        EXPLICIT_LE,
        &element(0x7FE0, 0x0010, b"OB", 0xFFFF_FFF0, &[]),
    );
    file.resize(412, 0);
    file
}

/// Runs `lungmotion ingest --ct <input>` under a virtual memory limit; (exit code, stderr).
fn ingest_in_child(input: &Path, out: &Path, limit_kib: u64) -> (Option<i32>, String) {
    let binary = env!("CARGO_BIN_EXE_lungmotion");
    let script = format!("ulimit -v {limit_kib}; exec \"$0\" ingest --ct \"$1\" --out \"$2\"",);
    let output = Command::new("sh")
        .arg("-c")
        .arg(script)
        .arg(binary)
        .arg(input)
        .arg(out)
        .output()
        .unwrap();
    (
        output.status.code(),
        String::from_utf8_lossy(&output.stderr).into_owned(),
    )
}

#[test]
fn deeply_nested_sequences_do_not_take_the_process_down() {
    let dir = scratch("nested");
    let path = dir.join("nested.dcm");
    std::fs::write(&path, part10(EXPLICIT_LE, &nested_sequences(200_000))).unwrap();
    // In a child process: before the pre-scan this overflowed the stack (exit 134).
    let (code, stderr) = ingest_in_child(&path, &dir.join("out"), 2_000_000);
    assert_eq!(code, Some(2), "{stderr}");
    assert!(
        stderr.contains("nested.dcm") && stderr.contains("nested more than 32 deep"),
        "{stderr}"
    );
    std::fs::remove_dir_all(dir).unwrap();
}

#[test]
fn nesting_is_bounded_at_32_sequences_and_allowed_below() {
    let dir = scratch("nesting-bound");
    let (paths, volume) = write_small_series(&dir);
    // A private sequence 31 deep in every slice: still read.
    let mut deep = nested_sequences(31);
    for p in &paths {
        let mut bytes = std::fs::read(p).unwrap();
        let pixels = find_pixel_data(&bytes);
        // (0009,1000) sorts before PixelData: insert just before it.
        deep[0..4].copy_from_slice(&[0x09, 0x00, 0x00, 0x10]);
        bytes.splice(pixels..pixels, deep.iter().copied());
        std::fs::write(p, bytes).unwrap();
    }
    let series = read_dicom_series(&dir).unwrap();
    assert_eq!(series.volume.as_slice(), volume.as_slice());
    // 33 deep in a file of its own: skipped, naming the bound.
    std::fs::write(
        dir.join("deep.dcm"),
        part10(EXPLICIT_LE, &nested_sequences(33)),
    )
    .unwrap();
    let series = read_dicom_series(&dir).unwrap();
    let all = series.warnings.join("\n");
    assert!(
        all.contains("deep.dcm: skipped") && all.contains("nested more than 32 deep"),
        "{all}"
    );
    std::fs::remove_dir_all(dir).unwrap();
}

/// Byte offset of the Pixel Data element header in an explicit VR little endian file.
fn find_pixel_data(bytes: &[u8]) -> usize {
    bytes
        .windows(6)
        .rposition(|w| {
            w == [0xE0, 0x7F, 0x10, 0x00, b'O', b'W'] || w == [0xE0, 0x7F, 0x10, 0x00, b'O', b'B']
        })
        .expect("pixel data")
}

#[test]
fn a_four_gib_length_is_refused_under_a_2_gb_memory_limit() {
    let dir = scratch("four-gib");
    let path = dir.join("huge.dcm");
    std::fs::write(&path, four_gib_declaration()).unwrap();
    assert_eq!(std::fs::metadata(&path).unwrap().len(), 412);
    let started = Instant::now();
    let (code, stderr) = ingest_in_child(&path, &dir.join("out"), 2_000_000);
    assert_eq!(code, Some(2), "{stderr}");
    assert!(
        stderr.contains("PixelData (7FE0,0010) at byte 0 declares 4294967280 bytes but only"),
        "{stderr}"
    );
    assert!(started.elapsed() < Duration::from_secs(10));
    std::fs::remove_dir_all(dir).unwrap();
}

#[test]
fn twenty_hostile_files_beside_a_series_are_skipped_quickly() {
    let dir = scratch("twenty");
    let (_, volume) = write_small_series(&dir);
    for k in 0..20 {
        std::fs::write(
            dir.join(format!("hostile-{k:02}.dcm")),
            four_gib_declaration(),
        )
        .unwrap();
    }
    let started = Instant::now();
    let series = read_dicom_series(&dir).unwrap();
    let elapsed = started.elapsed();
    assert!(elapsed < Duration::from_secs(5), "{elapsed:?}");
    assert_eq!(series.volume.as_slice(), volume.as_slice());
    assert_eq!(series.warnings.len(), 20, "{:?}", series.warnings);
    for k in 0..20 {
        let name = format!("hostile-{k:02}.dcm: skipped");
        assert!(
            series
                .warnings
                .iter()
                .any(|w| w.contains(&name) && w.contains("declares 4294967280 bytes")),
            "{name}: {:?}",
            series.warnings
        );
    }
    std::fs::remove_dir_all(dir).unwrap();
}

/// Writes a copy of `bytes` with the file meta group length replaced by `length`.
fn with_meta_length(bytes: &[u8], length: u32) -> Vec<u8> {
    assert_eq!(&bytes[128..136], b"DICM\x02\x00\x00\x00");
    let mut copy = bytes.to_vec();
    copy[140..144].copy_from_slice(&length.to_le_bytes());
    copy
}

#[test]
fn a_wrong_meta_group_length_is_corrected_as_dcmtk_and_pydicom_do() {
    let dir = scratch("meta-length");
    let (paths, volume) = write_small_series(&dir);
    let original = std::fs::read(&paths[0]).unwrap();
    let declared = u32::from_le_bytes(original[140..144].try_into().unwrap());
    for (k, wrong) in [declared + 1000, declared - 30, 0xFFFF_FF00, 0]
        .into_iter()
        .enumerate()
    {
        std::fs::write(&paths[0], with_meta_length(&original, wrong)).unwrap();
        let started = Instant::now();
        let series = read_dicom_series(&dir).unwrap();
        assert!(started.elapsed() < Duration::from_secs(5), "case {k}");
        assert_eq!(series.volume.as_slice(), volume.as_slice(), "case {k}");
        let all = series.warnings.join("\n");
        assert!(
            all.contains(&format!(
                "Group Length (0002,0000) said {wrong} bytes, its elements take {declared}: \
                 corrected"
            )) && all.contains("IMG0001.dcm"),
            "case {k}: {all}"
        );
    }
    std::fs::remove_dir_all(dir).unwrap();
}

#[test]
fn flipped_header_bytes_are_refused_quickly_with_their_reason() {
    let dir = scratch("flipped");
    let (paths, _) = write_small_series(&dir);
    let original = std::fs::read(&paths[0]).unwrap();
    let pixels = find_pixel_data(&original);
    let transfer_syntax = original
        .windows(6)
        .position(|w| w == [2, 0, 0x10, 0, b'U', b'I'])
        .unwrap();
    let cases: Vec<(&str, Vec<u8>, &str)> = vec![
        (
            "no-marker",
            flip(&original, 129),
            "no DICM marker at byte 128",
        ),
        // The high byte of Pixel Data's length: 16 MB more than the file holds.
        (
            "pixel-length",
            flip(&original, pixels + 10),
            "PixelData (7FE0,0010) at byte",
        ),
        // The high byte of the Transfer Syntax UID's length: past the end of the file.
        (
            "meta-length",
            flip(&original, transfer_syntax + 7),
            "meta element (0002,0010) declares",
        ),
    ];
    for (name, bytes, reason) in &cases {
        let path = dir.join(format!("{name}.dcm"));
        std::fs::write(&path, bytes).unwrap();
        let started = Instant::now();
        let e = read_dicom_series(&path).unwrap_err().to_string();
        assert!(started.elapsed() < Duration::from_secs(2), "{name}");
        assert!(
            e.contains(&format!("{name}.dcm")) && e.contains(reason),
            "{name}: {e}"
        );
        std::fs::remove_file(path).unwrap();
    }
    // Every single byte of the header flipped in turn: read or refused, each quickly.
    let slow = (132..pixels + 12)
        .filter(|&at| {
            let path = dir.join("one.dcm");
            std::fs::write(&path, flip(&original, at)).unwrap();
            let started = Instant::now();
            if let Err(e) = read_dicom_series(&path) {
                assert!(e.to_string().contains("one.dcm"), "{e}");
            }
            started.elapsed() > Duration::from_secs(1)
        })
        .collect::<Vec<_>>();
    assert!(slow.is_empty(), "slow at bytes {slow:?}");
    std::fs::remove_dir_all(dir).unwrap();
}

fn flip(bytes: &[u8], at: usize) -> Vec<u8> {
    let mut copy = bytes.to_vec();
    copy[at] ^= 0xFF;
    copy
}

#[test]
fn a_deflated_data_set_that_inflates_250_times_is_refused() {
    let dir = scratch("deflate-bomb");
    let mut dataset = element(0x0008, 0x0060, b"CS", 2, b"CT");
    dataset.extend(element(0x0009, 0x1000, b"OB", 64 << 20, &[]));
    dataset.resize(dataset.len() + (64 << 20), 0);
    let mut deflated = flate2::write::DeflateEncoder::new(Vec::new(), flate2::Compression::best());
    deflated.write_all(&dataset).unwrap();
    let compressed = deflated.finish().unwrap();
    assert!(compressed.len() * 250 < dataset.len());
    let path = dir.join("bomb.dcm");
    std::fs::write(&path, part10(DEFLATED_EXPLICIT_LE, &compressed)).unwrap();
    let e = read_dicom_series(&path).unwrap_err().to_string();
    assert!(
        e.contains("bomb.dcm") && e.contains("refused as a decompression bomb"),
        "{e}"
    );
    std::fs::remove_dir_all(dir).unwrap();
}

#[test]
fn the_memory_budget_bounds_one_file_and_the_whole_read() {
    let dir = scratch("budget");
    let (paths, volume) = write_small_series(&dir);
    let file_bytes = std::fs::metadata(&paths[0]).unwrap().len();
    let read = |budget: u64| {
        let options = DicomReadOptions {
            memory_budget_bytes: Some(budget),
            ..DicomReadOptions::default()
        };
        read_dicom_series_with(&dir, &options)
    };
    let series = read(64 << 20).unwrap();
    assert_eq!(series.volume.as_slice(), volume.as_slice());
    // Below one file's size: every file is skipped for it, by name.
    let e = read(file_bytes / 2).unwrap_err().to_string();
    assert!(
        e.contains("no readable DICOM image (4 skipped")
            && e.contains("of memory to read, more than the")
            && e.contains("this read may use"),
        "{e}"
    );
    // Parsed, a file of 6 × 5 pixels takes about 10 times its size (224 bytes per element):
    // room for one file but not four, so the read as a whole is refused.
    let e = read(file_bytes * 16).unwrap_err().to_string();
    assert!(
        e.contains("need more memory than this read may use") && e.contains("already hold"),
        "{e}"
    );
    std::fs::remove_dir_all(dir).unwrap();
}

#[test]
fn a_zip_is_held_to_the_reads_memory_budget_before_any_file_is_parsed() {
    let dir = scratch("zip-budget");
    let series = dir.join("series");
    std::fs::create_dir_all(&series).unwrap();
    let (paths, volume) = write_small_series(&series);
    let zip_path = dir.join("series.zip");
    let mut zip = zip::ZipWriter::new(std::fs::File::create(&zip_path).unwrap());
    let mut entry_bytes = 0;
    for path in &paths {
        let bytes = std::fs::read(path).unwrap();
        entry_bytes += bytes.len() as u64;
        let name = path.file_name().unwrap().to_string_lossy();
        zip.start_file(name, zip::write::SimpleFileOptions::default())
            .unwrap();
        zip.write_all(&bytes).unwrap();
    }
    zip.finish().unwrap();
    let read = |budget: u64| {
        let options = DicomReadOptions {
            memory_budget_bytes: Some(budget),
            ..DicomReadOptions::default()
        };
        read_dicom_series_with(&zip_path, &options)
    };
    assert_eq!(read(64 << 20).unwrap().volume.as_slice(), volume.as_slice());
    // The entries alone overrun the budget: refused while decompressing, naming it.
    let e = read(entry_bytes / 2).unwrap_err().to_string();
    assert!(
        e.contains("series.zip")
            && e.contains(&format!("more than {} bytes", entry_bytes / 2))
            && e.contains("the memory this DICOM read may use"),
        "{e}"
    );
    std::fs::remove_dir_all(dir).unwrap();
}

#[test]
fn a_4dct_whose_phases_share_one_series_is_refused_naming_the_phase_attribute() {
    let dir = scratch("4dct-one-series");
    let (phase1, volume) = write_small_series(&dir);
    let uid = open_file(&phase1[0])
        .unwrap()
        .element(tags::SERIES_INSTANCE_UID)
        .unwrap()
        .to_str()
        .unwrap()
        .into_owned();
    // The second phase: other images at the same positions, in the same series.
    let other = dir.join("phase2");
    std::fs::create_dir_all(&other).unwrap();
    let exhaled = Volume::from_data(
        volume.geometry,
        volume.as_slice().iter().map(|v| v + 40.0).collect(),
    )
    .unwrap();
    for path in write_ct_series(&exhaled, &other, &CtSeriesMetadata::default()).unwrap() {
        edit(&path, |obj| {
            obj.put(DataElement::new(
                tags::SERIES_INSTANCE_UID,
                VR::UI,
                PrimitiveValue::from(uid.as_str()),
            ));
            obj.put(DataElement::new(
                tags::ACQUISITION_NUMBER,
                VR::IS,
                PrimitiveValue::from("2"),
            ));
        });
    }
    let e = read_dicom_series(&dir).unwrap_err().to_string();
    assert!(
        e.contains("duplicate slice position")
            && e.contains("AcquisitionNumber (1 and 2)")
            && e.contains("4D-CT"),
        "{e}"
    );
    std::fs::remove_dir_all(dir).unwrap();
}

#[test]
fn a_series_with_every_element_as_vr_un_reads_like_the_original() {
    let un_dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/dicom/un-vr");
    let series = read_dicom_series(&un_dir).unwrap();
    assert_eq!(series.info.modality, "CT");
    assert_eq!(series.info.rows, 64);
    let g = &series.volume.geometry;
    assert_eq!(g.dims, [64, 64, 3]);
    // The slice spacing is the mean over these 3 slices' rounded positions.
    for (got, want) in g.spacing_mm.iter().zip([4.171872, 4.171872, 3.98734]) {
        assert!((got - want).abs() < 1e-3, "{:?}", g.spacing_mm);
    }
    for (got, want) in g.origin_lps_mm.iter().zip([-128.414, -264.414, -360.256]) {
        assert!((got - want).abs() < 1e-3, "{:?}", g.origin_lps_mm);
    }
    let all = series.warnings.join("\n");
    assert!(
        all.contains("3 file(s) repaired on reading")
            && all.contains(
                "stored with VR UN (unknown) were read with the standard dictionary's VR"
            ),
        "{all}"
    );
    let Some(cip) = cip_chest_ct64() else {
        eprintln!("skipped: the CIP series is not in the shared data");
        return;
    };
    let dir = scratch("un-original");
    for name in ["IMG0001.dcm", "IMG0002.dcm", "IMG0003.dcm"] {
        std::fs::copy(cip.join("dicom").join(name), dir.join(name)).unwrap();
    }
    let original = read_dicom_series(&dir).unwrap();
    assert!(original.volume.geometry.same_grid(g, 1e-9));
    assert_eq!(original.volume.as_slice(), series.volume.as_slice());
    assert_eq!(
        original.info.series_instance_uid,
        series.info.series_instance_uid
    );
    std::fs::remove_dir_all(dir).unwrap();
}

#[test]
fn missing_rows_are_named_not_reported_as_another_modality() {
    let dir = scratch("no-rows");
    let (paths, _) = write_small_series(&dir);
    for p in &paths {
        edit(p, |obj| {
            obj.remove_element(tags::ROWS);
        });
    }
    let e = read_dicom_series(&dir).unwrap_err().to_string();
    assert!(
        e.contains("4 files: Rows (0028,0010) is missing: the image size is unknown"),
        "{e}"
    );
    assert!(!e.contains("found modality"), "{e}");
    std::fs::remove_dir_all(dir).unwrap();
}

#[test]
fn float_pixel_data_is_named_as_the_fault() {
    let dir = scratch("float-pixels");
    let (paths, _) = write_small_series(&dir);
    for p in &paths {
        edit(p, |obj| {
            obj.remove_element(tags::PIXEL_DATA);
            obj.put(DataElement::new(
                tags::FLOAT_PIXEL_DATA,
                VR::OF,
                PrimitiveValue::F32(vec![0.5f32; 30].into()),
            ));
        });
    }
    let e = read_dicom_series(&dir).unwrap_err().to_string();
    assert!(
        e.contains("Float Pixel Data (7FE0,0008)") && e.contains("not supported"),
        "{e}"
    );
    assert!(!e.contains("truncated"), "{e}");
    std::fs::remove_dir_all(dir).unwrap();
}

#[test]
fn a_modality_stored_as_bytes_is_shown_as_text() {
    let dir = scratch("modality-bytes");
    let (paths, _) = write_small_series(&dir);
    for p in &paths {
        edit(p, |obj| {
            obj.put(DataElement::new(
                tags::MODALITY,
                VR::OB,
                PrimitiveValue::U8(b"MR".to_vec().into()),
            ));
        });
    }
    let e = read_dicom_series(&dir).unwrap_err().to_string();
    assert!(e.contains("found modality MR"), "{e}");
    assert!(!e.contains("77\\82"), "{e}");
    std::fs::remove_dir_all(dir).unwrap();
}
