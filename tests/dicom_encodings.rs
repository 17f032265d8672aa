//! DICOM as hospitals send it, on files made by other tools (DCMTK, GDCM, pydicom: see
//! tests/data/dicom/make_reference_files.py): JPEG-LS lossless and near-lossless, 12-bit
//! JPEG, lossy JPEG 2000, one Enhanced CT file, and folders holding several series.

use std::path::{Path, PathBuf};

use dicom_core::value::PixelFragmentSequence;
use dicom_core::{DataElement, PrimitiveValue, VR};
use dicom_dictionary_std::tags;
use dicom_object::{open_file, DefaultDicomObject};
use lungmotion::formats::dicom::{
    read_dicom_series, read_dicom_series_with, DicomReadOptions, DicomSeries, SeriesChoice,
};

fn data(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("tests/data/dicom")
        .join(name)
}

/// A fresh, empty directory for one test.
fn scratch(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!(
        "lungmotion-dicom-enc-{}-{name}",
        std::process::id()
    ));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

fn read(name: &str) -> DicomSeries {
    read_dicom_series(&data(name)).unwrap_or_else(|e| panic!("{name}: {e}"))
}

/// Copies the files of stored series `name` into `dir/name`.
fn copy_series(name: &str, dir: &Path) -> Vec<PathBuf> {
    let to = dir.join(name);
    std::fs::create_dir_all(&to).unwrap();
    let mut copied = Vec::new();
    for entry in std::fs::read_dir(data(name)).unwrap() {
        let from = entry.unwrap().path();
        let path = to.join(from.file_name().unwrap());
        std::fs::copy(&from, &path).unwrap();
        copied.push(path);
    }
    copied
}

fn edit(path: &Path, change: impl FnOnce(&mut DefaultDicomObject)) {
    let mut obj = open_file(path).unwrap();
    change(&mut obj);
    obj.write_to_file(path).unwrap();
}

/// Largest and mean absolute difference, HU.
fn differences(a: &[f32], b: &[f32]) -> (f32, f64) {
    assert_eq!(a.len(), b.len());
    let max = a
        .iter()
        .zip(b)
        .map(|(x, y)| (x - y).abs())
        .fold(0.0, f32::max);
    let mean = a
        .iter()
        .zip(b)
        .map(|(x, y)| f64::from((x - y).abs()))
        .sum::<f64>()
        / a.len() as f64;
    (max, mean)
}

/// HU the encoding tool itself decoded, in z order, i fastest.
fn reference_hu(name: &str) -> Vec<f32> {
    std::fs::read(data(name))
        .unwrap()
        .chunks_exact(2)
        .map(|b| f32::from(i16::from_le_bytes([b[0], b[1]])))
        .collect()
}

fn assert_same_geometry(a: &DicomSeries, b: &DicomSeries) {
    let (ga, gb) = (a.volume.geometry, b.volume.geometry);
    assert_eq!(ga.dims, gb.dims);
    for axis in 0..3 {
        assert!(
            (ga.spacing_mm[axis] - gb.spacing_mm[axis]).abs() < 1e-6,
            "{ga:?} {gb:?}"
        );
        assert!(
            (ga.origin_lps_mm[axis] - gb.origin_lps_mm[axis]).abs() < 1e-6,
            "{ga:?} {gb:?}"
        );
        for c in 0..3 {
            assert!((ga.direction_lps[axis][c] - gb.direction_lps[axis][c]).abs() < 1e-9);
        }
    }
}

#[test]
fn jpeg_ls_lossless_from_dcmtk_gives_the_original_voxels_exactly() {
    let original = read("native");
    let jls = read("jpegls-lossless");
    assert_eq!(jls.info.transfer_syntax_uid, "1.2.840.10008.1.2.4.80");
    assert_eq!(original.volume.geometry.dims, [64, 64, 4]);
    assert_same_geometry(&original, &jls);
    assert_eq!(jls.volume.as_slice(), original.volume.as_slice());
    // Signed data: the lungs are below −500 HU.
    assert!(jls.volume.as_slice().iter().any(|&v| v < -900.0));
}

