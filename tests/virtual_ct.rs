//! The virtual 4D-CT: the motion over the whole CT inverts to its stated residual on an
//! analytic motion; the demo phantom's virtual end-inhale phase, segmented by the project's
//! own ingest, holds the trace's lung volume and its diaphragm dome sits where the field
//! says; the DICOM phase series sit in the planning CT's study (read by pydicom) and equal
//! the NIfTI phases; the option's bad values and too many phases are refused by name.

use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use lungmotion::breathing::BreathingTrace;
use lungmotion::formats::dicom::read_dicom_series;
use lungmotion::formats::nifti::{read_nifti, read_nifti_vector_field};
use lungmotion::ingest::pipeline::ingest_scan;
use lungmotion::ingest::scan::load_ct;
use lungmotion::model::{Material, VoxelGrid};
use lungmotion::outputs::radiotherapy::ct_motion::{ct_grid_motion, CtMotionSettings};
use lungmotion::outputs::radiotherapy::virtual_ct::{warp_ct_int16, warp_ct_into};
use lungmotion::outputs::radiotherapy::PhaseMotion;
use lungmotion::run::demo::{demo_config, demo_inputs, sample_volumes_dir};
use lungmotion::run::{run_breathing, RunConfig, RunInputs, RunSummary, SilentObserver};
use lungmotion::volume::{Volume, VolumeGeometry};
use nalgebra::{Matrix3, Vector3};

/// An 80 mm cube of 10 mm elements centred on (0, 0, 0) mm, moved by an affine map (a
/// translation and a stretch up to 8 %), inside a CT of 1.5 × 1.5 × 2.5 mm voxels.
#[test]
fn an_affine_motion_is_reproduced_inside_and_inverts_to_the_stated_residual() {
    let mesh = VoxelGrid::filled_box([8, 8, 8], [0.01; 3], Vector3::new(-0.04, -0.04, -0.04))
        .to_mesh(Material::LUNG)
        .unwrap()
        .mesh;
    let a = Matrix3::new(0.05, 0.01, 0.0, 0.0, 0.03, -0.01, 0.02, 0.0, 0.08);
    let b_mm = Vector3::new(2.0, -1.0, -3.0);
    let u_mm = |x_mm: Vector3<f64>| a * x_mm + b_mm;
    let positions: Vec<Vector3<f64>> = mesh
        .rest_positions_m
        .iter()
        .map(|x| x + u_mm(x * 1e3) * 1e-3)
        .collect();
    let ct = VolumeGeometry::axis_aligned([100, 100, 60], [1.5, 1.5, 2.5], [-75.0, -75.0, -75.0]);
    let motion = ct_grid_motion(&ct, &mesh, &positions, CtMotionSettings::default()).unwrap();
    // Well inside the cube (all eight grid corners in the mesh) the grid holds u exactly.
    let mut worst_forward = 0.0f64;
    let mut worst_round_trip = 0.0f64;
    let steps = [-31.3, -17.0, -2.2, 9.9, 24.4, 31.0];
    for &x in &steps {
        for &y in &steps {
            for &z in &steps {
                let p = Vector3::new(x, y, z);
                let moved = Vector3::from(motion.moved_lps_mm(p.into()));
                worst_forward = worst_forward.max((moved - p - u_mm(p)).norm());
                let back = Vector3::from(motion.source_lps_mm(moved.into()));
                worst_round_trip = worst_round_trip.max((back - p).norm());
            }
        }
    }
    assert!(worst_forward < 1e-3, "forward off by {worst_forward} mm");
    assert!(
        worst_round_trip < 0.01,
        "round trip off by {worst_round_trip} mm"
    );
    let r = motion.inverse_report();
    println!("affine motion: inverse residual {r:?}");
    assert_eq!(r.unconverged_nodes, 0, "{r:?}");
    // The stated residual (README, Outputs): at the nodes within the 0.01 mm tolerance;
    // between them, where the cube's edge bends the extension, within 0.5 mm.
    assert!(
        r.lung_node_max_mm <= 0.01 && r.all_node_max_mm <= 0.01,
        "{r:?}"
    );
    assert!(
        r.lung_cell_max_mm < 0.5 && r.lung_cell_p99_mm < 0.1,
        "{r:?}"
    );
    // No seam at the pleura: 1 mm either side of the cube's top face, u agrees within the
    // extension's slope over 2 mm.
    let top = |dz: f64| Vector3::from(motion.displacement_mm([5.0, 5.0, 40.0 + dz]));
    let seam = (top(1.0) - top(-1.0)).norm();
    assert!(seam < 0.5, "u jumps {seam} mm across the surface");
    // The extension decays: faster beside the cube (chest wall) than below it (abdomen).
    let beside = Vector3::from(motion.displacement_mm([70.0, 0.0, 0.0])).norm();
    let below = Vector3::from(motion.displacement_mm([0.0, 0.0, -70.0])).norm();
    let at_side_face = u_mm(Vector3::new(40.0, 0.0, 0.0)).norm();
    let at_bottom_face = u_mm(Vector3::new(0.0, 0.0, -40.0)).norm();
    println!(
        "30 mm beside: {beside:.2} of {at_side_face:.2} mm; 30 mm below: {below:.2} of \
         {at_bottom_face:.2} mm"
    );
    assert!(beside < 0.25 * at_side_face, "{beside} of {at_side_face}");
    assert!(below > 0.6 * at_bottom_face, "{below} of {at_bottom_face}");
}

