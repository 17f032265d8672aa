//! DICOM CT series: writer/reader round trips, transfer syntaxes, the real reference series,
//! and refusal of broken or hostile input. Fixtures are written at test time into temp dirs.

use std::io::{Cursor, Write};
use std::path::{Path, PathBuf};
use std::time::Instant;

use dicom_core::value::PixelFragmentSequence;
use dicom_core::{DataElement, Length, PrimitiveValue, VR};
use dicom_dictionary_std::tags;
use dicom_object::{open_file, DefaultDicomObject};
use dicom_pixeldata::Transcode;
use dicom_transfer_syntax_registry::entries;
use lungmotion::datasets::{cip_chest_ct64, totalseg_abdomen_ct};
use lungmotion::formats::dicom::{
    read_dicom_series, read_dicom_series_with, write_ct_series, CtSeriesMetadata, DicomReadOptions,
};
use lungmotion::formats::nrrd::read_nrrd;
use lungmotion::volume::{Volume, VolumeGeometry};
use nalgebra::{Rotation3, Unit, Vector3};

/// A fresh, empty directory for one test.
fn scratch(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("lungmotion-dicom-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// An oblique, non-square grid (so a rows/columns or axis mix-up shows) with values that
/// need rounding and cover air to dense bone.
fn oblique_volume(dims: [usize; 3]) -> Volume<f32> {
    let rotation =
        Rotation3::from_axis_angle(&Unit::new_normalize(Vector3::new(1.0, 2.0, 3.0)), 0.4);
    let m = rotation.matrix();
    let column = |c: usize| [m[(0, c)], m[(1, c)], m[(2, c)]];
    let geometry = VolumeGeometry {
        dims,
        spacing_mm: [0.7, 0.8, 2.5],
        origin_lps_mm: [-120.5, 33.25, -400.125],
        direction_lps: [column(0), column(1), column(2)],
    };
    let data = (0..geometry.voxel_count())
        .map(|n| -1024.0 + ((n * 7919) % 3100) as f32 + 0.3 * ((n % 3) as f32))
        .collect();
    Volume::from_data(geometry, data).unwrap()
}

/// A smooth axis-aligned volume (JPEG-friendly) in −1000…1000 HU.
fn smooth_volume(dims: [usize; 3]) -> Volume<f32> {
    let geometry = VolumeGeometry::axis_aligned(dims, [1.0, 1.0, 2.0], [-10.0, -20.0, -30.0]);
    let mut data = Vec::with_capacity(geometry.voxel_count());
    for k in 0..dims[2] {
        for j in 0..dims[1] {
            for i in 0..dims[0] {
                let x = i as f32 / dims[0] as f32;
                let y = j as f32 / dims[1] as f32;
                data.push(-1000.0 + 2000.0 * (0.5 + 0.5 * (6.0 * x + 4.0 * y + k as f32).sin()));
            }
        }
    }
    Volume::from_data(geometry, data).unwrap()
}

fn write_series(dir: &Path, volume: &Volume<f32>, seed: u64) -> Vec<PathBuf> {
    let meta = CtSeriesMetadata {
        uid_seed: seed,
        ..CtSeriesMetadata::default()
    };
    write_ct_series(volume, dir, &meta).unwrap()
}

fn edit(path: &Path, change: impl FnOnce(&mut DefaultDicomObject)) {
    let mut obj = open_file(path).unwrap();
    change(&mut obj);
    obj.write_to_file(path).unwrap();
}

fn put_ds(obj: &mut DefaultDicomObject, tag: dicom_core::Tag, value: &str) {
    obj.put(DataElement::new(tag, VR::DS, PrimitiveValue::from(value)));
}

fn read_err(input: &Path) -> String {
    read_dicom_series(input).unwrap_err().to_string()
}

fn assert_same_geometry(a: &VolumeGeometry, b: &VolumeGeometry, tol_mm: f64) {
    assert_eq!(a.dims, b.dims);
    for axis in 0..3 {
        assert!(
            (a.spacing_mm[axis] - b.spacing_mm[axis]).abs() <= tol_mm,
            "spacing {:?} vs {:?}",
            a.spacing_mm,
            b.spacing_mm
        );
        assert!(
            (a.origin_lps_mm[axis] - b.origin_lps_mm[axis]).abs() <= tol_mm,
            "origin {:?} vs {:?}",
            a.origin_lps_mm,
            b.origin_lps_mm
        );
    }
    assert!(a.same_grid(b, tol_mm), "{a:?} vs {b:?}");
}

fn rounded(volume: &Volume<f32>) -> Vec<f32> {
    volume.as_slice().iter().map(|v| v.round()).collect()
}

#[test]
fn an_oblique_series_round_trips_with_unsorted_file_names() {
    let dir = scratch("roundtrip");
    let volume = oblique_volume([23, 17, 9]);
    let paths = write_series(&dir, &volume, 7);
    assert_eq!(paths.len(), 9);
    assert!(paths[0].ends_with("IMG0001.dcm") && paths[8].ends_with("IMG0009.dcm"));
    // Names that sort against the slice order: ordering must come from the positions.
    for (k, p) in paths.iter().enumerate() {
        std::fs::rename(p, dir.join(format!("S{}.dcm", 9 - k))).unwrap();
    }
    let series = read_dicom_series(&dir).unwrap();
    assert_same_geometry(&series.volume.geometry, &volume.geometry, 1e-4);
    let direction_error = (series.volume.geometry.direction() - volume.geometry.direction())
        .abs()
        .max();
    assert!(direction_error < 1e-9, "direction error {direction_error}");
    assert_eq!(series.volume.as_slice(), rounded(&volume));
    assert!(series.warnings.is_empty(), "{:?}", series.warnings);
    let info = &series.info;
    assert_eq!((info.rows, info.columns, info.slice_count), (17, 23, 9));
    assert_eq!(info.modality, "CT");
    assert_eq!(info.transfer_syntax_uid, "1.2.840.10008.1.2.1");
    assert_eq!(info.patient_position.as_deref(), Some("HFS"));
    // Nothing identifying leaks into the description.
    let json = serde_json::to_string(info).unwrap();
    assert!(!json.contains("PHANTOM^THORAX") && !json.contains("LUNGMOTION-PHANTOM"));

    // Same seed and data give the same UIDs; another seed gives another series.
    let again = scratch("roundtrip-again");
    write_series(&again, &volume, 7);
    let other = scratch("roundtrip-other");
    write_series(&other, &volume, 8);
    let uid_of = |d: &Path| read_dicom_series(d).unwrap().info.series_instance_uid;
    assert_eq!(uid_of(&again), info.series_instance_uid);
    assert_ne!(uid_of(&other), info.series_instance_uid);
    for d in [dir, again, other] {
        std::fs::remove_dir_all(d).unwrap();
    }
}

#[test]
fn values_outside_int16_use_a_rescale_intercept() {
    let dir = scratch("intercept");
    let mut volume = smooth_volume([8, 6, 3]);
    volume
        .as_slice_mut()
        .iter_mut()
        .for_each(|v| *v = *v * 30.0 + 20_000.0);
    let max = volume.as_slice().iter().cloned().fold(f32::MIN, f32::max);
    assert!(max > 40_000.0);
    let paths = write_series(&dir, &volume, 1);
    let obj = open_file(&paths[0]).unwrap();
    let intercept: f64 = obj
        .element(tags::RESCALE_INTERCEPT)
        .unwrap()
        .to_float64()
        .unwrap();
    assert!(intercept != 0.0);
    let series = read_dicom_series(&dir).unwrap();
    assert_eq!(series.volume.as_slice(), rounded(&volume));
    std::fs::remove_dir_all(dir).unwrap();
}

/// Copies a series into `dir` with every file passed through `change`.
fn transcoded_copy(
    src: &[PathBuf],
    dir: &Path,
    change: impl Fn(&mut DefaultDicomObject) + Sync,
) -> PathBuf {
    std::fs::create_dir_all(dir).unwrap();
    for p in src {
        let mut obj = open_file(p).unwrap();
        change(&mut obj);
        obj.write_to_file(dir.join(p.file_name().unwrap())).unwrap();
    }
    dir.to_path_buf()
}

#[test]
fn native_transfer_syntaxes_read_identically() {
    let dir = scratch("native-ts");
    let volume = oblique_volume([19, 13, 5]);
    let src = write_series(&dir.join("src"), &volume, 3);
    let reference = read_dicom_series(&dir.join("src")).unwrap();
    for (name, uid) in [
        ("implicit", "1.2.840.10008.1.2"),
        ("big", "1.2.840.10008.1.2.2"),
        ("deflate", "1.2.840.10008.1.2.1.99"),
    ] {
        let out = transcoded_copy(&src, &dir.join(name), |obj| match name {
            "implicit" => obj
                .transcode(&entries::IMPLICIT_VR_LITTLE_ENDIAN.erased())
                .unwrap(),
            "big" => obj
                .transcode(&entries::EXPLICIT_VR_BIG_ENDIAN.erased())
                .unwrap(),
            _ => obj
                .transcode(&entries::DEFLATED_EXPLICIT_VR_LITTLE_ENDIAN.erased())
                .unwrap(),
        });
        let series = read_dicom_series(&out).unwrap();
        assert_eq!(series.info.transfer_syntax_uid, uid, "{name}");
        assert_eq!(
            series.volume.as_slice(),
            reference.volume.as_slice(),
            "{name}"
        );
        assert_same_geometry(&series.volume.geometry, &reference.volume.geometry, 1e-9);
    }
    // Pixel Data is the last element: in the big-endian file its bytes are swapped, so the
    // equality above is not a no-op.
    let le = std::fs::read(&src[0]).unwrap();
    let be = std::fs::read(dir.join("big").join(src[0].file_name().unwrap())).unwrap();
    let tail = 19 * 13 * 2;
    let (le, be) = (&le[le.len() - tail..], &be[be.len() - tail..]);
    assert_ne!(le, be);
    assert!(le
        .chunks(2)
        .zip(be.chunks(2))
        .all(|(a, b)| a[0] == b[1] && a[1] == b[0]));
    std::fs::remove_dir_all(dir).unwrap();
}

/// Appends the `count` low bits of `value` to a JPEG entropy-coded stream, stuffing 0xFF.
struct BitWriter {
    bytes: Vec<u8>,
    accumulator: u32,
    filled: u32,
}

impl BitWriter {
    fn put(&mut self, value: u32, count: u32) {
        for bit in (0..count).rev() {
            self.accumulator = (self.accumulator << 1) | ((value >> bit) & 1);
            self.filled += 1;
            if self.filled == 8 {
                let byte = self.accumulator as u8;
                self.bytes.push(byte);
                if byte == 0xFF {
                    self.bytes.push(0);
                }
                self.accumulator = 0;
                self.filled = 0;
            }
        }
    }

    fn finish(mut self) -> Vec<u8> {
        while self.filled != 0 {
            self.put(1, 1);
        }
        self.bytes
    }
}

/// Encodes a 16-bit frame as JPEG lossless (ITU T.81 process 14, SOF3), first-order
/// predictor, one Huffman table giving each of the 17 difference categories a 5-bit code.
fn jpeg_lossless(samples: &[u16], rows: usize, columns: usize) -> Vec<u8> {
    let mut out = vec![0xFF, 0xD8];
    // DHT: class 0, id 0; 17 codes of length 5 for categories 0…16.
    out.extend_from_slice(&[0xFF, 0xC4, 0, 19 + 17, 0x00]);
    let mut counts = [0u8; 16];
    counts[4] = 17;
    out.extend_from_slice(&counts);
    out.extend((0..17u8).collect::<Vec<_>>());
    // SOF3: 16-bit precision, one component.
    out.extend_from_slice(&[0xFF, 0xC3, 0, 11, 16]);
    out.extend_from_slice(&(rows as u16).to_be_bytes());
    out.extend_from_slice(&(columns as u16).to_be_bytes());
    out.extend_from_slice(&[1, 1, 0x11, 0]);
    // SOS: predictor 1 (left), point transform 0.
    out.extend_from_slice(&[0xFF, 0xDA, 0, 8, 1, 1, 0x00, 1, 0, 0]);
    let mut bits = BitWriter {
        bytes: Vec::new(),
        accumulator: 0,
        filled: 0,
    };
    for j in 0..rows {
        for i in 0..columns {
            let prediction = match (i, j) {
                (0, 0) => 1 << 15,
                (0, _) => i32::from(samples[(j - 1) * columns]),
                _ => i32::from(samples[j * columns + i - 1]),
            };
            let mut diff = i32::from(samples[j * columns + i]) - prediction;
            if diff > 32768 {
                diff -= 65536;
            } else if diff < -32767 {
                diff += 65536;
            }
            let category = 32 - diff.unsigned_abs().leading_zeros();
            bits.put(category, 5);
            if category > 0 && category < 16 {
                let extra = if diff > 0 { diff } else { diff - 1 };
                bits.put(extra as u32 & ((1 << category) - 1), category);
            }
        }
    }
    out.extend(bits.finish());
    out.extend_from_slice(&[0xFF, 0xD9]);
    out
}

#[test]
fn jpeg_lossless_reads_identically() {
    // dicom-rs has no JPEG lossless encoder: the test encodes with its own SOF3 writer and the
    // reader decodes with dicom-rs (jpeg-decoder).
    let dir = scratch("jpeg-lossless");
    let volume = oblique_volume([21, 11, 4]);
    let src = write_series(&dir.join("src"), &volume, 4);
    let out = transcoded_copy(&src, &dir.join("jpegll"), |obj| {
        let samples: Vec<u16> = obj
            .element(tags::PIXEL_DATA)
            .unwrap()
            .to_multi_int::<u16>()
            .unwrap();
        let mut fragment = jpeg_lossless(&samples, 11, 21);
        if fragment.len() % 2 == 1 {
            fragment.push(0);
        }
        obj.put(DataElement::new_with_len(
            tags::PIXEL_DATA,
            VR::OB,
            Length::UNDEFINED,
            PixelFragmentSequence::new(vec![], vec![fragment]),
        ));
        obj.update_meta(|m| {
            m.set_transfer_syntax(&entries::JPEG_LOSSLESS_NON_HIERARCHICAL_FIRST_ORDER_PREDICTION)
        });
    });
    let series = read_dicom_series(&out).unwrap();
    assert_eq!(series.info.transfer_syntax_uid, "1.2.840.10008.1.2.4.70");
    assert_eq!(series.volume.as_slice(), rounded(&volume));
    std::fs::remove_dir_all(dir).unwrap();
}

/// Reading speed of a clinical-size series (run with `--ignored --nocapture`).
#[test]
#[ignore]
fn a_512_by_512_by_300_series_reads_at_disk_speed() {
    let dir = scratch("large");
    let geometry = VolumeGeometry::axis_aligned([512, 512, 300], [0.7, 0.7, 1.0], [0.0; 3]);
    let data = (0..geometry.voxel_count())
        .map(|n| ((n * 7919) % 3000) as f32 - 1024.0)
        .collect();
    let volume = Volume::from_data(geometry, data).unwrap();
    let started = Instant::now();
    write_series(&dir, &volume, 1);
    let write_s = started.elapsed().as_secs_f64();
    let started = Instant::now();
    let mut bytes = 0usize;
    for entry in std::fs::read_dir(&dir).unwrap() {
        bytes += std::fs::read(entry.unwrap().path()).unwrap().len();
    }
    let raw_read_s = started.elapsed().as_secs_f64();
    let started = Instant::now();
    let series = read_dicom_series(&dir).unwrap();
    let read_s = started.elapsed().as_secs_f64();
    println!(
        "512×512×300 ({:.0} MB): write {write_s:.2} s, plain file reads {raw_read_s:.2} s, \
         read_dicom_series {read_s:.2} s",
        bytes as f64 / 1e6
    );
    assert_eq!(series.volume.as_slice(), volume.as_slice());
    std::fs::remove_dir_all(dir).unwrap();
}

/// PackBits as RLE Lossless (PS3.5 G.3.1) uses it: replicate runs of ≥ 3, literals otherwise.
fn packbits(bytes: &[u8], out: &mut Vec<u8>) {
    let mut i = 0;
    while i < bytes.len() {
        let mut run = 1;
        while i + run < bytes.len() && bytes[i + run] == bytes[i] && run < 128 {
            run += 1;
        }
        if run >= 3 {
            out.push((1i16 - run as i16) as i8 as u8);
            out.push(bytes[i]);
            i += run;
            continue;
        }
        let start = i;
        while i < bytes.len() && i - start < 128 {
            let repeats =
                i + 2 < bytes.len() && bytes[i] == bytes[i + 1] && bytes[i] == bytes[i + 2];
            if repeats {
                break;
            }
            i += 1;
        }
        out.push((i - start - 1) as u8);
        out.extend_from_slice(&bytes[start..i]);
    }
}

/// Re-encodes a 16-bit native frame as one RLE Lossless fragment (high bytes, then low bytes).
fn rle_encode(obj: &mut DefaultDicomObject) {
    let pixels: Vec<u16> = obj
        .element(tags::PIXEL_DATA)
        .unwrap()
        .to_multi_int::<u16>()
        .unwrap();
    let high: Vec<u8> = pixels.iter().map(|v| (v >> 8) as u8).collect();
    let low: Vec<u8> = pixels.iter().map(|v| (v & 0xFF) as u8).collect();
    let mut segments = Vec::new();
    let mut offsets = Vec::new();
    for plane in [&high, &low] {
        offsets.push(64 + segments.len() as u32);
        packbits(plane, &mut segments);
        if segments.len() % 2 == 1 {
            segments.push(0);
        }
    }
    let mut fragment = Vec::with_capacity(64 + segments.len());
    fragment.extend_from_slice(&2u32.to_le_bytes());
    for n in 0..15 {
        fragment.extend_from_slice(&offsets.get(n).copied().unwrap_or(0).to_le_bytes());
    }
    fragment.extend_from_slice(&segments);
    obj.put(DataElement::new_with_len(
        tags::PIXEL_DATA,
        VR::OB,
        Length::UNDEFINED,
        PixelFragmentSequence::new(vec![], vec![fragment]),
    ));
    obj.update_meta(|m| m.set_transfer_syntax(&entries::RLE_LOSSLESS));
}

#[test]
fn rle_lossless_reads_identically() {
    // dicom-rs has no RLE encoder: the test encodes with its own PackBits writer and the
    // reader decodes with dicom-rs's RLE decoder.
    let dir = scratch("rle");
    let volume = oblique_volume([21, 11, 4]);
    let src = write_series(&dir.join("src"), &volume, 4);
    let out = transcoded_copy(&src, &dir.join("rle"), rle_encode);
    let series = read_dicom_series(&out).unwrap();
    assert_eq!(series.info.transfer_syntax_uid, "1.2.840.10008.1.2.5");
    assert_eq!(series.volume.as_slice(), rounded(&volume));
    std::fs::remove_dir_all(dir).unwrap();
}

#[test]
fn jpeg_baseline_of_an_8_bit_unsigned_series_reads_within_tolerance() {
    // JPEG baseline holds 8 bits: the series is first stored as unsigned 8-bit values with
    // RescaleSlope 8 and RescaleIntercept −1000, which also exercises the reader's unsigned
    // 8-bit path and the rescale, then transcoded with dicom-rs's JPEG encoder (quality 85).
    let dir = scratch("jpeg");
    let volume = smooth_volume([32, 24, 3]);
    let src = write_series(&dir.join("src"), &volume, 5);
    let to_8_bit = |obj: &mut DefaultDicomObject| {
        let stored: Vec<i16> = obj
            .element(tags::PIXEL_DATA)
            .unwrap()
            .to_multi_int::<u16>()
            .unwrap()
            .into_iter()
            .map(|v| v as i16)
            .collect();
        let bytes: Vec<u8> = stored
            .iter()
            .map(|&hu| ((f64::from(hu) + 1000.0) / 8.0).round().clamp(0.0, 255.0) as u8)
            .collect();
        for (tag, v) in [
            (tags::BITS_ALLOCATED, 8u16),
            (tags::BITS_STORED, 8),
            (tags::HIGH_BIT, 7),
            (tags::PIXEL_REPRESENTATION, 0),
        ] {
            obj.put(DataElement::new(tag, VR::US, PrimitiveValue::from(v)));
        }
        put_ds(obj, tags::RESCALE_SLOPE, "8");
        put_ds(obj, tags::RESCALE_INTERCEPT, "-1000");
        obj.put(DataElement::new(
            tags::PIXEL_DATA,
            VR::OB,
            PrimitiveValue::from(bytes),
        ));
    };
    let native8 = transcoded_copy(&src, &dir.join("u8"), to_8_bit);
    let exact = read_dicom_series(&native8).unwrap();
    let quantised: Vec<f32> = volume
        .as_slice()
        .iter()
        .map(|&hu| ((hu.round() + 1000.0) / 8.0).round().clamp(0.0, 255.0) * 8.0 - 1000.0)
        .collect();
    assert_eq!(exact.volume.as_slice(), quantised);

    let jpeg = transcoded_copy(&src, &dir.join("jpeg"), |obj| {
        to_8_bit(obj);
        obj.transcode(&entries::JPEG_BASELINE.erased()).unwrap();
    });
    let lossy = read_dicom_series(&jpeg).unwrap();
    assert_eq!(lossy.info.transfer_syntax_uid, "1.2.840.10008.1.2.4.50");
    let errors: Vec<f32> = lossy
        .volume
        .as_slice()
        .iter()
        .zip(exact.volume.as_slice())
        .map(|(a, b)| (a - b).abs())
        .collect();
    let max = errors.iter().cloned().fold(0.0, f32::max);
    let mean = errors.iter().sum::<f32>() / errors.len() as f32;
    println!("JPEG baseline q85: mean |error| {mean:.2} HU, max {max:.1} HU");
    // A few 8-HU steps at most on a smooth image; a decoding error would be hundreds of HU.
    assert!(max <= 80.0 && mean <= 16.0, "mean {mean}, max {max}");
    std::fs::remove_dir_all(dir).unwrap();
}

#[test]
fn a_zipped_series_reads_like_the_directory() {
    let dir = scratch("zip");
    let volume = oblique_volume([9, 7, 4]);
    let paths = write_series(&dir.join("src"), &volume, 6);
    let mut w = zip::ZipWriter::new(Cursor::new(Vec::new()));
    let options = zip::write::SimpleFileOptions::default()
        .compression_method(zip::CompressionMethod::Deflated);
    w.add_directory("export/", options).unwrap();
    for p in paths.iter().rev() {
        let name = format!("export/{}", p.file_name().unwrap().to_string_lossy());
        w.start_file(name, options).unwrap();
        w.write_all(&std::fs::read(p).unwrap()).unwrap();
    }
    w.start_file("export/DICOMDIR", options).unwrap();
    w.write_all(b"not parsed").unwrap();
    let zip_path = dir.join("export.zip");
    std::fs::write(&zip_path, w.finish().unwrap().into_inner()).unwrap();
    let series = read_dicom_series(&zip_path).unwrap();
    assert_eq!(series.volume.as_slice(), rounded(&volume));
    assert!(series.warnings.is_empty(), "{:?}", series.warnings);
    std::fs::remove_dir_all(dir).unwrap();
}

#[test]
#[cfg_attr(
    not(shared_data),
    ignore = "needs the shared CT data (../shared/data or LUNGMOTION_SHARED_DATA; see README)"
)]
fn the_cip_series_matches_its_nrrd_exactly() {
    let Some(case) = cip_chest_ct64() else {
        println!("skipped: shared data not found");
        return;
    };
    let started = Instant::now();
    let series = read_dicom_series(&case.join("dicom")).unwrap();
    println!(
        "CIP 64×64×79 read in {:.1} ms",
        started.elapsed().as_secs_f64() * 1e3
    );
    let nrrd = read_nrrd(&case.join("ct-64.nrrd")).unwrap();
    assert_same_geometry(&series.volume.geometry, &nrrd.geometry, 1e-3);
    let max_difference = series
        .volume
        .as_slice()
        .iter()
        .zip(nrrd.as_slice())
        .map(|(a, b)| (a - b).abs())
        .fold(0.0f32, f32::max);
    assert_eq!(max_difference, 0.0);
    assert_eq!(series.info.slice_count, 79);
    // The files are Implicit VR Little Endian (the data README says explicit).
    assert_eq!(series.info.transfer_syntax_uid, "1.2.840.10008.1.2");
}