#[test]
fn jpeg_ls_near_lossless_from_dcmtk_stays_within_its_near_parameter() {
    let original = read("native");
    let near = read("jpegls-near2");
    assert_eq!(near.info.transfer_syntax_uid, "1.2.840.10008.1.2.4.81");
    assert_same_geometry(&original, &near);
    let (max, mean) = differences(near.volume.as_slice(), original.volume.as_slice());
    eprintln!("JPEG-LS NEAR=2: largest error {max} HU, mean {mean:.3} HU");
    // NEAR = 2 bounds every sample's error; a lossy stream differs somewhere.
    assert!((1.0..=2.0).contains(&max), "largest error {max} HU");
}

#[test]
fn jpeg_12_bit_from_dcmtk_matches_dcmtk_own_decoding() {
    let original = read("native");
    let jpeg = read("jpeg12");
    assert_eq!(jpeg.info.transfer_syntax_uid, "1.2.840.10008.1.2.4.51");
    assert_same_geometry(&original, &jpeg);
    // The inverse DCT is exact here and integer in libjpeg: one grey level apart at most.
    let (max, mean) = differences(
        jpeg.volume.as_slice(),
        &reference_hu("jpeg12.reference-hu.i16le"),
    );
    eprintln!("12-bit JPEG vs dcmdjpeg: largest {max} HU, mean {mean:.3} HU");
    assert!(max <= 1.0, "largest difference from dcmdjpeg {max} HU");
    let (max, mean) = differences(jpeg.volume.as_slice(), original.volume.as_slice());
    eprintln!("12-bit JPEG q85 vs original: largest {max} HU, mean {mean:.3} HU");
    assert!(mean < 20.0, "mean error {mean} HU");
}

#[test]
fn jpeg_2000_lossy_from_gdcm_matches_gdcm_own_decoding() {
    let original = read("native");
    let j2k = read("j2k-lossy");
    assert_eq!(j2k.info.transfer_syntax_uid, "1.2.840.10008.1.2.4.91");
    assert_same_geometry(&original, &j2k);
    let (max, mean) = differences(
        j2k.volume.as_slice(),
        &reference_hu("j2k-lossy.reference-hu.i16le"),
    );
    eprintln!("JPEG 2000 lossy vs gdcmconv --raw: largest {max} HU, mean {mean:.3} HU");
    assert!(
        max <= 1.0,
        "largest difference from GDCM's decoding {max} HU"
    );
    let (max, mean) = differences(j2k.volume.as_slice(), original.volume.as_slice());
    eprintln!("JPEG 2000 lossy vs original: largest {max} HU, mean {mean:.3} HU");
    // gdcmconv -q 80 asks for 80 dB PSNR over the 16-bit range: about 5 HU on average.
    assert!(max > 0.0 && mean < 10.0, "largest {max} HU, mean {mean} HU");
}

#[test]
fn a_broken_jpeg_ls_stream_is_refused_naming_the_file_and_codec() {
    let dir = scratch("broken-jls");
    let files = copy_series("jpegls-lossless", &dir);
    edit(&files[0], |obj| {
        let fragment = obj
            .get(tags::PIXEL_DATA)
            .unwrap()
            .value()
            .fragments()
            .unwrap()[0]
            .clone();
        let half = fragment[..fragment.len() / 2].to_vec();
        obj.put(DataElement::new(
            tags::PIXEL_DATA,
            VR::OB,
            PixelFragmentSequence::new(vec![], vec![half]),
        ));
    });
    let e = read_dicom_series(&dir).unwrap_err().to_string();
    let name = files[0].file_name().unwrap().to_string_lossy().to_string();
    assert!(
        e.contains(&name) && e.contains("cannot decode the JPEG-LS pixel data"),
        "{e}"
    );
    std::fs::remove_dir_all(dir).unwrap();
}