/// The demo (phantom DICOM, two 500 mL breaths, 10 phases, 8 mm elements) with the virtual
/// CT as NIfTI and DICOM, run once for the tests below.
fn demo_run() -> &'static (PathBuf, RunSummary) {
    static RUN: OnceLock<(PathBuf, RunSummary)> = OnceLock::new();
    RUN.get_or_init(|| {
        let out = std::env::temp_dir().join(format!("lm-virtual-ct-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&out);
        let inputs = demo_inputs(&sample_volumes_dir()).unwrap();
        let summary = run_breathing(&inputs, &demo_config(8.0), &out, &mut SilentObserver).unwrap();
        (out, summary)
    })
}

#[test]
fn the_demo_writes_every_phase_and_the_projections_with_their_residual() {
    let (out, summary) = demo_run();
    let v = summary.virtual_ct.as_ref().expect("virtual_ct section");
    println!(
        "virtual CT: {} phases + MIP + AIP, NIfTI and DICOM, {} bytes, {:.2} s (of a {:.2} s \
         run), grid {:?} at {} mm",
        v.phases.len(),
        v.bytes_written,
        v.time_s,
        summary.timings_s.get("total").copied().unwrap_or(f64::NAN),
        v.grid_dims,
        v.grid_spacing_mm
    );
    assert_eq!(v.phases.len(), 10);
    for (k, p) in v.phases.iter().enumerate() {
        assert_eq!(p.label.percent, Some(10.0 * k as f64));
        assert!(out.join(p.nifti.as_ref().unwrap()).is_file());
        assert!(out.join(p.dicom.as_ref().unwrap()).is_dir());
        let r = &p.inverse_residual;
        println!("phase {k}: {r:?}");
        assert_eq!(r.unconverged_nodes, 0, "phase {k}: {r:?}");
        assert!(r.lung_cell_p99_mm < 0.1, "phase {k}: {r:?}");
    }
    assert_eq!(v.phases[0].label.breathing, "end-inhale");
    for f in ["mip-ct.nii.gz", "aip-ct.nii.gz"] {
        assert!(out.join(f).is_file(), "{f}");
    }
    assert!(out.join("mip-ct-dicom").is_dir() && out.join("aip-ct-dicom").is_dir());
    // The phases are the run's own: each frame's phase_percent.
    for (p, f) in v.phases.iter().zip(&summary.frames) {
        assert_eq!(
            p.label.percent, f.summary.phase_percent,
            "frame {}",
            p.frame
        );
        assert_eq!(p.frame, f.summary.index);
    }
    // The MIP is at least every phase, voxel by voxel, and the AIP is their mean (rounded
    // to whole HU as a CT series stores them).
    let mip = read_nifti(&out.join("mip-ct.nii.gz")).unwrap();
    let aip = read_nifti(&out.join("aip-ct.nii.gz")).unwrap();
    let mut sum = vec![0.0f64; mip.as_slice().len()];
    let mut mip_reached = vec![false; sum.len()];
    for p in &v.phases {
        let phase = read_nifti(&out.join(p.nifti.as_ref().unwrap())).unwrap();
        assert!(phase.geometry.same_grid(&mip.geometry, 1e-6));
        for (n, (&m, &x)) in mip.as_slice().iter().zip(phase.as_slice()).enumerate() {
            assert!(m >= x, "frame {}: voxel {n}: MIP {m} < {x}", p.frame);
            mip_reached[n] |= m == x;
            sum[n] += f64::from(x);
        }
    }
    assert!(
        mip_reached.iter().all(|&r| r),
        "the MIP is some phase's value everywhere"
    );
    let count = v.phases.len() as f64;
    let worst = aip
        .as_slice()
        .iter()
        .zip(&sum)
        .map(|(&a, &s)| (f64::from(a) - s / count).abs())
        .fold(0.0f64, f64::max);
    println!("AIP against the phases' mean: at most {worst:.3} HU apart");
    assert!(worst <= 0.501, "the AIP is {worst} HU from the mean");
    let moved = mip
        .as_slice()
        .iter()
        .zip(aip.as_slice())
        .filter(|(m, a)| *m - *a > 50.0)
        .count();
    println!("voxels where the MIP exceeds the AIP by more than 50 HU: {moved}");
    assert!(moved > 1000, "the phases hardly differ: {moved} voxels");
    let json = std::fs::read_to_string(out.join("summary.json")).unwrap();
    let value: serde_json::Value = serde_json::from_str(&json).unwrap();
    assert_eq!(value["virtual_ct"]["grid_spacing_mm"], 4.0);
    assert!(value["virtual_ct"]["bytes_written"].as_u64().unwrap() > 0);
}

/// The HU crossing of `threshold_hu` below the lowest lung voxel of column (i, j), as an LPS
/// z in mm (linear between voxel centres); `None` if the column holds no lung.
fn dome_z_mm(ct: &Volume<f32>, lungs: &Volume<u8>, i: usize, j: usize) -> Option<f64> {
    let g = ct.geometry;
    let lowest = (0..g.dims[2]).find(|&k| lungs.get(i, j, k) != 0)?;
    let k_low = lowest.checked_sub(1)?;
    let (below, above) = (ct.get(i, j, k_low) as f64, ct.get(i, j, lowest) as f64);
    let threshold = -400.0;
    let t = ((below - threshold) / (below - above)).clamp(0.0, 1.0);
    let z = |k: f64| g.voxel_to_lps_mm(Vector3::new(i as f64, j as f64, k)).z;
    Some(z(k_low as f64 + t))
}

#[test]
fn every_virtual_phase_holds_the_traces_volume_and_the_end_inhale_dome_sits_where_the_field_says() {
    let (out, summary) = demo_run();
    let end_inhale = summary.end_inhale.as_ref().expect("the demo breathes in");
    let frame = end_inhale.frame;
    let settings = demo_config(8.0).ingest_settings();
    let planning = load_ct(&sample_volumes_dir().join("phantom-dicom")).unwrap();
    let rest = ingest_scan(&planning, &settings).unwrap();
    let rest_ml = rest.summary.lung_volume_ml;
    // Every phase, segmented by the project's own ingest, holds the scanned volume plus the
    // trace's change at its instant.
    let mut worst_error = 0.0f64;
    let mut inhaled = None;
    for f in &summary.frames {
        let k = f.summary.index;
        let phase = load_ct(&out.join(format!("frames/{k}/virtual-ct.nii.gz"))).unwrap();
        let ingested = ingest_scan(&phase, &settings).unwrap();
        let change_ml = f.summary.target_volume_ml;
        let expected_ml = rest_ml + change_ml;
        let got_ml = ingested.summary.lung_volume_ml;
        let error = (got_ml - expected_ml) / expected_ml;
        println!(
            "frame {k} ({:?} %): lung volume rest {rest_ml:.0} mL, trace {change_ml:+.0} mL, \
             virtual phase {got_ml:.0} mL (expected {expected_ml:.0}): {:+.2} % of the volume, \
             {:+.0} mL off",
            f.summary.phase_percent,
            100.0 * error,
            got_ml - expected_ml
        );
        worst_error = worst_error.max(error.abs());
        if k == frame {
            inhaled = Some((phase, ingested));
        }
    }
    println!("worst phase: {:.2} % of the volume", 100.0 * worst_error);
    assert!(worst_error <= 0.02, "{:.2} %", 100.0 * worst_error);
    let (phase, inhaled) = inhaled.expect("the end-inhale frame is a frame");

    // The dome: columns around the right lung's base landmark, at rest and in the phase,
    // against the written displacement field's cranio-caudal component at the lowest lung
    // voxel.
    let (field_geometry, field) =
        read_nifti_vector_field(&out.join(format!("frames/{frame}/displacement.nii.gz"))).unwrap();
    let ct = &planning.ct;
    let lungs = &rest.segmentation.lungs;
    let description: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(sample_volumes_dir().join("phantom.json")).unwrap(),
    )
    .unwrap();
    let base: [f64; 3] =
        serde_json::from_value(description["landmarks"]["right_lung_base_lps_mm"].clone()).unwrap();
    let centre = ct.geometry.lps_mm_to_voxel(Vector3::from(base));
    let (ci, cj) = (centre.x.round() as usize, centre.y.round() as usize);
    let mut worst = 0.0f64;
    let mut columns = 0;
    for j in cj - 1..=cj + 1 {
        for i in ci - 1..=ci + 1 {
            let (Some(z_rest), Some(z_phase)) = (
                dome_z_mm(ct, lungs, i, j),
                dome_z_mm(&phase.ct, &inhaled.segmentation.lungs, i, j),
            ) else {
                continue;
            };
            let lowest = (0..ct.geometry.dims[2])
                .find(|&k| lungs.get(i, j, k) != 0)
                .unwrap();
            let p = ct
                .geometry
                .voxel_to_lps_mm(Vector3::new(i as f64, j as f64, lowest as f64));
            let f = field_geometry
                .lps_mm_to_voxel(p)
                .map(|v| v.round() as usize);
            let u = field[field_geometry.index(f.x, f.y, f.z)];
            let expected = z_rest + f64::from(u[2]);
            println!(
                "column ({i}, {j}): dome at rest {z_rest:.1} mm, field says {expected:.1} mm \
                 (u_z {:+.1}), virtual end-inhale {z_phase:.1} mm",
                u[2]
            );
            worst = worst.max((z_phase - expected).abs());
            columns += 1;
        }
    }
    assert!(columns >= 5, "only {columns} columns reach the dome");
    assert!(
        worst < 2.0,
        "the dome is {worst:.2} mm from where the field says"
    );
}