#[test]
#[cfg_attr(
    not(shared_data),
    ignore = "needs the shared CT data (../shared/data or LUNGMOTION_SHARED_DATA; see README)"
)]
fn the_totalsegmentator_jpeg2000_series_reads_in_position_order() {
    let Some(case) = totalseg_abdomen_ct() else {
        println!("skipped: shared data not found");
        return;
    };
    let started = Instant::now();
    let series = read_dicom_series(&case.join("dicom")).unwrap();
    println!(
        "TotalSegmentator 512×512×20 JPEG 2000 read in {:.0} ms",
        started.elapsed().as_secs_f64() * 1e3
    );
    let g = series.volume.geometry;
    assert_eq!(g.dims, [512, 512, 20]);
    assert!((g.spacing_mm[0] - 0.977).abs() < 0.001 && (g.spacing_mm[1] - 0.977).abs() < 0.001);
    // 3 mm thick slices every 2 mm: 20 positions from −804.5 to −766.5 mm.
    assert!((g.spacing_mm[2] - 2.0).abs() < 1e-3, "{:?}", g.spacing_mm);
    // IOP 1\0\0\0\1\0: the normal is +z, so k runs upwards from the lowest slice.
    let first_z = g.origin_lps_mm[2];
    let last_z = g.voxel_to_lps_mm(Vector3::new(0.0, 0.0, 19.0)).z;
    assert!(
        (first_z + 804.5).abs() < 1e-3 && (last_z + 766.5).abs() < 1e-3,
        "{first_z} {last_z}"
    );
    assert_eq!(series.info.transfer_syntax_uid, "1.2.840.10008.1.2.4.90");
    let min = series
        .volume
        .as_slice()
        .iter()
        .cloned()
        .fold(f32::MAX, f32::min);
    let max = series
        .volume
        .as_slice()
        .iter()
        .cloned()
        .fold(f32::MIN, f32::max);
    let air = series
        .volume
        .as_slice()
        .iter()
        .filter(|&&v| v < -900.0)
        .count();
    println!("HU range {min} … {max}, {air} voxels below −900 HU");
    assert!((-1100.0..=-900.0).contains(&min) && max > 300.0 && max < 4000.0);
    assert!(air > 100_000, "{air}");
}

