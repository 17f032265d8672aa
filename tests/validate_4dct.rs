//! `lungmotion validate --4dct` on the 4D phantom, whose motion is an analytic field the
//! mass–spring model knows nothing of: the report's structure, the model beating the
//! no-motion baseline at end-inhale, the trace against the drawn lung volumes, the landmark
//! formats, and the refusals (grids that differ, landmark files that do not fit, a phase
//! without lungs) with the CLI's exit status.

use std::path::{Path, PathBuf};
use std::process::Command;

use lungmotion::formats::nifti::write_nifti_ct;
use lungmotion::ingest::four_dct::list_four_dct_phases;
use lungmotion::phantom::{
    generate_breathing_phantom, write_four_dct_phantom, BreathingMotion, FourDctPhantomDescription,
    FourDctPhantomSettings, PhantomSettings, Tissue,
};
use lungmotion::run::RunConfig;
use lungmotion::validation::four_dct::{validate_four_dct, FourDctOptions};
use lungmotion::validation::landmarks::{read_landmarks, LandmarkInput};
use lungmotion::Error;

/// Coarse voxels keep every phase's segmentation to a fraction of a second.
const SPACING_MM: f64 = 4.0;
/// Elements coarse enough that the model is built and solved in seconds.
const ELEMENT_SIZE_MM: f64 = 10.0;