#[test]
fn enhanced_ct_from_pydicom_reads_as_the_classic_series() {
    let original = read("native");
    let enhanced = read("enhanced-ct.dcm");
    assert_eq!(enhanced.info.slice_count, 4);
    // Frames are stored top to bottom; the volume is ordered along the normal all the same.
    assert_same_geometry(&original, &enhanced);
    assert_eq!(enhanced.volume.as_slice(), original.volume.as_slice());
}

#[test]
fn enhanced_ct_whose_frame_count_disagrees_with_its_functional_groups_is_refused() {
    let dir = scratch("enhanced-count");
    let path = dir.join("enhanced.dcm");
    std::fs::copy(data("enhanced-ct.dcm"), &path).unwrap();
    edit(&path, |obj| {
        obj.put(DataElement::new(
            tags::NUMBER_OF_FRAMES,
            VR::IS,
            PrimitiveValue::from("3"),
        ));
    });
    let e = read_dicom_series(&dir).unwrap_err().to_string();
    assert!(
        e.contains("PerFrameFunctionalGroupsSequence")
            && e.contains("4 items for NumberOfFrames 3"),
        "{e}"
    );
    std::fs::remove_dir_all(dir).unwrap();
}

#[test]
fn enhanced_ct_frame_without_a_position_is_refused_naming_the_frame() {
    let dir = scratch("enhanced-position");
    let path = dir.join("enhanced.dcm");
    std::fs::copy(data("enhanced-ct.dcm"), &path).unwrap();
    edit(&path, |obj| {
        let mut groups = obj
            .get(tags::PER_FRAME_FUNCTIONAL_GROUPS_SEQUENCE)
            .unwrap()
            .items()
            .unwrap()
            .to_vec();
        groups[2].remove_element(tags::PLANE_POSITION_SEQUENCE);
        obj.put(DataElement::new(
            tags::PER_FRAME_FUNCTIONAL_GROUPS_SEQUENCE,
            VR::SQ,
            dicom_core::value::DataSetSequence::from(groups),
        ));
    });
    let e = read_dicom_series(&dir).unwrap_err().to_string();
    assert!(
        e.contains("frame 3 of 4") && e.contains("ImagePositionPatient (0020,0032) is missing"),
        "{e}"
    );
    std::fs::remove_dir_all(dir).unwrap();
}

/// A folder as a PACS export leaves it: the same four slices in three series (uncompressed,
/// JPEG-LS, JPEG 2000) plus a scout.
fn several_series(name: &str) -> PathBuf {
    let dir = scratch(name);
    copy_series("native", &dir);
    copy_series("jpegls-lossless", &dir);
    copy_series("j2k-lossy", &dir);
    dir
}

fn choose(dir: &Path, choice: &str) -> Result<DicomSeries, String> {
    let options = DicomReadOptions {
        series: Some(choice.parse().unwrap()),
        ..DicomReadOptions::default()
    };
    read_dicom_series_with(dir, &options).map_err(|e| e.to_string())
}

#[test]
fn several_ct_series_without_a_choice_are_listed_with_how_to_choose() {
    let dir = several_series("listed");
    let e = read_dicom_series(&dir).unwrap_err().to_string();
    assert!(e.contains("3 CT series found"), "{e}");
    for description in [
        "native (pydicom)",
        "JPEG-LS lossless (dcmcjpls)",
        "JPEG 2000 lossy (gdcmconv)",
    ] {
        assert!(e.contains(description), "{e}");
    }
    assert!(
        e.contains("number 2") && e.contains("number 3") && e.contains("number 6"),
        "{e}"
    );
    assert!(e.contains("4 files, 64×64 pixels"), "{e}");
    assert!(
        e.contains("--series") && e.contains("series = ") && e.contains("?series="),
        "{e}"
    );
    std::fs::remove_dir_all(dir).unwrap();
}