#[test]
fn non_dicom_and_truncated_files_are_skipped_with_a_warning() {
    let dir = scratch("mixed");
    let volume = oblique_volume([8, 6, 4]);
    let paths = write_series(&dir, &volume, 9);
    std::fs::write(dir.join("notes.txt"), "exported by the PACS").unwrap();
    let bytes = std::fs::read(&paths[1]).unwrap();
    std::fs::write(dir.join("partial.dcm"), &bytes[..bytes.len() / 2]).unwrap();
    std::fs::write(dir.join("short-pixels.dcm"), &bytes[..bytes.len() - 20]).unwrap();
    std::fs::write(dir.join("DICOMDIR"), "directory record, ignored").unwrap();
    let series = read_dicom_series(&dir).unwrap();
    assert_eq!(series.volume.as_slice(), rounded(&volume));
    assert_eq!(series.warnings.len(), 3, "{:?}", series.warnings);
    let all = series.warnings.join("\n");
    for name in ["notes.txt", "partial.dcm", "short-pixels.dcm"] {
        assert!(all.contains(&format!("{name}: skipped")), "{all}");
    }
    assert!(!all.contains("DICOMDIR"));
    std::fs::remove_dir_all(dir).unwrap();
}

#[test]
fn a_directory_of_garbage_is_refused() {
    let dir = scratch("garbage");
    std::fs::write(dir.join("a.dcm"), vec![0u8; 300]).unwrap();
    std::fs::write(dir.join("b.txt"), "hello").unwrap();
    let e = read_err(&dir);
    assert!(
        e.contains("no readable DICOM") && e.contains("2 skipped"),
        "{e}"
    );
    std::fs::remove_dir_all(&dir).unwrap();
    std::fs::create_dir_all(&dir).unwrap();
    let e = read_err(&dir);
    assert!(e.contains("no files"), "{e}");
    std::fs::remove_dir_all(dir).unwrap();
}

