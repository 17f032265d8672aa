//! An independent reader places our displacement fields where the model says: SimpleITK
//! reads a run's `displacement.nii.gz` (the lung box by default, and the whole CT grid on
//! request) as a `DisplacementFieldTransform`, maps the centre of every lung voxel of the CT
//! (its position computed by ITK from the CT file itself), and each must land at the voxel
//! plus the model's displacement there: the mesh's own interpolation of the frame's node
//! positions, within the 1/64 mm rounding of the file.

use std::path::{Path, PathBuf};

use lungmotion::breathing::BreathingTrace;
use lungmotion::formats::vtk::read_vtu;
use lungmotion::ingest::pipeline::ingest_scan;
use lungmotion::ingest::scan::load_ct;
use lungmotion::motion::lung_scene;
use lungmotion::outputs::displacement_field::{FieldGrid, FieldSampler, FIELD_STEPS_PER_MM};
use lungmotion::run::{run_breathing, RunConfig, RunInputs, SilentObserver};
use nalgebra::Vector3;

fn phantom() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("sample-volumes/phantom-ct.nii.gz")
}

fn config(field_grid: &str) -> RunConfig {
    RunConfig::from_toml(&format!(
        "element_size_mm = 12.0\n[motion]\ninstants = {{ kind = \"every_sample\" }}\n\
         solve_every_frame = true\n[outputs]\nmesh_vtu = true\nfield_grid = \"{field_grid}\"\n"
    ))
    .unwrap()
}

