//! The DICOM Deformable Spatial Registrations (REG) of a run, read by readers this project did
//! not write: pydicom + numpy check the SOP class, the CT's patient, study and frame of
//! reference, the identity matrices and the grid, then apply each REG's vectors (trilinear on
//! the grid) to the tracked points' rest positions and land on `trajectories.csv`'s moved
//! positions within 0.1 mm; DCMTK's `dcmdump` parses every object, and dicom3tools'
//! `dciodvfy` validates one against the IOD when it is installed.

use std::path::{Path, PathBuf};
use std::process::Command;

use lungmotion::run::demo::{demo_config, demo_inputs, sample_volumes_dir};
use lungmotion::run::{run_breathing, RunConfig, SilentObserver};

/// A fresh output directory for `name`.
fn out_dir(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("lm-reg-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    dir
}

/// Whether python3 imports pydicom and numpy (the skip is said, never silent).
fn pydicom_available() -> bool {
    let ok = Command::new("python3")
        .args(["-c", "import pydicom, numpy"])
        .output()
        .is_ok_and(|o| o.status.success());
    if !ok {
        eprintln!("SKIPPED: needs python3 with pydicom and numpy (pip install pydicom numpy)");
    }
    ok
}

/// Reads every `frames/<k>/registration.dcm` of `out` and checks it against the CT slice
/// `ct_file` and `trajectories.csv`; prints one JSON line of findings.
const CHECK_REGISTRATIONS: &str = r#"
import json, sys, glob, os
import numpy as np
import pydicom

out, ct_file = sys.argv[1], sys.argv[2]
ct = pydicom.dcmread(ct_file)
rows = [l.strip().split(",") for l in open(os.path.join(out, "trajectories.csv"))][1:]
found = {"objects": 0, "worst_mm": 0.0, "largest_motion_mm": 0.0, "problems": []}
def problem(s):
    found["problems"].append(s)
identity = [1.0,0,0,0, 0,1.0,0,0, 0,0,1.0,0, 0,0,0,1.0]
series = set()
for path in sorted(glob.glob(os.path.join(out, "frames", "*", "registration.dcm"))):
    frame = int(os.path.basename(os.path.dirname(path)))
    ds = pydicom.dcmread(path)
    found["objects"] += 1
    if ds.SOPClassUID != "1.2.840.10008.5.1.4.1.1.66.3": problem(f"{path}: SOP class {ds.SOPClassUID}")
    if ds.Modality != "REG": problem(f"{path}: modality {ds.Modality}")
    for kw in ["StudyInstanceUID", "FrameOfReferenceUID", "PatientID", "PatientName"]:
        if str(getattr(ds, kw)) != str(getattr(ct, kw)): problem(f"{path}: {kw} differs from the CT's")
    if ds.SeriesInstanceUID == ct.SeriesInstanceUID: problem(f"{path}: the CT's series UID")
    series.add(ds.SeriesInstanceUID)
    if f"frame {frame}" not in ds.SeriesDescription: problem(f"{path}: series description {ds.SeriesDescription}")
    item = ds.DeformableRegistrationSequence[0]
    if item.SourceFrameOfReferenceUID != ct.FrameOfReferenceUID: problem(f"{path}: source frame of reference")
    for seq in ["PreDeformationMatrixRegistrationSequence", "PostDeformationMatrixRegistrationSequence"]:
        m = getattr(item, seq)[0]
        if [float(v) for v in m.FrameOfReferenceTransformationMatrix] != identity: problem(f"{path}: {seq} not identity")
        if m.FrameOfReferenceTransformationMatrixType != "RIGID": problem(f"{path}: {seq} type")
    grid = item.DeformableRegistrationGridSequence[0]
    iop = np.array([float(v) for v in grid.ImageOrientationPatient])
    if not np.allclose(iop, [float(v) for v in ct.ImageOrientationPatient]): problem(f"{path}: orientation {iop}")
    x, y = iop[:3], iop[3:]
    z = np.cross(x, y)
    origin = np.array([float(v) for v in grid.ImagePositionPatient])
    nx, ny, nz = [int(v) for v in grid.GridDimensions]
    res = np.array([float(v) for v in grid.GridResolution])
    found["grid"] = [nx, ny, nz]
    found["spacing_mm"] = res.tolist()
    raw = grid.VectorGridData
    if len(raw) != nx * ny * nz * 12: problem(f"{path}: {len(raw)} bytes of vectors for {nx}x{ny}x{nz}")
    v = np.frombuffer(raw, dtype="<f4").reshape(nz, ny, nx, 3).astype(np.float64)
    found["largest_motion_mm"] = max(found["largest_motion_mm"], float(np.abs(v).max()))
    for r in rows:
        if int(r[0]) != frame: continue
        rest = np.array([float(c) for c in r[3:6]])
        moved = np.array([float(c) for c in r[6:9]])
        d = rest - origin
        f = np.array([d @ x / res[0], d @ y / res[1], d @ z / res[2]])
        i0 = np.floor(f).astype(int)
        t = f - i0
        if (i0 < 0).any() or (i0 + 1 >= [nx, ny, nz]).any():
            problem(f"{path}: point {r[2]} outside the grid"); continue
        u = np.zeros(3)
        for dz in (0, 1):
            for dy in (0, 1):
                for dx in (0, 1):
                    w = (t[0] if dx else 1 - t[0]) * (t[1] if dy else 1 - t[1]) * (t[2] if dz else 1 - t[2])
                    u += w * v[i0[2] + dz, i0[1] + dy, i0[0] + dx]
        found["worst_mm"] = max(found["worst_mm"], float(np.abs(rest + u - moved).max()))
found["distinct_series"] = len(series)
print(json.dumps(found))
"#;

/// Runs pydicom's check over `out`; returns its findings.
fn check_with_pydicom(out: &Path, ct_file: &Path) -> serde_json::Value {
    let output = Command::new("python3")
        .args(["-c", CHECK_REGISTRATIONS])
        .arg(out)
        .arg(ct_file)
        .output()
        .expect("python3 runs");
    assert!(
        output.status.success(),
        "pydicom could not read the registrations: {}",
        String::from_utf8_lossy(&output.stderr)
    );
    serde_json::from_slice(&output.stdout).expect("one JSON line")
}

#[test]
fn the_demo_registrations_carry_the_tracked_points_to_their_trajectories() {
    if !pydicom_available() {
        return;
    }
    let out = out_dir("demo");
    let inputs = demo_inputs(&sample_volumes_dir()).unwrap();
    let summary = run_breathing(&inputs, &demo_config(8.0), &out, &mut SilentObserver).unwrap();
    let frames = summary.frames.len();
    for record in &summary.frames {
        let file = record.files.registration_dicom.as_deref().expect("listed");
        assert!(out.join(file).is_file(), "{file}");
    }
    let ct_file = sample_volumes_dir().join("phantom-dicom/IMG0001.dcm");
    let found = check_with_pydicom(&out, &ct_file);
    eprintln!("pydicom: {found}");
    assert_eq!(found["problems"], serde_json::json!([]), "{found}");
    assert_eq!(found["objects"], frames);
    assert_eq!(found["distinct_series"], frames);
    assert_eq!(found["spacing_mm"], serde_json::json!([3.0, 3.0, 3.0]));
    // The tumour moves 13.6 mm at end-inhale: vectors of that size, applied where the REG
    // says, land on the trajectories within 0.1 mm.
    assert!(
        found["largest_motion_mm"].as_f64().unwrap() > 10.0,
        "{found}"
    );
    let worst = found["worst_mm"].as_f64().unwrap();
    assert!(
        worst < 0.1,
        "REG vectors miss trajectories.csv by {worst} mm"
    );
    check_with_dcmtk_and_dicom3tools(&out.join("frames/0/registration.dcm"));
    std::fs::remove_dir_all(&out).unwrap();
}

/// `dcmdump` parses the object; `dciodvfy` (when installed) finds no error against the
/// Deformable Spatial Registration IOD.
fn check_with_dcmtk_and_dicom3tools(file: &Path) {
    match Command::new("dcmdump").arg("-q").arg(file).output() {
        Ok(o) => {
            let text = String::from_utf8_lossy(&o.stdout);
            assert!(
                o.status.success() && o.stderr.is_empty(),
                "dcmdump: {}",
                String::from_utf8_lossy(&o.stderr)
            );
            assert!(text.contains("(0064,0009) OF"), "{text}");
        }
        Err(_) => eprintln!("SKIPPED dcmdump: DCMTK is not installed (apt-get install dcmtk)"),
    }
    match Command::new("dciodvfy").arg("-new").arg(file).output() {
        Ok(o) => {
            let report = String::from_utf8_lossy(&o.stderr).to_string();
            eprintln!("dciodvfy:\n{report}");
            let errors: Vec<&str> = report.lines().filter(|l| l.starts_with("Error")).collect();
            assert!(errors.is_empty(), "dciodvfy: {errors:#?}");
        }
        Err(_) => {
            eprintln!(
                "SKIPPED dciodvfy: dicom3tools is not installed (apt-get install dicom3tools)"
            )
        }
    }
}

#[test]
fn a_nifti_ct_gets_a_generated_study_shared_by_its_registrations() {
    if !pydicom_available() {
        return;
    }
    let out = out_dir("nifti");
    let mut inputs = demo_inputs(&sample_volumes_dir()).unwrap();
    inputs.ct_path = sample_volumes_dir().join("phantom-ct.nii.gz");
    let mut config = demo_config(12.0);
    config.outputs.registration_spacing_mm = 5.0;
    run_breathing(&inputs, &config, &out, &mut SilentObserver).unwrap();
    let script = r#"
import sys, glob, pydicom
objs = [pydicom.dcmread(p) for p in sorted(glob.glob(sys.argv[1] + "/frames/*/registration.dcm"))]
print(len(objs), len({o.StudyInstanceUID for o in objs}), len({o.FrameOfReferenceUID for o in objs}),
      all(o.DeformableRegistrationSequence[0].SourceFrameOfReferenceUID == o.FrameOfReferenceUID for o in objs),
      objs[0].PatientID, [float(v) for v in objs[0].DeformableRegistrationSequence[0].DeformableRegistrationGridSequence[0].GridResolution])
"#;
    let o = Command::new("python3")
        .args(["-c", script])
        .arg(&out)
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&o.stdout).to_string();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    // Ten phases, one study, one frame of reference (the source's too), a fictitious patient.
    assert!(
        text.starts_with("10 1 1 True LUNGMOTION-") && text.contains("[5.0, 5.0, 5.0]"),
        "{text}"
    );
    std::fs::remove_dir_all(&out).unwrap();
}