#[test]
fn two_ct_series_are_listed_unless_one_is_chosen() {
    let dir = scratch("two-series");
    let first = oblique_volume([8, 6, 3]);
    let second = smooth_volume([5, 4, 6]);
    write_series(&dir.join("a"), &first, 1);
    write_series(&dir.join("b/c"), &second, 2);
    let e = read_err(&dir);
    let uid_a = read_dicom_series(&dir.join("a"))
        .unwrap()
        .info
        .series_instance_uid;
    let uid_b = read_dicom_series(&dir.join("b"))
        .unwrap()
        .info
        .series_instance_uid;
    assert!(
        e.contains("2 CT series") && e.contains(&uid_a) && e.contains(&uid_b),
        "{e}"
    );
    assert!(e.contains("3 files") && e.contains("6 files"), "{e}");
    let options = DicomReadOptions {
        series: Some(lungmotion::formats::dicom::SeriesChoice::Uid(uid_b.clone())),
        ..DicomReadOptions::default()
    };
    let chosen = read_dicom_series_with(&dir, &options).unwrap();
    assert_eq!(chosen.volume.as_slice(), rounded(&second));
    let options = DicomReadOptions {
        series: Some(lungmotion::formats::dicom::SeriesChoice::Uid(
            "1.2.3".into(),
        )),
        ..DicomReadOptions::default()
    };
    let e = read_dicom_series_with(&dir, &options)
        .unwrap_err()
        .to_string();
    assert!(e.contains("no series 1.2.3") && e.contains(&uid_a), "{e}");
    std::fs::remove_dir_all(dir).unwrap();
}