/// Whether `python3 -c "import pydicom"` works; says why not when it does not.
fn pydicom_available() -> bool {
    let ok = std::process::Command::new("python3")
        .args(["-c", "import pydicom, numpy"])
        .output()
        .is_ok_and(|o| o.status.success());
    if !ok {
        eprintln!("skipped: needs python3 with pydicom and numpy (pip install pydicom numpy)");
    }
    ok
}

/// pydicom's reading of the first file of each series directory: study, frame of reference,
/// patient, series UIDs, the respiratory attributes, file count and distinct instance UIDs.
fn pydicom_summary(dirs: &[PathBuf]) -> serde_json::Value {
    let script = r#"
import json, os, sys
import pydicom
out = []
for d in sys.argv[1:]:
    files = sorted(os.path.join(d, f) for f in os.listdir(d) if f.endswith(".dcm"))
    ds = pydicom.dcmread(files[0])
    sops = {pydicom.dcmread(f, stop_before_pixels=True).SOPInstanceUID for f in files}
    sync = ds.get((0x0020, 0x9253))
    item = sync.value[0] if sync is not None else None
    out.append({
        "study": ds.StudyInstanceUID,
        "frame_of_reference": ds.FrameOfReferenceUID,
        "patient_id": ds.PatientID,
        "patient_name": str(ds.PatientName),
        "series": ds.SeriesInstanceUID,
        "description": ds.get("SeriesDescription", ""),
        "sop_class": ds.SOPClassUID,
        "files": len(files),
        "distinct_sops": len(sops),
        "compensation": ds.get("RespiratoryMotionCompensationTechnique"),
        "signal_source": ds.get("RespiratorySignalSource"),
        "percent": None if item is None or "NominalPercentageOfRespiratoryPhase" not in item
            else float(item.NominalPercentageOfRespiratoryPhase),
        "cycle_position": None if item is None else item.get("StartingRespiratoryPhase"),
        "temporal_position": ds.get("TemporalPositionIdentifier"),
    })
    # Pixel data and geometry: slices in instance order, HU through the rescale.
    import numpy as np
    slices = sorted((pydicom.dcmread(f) for f in files), key=lambda s: int(s.InstanceNumber))
    hu = np.stack([s.pixel_array.astype(np.float64) * float(s.RescaleSlope)
                   + float(s.RescaleIntercept) for s in slices])
    out[-1].update({
        "shape_kji": list(hu.shape),
        "hu_sum": float(hu.sum()),
        "hu_min": float(hu.min()),
        "hu_max": float(hu.max()),
        "first_position": [float(v) for v in slices[0].ImagePositionPatient],
        "last_position": [float(v) for v in slices[-1].ImagePositionPatient],
        "pixel_spacing": [float(v) for v in slices[0].PixelSpacing],
        "orientation": [float(v) for v in slices[0].ImageOrientationPatient],
    })
print(json.dumps(out, default=str))
"#;
    let output = std::process::Command::new("python3")
        .args(["-c", script])
        .args(dirs)
        .output()
        .unwrap();
    assert!(
        output.status.success(),
        "pydicom: {}",
        String::from_utf8_lossy(&output.stderr)
    );
    serde_json::from_slice(&output.stdout).unwrap()
}