#[test]
fn a_series_is_chosen_by_number_description_or_uid() {
    let dir = several_series("chosen");
    let by_number = choose(&dir, "3").unwrap();
    assert_eq!(by_number.info.transfer_syntax_uid, "1.2.840.10008.1.2.4.80");
    let by_description = choose(&dir, "description:  JPEG 2000 LOSSY (gdcmconv) ").unwrap();
    assert_eq!(
        by_description.info.transfer_syntax_uid,
        "1.2.840.10008.1.2.4.91"
    );
    let uid = by_number.info.series_instance_uid.clone();
    let by_uid = choose(&dir, &uid).unwrap();
    assert_eq!(by_uid.info.series_instance_uid, uid);
    assert_eq!(by_uid.volume.as_slice(), by_number.volume.as_slice());
    let e = choose(&dir, "number:9").unwrap_err();
    assert!(
        e.contains("no series numbered 9") && e.contains(&uid),
        "{e}"
    );
    let e = choose(&dir, "description:arterial phase").unwrap_err();
    assert!(e.contains("no series described \"arterial phase\""), "{e}");
    std::fs::remove_dir_all(dir).unwrap();
}

#[test]
fn a_scout_beside_the_volume_is_ignored_with_a_warning() {
    let dir = scratch("scout");
    copy_series("native", &dir);
    for path in copy_series("jpeg12", &dir) {
        edit(&path, |obj| {
            obj.put(DataElement::new(
                tags::IMAGE_TYPE,
                VR::CS,
                PrimitiveValue::from("ORIGINAL\\PRIMARY\\LOCALIZER"),
            ));
        });
    }
    let series = read_dicom_series(&dir).unwrap();
    assert_eq!(
        series.info.series_description.as_deref(),
        Some("native (pydicom)")
    );
    assert!(
        series
            .warnings
            .iter()
            .any(|w| w.contains("ignored the other series")
                && w.contains("JPEG extended 12-bit (dcmcjpeg)")),
        "{:?}",
        series.warnings
    );
    // A scout is still readable when asked for.
    let scout = choose(&dir, "number:5").unwrap();
    assert_eq!(scout.info.transfer_syntax_uid, "1.2.840.10008.1.2.4.51");
    std::fs::remove_dir_all(dir).unwrap();
}

#[test]
fn series_choices_parse_by_prefix_or_shape() {
    let parse = |s: &str| s.parse::<SeriesChoice>().map_err(|e| e.to_string());
    assert_eq!(parse("12"), Ok(SeriesChoice::Number(12)));
    assert_eq!(
        parse("1.2.840.113619.2"),
        Ok(SeriesChoice::Uid("1.2.840.113619.2".into()))
    );
    assert_eq!(
        parse("AX 1.25mm lung"),
        Ok(SeriesChoice::Description("AX 1.25mm lung".into()))
    );
    assert_eq!(
        parse("description:3"),
        Ok(SeriesChoice::Description("3".into()))
    );
    assert_eq!(parse("UID:1.2.3"), Ok(SeriesChoice::Uid("1.2.3".into())));
    let e = parse("number:three").unwrap_err();
    assert!(e.contains("\"three\" is not an integer"), "{e}");
    assert!(parse("uid:").unwrap_err().contains("empty"));
}