#[test]
fn an_mr_series_is_refused_naming_the_modality() {
    let dir = scratch("mr");
    for p in write_series(&dir, &oblique_volume([6, 5, 3]), 1) {
        edit(&p, |obj| {
            obj.put(DataElement::new(
                tags::MODALITY,
                VR::CS,
                PrimitiveValue::from("MR"),
            ));
        });
    }
    let e = read_err(&dir);
    assert!(e.contains("no CT image series") && e.contains("MR"), "{e}");
    std::fs::remove_dir_all(dir).unwrap();
}

/// Writes a 5-slice series and applies `change` to slice `k` (0-based) before reading.
fn broken_series(
    name: &str,
    k: usize,
    change: impl FnOnce(&mut DefaultDicomObject),
) -> (PathBuf, String) {
    let dir = scratch(name);
    let paths = write_series(&dir, &oblique_volume([6, 5, 5]), 1);
    edit(&paths[k], change);
    let e = read_err(&dir);
    std::fs::remove_dir_all(&dir).unwrap();
    (paths[k].clone(), e)
}

#[test]
fn missing_geometry_tags_are_named() {
    let (path, e) = broken_series("no-ipp", 2, |obj| {
        obj.remove_element(tags::IMAGE_POSITION_PATIENT);
    });
    let file = path.file_name().unwrap().to_string_lossy().to_string();
    assert!(
        e.contains("ImagePositionPatient")
            && e.contains("(0020,0032)")
            && e.contains("missing")
            && e.contains(&file),
        "{e}"
    );
    let (_, e) = broken_series("no-iop", 0, |obj| {
        obj.remove_element(tags::IMAGE_ORIENTATION_PATIENT);
    });
    assert!(
        e.contains("ImageOrientationPatient") && e.contains("missing"),
        "{e}"
    );
    let (_, e) = broken_series("no-spacing", 4, |obj| {
        obj.remove_element(tags::PIXEL_SPACING);
    });
    assert!(e.contains("PixelSpacing") && e.contains("missing"), "{e}");
}