#[test]
fn the_dicom_phases_sit_in_the_planning_study_and_equal_the_nifti_phases() {
    let (out, summary) = demo_run();
    let v = summary.virtual_ct.as_ref().unwrap();
    // The project's own reader: every DICOM phase equals its NIfTI phase (both whole HU).
    for p in v.phases.iter().step_by(3) {
        let dicom = read_dicom_series(&out.join(p.dicom.as_ref().unwrap())).unwrap();
        let nifti = read_nifti(&out.join(p.nifti.as_ref().unwrap())).unwrap();
        assert!(dicom.volume.geometry.same_grid(&nifti.geometry, 1e-3));
        let worst = dicom
            .volume
            .as_slice()
            .iter()
            .zip(nifti.as_slice())
            .map(|(a, b)| (a - b).abs())
            .fold(0.0f32, f32::max);
        assert!(worst <= 0.5, "frame {}: {worst} HU apart", p.frame);
    }
    if !pydicom_available() {
        return;
    }
    let planning = sample_volumes_dir().join("phantom-dicom");
    let mut dirs = vec![planning];
    dirs.extend(v.phases.iter().map(|p| out.join(p.dicom.as_ref().unwrap())));
    dirs.push(out.join("mip-ct-dicom"));
    dirs.push(out.join("aip-ct-dicom"));
    let read = pydicom_summary(&dirs);
    let series = read.as_array().unwrap();
    let ct = &series[0];
    let mut uids = std::collections::BTreeSet::new();
    for (n, s) in series.iter().enumerate().skip(1) {
        for key in ["study", "frame_of_reference", "patient_id", "patient_name"] {
            assert_eq!(s[key], ct[key], "series {n}: {key}");
        }
        assert_ne!(s["series"], ct["series"]);
        assert!(uids.insert(s["series"].as_str().unwrap().to_string()));
        assert_eq!(s["sop_class"], "1.2.840.10008.5.1.4.1.1.2");
        assert_eq!(s["files"], s["distinct_sops"], "series {n}");
        assert_eq!(s["files"], ct["files"], "series {n}");
    }
    for (k, s) in series[1..=v.phases.len()].iter().enumerate() {
        let percent = 10.0 * k as f64;
        assert_eq!(s["percent"].as_f64(), Some(percent), "phase {k}");
        assert_eq!(s["compensation"], "RETROSPECTIVE");
        assert_eq!(s["signal_source"], "SPIROMETER");
        // pydicom's IS is an int, which json writes as a number.
        assert_eq!(
            s["temporal_position"].as_u64(),
            Some(k as u64 + 1),
            "phase {k}"
        );
        let description = s["description"].as_str().unwrap();
        assert!(
            description.starts_with(&format!("lungmotion virtual 4D-CT phase {percent:.0}% (")),
            "{description}"
        );
    }
    // Pixel data and geometry as pydicom decodes them equal the NIfTI phases'.
    let expected: Vec<(String, PathBuf)> = v
        .phases
        .iter()
        .map(|p| {
            (
                format!("frame {}", p.frame),
                out.join(p.nifti.as_ref().unwrap()),
            )
        })
        .chain([
            ("MIP".to_string(), out.join("mip-ct.nii.gz")),
            ("AIP".to_string(), out.join("aip-ct.nii.gz")),
        ])
        .collect();
    for ((what, nifti), s) in expected.iter().zip(&series[1..]) {
        let volume = read_nifti(nifti).unwrap();
        let g = volume.geometry;
        let shape: Vec<usize> = serde_json::from_value(s["shape_kji"].clone()).unwrap();
        assert_eq!(shape, vec![g.dims[2], g.dims[1], g.dims[0]], "{what}");
        let sum: f64 = volume.as_slice().iter().map(|&x| f64::from(x)).sum();
        let got = s["hu_sum"].as_f64().unwrap();
        assert!(
            (got - sum).abs() < 0.5,
            "{what}: pydicom HU sum {got}, NIfTI {sum}"
        );
        let close = |key: &str, want: Vector3<f64>| {
            let p: Vec<f64> = serde_json::from_value(s[key].clone()).unwrap();
            let d = (Vector3::new(p[0], p[1], p[2]) - want).norm();
            assert!(d < 1e-3, "{what}: {key} {p:?} vs {want}");
        };
        close("first_position", g.voxel_to_lps_mm(Vector3::zeros()));
        let last = Vector3::new(0.0, 0.0, (g.dims[2] - 1) as f64);
        close("last_position", g.voxel_to_lps_mm(last));
        let spacing: Vec<f64> = serde_json::from_value(s["pixel_spacing"].clone()).unwrap();
        // PixelSpacing is row spacing (between rows, along j) then column spacing (along i).
        assert!(
            (spacing[0] - g.spacing_mm[1]).abs() < 1e-6
                && (spacing[1] - g.spacing_mm[0]).abs() < 1e-6,
            "{what}: {spacing:?}"
        );
        assert_eq!(s["orientation"], ct["orientation"], "{what}");
        assert!(s["hu_min"].as_f64().unwrap() < -500.0 && s["hu_max"].as_f64().unwrap() > 0.0);
    }
    assert_eq!(series[1]["cycle_position"], "MAXIMUM");
    let mip = &series[v.phases.len() + 1];
    assert!(mip["description"].as_str().unwrap().contains("MIP"));
    assert!(mip["percent"].is_null());
}