#[test]
fn the_cli_reads_the_series_named_by_series_and_lists_them_without_it() {
    let dir = scratch("cli");
    let phantom = Path::new(env!("CARGO_MANIFEST_DIR")).join("sample-volumes/phantom-dicom");
    let to = dir.join("phantom");
    std::fs::create_dir_all(&to).unwrap();
    for entry in std::fs::read_dir(phantom).unwrap() {
        let from = entry.unwrap().path();
        std::fs::copy(&from, to.join(from.file_name().unwrap())).unwrap();
    }
    copy_series("native", &dir);
    let ingest = |extra: &[&str]| {
        std::process::Command::new(env!("CARGO_BIN_EXE_lungmotion"))
            .args(["ingest", "--element-size", "16", "--ct"])
            .arg(&dir)
            .arg("--out")
            .arg(dir.join("out"))
            .args(extra)
            .output()
            .unwrap()
    };
    let refused = ingest(&[]);
    let stderr = String::from_utf8_lossy(&refused.stderr);
    assert_eq!(refused.status.code(), Some(2), "{stderr}");
    assert!(
        stderr.contains("2 CT series found")
            && stderr.contains("lungmotion thorax phantom")
            && stderr.contains("--series"),
        "{stderr}"
    );
    let chosen = ingest(&["--series", "description:LUNGMOTION THORAX PHANTOM"]);
    let stderr = String::from_utf8_lossy(&chosen.stderr);
    assert!(chosen.status.success(), "{stderr}");
    assert!(dir.join("out/ingest.json").is_file());
    std::fs::remove_dir_all(dir).unwrap();
}

#[test]
fn the_run_configuration_names_the_series_with_the_same_syntax() {
    use lungmotion::run::RunConfig;
    let config = RunConfig::from_toml("series = \"number:3\"").unwrap();
    assert_eq!(config.series, Some(SeriesChoice::Number(3)));
    assert_eq!(
        config.dicom_read_options().series,
        Some(SeriesChoice::Number(3))
    );
    let e = RunConfig::from_toml("series = \"number:three\"")
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("series") && e.contains("is not an integer"),
        "{e}"
    );
}

#[test]
fn compressed_enhanced_ct_decodes_frame_by_frame() {
    let original = read("native");
    for (name, syntax) in [
        ("enhanced-ct-jpegls.dcm", "1.2.840.10008.1.2.4.80"),
        ("enhanced-ct-j2k.dcm", "1.2.840.10008.1.2.4.90"),
    ] {
        let enhanced = read(name);
        assert_eq!(enhanced.info.transfer_syntax_uid, syntax);
        assert_same_geometry(&original, &enhanced);
        assert_eq!(
            enhanced.volume.as_slice(),
            original.volume.as_slice(),
            "{name}"
        );
    }
}

/// The study context names, for every volume slice k, the instance it was read from (in the
/// slices' spatial order, not file order), and the CT's study and frame of reference, as a
/// reader of the files themselves finds them.
#[test]
fn study_context_references_each_slice_in_spatial_order() {
    let dir = Path::new(env!("CARGO_MANIFEST_DIR")).join("sample-volumes/phantom-dicom");
    let series = read_dicom_series(&dir).unwrap();
    let study = &series.study;
    assert!(study.from_input);
    assert_eq!(study.slices.len(), series.volume.geometry.dims[2]);
    let g = series.volume.geometry;
    let normal = g.direction_lps[2];
    for entry in std::fs::read_dir(&dir).unwrap() {
        let obj = open_file(entry.unwrap().path()).unwrap();
        let get = |tag| {
            obj.element(tag)
                .unwrap()
                .to_str()
                .unwrap()
                .trim()
                .to_string()
        };
        assert_eq!(get(tags::STUDY_INSTANCE_UID), study.study_instance_uid);
        assert_eq!(
            get(tags::FRAME_OF_REFERENCE_UID),
            study.frame_of_reference_uid
        );
        assert_eq!(get(tags::PATIENT_ID), study.patient_id);
        let position: Vec<f64> = obj
            .element(tags::IMAGE_POSITION_PATIENT)
            .unwrap()
            .to_multi_float64()
            .unwrap();
        let along: f64 = (0..3)
            .map(|a| (position[a] - g.origin_lps_mm[a]) * normal[a])
            .sum();
        let k = (along / g.spacing_mm[2]).round() as usize;
        assert_eq!(
            study.slices[k].sop_instance_uid,
            get(tags::SOP_INSTANCE_UID),
            "slice {k}"
        );
        assert_eq!(study.slices[k].sop_class_uid, get(tags::SOP_CLASS_UID));
    }
}