#[test]
fn zero_and_negative_pixel_spacing_are_refused() {
    for (name, value) in [
        ("zero-spacing", "0\\0.7"),
        ("negative-spacing", "0.8\\-0.7"),
    ] {
        let (path, e) = broken_series(name, 3, |obj| put_ds(obj, tags::PIXEL_SPACING, value));
        let file = path.file_name().unwrap().to_string_lossy().to_string();
        assert!(
            e.contains("PixelSpacing") && e.contains("positive") && e.contains(&file),
            "{name}: {e}"
        );
    }
}

#[test]
fn an_inconsistent_slice_is_refused() {
    let (_, e) = broken_series("other-spacing", 1, |obj| {
        put_ds(obj, tags::PIXEL_SPACING, "0.8\\0.9")
    });
    assert!(e.contains("PixelSpacing") && e.contains("differs"), "{e}");
}

#[test]
fn gantry_tilt_is_refused_with_its_angle() {
    let dir = scratch("tilt");
    let volume = smooth_volume([6, 5, 5]);
    let paths = write_series(&dir, &volume, 1);
    let tilt = 15f64.to_radians();
    for (k, p) in paths.iter().enumerate() {
        edit(p, |obj| {
            let ipp = obj
                .element(tags::IMAGE_POSITION_PATIENT)
                .unwrap()
                .to_multi_float64()
                .unwrap();
            let y = ipp[1] + k as f64 * 2.0 * tilt.tan();
            put_ds(
                obj,
                tags::IMAGE_POSITION_PATIENT,
                &format!("{}\\{y}\\{}", ipp[0], ipp[2]),
            );
        });
    }
    let e = read_err(&dir);
    assert!(e.contains("gantry tilt") && e.contains("15.00°"), "{e}");
    std::fs::remove_dir_all(dir).unwrap();
}