#[test]
fn a_grid_too_large_is_refused_with_its_size_and_the_remedy_and_nothing_is_published() {
    let out = out_dir("too-large");
    let inputs = demo_inputs(&sample_volumes_dir()).unwrap();
    let mut config = demo_config(12.0);
    config.outputs.registration_spacing_mm = 0.5;
    let err = run_breathing(&inputs, &config, &out, &mut SilentObserver)
        .unwrap_err()
        .to_string();
    assert!(
        err.contains("DICOM registration grid")
            && err.contains("MB limit")
            && err.contains("outputs.registration_spacing_mm"),
        "{err}"
    );
    assert!(!out.exists(), "a refused run publishes nothing");
}

#[test]
fn invalid_registration_options_are_named() {
    let err = |t: &str| RunConfig::from_toml(t).unwrap_err().to_string();
    for bad in ["0", "-3", "25", "nan"] {
        let e = err(&format!("[outputs]\nregistration_spacing_mm = {bad}"));
        assert!(
            e.contains("outputs.registration_spacing_mm") && e.contains("0.5–20 mm"),
            "{bad}: {e}"
        );
    }
    // The TOML reader names the type it wanted (not the key: `from_toml` keeps its message).
    let e = err("[outputs]\nregistration = 1");
    assert!(e.contains("expected a boolean"), "{e}");
    let e = err("[outputs]\nregistration_grid = 3");
    assert!(e.contains("registration_grid"), "{e}");
}

