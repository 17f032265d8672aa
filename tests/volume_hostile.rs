//! Hostile volume files (NIfTI, NRRD, MetaImage, zip): each declares more than it holds, or a
//! geometry no lung model can use, and must be refused quickly, by its named reason, without
//! allocating what it declares.

use std::io::{Cursor, Write};
use std::path::{Path, PathBuf};
use std::time::{Duration, Instant};

use lungmotion::formats::archive::{read_zip_entries, ArchiveLimits};
use lungmotion::formats::budget::ScanBudget;
use lungmotion::formats::metaimage::read_mha;
use lungmotion::formats::nifti::{read_nifti_bytes, read_nifti_bytes_within, write_nifti_ct};
use lungmotion::formats::nrrd::{parse_nrrd, parse_nrrd_within};
use lungmotion::ingest::pipeline::{ingest_scan, IngestSettings};
use lungmotion::ingest::scan::load_ct;
use lungmotion::volume::{Volume, VolumeGeometry};

fn scratch_dir(test: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("lm-hostile-{}-{test}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

fn assert_mentions(message: &str, words: &[&str]) {
    for w in words {
        assert!(message.contains(w), "'{w}' missing from: {message}");
    }
}

/// Refusals must come at once: nothing the size of the declaration was inflated.
fn assert_quick(start: Instant) {
    let elapsed = start.elapsed();
    assert!(elapsed < Duration::from_secs(2), "took {elapsed:?}");
}

fn gzip(bytes: &[u8]) -> Vec<u8> {
    let mut e = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::best());
    e.write_all(bytes).unwrap();
    e.finish().unwrap()
}

/// `head` then `zero_mib` MiB of zeros as concatenated gzip members (as `cat a.gz b.gz`
/// makes; every gzip reader inflates them as one stream), built from one compressed MiB so
/// the test does not spend seconds compressing.
fn gzip_with_zeros(head: &[u8], zero_mib: usize) -> Vec<u8> {
    let mut out = gzip(head);
    let member = gzip(&vec![0u8; 1 << 20]);
    for _ in 0..zero_mib {
        out.extend_from_slice(&member);
    }
    out
}

/// A NIfTI-1 header (352 bytes, voxels at 352), uint8, 1 mm axis-aligned sform.
fn nifti1_header(dims: [i16; 3], datatype: i16, bitpix: i16) -> Vec<u8> {
    let mut h = vec![0u8; 352];
    let mut put = |o: usize, b: &[u8]| h[o..o + b.len()].copy_from_slice(b);
    put(0, &348i32.to_le_bytes());
    for (a, d) in [3, dims[0], dims[1], dims[2], 1, 1, 1, 1]
        .iter()
        .enumerate()
    {
        put(40 + 2 * a, &d.to_le_bytes());
    }
    put(70, &datatype.to_le_bytes());
    put(72, &bitpix.to_le_bytes());
    for a in 0..8 {
        put(76 + 4 * a, &1f32.to_le_bytes());
    }
    put(108, &352f32.to_le_bytes());
    put(123, &[2]);
    put(254, &1i16.to_le_bytes());
    for r in 0..3 {
        put(280 + 16 * r + 4 * r, &1f32.to_le_bytes());
    }
    put(344, b"n+1\0");
    h
}

// ---------------------------------------------------------------------------------------
// NIfTI
// ---------------------------------------------------------------------------------------

#[test]
fn gzip_nifti_declaring_eight_gib_of_float32_is_refused_by_the_budget_before_inflating() {
    // The 2 MB file: 2048 × 1024 × 1024 uint8 (here with its zeros cut short, since
    // the header alone must decide).
    let bytes = gzip_with_zeros(&nifti1_header([2048, 1024, 1024], 2, 8), 4);
    let start = Instant::now();
    let e = read_nifti_bytes(&bytes, "bomb.nii.gz")
        .unwrap_err()
        .to_string();
    assert_mentions(
        &e,
        &[
            "bomb.nii.gz",
            "2048×1024×1024 voxels = 8.0 GiB of float32",
            "over the budget of",
            "set by",
        ],
    );
    assert_quick(start);
}

#[test]
fn gzip_nifti_inflating_beyond_the_ratio_cap_is_refused_before_inflating() {
    // 512³ uint8 zeros: 128 MiB from about 130 kB, within the memory budget but ≈ 1 000×.
    let bytes = gzip_with_zeros(&nifti1_header([512, 512, 512], 2, 8), 128);
    assert!(bytes.len() < 200_000, "{}", bytes.len());
    let start = Instant::now();
    let e = read_nifti_bytes(&bytes, "zeros.nii.gz")
        .unwrap_err()
        .to_string();
    assert_mentions(&e, &["zeros.nii.gz", "gzip stream", "cap of 250×", "bomb"]);
    assert_quick(start);
    // A vox_offset far beyond the header counts: skipping it is inflating too.
    let mut head = nifti1_header([2, 2, 2], 2, 8);
    head[108..112].copy_from_slice(&4.0e9f32.to_le_bytes());
    let e = read_nifti_bytes(&gzip(&head), "offset.nii.gz")
        .unwrap_err()
        .to_string();
    assert_mentions(&e, &["offset.nii.gz", "cap of 250×"]);
}

#[test]
fn a_memory_budget_refuses_a_raw_nifti_naming_what_set_it() {
    let mut bytes = nifti1_header([300, 300, 4], 4, 16);
    bytes.extend(std::iter::repeat_n(0u8, 300 * 300 * 4 * 2));
    let budget = ScanBudget {
        max_volume_bytes: 1 << 20,
        set_by: "a test's 1 MiB".into(),
        ..ScanBudget::default()
    };
    let e = read_nifti_bytes_within(&bytes, "ct.nii", &budget)
        .unwrap_err()
        .to_string();
    assert_mentions(
        &e,
        &[
            "ct.nii",
            "300×300×4 voxels = 1.4 MiB of float32",
            "budget of 1.0 MiB (set by a test's 1 MiB)",
        ],
    );
    // The same file within the default budget reads.
    assert_eq!(
        read_nifti_bytes(&bytes, "ct.nii").unwrap().dims(),
        [300, 300, 4]
    );
}

// ---------------------------------------------------------------------------------------
// NRRD
// ---------------------------------------------------------------------------------------

fn nrrd_header(sizes: &str, kind: &str, encoding: &str, extra: &str) -> Vec<u8> {
    format!(
        "NRRD0004\ntype: {kind}\ndimension: 3\nspace: left-posterior-superior\n\
         sizes: {sizes}\nspace directions: (1,0,0) (0,1,0) (0,0,1)\nendian: little\n\
         encoding: {encoding}\n{extra}space origin: (0,0,0)\n\n"
    )
    .into_bytes()
}

#[test]
fn gzip_nrrd_bombs_are_refused_by_ratio_and_budget_before_inflating() {
    let start = Instant::now();
    // 512³ uchar zeros from ≈ 130 kB.
    let mut bytes = nrrd_header("512 512 512", "uchar", "gzip", "");
    let zeros = gzip_with_zeros(&[], 128);
    bytes.extend_from_slice(&zeros);
    let e = parse_nrrd(&bytes, "zeros.nrrd").unwrap_err().to_string();
    assert_mentions(&e, &["zeros.nrrd", "gzip data", "cap of 250×"]);
    // 2048 × 1024 × 1024 declared: over any budget, refused before reserving it.
    let mut bytes = nrrd_header("2048 1024 1024", "uchar", "gzip", "");
    bytes.extend_from_slice(&gzip(&[0u8; 64]));
    let e = parse_nrrd(&bytes, "huge.nrrd").unwrap_err().to_string();
    assert_mentions(
        &e,
        &["huge.nrrd", "2048×1024×1024", "8.0 GiB", "over the budget"],
    );
    assert_quick(start);
    // A small memory budget names its source.
    let mut bytes = nrrd_header("200 200 10", "short", "raw", "");
    bytes.extend(std::iter::repeat_n(0u8, 200 * 200 * 10 * 2));
    let budget = ScanBudget {
        max_volume_bytes: 1 << 20,
        set_by: "the test".into(),
        ..ScanBudget::default()
    };
    let e = parse_nrrd_within(&bytes, "small.nrrd", &budget)
        .unwrap_err()
        .to_string();
    assert_mentions(
        &e,
        &["1.5 MiB of float32", "budget of 1.0 MiB (set by the test)"],
    );
}

#[test]
fn nrrd_headers_the_reader_cannot_honour_are_refused_by_name() {
    let data = [0u8; 2 * 3 * 4 * 2];
    for (extra, words) in [
        ("byte skip: 2\n", &["'byte skip: 2'", "not supported"][..]),
        ("line skip: 1\n", &["'line skip: 1'"][..]),
    ] {
        let mut bytes = nrrd_header("2 3 4", "short", "raw", extra);
        bytes.extend_from_slice(&data);
        let e = parse_nrrd(&bytes, "skip.nrrd").unwrap_err().to_string();
        assert_mentions(&e, words);
    }
    let mut bytes = nrrd_header("2 3 4", "short", "raw", "").replace_endian("middle");
    bytes.extend_from_slice(&data);
    let e = parse_nrrd(&bytes, "e.nrrd").unwrap_err().to_string();
    assert_mentions(&e, &["endian 'middle'"]);
    // "byte skip: 0" is the default and reads.
    let mut bytes = nrrd_header("2 3 4", "short", "raw", "byte skip: 0\n");
    bytes.extend_from_slice(&data);
    parse_nrrd(&bytes, "ok.nrrd").unwrap();
    // A header with no ending empty line in its first MiB is not searched further.
    let mut bytes = b"NRRD0004\ntype: short\n# ".to_vec();
    bytes.extend(std::iter::repeat_n(b'x', 3 << 20));
    let e = parse_nrrd(&bytes, "long.nrrd").unwrap_err().to_string();
    assert_mentions(&e, &["long.nrrd", "within its first 1048576 bytes"]);
}

trait ReplaceEndian {
    fn replace_endian(self, endian: &str) -> Vec<u8>;
}

impl ReplaceEndian for Vec<u8> {
    fn replace_endian(self, endian: &str) -> Vec<u8> {
        String::from_utf8(self)
            .unwrap()
            .replace("endian: little", &format!("endian: {endian}"))
            .into_bytes()
    }
}

// ---------------------------------------------------------------------------------------
// MetaImage
// ---------------------------------------------------------------------------------------

fn mha_file(dir: &Path, dim_size: &str, channels: &str, data_bytes: usize) -> PathBuf {
    let path = dir.join("x.mha");
    let mut bytes = format!(
        "ObjectType = Image\nNDims = 3\nBinaryData = True\nBinaryDataByteOrderMSB = False\n\
         CompressedData = False\nTransformMatrix = 1 0 0 0 1 0 0 0 1\nOffset = 0 0 0\n\
         ElementSpacing = 1 1 1\nDimSize = {dim_size}\nElementNumberOfChannels = {channels}\n\
         ElementType = MET_FLOAT\nElementDataFile = LOCAL\n"
    )
    .into_bytes();
    bytes.extend(std::iter::repeat_n(0u8, data_bytes));
    std::fs::write(&path, bytes).unwrap();
    path
}

#[test]
fn metaimage_declared_sizes_are_checked_not_truncated_or_overflowed() {
    let dir = scratch_dir("mha");
    let ok = mha_file(&dir, "2 3 4", "3", 2 * 3 * 4 * 3 * 4);
    assert_eq!(read_mha(&ok).unwrap().1, 3);
    // A fractional size was silently truncated to 2.
    let e = read_mha(&mha_file(&dir, "2.5 3 4", "1", 2 * 3 * 4 * 4))
        .unwrap_err()
        .to_string();
    assert_mentions(&e, &["DimSize", "'2.5' is not a whole number"]);
    // A channel count whose product with the voxels overflows panicked.
    let e = read_mha(&mha_file(&dir, "2 3 4", "4611686018427387904", 96))
        .unwrap_err()
        .to_string();
    assert_mentions(&e, &["ElementNumberOfChannels", "1 to 16"]);
    let e = read_mha(&mha_file(&dir, "-2 3 4", "1", 96))
        .unwrap_err()
        .to_string();
    assert_mentions(&e, &["'-2' is not a whole number"]);
    let e = read_mha(&mha_file(&dir, "2 3", "1", 96))
        .unwrap_err()
        .to_string();
    assert_mentions(&e, &["DimSize", "needs 3 numbers, has 2"]);
    // No ElementDataFile in the first MiB: the header search stops there.
    let path = dir.join("long.mha");
    let mut bytes = b"NDims = 3\n".to_vec();
    bytes.extend(std::iter::repeat_n(b'x', 2 << 20));
    std::fs::write(&path, bytes).unwrap();
    let e = read_mha(&path).unwrap_err().to_string();
    assert_mentions(
        &e,
        &["ends before ElementDataFile (searched 1048576 bytes)"],
    );
    std::fs::remove_dir_all(dir).unwrap();
}

// ---------------------------------------------------------------------------------------
// Zip
// ---------------------------------------------------------------------------------------

/// Offsets of every central-directory record (signature PK\1\2) in a zip.
fn central_records(zip: &[u8]) -> Vec<usize> {
    zip.windows(4)
        .enumerate()
        .filter(|(_, w)| *w == b"PK\x01\x02")
        .map(|(i, _)| i)
        .collect()
}

#[test]
fn a_zip_entry_lying_about_its_compressed_size_keeps_the_ratio_cap() {
    use zip::write::SimpleFileOptions;
    let mut w = zip::ZipWriter::new(Cursor::new(Vec::new()));
    let options = SimpleFileOptions::default().compression_method(zip::CompressionMethod::Deflated);
    w.start_file("zeros.dcm", options).unwrap();
    w.write_all(&vec![0u8; 64 << 20]).unwrap();
    let mut zip = w.finish().unwrap().into_inner();
    // 64 MiB from ≈ 64 kB: refused as it stands.
    let e = read_zip_entries(Cursor::new(zip.clone()), "z.zip", &ArchiveLimits::default())
        .unwrap_err()
        .to_string();
    assert_mentions(&e, &["zeros.dcm", "250×"]);
    // The same entry declaring a 1 GB compressed size in the central directory (offset 20 of
    // the record) widened its own cap to 250 GB and was read.
    let record = central_records(&zip)[0];
    zip[record + 20..record + 24].copy_from_slice(&1_000_000_000u32.to_le_bytes());
    match read_zip_entries(Cursor::new(zip), "z.zip", &ArchiveLimits::default()) {
        Ok(entries) => panic!("accepted {} bytes", entries[0].data.len()),
        Err(e) => {
            let e = e.to_string();
            assert!(e.contains("250×") || e.contains("unreadable"), "{e}");
        }
    }
}

// ---------------------------------------------------------------------------------------
// Geometry a lung model cannot use
// ---------------------------------------------------------------------------------------

#[test]
fn slices_too_thick_for_a_lung_model_are_refused_for_every_format() {
    let dir = scratch_dir("thick");
    let geometry = VolumeGeometry::axis_aligned([20, 20, 8], [1.5, 1.5, 12.0], [0.0; 3]);
    let mut ct = Volume::filled(geometry, -1000.0f32).unwrap();
    ct.as_slice_mut()[..400].fill(40.0);
    let nii = dir.join("thick.nii.gz");
    write_nifti_ct(&nii, &ct).unwrap();
    let e = load_ct(&nii).unwrap_err().to_string();
    assert_mentions(
        &e,
        &[
            "thick.nii.gz",
            "1.5 × 1.5 × 12 mm",
            "12 mm apart (axis 2)",
            "10 mm",
        ],
    );
    // The case: the CIP CT with 40 mm slices, as NRRD.
    let cip = lungmotion::datasets::cip_chest_ct64();
    match cip.as_ref().map(|d| d.join("ct-64.nrrd")) {
        Some(path) if path.exists() => {
            let text = std::fs::read(&path).unwrap();
            let needle = b"(0,0,3.9873417721518987)";
            let at = text
                .windows(needle.len())
                .position(|w| w == needle)
                .expect("CIP z spacing");
            let mut thick = text[..at].to_vec();
            thick.extend_from_slice(b"(0,0,39.873417721518987)");
            thick.extend_from_slice(&text[at + needle.len()..]);
            let path = dir.join("cip-40mm.nrrd");
            std::fs::write(&path, thick).unwrap();
            let e = load_ct(&path).unwrap_err().to_string();
            assert_mentions(&e, &["cip-40mm.nrrd", "39.87 mm apart", "too coarse"]);
        }
        _ => eprintln!("skipped the CIP case: shared data absent"),
    }
    std::fs::remove_dir_all(dir).unwrap();
}

#[test]
fn a_lung_volume_beyond_adult_lungs_is_refused_naming_the_litres() {
    // The phantom (5.5 L of lungs at 5 mm) relabelled as 9.9 mm slices: within the spacing
    // limit, but its lungs now hold 11.2 L.
    let phantom = Path::new(env!("CARGO_MANIFEST_DIR")).join("sample-volumes/phantom-ct.nii.gz");
    let mut scan = load_ct(&phantom).unwrap();
    scan.ct.geometry.spacing_mm[2] = 9.9;
    let mut settings = IngestSettings::default();
    settings.model.element_size_mm = 16.0;
    let e = match ingest_scan(&scan, &settings) {
        Ok(outcome) => panic!("accepted {} mL", outcome.summary.lung_volume_ml),
        Err(e) => e.to_string(),
    };
    assert_mentions(&e, &["segmented lungs hold 11.2 L", "1–10 L", "9.90 mm"]);
}