#[test]
fn duplicate_slices_are_dropped_when_identical_and_refused_otherwise() {
    let dir = scratch("duplicate");
    let volume = oblique_volume([6, 5, 4]);
    let paths = write_series(&dir, &volume, 1);
    let copy = dir.join("copy-of-2.dcm");
    std::fs::copy(&paths[1], &copy).unwrap();
    let series = read_dicom_series(&dir).unwrap();
    assert_eq!(series.volume.as_slice(), rounded(&volume));
    assert_eq!(series.warnings.len(), 1);
    assert!(
        series.warnings[0].contains("duplicate") && series.warnings[0].contains("IMG0002.dcm"),
        "{:?}",
        series.warnings
    );
    edit(&copy, |obj| put_ds(obj, tags::RESCALE_INTERCEPT, "5"));
    let e = read_err(&dir);
    assert!(
        e.contains("duplicate slice position")
            && e.contains("copy-of-2.dcm")
            && e.contains("IMG0002.dcm"),
        "{e}"
    );
    std::fs::remove_dir_all(dir).unwrap();
}

#[test]
fn a_missing_slice_is_reported_as_a_gap() {
    let dir = scratch("gap");
    let paths = write_series(&dir, &oblique_volume([6, 5, 6]), 1);
    std::fs::remove_file(&paths[2]).unwrap();
    let e = read_err(&dir);
    assert!(
        e.contains("non-uniform slice spacing")
            && e.contains("5.000 mm between")
            && e.contains("IMG0002.dcm")
            && e.contains("IMG0004.dcm")
            && e.contains("typical 2.500 mm"),
        "{e}"
    );
    std::fs::remove_dir_all(dir).unwrap();
}

#[test]
fn absurd_image_sizes_are_refused_before_allocating() {
    let dir = scratch("absurd");
    let paths = write_series(&dir, &oblique_volume([6, 5, 2]), 1);
    for p in &paths {
        edit(p, |obj| {
            for tag in [tags::ROWS, tags::COLUMNS] {
                obj.put(DataElement::new(
                    tag,
                    VR::US,
                    PrimitiveValue::from(60_000u16),
                ));
            }
        });
    }
    let started = Instant::now();
    let e = read_err(&dir);
    assert!(e.contains("absurd grid") && e.contains("60000"), "{e}");
    assert!(started.elapsed().as_secs_f64() < 2.0);
    std::fs::remove_dir_all(dir).unwrap();
}

#[test]
fn a_single_slice_is_not_a_volume() {
    let dir = scratch("single");
    let paths = write_series(&dir, &oblique_volume([6, 5, 2]), 1);
    let e = read_err(&paths[0]);
    assert!(
        e.contains("only 1 slice") && e.contains("at least 2"),
        "{e}"
    );
    std::fs::remove_dir_all(dir).unwrap();
}