/// `lungmotion run --registration-spacing 6`: the flag turns the registrations on at that
/// spacing, `summary.json` lists one per frame, and pydicom reads the spacing back.
#[cfg(feature = "cli")]
#[test]
fn the_cli_flag_writes_the_registrations_at_its_spacing() {
    if !pydicom_available() {
        return;
    }
    let dir = out_dir("cli");
    std::fs::create_dir_all(&dir).unwrap();
    // One sin² breath of 300 mL over 4 s at 5 Hz.
    let mut csv = String::from("time_s,volume_ml\n");
    for i in 0..=20 {
        let t = f64::from(i) * 0.2;
        let v = 300.0 * (std::f64::consts::PI * t / 4.0).sin().powi(2);
        csv.push_str(&format!("{t:.1},{v:.3}\n"));
    }
    std::fs::write(dir.join("trace.csv"), csv).unwrap();
    let out = dir.join("out");
    let o = Command::new(env!("CARGO_BIN_EXE_lungmotion"))
        .arg("run")
        .arg("--ct")
        .arg(sample_volumes_dir().join("phantom-ct.nii.gz"))
        .arg("--trace")
        .arg(dir.join("trace.csv"))
        .arg("--out")
        .arg(&out)
        .args([
            "--element-size",
            "12",
            "--registration-spacing",
            "6",
            "--quiet",
        ])
        .output()
        .unwrap();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let summary: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("summary.json")).unwrap()).unwrap();
    let frames = summary["frames"].as_array().unwrap();
    assert!(frames.len() >= 2, "{} frames", frames.len());
    for (k, frame) in frames.iter().enumerate() {
        assert_eq!(
            frame["files"]["registration_dicom"],
            format!("frames/{k}/registration.dcm"),
            "{frame}"
        );
    }
    let script = r#"
import sys, pydicom
g = pydicom.dcmread(sys.argv[1]).DeformableRegistrationSequence[0].DeformableRegistrationGridSequence[0]
print([float(v) for v in g.GridResolution])
"#;
    let o = Command::new("python3")
        .args(["-c", script])
        .arg(out.join("frames/0/registration.dcm"))
        .output()
        .unwrap();
    let text = String::from_utf8_lossy(&o.stdout).to_string();
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    assert_eq!(text.trim(), "[6.0, 6.0, 6.0]");
    std::fs::remove_dir_all(&dir).unwrap();
}