/// Runs the phantom through a +300 mL breath with the fields on `field_grid`; returns the
/// output directory.
fn run(field_grid: &str) -> PathBuf {
    let out = std::env::temp_dir().join(format!("lm-itk-warp-{field_grid}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&out);
    let inputs = RunInputs {
        ct_path: phantom(),
        trace: BreathingTrace::new(vec![0.0, 1.0, 2.0], vec![0.0, 300.0, 0.0]).unwrap(),
        trace_source: "test: +300 mL".into(),
        points: Vec::new(),
        target: None,
    };
    run_breathing(&inputs, &config(field_grid), &out, &mut SilentObserver).unwrap();
    out
}

/// The model's displacement (mm, LPS, rounded as written) at every lung voxel of the CT,
/// `(i, j, k, [ux, uy, uz])`, from the node positions of frame 1's `mesh.vtu`, interpolated
/// on the whole CT grid.
fn model_displacements(out: &Path) -> Vec<([usize; 3], [f32; 3])> {
    let config = config("ct");
    let scan = load_ct(&phantom()).unwrap();
    let outcome = ingest_scan(&scan, &config.ingest_settings()).unwrap();
    let scene = lung_scene(&outcome.model).unwrap();
    let mesh = &scene.mesh;
    let vtu = read_vtu(&out.join("frames/1/mesh.vtu")).unwrap();
    assert_eq!(vtu.points_lps_mm.len(), mesh.rest_positions_m.len());
    let positions_m: Vec<Vector3<f64>> = vtu
        .points_lps_mm
        .iter()
        .map(|p| Vector3::from(*p) * 1e-3)
        .collect();
    let moved = positions_m
        .iter()
        .zip(&mesh.rest_positions_m)
        .filter(|(x, r)| (*x - *r).norm() > 1e-3)
        .count();
    assert!(
        moved > mesh.rest_positions_m.len() / 4,
        "{moved} nodes moved"
    );
    let lungs = &outcome.segmentation.lungs;
    let sampler =
        FieldSampler::new(lungs, mesh, &outcome.model.element_lung, FieldGrid::Ct).unwrap();
    let mut field = vec![[0.0f32; 3]; lungs.geometry.voxel_count()];
    sampler.sample_mm(mesh, &positions_m, &mut field);
    let [nx, ny, _] = lungs.geometry.dims;
    lungs
        .as_slice()
        .iter()
        .enumerate()
        .filter(|(_, &l)| l != 0)
        .map(|(n, _)| ([n % nx, (n / nx) % ny, n / (nx * ny)], field[n]))
        .collect()
}

/// SimpleITK's largest |(T(p) − p) − u| over the voxels, mm, where p is the voxel's centre as
/// ITK computes it from `ct` and T the field's transform; and the field's size.
fn itk_worst_error_mm(field: &Path, ct: &Path, voxels: &Path) -> (f64, String) {
    let script = r#"
import sys
import SimpleITK as sitk
field_path, ct_path, voxels_path = sys.argv[1:4]
ct = sitk.ReadImage(ct_path)
field = sitk.ReadImage(field_path)
size = "x".join(map(str, field.GetSize()))
tx = sitk.DisplacementFieldTransform(sitk.Cast(field, sitk.sitkVectorFloat64))
rows = [[float(v) for v in line.split(",")] for line in open(voxels_path) if line.strip()]
worst = 0.0
for i, j, k, ux, uy, uz in rows:
    p = ct.TransformIndexToPhysicalPoint((int(i), int(j), int(k)))
    q = tx.TransformPoint(p)
    worst = max(worst, abs(q[0] - p[0] - ux), abs(q[1] - p[1] - uy), abs(q[2] - p[2] - uz))
print(len(rows), worst, size)
"#;
    let output = std::process::Command::new("python3")
        .args(["-c", script])
        .args([field, ct, voxels])
        .output()
        .expect("python3 is needed (with SimpleITK: pip install SimpleITK)");
    assert!(
        output.status.success(),
        "SimpleITK could not warp with {}: {} (pip install SimpleITK)",
        field.display(),
        String::from_utf8_lossy(&output.stderr)
    );
    let stdout = String::from_utf8_lossy(&output.stdout).to_string();
    let words: Vec<&str> = stdout.split_whitespace().collect();
    (words[1].parse().unwrap(), words[2].to_string())
}

#[test]
#[cfg_attr(
    not(feature = "slow-tests"),
    ignore = "needs python3 with SimpleITK (pip install SimpleITK; .ci/run installs it): \
              cargo test --features slow-tests --test field_itk_warp"
)]
fn simpleitk_lands_every_lung_voxel_where_the_model_says_on_the_lung_box_and_the_ct_grid() {
    let boxed = run("lung_box");
    let whole = run("ct");
    let expected = model_displacements(&boxed);
    // Frame 1 is the +300 mL inhale: the field varies from voxel to voxel, so a grid off by
    // one voxel, a flipped axis or RAS components would miss by far more than the tolerance.
    let largest = expected
        .iter()
        .map(|(_, u)| u.iter().map(|c| c.abs()).fold(0.0f32, f32::max))
        .fold(0.0, f32::max);
    assert!(largest > 2.0, "largest displacement {largest} mm");
    let voxels = boxed.join("lung-voxels.csv");
    let rows: String = expected
        .iter()
        .map(|([i, j, k], u)| format!("{i},{j},{k},{},{},{}\n", u[0], u[1], u[2]))
        .collect();
    std::fs::write(&voxels, rows).unwrap();
    // Values are exact at voxel centres; what is left is ITK's float index arithmetic.
    let tolerance_mm = 0.1 / f64::from(FIELD_STEPS_PER_MM);
    let mut sizes = Vec::new();
    for out in [&boxed, &whole] {
        let field = out.join("frames/1/displacement.nii.gz");
        let (worst_mm, size) = itk_worst_error_mm(&field, &phantom(), &voxels);
        assert!(
            worst_mm <= tolerance_mm,
            "{}: a lung voxel lands {worst_mm} mm from where the model says",
            field.display()
        );
        sizes.push(size);
    }
    assert_eq!(sizes[1], "76x56x68", "the whole-CT field has the CT's grid");
    assert_ne!(sizes[0], sizes[1], "the lung box is smaller than the CT");
    // Both runs came from the same model: the same node positions at frame 1.
    let whole_vtu = read_vtu(&whole.join("frames/1/mesh.vtu")).unwrap();
    let boxed_vtu = read_vtu(&boxed.join("frames/1/mesh.vtu")).unwrap();
    assert_eq!(whole_vtu.points_lps_mm, boxed_vtu.points_lps_mm);
    for out in [boxed, whole] {
        let _ = std::fs::remove_dir_all(out);
    }
}