#[test]
fn hostile_zips_are_refused() {
    let dir = scratch("hostile-zip");
    let paths = write_series(&dir.join("src"), &oblique_volume([6, 5, 3]), 1);
    let options = zip::write::SimpleFileOptions::default()
        .compression_method(zip::CompressionMethod::Deflated);

    let mut w = zip::ZipWriter::new(Cursor::new(Vec::new()));
    for p in &paths {
        w.start_file(p.file_name().unwrap().to_string_lossy(), options)
            .unwrap();
        w.write_all(&std::fs::read(p).unwrap()).unwrap();
    }
    w.start_file("../../outside.dcm", options).unwrap();
    w.write_all(b"x").unwrap();
    let escape = dir.join("escape.zip");
    std::fs::write(&escape, w.finish().unwrap().into_inner()).unwrap();
    let e = read_err(&escape);
    assert!(
        e.contains("escape.zip") && e.contains("../../outside.dcm"),
        "{e}"
    );

    let mut w = zip::ZipWriter::new(Cursor::new(Vec::new()));
    w.start_file("IMG0001.dcm", options).unwrap();
    let zeros = vec![0u8; 1 << 20];
    for _ in 0..200 {
        w.write_all(&zeros).unwrap();
    }
    let bomb = dir.join("bomb.zip");
    std::fs::write(&bomb, w.finish().unwrap().into_inner()).unwrap();
    let e = read_err(&bomb);
    assert!(
        e.contains("bomb.zip") && e.contains("decompression bomb"),
        "{e}"
    );
    std::fs::remove_dir_all(dir).unwrap();
}

/// Rewrites each slice's stored values through `change` (value, slice index) with new pixel
/// attributes, keeping 16-bit allocation.
fn restore_pixels(
    paths: &[PathBuf],
    bits_stored: u16,
    signed: bool,
    intercept: &str,
    change: impl Fn(i32) -> u16,
) {
    for p in paths {
        edit(p, |obj| {
            let stored: Vec<u16> = obj
                .element(tags::PIXEL_DATA)
                .unwrap()
                .to_multi_int::<u16>()
                .unwrap()
                .into_iter()
                .map(|v| change(i32::from(v as i16)))
                .collect();
            for (tag, v) in [
                (tags::BITS_STORED, bits_stored),
                (tags::HIGH_BIT, bits_stored - 1),
                (tags::PIXEL_REPRESENTATION, u16::from(signed)),
            ] {
                obj.put(DataElement::new(tag, VR::US, PrimitiveValue::from(v)));
            }
            put_ds(obj, tags::RESCALE_INTERCEPT, intercept);
            obj.put(DataElement::new(
                tags::PIXEL_DATA,
                VR::OW,
                PrimitiveValue::U16(stored.into()),
            ));
        });
    }
}

#[test]
fn twelve_bit_pixels_ignore_the_unused_high_bits() {
    // Classic CT storage: 12 bits stored in 16 allocated, with junk (e.g. overlay bits) above.
    let volume = oblique_volume([7, 5, 3]);
    let expected = rounded(&volume);

    let dir = scratch("u12");
    let paths = write_series(&dir, &volume, 1);
    restore_pixels(&paths, 12, false, "-1024", |hu| 0xF000 | (hu + 1024) as u16);
    assert_eq!(read_dicom_series(&dir).unwrap().volume.as_slice(), expected);
    std::fs::remove_dir_all(&dir).unwrap();

    let smooth = smooth_volume([7, 5, 3]);
    let dir = scratch("s12");
    let paths = write_series(&dir, &smooth, 1);
    // Two's complement in 12 bits, with a pattern above that is not a sign extension.
    restore_pixels(&paths, 12, true, "0", |hu| 0x5000 | ((hu as u16) & 0x0FFF));
    let series = read_dicom_series(&dir).unwrap();
    assert_eq!(series.volume.as_slice(), rounded(&smooth));
    assert!(series.volume.as_slice().iter().any(|&v| v < -500.0));
    std::fs::remove_dir_all(dir).unwrap();
}

#[test]
fn multi_frame_images_are_refused_clearly() {
    let dir = scratch("multiframe");
    let paths = write_series(&dir, &oblique_volume([6, 5, 3]), 1);
    for p in &paths {
        edit(p, |obj| {
            let mut two: Vec<u16> = obj
                .element(tags::PIXEL_DATA)
                .unwrap()
                .to_multi_int::<u16>()
                .unwrap();
            two.extend(two.clone());
            obj.put(DataElement::new(
                tags::PIXEL_DATA,
                VR::OW,
                PrimitiveValue::U16(two.into()),
            ));
            obj.put(DataElement::new(
                tags::NUMBER_OF_FRAMES,
                VR::IS,
                PrimitiveValue::from("2"),
            ));
        });
    }
    let e = read_err(&dir);
    assert!(e.contains("2 frames") && e.contains("multi-frame"), "{e}");
    std::fs::remove_dir_all(dir).unwrap();
}

#[test]
fn the_writer_refuses_what_it_cannot_store() {
    let dir = scratch("writer-refusals");
    let mut volume = smooth_volume([4, 4, 2]);
    volume.as_slice_mut()[5] = f32::NAN;
    let e = write_ct_series(&volume, &dir, &CtSeriesMetadata::default())
        .unwrap_err()
        .to_string();
    assert!(e.contains("non-finite"), "{e}");
    volume.as_slice_mut()[5] = 70_000.0;
    volume.as_slice_mut()[6] = -1_000.0;
    let e = write_ct_series(&volume, &dir, &CtSeriesMetadata::default())
        .unwrap_err()
        .to_string();
    assert!(e.contains("16 bits"), "{e}");
    assert_eq!(std::fs::read_dir(&dir).unwrap().count(), 0);
    std::fs::remove_dir_all(dir).unwrap();
}
