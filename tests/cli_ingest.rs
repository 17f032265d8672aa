//! `lungmotion ingest` as scripts use it: the files and fields the command-line contract
//! promises, on the bundled phantom, and clear refusals that leave earlier outputs intact.
#![cfg(feature = "cli")]

mod common;

use std::path::Path;

use common::{absent_temp_dir, bin, sample};

use lungmotion::formats::{nifti, vtk};
use lungmotion::outputs::quicklook::read_png;

fn run_ingest(ct: &Path, out: &Path, extra: &[&str]) -> std::process::Output {
    bin()
        .arg("ingest")
        .arg("--ct")
        .arg(ct)
        .arg("--out")
        .arg(out)
        .args(extra)
        .output()
        .unwrap()
}

#[test]
fn ingest_of_the_dicom_phantom_writes_the_promised_files_and_fields() {
    let out = absent_temp_dir("phantom");
    let o = run_ingest(&sample("phantom-dicom"), &out, &["--element-size", "10"]);
    let stderr = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{stderr}");

    let ct = nifti::read_nifti(&sample("phantom-ct.nii.gz")).unwrap();
    let mask = nifti::read_nifti_labels(&out.join("lung-mask.nii.gz")).unwrap();
    assert!(
        mask.geometry.same_grid(&ct.geometry, 1e-3),
        "mask not on the CT grid"
    );
    assert!(mask.as_slice().iter().all(|&v| v <= 2));
    // Right lung (1) on the patient's right, which is −x in LPS.
    let mean_x = |label: u8| {
        let (mut s, mut n) = (0.0, 0usize);
        for (idx, &v) in mask.as_slice().iter().enumerate() {
            if v == label {
                let [nx, ny, _] = mask.geometry.dims;
                let ijk = nalgebra::Vector3::new(
                    (idx % nx) as f64,
                    ((idx / nx) % ny) as f64,
                    (idx / (nx * ny)) as f64,
                );
                s += mask.geometry.voxel_to_lps_mm(ijk).x;
                n += 1;
            }
        }
        s / n as f64
    };
    assert!(mean_x(1) < -30.0 && mean_x(2) > 30.0);

    let groups = nifti::read_nifti_labels(&out.join("groups.nii.gz")).unwrap();
    assert!(groups.geometry.same_grid(&ct.geometry, 1e-3));
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("ingest.json")).unwrap()).unwrap();
    for key in [
        "lung_volume_ml",
        "right_volume_ml",
        "left_volume_ml",
        "element_size_mm",
        "elements",
        "nodes",
    ] {
        assert!(
            json[key].as_f64().is_some_and(|v| v > 0.0),
            "{key}: {}",
            json[key]
        );
    }
    assert_eq!(json["element_size_mm"].as_f64(), Some(10.0));
    let total = json["lung_volume_ml"].as_f64().unwrap();
    let sides =
        json["right_volume_ml"].as_f64().unwrap() + json["left_volume_ml"].as_f64().unwrap();
    assert!((total - sides).abs() < 1.0);
    // Every group has nodes and its code is listed; the codes in groups.nii.gz are those.
    let codes = json["group_codes"].as_object().unwrap();
    for (code, entry) in codes {
        let name = entry["name"].as_str().unwrap();
        assert!(json["group_nodes"][name].as_u64().unwrap() > 0, "{name}");
        let code: u8 = code.parse().unwrap();
        assert!(
            groups.as_slice().contains(&code),
            "code {code} ({name}) absent from groups.nii.gz"
        );
    }
    assert!(groups
        .as_slice()
        .iter()
        .all(|&g| g == 0 || codes.contains_key(&g.to_string())));

    let mesh = vtk::read_vtu(&out.join("mesh.vtu")).unwrap();
    assert_eq!(mesh.cells.len() as f64, json["elements"].as_f64().unwrap());
    assert_eq!(
        mesh.points_lps_mm.len() as f64,
        json["nodes"].as_f64().unwrap()
    );
    vtk::read_vtp_surface(&out.join("surface.vtp")).unwrap();
    for plane in ["axial", "coronal", "sagittal"] {
        let png = read_png(&out.join(format!("quicklook-{plane}.png"))).unwrap();
        assert!(png.width > 50 && png.height > 50);
    }
    std::fs::remove_dir_all(&out).ok();
}

#[test]
fn nifti_and_dicom_inputs_give_the_same_lungs() {
    let (a, b) = (absent_temp_dir("nii"), absent_temp_dir("dcm"));
    assert!(run_ingest(&sample("phantom-ct.nii.gz"), &a, &[])
        .status
        .success());
    assert!(run_ingest(&sample("phantom-dicom"), &b, &[])
        .status
        .success());
    let ma = nifti::read_nifti_labels(&a.join("lung-mask.nii.gz")).unwrap();
    let mb = nifti::read_nifti_labels(&b.join("lung-mask.nii.gz")).unwrap();
    assert_eq!(ma.as_slice(), mb.as_slice());
    std::fs::remove_dir_all(&a).ok();
    std::fs::remove_dir_all(&b).ok();
}

#[test]
fn bad_inputs_are_refused_by_name_and_earlier_outputs_survive() {
    let out = absent_temp_dir("bad");
    assert!(run_ingest(&sample("phantom-ct.nii.gz"), &out, &[])
        .status
        .success());
    let before = std::fs::read(out.join("ingest.json")).unwrap();

    let missing = out.join("no-such-scan");
    let o = run_ingest(&missing, &out, &[]);
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && e.contains("no-such-scan"), "{e}");

    let text = out.join("notes.txt");
    std::fs::write(&text, "not a scan").unwrap();
    let o = run_ingest(&text, &out, &[]);
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(
        !o.status.success() && e.contains("notes.txt") && e.contains("not a DICOM"),
        "{e}"
    );

    let o = run_ingest(
        &sample("phantom-ct.nii.gz"),
        &out,
        &["--element-size", "50"],
    );
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && e.contains("50"), "{e}");

    let labels_only = sample("phantom-truth.nii.gz");
    let o = run_ingest(&labels_only, &out, &[]);
    let e = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && e.contains("Hounsfield"), "{e}");

    assert_eq!(std::fs::read(out.join("ingest.json")).unwrap(), before);
    std::fs::remove_dir_all(&out).ok();
}