fn scratch(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("lm-4dct-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

fn phantom_settings() -> PhantomSettings {
    PhantomSettings {
        spacing_mm: [SPACING_MM; 3],
        ..PhantomSettings::default()
    }
}

/// A 4D phantom of the given amplitudes (0 rest, 1 end-inhale) in `dir`.
fn four_dct(dir: &Path, amplitudes: &[f64]) -> FourDctPhantomDescription {
    let settings = FourDctPhantomSettings {
        phantom: phantom_settings(),
        end_inhale: BreathingMotion::END_INHALE,
        amplitudes: amplitudes.to_vec(),
    };
    write_four_dct_phantom(&settings, dir).expect("4D phantom written")
}

fn options(landmarks: Option<LandmarkInput>) -> FourDctOptions {
    FourDctOptions {
        landmarks,
        config: RunConfig {
            element_size_mm: ELEMENT_SIZE_MM,
            ..RunConfig::default()
        },
        ..FourDctOptions::default()
    }
}

fn lungmotion(args: &[&std::ffi::OsStr]) -> std::process::Output {
    Command::new(env!("CARGO_BIN_EXE_lungmotion"))
        .args(args)
        .output()
        .expect("lungmotion runs")
}

#[test]
fn the_model_beats_no_motion_on_the_4d_phantom_and_the_report_says_so() {
    let dir = scratch("report");
    let phantom = four_dct(&dir, &[0.5, 0.0, 1.0]);
    let out = dir.join("out");
    std::fs::create_dir_all(&out).unwrap();
    let landmarks = LandmarkInput::DirLab(dir.join("landmarks"));
    let report = validate_four_dct(
        &dir.join("phases"),
        &out,
        &options(Some(landmarks)),
        &mut |_| {},
    )
    .expect("validation runs");

    // Structure: every phase in order, the reference by smallest volume, files written.
    let names: Vec<&str> = report.phases.iter().map(|p| p.name.as_str()).collect();
    assert_eq!(names, ["T00", "T33", "T66"]);
    assert_eq!(
        report.reference.name, "T33",
        "the rest state has the least air"
    );
    assert!(report.reference.chosen_by.contains("smallest lung volume"));
    for file in ["report.json", "report.md"] {
        assert!(out.join(file).is_file(), "{file}");
    }
    let json: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("report.json")).unwrap()).unwrap();
    assert_eq!(json["phases"].as_array().unwrap().len(), 3);
    assert!(json["phases"][2]["landmarks"]["model"]["p95_mm"].is_number());
    for p in &report.phases {
        let overlay = out.join(p.overlay.as_ref().expect("overlay written"));
        let image = lungmotion::outputs::quicklook::read_png(&overlay).expect("a PNG");
        assert!(image.width > 50 && image.height > 50);
    }

    // The trace is the segmented volumes relative to the reference's, which must match the
    // drawn lung labels: within 5 % per phase (at 4 mm the segmentation keeps partial-volume
    // voxels the labels, taken at voxel centres, leave out: +1.6 % to +4.0 % when this was
    // written) and the volume change within 150 mL, about one 4 mm voxel layer over the flat
    // tops of both domes, which the threshold keeps in one phase and not in another (−82 mL
    // at end-inhale, −129 mL at half amplitude then); a trace of absolute volumes or of the
    // wrong sign is off by thousands or hundreds of millilitres.
    let drawn_ml: Vec<f64> = phantom
        .phases
        .iter()
        .map(|d| d.right_lung_volume_ml + d.left_lung_volume_ml)
        .collect();
    for (p, &drawn) in report.phases.iter().zip(&drawn_ml) {
        let rel = (p.lung_volume_ml - drawn).abs() / drawn;
        assert!(
            rel < 0.05,
            "phase {}: segmented {:.0} mL against drawn {drawn:.0} mL",
            p.name,
            p.lung_volume_ml
        );
        let drawn_change = drawn - drawn_ml[1];
        let segmented_change = p.lung_volume_ml - report.phases[1].lung_volume_ml;
        assert!((p.volume_change_ml - segmented_change).abs() < 1e-6);
        assert!(
            (p.volume_change_ml - drawn_change).abs() <= 150.0,
            "phase {}: volume change {:.0} mL against drawn {drawn_change:.0} mL",
            p.name,
            p.volume_change_ml
        );
        assert!((p.simulated_volume_change_ml - p.volume_change_ml).abs() < 10.0);
    }
    let reference = &report.phases[1];
    assert_eq!(reference.volume_change_ml, 0.0);
    assert!(reference.dice > 0.995, "identity: Dice {}", reference.dice);
    let inhale = &report.phases[2];
    assert!(
        inhale.volume_change_ml > 300.0,
        "{}",
        inhale.volume_change_ml
    );

    // End-inhale: the prediction is closer to the real phase than no motion at all.
    assert!(
        inhale.dice > inhale.no_motion_dice,
        "Dice {} against no motion {}",
        inhale.dice,
        inhale.no_motion_dice
    );
    let lm = inhale.landmarks.expect("landmark errors");
    assert!(
        lm.model.mean_mm < 0.8 * lm.no_motion.mean_mm,
        "landmarks: model {:?} against no motion {:?}",
        lm.model,
        lm.no_motion
    );
    for base in &inhale.lung_base {
        let (e, none) = (base.error_mm.unwrap(), base.no_motion_error_mm.unwrap());
        assert!(none > 8.0, "the base descends at end-inhale ({none} mm)");
        assert!(
            e.abs() < none.abs(),
            "lung {}: {e} against {none}",
            base.lung
        );
    }
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn landmarks_round_trip_exactly_through_both_formats() {
    let dir = scratch("landmarks");
    let phantom = four_dct(&dir, &[1.0, 0.0]);
    let listed = list_four_dct_phases(&dir.join("phases"), &dir).unwrap();
    let g = phantom.geometry;
    let dirlab = read_landmarks(
        &LandmarkInput::DirLab(dir.join("landmarks")),
        &listed.phases,
        &g,
    )
    .expect("DIR-Lab files");
    let csv = read_landmarks(
        &LandmarkInput::Csv(dir.join("landmarks.csv")),
        &listed.phases,
        &g,
    )
    .expect("CSV");
    assert!(phantom.lung_landmarks_lps_mm[0].len() > 50);
    for read in [&dirlab, &csv] {
        assert_eq!(read.points.len(), 2);
        for (got, exact) in read.points.iter().zip(&phantom.lung_landmarks_lps_mm) {
            assert_eq!(got.len(), exact.len());
            for (a, b) in got.iter().zip(exact) {
                let d = (0..3).map(|k| (a[k] - b[k]).abs()).fold(0.0, f64::max);
                assert!(d < 1e-9, "{a:?} against {b:?}");
            }
        }
    }
    // The CSV is exact to the last bit; the voxel indices round through the grid's affine.
    assert_eq!(csv.points, phantom.lung_landmarks_lps_mm);
    // The drawn image agrees: every landmark lies in lung (or tumour) at every phase.
    for (k, phase) in phantom.phases.iter().enumerate() {
        let state = generate_breathing_phantom(&phantom_settings(), &phase.motion).unwrap();
        for p in &phantom.lung_landmarks_lps_mm[k] {
            let v = g
                .lps_mm_to_voxel(nalgebra::Vector3::from(*p))
                .map(f64::round);
            let label = state.truth.get(v.x as usize, v.y as usize, v.z as usize);
            assert!(
                [Tissue::RightLung, Tissue::LeftLung, Tissue::Tumour]
                    .iter()
                    .any(|t| t.code() == label),
                "phase {}: landmark {p:?} in label {label}",
                phase.name
            );
        }
    }
    let _ = std::fs::remove_dir_all(&dir);
}

/// Rewrites `file` with `edit` applied to its text.
fn edit(file: &Path, edit: impl FnOnce(String) -> String) {
    let text = std::fs::read_to_string(file).unwrap();
    std::fs::write(file, edit(text)).unwrap();
}

#[test]
fn landmark_files_that_do_not_fit_the_image_are_refused_by_file_line_and_value() {
    let dir = scratch("bad-landmarks");
    let phantom = four_dct(&dir, &[1.0, 0.0]);
    let listed = list_four_dct_phases(&dir.join("phases"), &dir).unwrap();
    let g = phantom.geometry;
    let lm = dir.join("landmarks");
    let t50 = lm.join("T50.txt");

    // One point fewer at one phase.
    edit(&t50, |t| {
        t.lines().skip(1).map(|l| format!("{l}\n")).collect()
    });
    let n = phantom.lung_landmarks_lps_mm[0].len();
    match read_landmarks(&LandmarkInput::DirLab(lm.clone()), &listed.phases, &g) {
        Err(Error::Points { file, reason, .. }) => {
            assert_eq!(file.as_deref(), Some(t50.as_path()));
            assert!(reason.contains(&format!("{} points", n - 1)), "{reason}");
            assert!(reason.contains(&n.to_string()), "{reason}");
        }
        other => panic!("expected a refusal, got {other:?}"),
    }

    // An index beyond the image on line 3.
    edit(&t50, |t| {
        let mut lines: Vec<String> = t.lines().map(str::to_string).collect();
        lines.insert(2, format!("10\t{}\t5", g.dims[1] + 7));
        lines.join("\n")
    });
    match read_landmarks(&LandmarkInput::DirLab(lm.clone()), &listed.phases, &g) {
        Err(Error::Points {
            file,
            point,
            reason,
        }) => {
            assert_eq!(file.as_deref(), Some(t50.as_path()));
            assert_eq!(point, Some(3));
            assert!(reason.contains(&format!("{}", g.dims[1] + 7)), "{reason}");
        }
        other => panic!("expected a refusal, got {other:?}"),
    }

    // A CSV row outside the image, and a phase the 4D-CT does not have.
    let csv = dir.join("landmarks.csv");
    edit(&csv, |t| format!("{t}T00,999,0,0,900\n"));
    let lines = std::fs::read_to_string(&csv).unwrap().lines().count();
    match read_landmarks(&LandmarkInput::Csv(csv.clone()), &listed.phases, &g) {
        Err(Error::Points { point, reason, .. }) => {
            assert_eq!(point, Some(lines));
            assert!(reason.contains("900"), "{reason}");
        }
        other => panic!("expected a refusal, got {other:?}"),
    }
    edit(&csv, |t| t.replace("T00,999,0,0,900", "T70,999,0,0,0"));
    match read_landmarks(&LandmarkInput::Csv(csv.clone()), &listed.phases, &g) {
        Err(Error::Points { reason, .. }) => assert!(reason.contains("\"T70\""), "{reason}"),
        other => panic!("expected a refusal, got {other:?}"),
    }

    // The command line refuses it with exit status 2 before segmenting anything.
    let out = lungmotion(&[
        "validate".as_ref(),
        "--4dct".as_ref(),
        dir.join("phases").as_os_str(),
        "--landmarks".as_ref(),
        lm.as_os_str(),
        "--out".as_ref(),
        dir.join("out").as_os_str(),
    ]);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "{stderr}");
    assert!(
        stderr.contains("T50.txt") && stderr.contains("line 3"),
        "{stderr}"
    );
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn phases_on_different_grids_are_refused_naming_both() {
    let dir = scratch("grids");
    four_dct(&dir, &[1.0, 0.0]);
    let coarser = generate_breathing_phantom(
        &PhantomSettings {
            spacing_mm: [5.0; 3],
            ..PhantomSettings::default()
        },
        &BreathingMotion::REST,
    )
    .unwrap();
    let t50 = dir.join("phases/T50.nii.gz");
    write_nifti_ct(&t50, &coarser.ct).unwrap();
    let out = dir.join("out");
    std::fs::create_dir_all(&out).unwrap();
    match validate_four_dct(&dir.join("phases"), &out, &options(None), &mut |_| {}) {
        Err(Error::InvalidScan { scan, reason }) => {
            assert_eq!(scan, t50);
            assert!(
                reason.contains("\"T50\"") && reason.contains("\"T00\""),
                "{reason}"
            );
            assert!(reason.contains("[4.0, 4.0, 4.0]") && reason.contains("[5.0, 5.0, 5.0]"));
        }
        other => panic!(
            "expected a refusal, got {:?}",
            other.map(|r| r.phases.len())
        ),
    }
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_phase_without_lungs_is_refused_naming_it_with_exit_status_2() {
    let dir = scratch("no-lungs");
    four_dct(&dir, &[1.0, 0.0]);
    // Phase T50 with its lungs filled with soft tissue (as a mislabelled abdomen series).
    let mut state =
        generate_breathing_phantom(&phantom_settings(), &BreathingMotion::REST).unwrap();
    let truth = state.truth.as_slice().to_vec();
    for (hu, label) in state.ct.as_slice_mut().iter_mut().zip(truth) {
        if label == Tissue::RightLung.code() || label == Tissue::LeftLung.code() {
            *hu = 40.0;
        }
    }
    write_nifti_ct(&dir.join("phases/T50.nii.gz"), &state.ct).unwrap();
    let out = lungmotion(&[
        "validate".as_ref(),
        "--4dct".as_ref(),
        dir.join("phases").as_os_str(),
        "--out".as_ref(),
        dir.join("out").as_os_str(),
    ]);
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "{stderr}");
    assert!(
        stderr.contains("phase \"T50\": no usable lungs"),
        "{stderr}"
    );
    assert!(!dir.join("out/report.json").exists());
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn phases_are_found_in_dicom_folders_and_in_a_zip_of_them() {
    use lungmotion::formats::dicom::{write_ct_series, CtSeriesMetadata};
    use lungmotion::ingest::four_dct::FourDctLayout;
    use lungmotion::ingest::scan::load_ct;
    use std::io::Write;

    let dir = scratch("layouts");
    let folders = dir.join("4dct");
    // Named so that plain string order (phase-10 before phase-2) is the wrong one.
    let names = ["phase-10", "phase-2"];
    for (k, name) in names.iter().enumerate() {
        let motion = BreathingMotion::END_INHALE.scaled(k as f64);
        let state = generate_breathing_phantom(&PhantomSettings::default(), &motion).unwrap();
        let series = folders.join(name);
        std::fs::create_dir_all(&series).unwrap();
        let meta = CtSeriesMetadata {
            uid_seed: k as u64 + 1,
            ..CtSeriesMetadata::default()
        };
        write_ct_series(&state.ct, &series, &meta).unwrap();
    }
    let zip_path = dir.join("4dct.zip");
    let mut zip = zip::ZipWriter::new(std::fs::File::create(&zip_path).unwrap());
    for name in names {
        for entry in std::fs::read_dir(folders.join(name)).unwrap() {
            let path = entry.unwrap().path();
            let file = path.file_name().unwrap().to_string_lossy().into_owned();
            zip.start_file(
                format!("4dct/{name}/{file}"),
                zip::write::SimpleFileOptions::default(),
            )
            .unwrap();
            zip.write_all(&std::fs::read(&path).unwrap()).unwrap();
        }
    }
    zip.finish().unwrap();

    let scratch_dir = dir.join("scratch");
    std::fs::create_dir_all(&scratch_dir).unwrap();
    for (input, layout) in [
        (&folders, FourDctLayout::DicomFolders),
        (&zip_path, FourDctLayout::DicomZip),
    ] {
        let listed = list_four_dct_phases(input, &scratch_dir).expect("phases found");
        assert_eq!(listed.layout, layout);
        let found: Vec<&str> = listed.phases.iter().map(|p| p.name.as_str()).collect();
        assert_eq!(found, ["phase-2", "phase-10"], "numbers compare as numbers");
        let a = load_ct(&listed.phases[0].path).unwrap();
        let b = load_ct(&listed.phases[1].path).unwrap();
        assert!(a.ct.geometry.same_grid(&b.ct.geometry, 1e-6));
        assert_ne!(a.ct.as_slice(), b.ct.as_slice(), "two breathing states");
        drop(listed);
    }
    // The zip's unpacked copy went with its listing.
    assert_eq!(std::fs::read_dir(&scratch_dir).unwrap().count(), 0);
    let _ = std::fs::remove_dir_all(&dir);
}