#[test]
fn a_bad_option_and_too_many_phases_are_refused_with_the_reason_and_the_remedy() {
    let e = RunConfig::from_toml("[outputs]\nvirtual_ct = \"sometimes\"")
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("outputs.virtual_ct") && e.contains("sometimes") && e.contains("\"both\""),
        "{e}"
    );
    let e = RunConfig::from_toml("[outputs]\noutside_lung_decay_mm = 0.0")
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("outputs.outside_lung_decay_mm") && e.contains("1–500"),
        "{e}"
    );
    let config = RunConfig::from_toml(
        "[motion]\ninstants = { kind = \"every_sample\" }\n[outputs]\nvirtual_ct = \"nifti\"",
    )
    .unwrap();
    // 20 s at 5 Hz: 101 frames. Refused before the CT is read (there is none here).
    let times: Vec<f64> = (0..=100).map(|i| i as f64 * 0.2).collect();
    let volumes = times
        .iter()
        .map(|t| 250.0 * (1.0 - (t * 1.5).cos()))
        .collect();
    let inputs = RunInputs {
        ct_path: Path::new("/nonexistent/ct").to_path_buf(),
        trace: BreathingTrace::new(times, volumes).unwrap(),
        trace_source: "test".into(),
        points: Vec::new(),
        target: None,
    };
    let out = std::env::temp_dir().join(format!("lm-vct-refused-{}", std::process::id()));
    let e = run_breathing(&inputs, &config, &out, &mut SilentObserver)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("outputs.virtual_ct") && e.contains("101") && e.contains("at most 40"),
        "{e}"
    );
    assert!(e.contains("phases") && e.contains("\"off\""), "{e}");
    assert!(!out.exists(), "nothing written");
}

/// The run's warp (index units, rows in parallel, int16) gives the straightforward one's
/// image (`warp_ct_into`: each voxel's LPS position through `PhaseMotion::source_lps_mm`) on
/// the phantom's CT, under a diaphragm-like motion of its own lung mesh, within 1 HU (the
/// two differ only in floating-point rounding, which can tip a value across a half HU).
#[test]
fn the_runs_int16_warp_equals_the_straightforward_one_on_the_phantom() {
    let settings = demo_config(8.0).ingest_settings();
    let planning = load_ct(&sample_volumes_dir().join("phantom-dicom")).unwrap();
    let rest = ingest_scan(&planning, &settings).unwrap();
    let mesh = &rest.model.mesh.mesh;
    let (z_low, z_high) = mesh
        .rest_positions_m
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), p| {
            (lo.min(p.z), hi.max(p.z))
        });
    // Down by up to 12 mm at the base fading to nothing at the apex, 3 mm forward (LPS −y).
    let positions: Vec<Vector3<f64>> = mesh
        .rest_positions_m
        .iter()
        .map(|p| {
            let base = (z_high - p.z) / (z_high - z_low);
            p + Vector3::new(0.0, -3.0 * base, -12.0 * base * base) * 1e-3
        })
        .collect();
    let ct = &planning.ct;
    let motion =
        ct_grid_motion(&ct.geometry, mesh, &positions, CtMotionSettings::default()).unwrap();
    let n = ct.geometry.voxel_count();
    let mut reference = vec![0.0f32; n];
    warp_ct_into(ct, &motion, &mut reference);
    let mut fast = vec![0i16; n];
    warp_ct_int16(ct, &motion, &mut fast);
    let mut worst = 0.0f32;
    let mut differing = 0usize;
    let mut moved = 0usize;
    for ((&r, &f), &c) in reference.iter().zip(&fast).zip(ct.as_slice()) {
        let d = (r - f32::from(f)).abs();
        worst = worst.max(d);
        differing += usize::from(d > 0.0);
        moved += usize::from((r - c).abs() > 50.0);
    }
    println!(
        "{n} voxels: {moved} changed by the motion by more than 50 HU; the fast warp differs \
         from the straightforward one at {differing}, by at most {worst} HU"
    );
    assert!(moved > 10_000, "the motion hardly moves the CT: {moved}");
    assert!(worst <= 1.0, "{worst} HU apart");
    assert!(differing * 10_000 < n, "{differing} of {n} voxels differ");
}
