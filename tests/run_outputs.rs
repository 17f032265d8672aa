//! What a run on the bundled phantom reports and writes, named by what it is: the breathing's
//! extremes (end-inhale, deepest expiration) in `summary.json` and on the console, the
//! costal wall-gap warning, the VTK arrays the README lists (read back by our reader and by
//! meshio), and the ingest quick looks' titles, legend and sagittal slice.

use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use lungmotion::breathing::BreathingTrace;
use lungmotion::formats::nifti::read_nifti_labels;
use lungmotion::formats::vtk::{read_vtp_surface, read_vtu, DataArray};
use lungmotion::outputs::ingest_files::group_palette;
use lungmotion::outputs::quicklook::{read_png, read_png_text, RgbImage};
use lungmotion::run::{
    run_breathing, BreathExtreme, RunConfig, RunInputs, RunSummary, SilentObserver,
};
use lungmotion::volume::Volume;
use nalgebra::Vector3;

/// Coarse elements and one solve per sample keep each run to a few seconds.
const ELEMENT_SIZE_MM: f64 = 12.0;

fn phantom() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("sample-volumes/phantom-ct.nii.gz")
}

fn scratch(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("lm-run-outputs-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    d
}

/// One sample a second with these volume changes, mL.
fn trace(volumes_ml: &[f64]) -> BreathingTrace {
    let times = (0..volumes_ml.len()).map(|i| i as f64).collect();
    BreathingTrace::new(times, volumes_ml.to_vec()).unwrap()
}

const CONFIG_TOML: &str = "element_size_mm = 12.0\n[motion]\ninstants = { kind = \"every_sample\" }\nsolve_every_frame = true\n[outputs]\nmesh_vtu = true\n";

fn config() -> RunConfig {
    let config = RunConfig::from_toml(CONFIG_TOML).unwrap();
    assert_eq!(config.element_size_mm, ELEMENT_SIZE_MM);
    config
}

fn run(name: &str, volumes_ml: &[f64]) -> (PathBuf, RunSummary) {
    run_with(name, volumes_ml, &config())
}

/// As [`run`], with `config`.
fn run_with(name: &str, volumes_ml: &[f64], config: &RunConfig) -> (PathBuf, RunSummary) {
    let out = scratch(name);
    let inputs = RunInputs {
        ct_path: phantom(),
        trace: trace(volumes_ml),
        trace_source: format!("test: {volumes_ml:?}"),
        points: Vec::new(),
        target: None,
    };
    let summary = run_breathing(&inputs, config, &out, &mut SilentObserver).unwrap();
    (out, summary)
}

/// A breath in to +200 mL, back, out to −150 mL and back, with every frame's mesh.
fn both_ways() -> &'static (PathBuf, RunSummary) {
    static RUN: OnceLock<(PathBuf, RunSummary)> = OnceLock::new();
    RUN.get_or_init(|| run("both-ways", &[0.0, 200.0, 0.0, -150.0, 0.0]))
}

fn summary_json(out: &Path) -> serde_json::Value {
    serde_json::from_str(&std::fs::read_to_string(out.join("summary.json")).unwrap()).unwrap()
}

#[cfg(feature = "cli")]
#[test]
fn a_trace_that_only_deflates_reports_its_deepest_expiration_not_an_end_inhale() {
    let dir = scratch("deflate");
    std::fs::create_dir_all(&dir).unwrap();
    std::fs::write(
        dir.join("trace.csv"),
        "time_s,volume_ml\n0,0\n1,-100\n2,-200\n3,-100\n4,0\n",
    )
    .unwrap();
    std::fs::write(dir.join("run.toml"), CONFIG_TOML).unwrap();
    let out = dir.join("out");
    let output = std::process::Command::new(env!("CARGO_BIN_EXE_lungmotion"))
        .args(["run", "--quiet", "--ct"])
        .arg(phantom())
        .arg("--trace")
        .arg(dir.join("trace.csv"))
        .arg("--config")
        .arg(dir.join("run.toml"))
        .arg("--out")
        .arg(&out)
        .output()
        .unwrap();
    let stdout = String::from_utf8_lossy(&output.stdout);
    assert!(
        output.status.success(),
        "{stdout}\n{}",
        String::from_utf8_lossy(&output.stderr)
    );
    // Before: "end-inhale (frame 0): max displacement 0.0 mm".
    assert!(!stdout.contains("end-inhale"), "{stdout}");
    let line = stdout
        .lines()
        .find(|l| l.starts_with("deepest expiration (frame 2, t = 2.00 s, -"))
        .unwrap_or_else(|| panic!("no deepest-expiration line in:\n{stdout}"));
    assert!(line.contains("max displacement"), "{line}");

    let json = summary_json(&out);
    assert!(json["end_inhale"].is_null(), "{}", json["end_inhale"]);
    let e = &json["deepest_expiration"];
    assert_eq!(e["kind"], "deepest_expiration");
    assert_eq!(e["frame"], 2);
    assert!((e["target_volume_ml"].as_f64().unwrap() + 200.0).abs() < 1e-6);
    assert!(e["simulated_volume_ml"].as_f64().unwrap() < -150.0, "{e}");
    // Breathing out, the base rises: the opposite of an inhale.
    let max_mm = e["max_displacement_mm"].as_f64().unwrap();
    let base_dz_mm = e["mean_base_dz_mm"].as_f64().unwrap();
    assert!(max_mm > 1.0 && base_dz_mm > 0.5, "{e}");
    assert!(out.join("deepest-expiration-displacement.png").is_file());
    assert!(!out.join("end-inhale-displacement.png").exists());
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_trace_going_both_ways_reports_both_extremes() {
    let (out, s) = both_ways();
    let inhale = s.end_inhale.as_ref().expect("the trace rises to +200 mL");
    let exhale = s
        .deepest_expiration
        .as_ref()
        .expect("the trace falls to -150 mL");
    assert_eq!((inhale.kind, inhale.frame), (BreathExtreme::EndInhale, 1));
    assert_eq!(
        (exhale.kind, exhale.frame),
        (BreathExtreme::DeepestExpiration, 3)
    );
    assert!(inhale.mean_base_dz_mm < -1.0, "{inhale:?}");
    assert!(exhale.mean_base_dz_mm > 0.5, "{exhale:?}");
    assert!(inhale
        .describe()
        .starts_with("end-inhale (frame 1, t = 1.00 s, +"));
    assert!(exhale
        .describe()
        .starts_with("deepest expiration (frame 3, t = 3.00 s, -"));
    assert_eq!(s.extremes().count(), 2);
    let json = summary_json(out);
    assert_eq!(json["end_inhale"]["frame"], 1);
    assert_eq!(json["deepest_expiration"]["frame"], 3);
    // The quick look shows the inhale, under its usual name.
    assert!(out.join("end-inhale-displacement.png").is_file());
    // A small breath keeps the costal nodes on the wall: no warning.
    for e in s.extremes() {
        assert_eq!(e.costal_nodes_off_wall, 0, "{e:?}");
        assert!(e.wall_gap_warning().is_none());
    }
    assert!(
        !s.warnings.iter().any(|w| w.contains("costal")),
        "{:?}",
        s.warnings
    );
}

#[test]
fn costal_nodes_far_off_the_wall_raise_a_warning_with_count_size_place_and_advice() {
    // On the rigid wall: the moving one (the default) keeps these nodes within 9 mm of it.
    let mut rigid = config();
    rigid.motion.rib_cage_share = 0.0;
    let (out, s) = run_with("large-breath", &[0.0, 1000.0, 0.0], &rigid);
    let e = s.end_inhale.as_ref().unwrap();
    // The bound is the element edge (at least 5 mm).
    assert_eq!(e.costal_wall_gap_warning_mm, ELEMENT_SIZE_MM);
    let max_gap_mm = e.costal_wall_gap_change_mm[2];
    assert!(
        max_gap_mm > ELEMENT_SIZE_MM,
        "largest gap change {max_gap_mm} mm"
    );
    assert!(e.costal_nodes_off_wall > 0);
    let w = s
        .warnings
        .iter()
        .find(|w| w.contains("costal"))
        .unwrap_or_else(|| panic!("no costal warning in {:?}", s.warnings));
    let p = e.costal_wall_gap_max_at_lps_mm;
    for needed in [
        format!("{} costal node", e.costal_nodes_off_wall),
        format!("more than {ELEMENT_SIZE_MM} mm"),
        format!("up to {max_gap_mm:.1} mm"),
        format!("LPS ({:.0}, {:.0}, {:.0}) mm", p[0], p[1], p[2]),
        "end-inhale (frame 1".to_string(),
        "tangent planes".to_string(),
        "smaller volume".to_string(),
        "--element-size".to_string(),
    ] {
        assert!(w.contains(&needed), "{needed:?} missing from: {w}");
    }
    // The node named is a costal node of the model, on the lungs' surface.
    let mesh = read_vtu(&out.join("ingest/mesh.vtu")).unwrap();
    let Some((_, DataArray::ScalarsU8(group))) = mesh.point_data.iter().find(|(n, _)| n == "group")
    else {
        panic!("ingest/mesh.vtu has no UInt8 point data `group`");
    };
    let nearest = mesh
        .points_lps_mm
        .iter()
        .enumerate()
        .min_by(|a, b| dist(a.1, &p).total_cmp(&dist(b.1, &p)))
        .unwrap();
    assert!(dist(nearest.1, &p) < 1e-6, "{p:?} is no mesh node");
    assert_eq!(group[nearest.0], 3, "the node at {p:?} is not costal (3)");
    let json = summary_json(&out);
    assert!(json["warnings"]
        .as_array()
        .unwrap()
        .iter()
        .any(|v| v.as_str() == Some(w)));
    assert_eq!(
        json["end_inhale"]["costal_nodes_off_wall"],
        e.costal_nodes_off_wall
    );
    let _ = std::fs::remove_dir_all(&out);
}

fn dist(a: &[f64; 3], b: &[f64; 3]) -> f64 {
    (Vector3::from(*a) - Vector3::from(*b)).norm()
}

/// Name, kind (UInt8, Int32, Float32 ×1 or ×3) and length of each array.
fn arrays(data: &[(String, DataArray)]) -> Vec<(String, &'static str, usize)> {
    data.iter()
        .map(|(name, a)| {
            let kind = match a {
                DataArray::ScalarsU8(_) => "UInt8",
                DataArray::ScalarsI32(_) => "Int32",
                DataArray::ScalarsF32(_) => "Float32",
                DataArray::VectorsF32(_) => "Float32x3",
            };
            (name.clone(), kind, a.len())
        })
        .collect()
}

fn has(list: &[(String, &'static str, usize)], name: &str, kind: &str, len: usize) -> bool {
    list.iter()
        .any(|(n, k, l)| n == name && *k == kind && *l == len)
}

#[test]
fn the_meshes_carry_lung_as_cell_data_and_group_as_point_data_as_the_readme_says() {
    let (out, _) = both_ways();
    let ingest = read_vtu(&out.join("ingest/mesh.vtu")).unwrap();
    let frame = read_vtu(&out.join("frames/1/mesh.vtu")).unwrap();
    let (points, cells) = (ingest.points_lps_mm.len(), ingest.cells.len());
    for (what, mesh) in [("ingest/mesh.vtu", &ingest), ("frames/1/mesh.vtu", &frame)] {
        assert_eq!(
            (mesh.points_lps_mm.len(), mesh.cells.len()),
            (points, cells),
            "{what}"
        );
        let (pd, cd) = (arrays(&mesh.point_data), arrays(&mesh.cell_data));
        assert!(
            has(&pd, "displacement_mm", "Float32x3", points),
            "{what}: {pd:?}"
        );
        assert!(has(&pd, "group", "UInt8", points), "{what}: {pd:?}");
        assert!(has(&cd, "lung", "UInt8", cells), "{what}: {cd:?}");
        assert!(has(&cd, "material_class", "Int32", cells), "{what}: {cd:?}");
    }
    // Same labels at rest and in the frame; both lungs, every group present.
    let labels = |m: &lungmotion::formats::vtk::VtuMesh, name: &str| -> Vec<u8> {
        m.point_data
            .iter()
            .chain(&m.cell_data)
            .find_map(|(n, a)| match a {
                DataArray::ScalarsU8(v) if n == name => Some(v.clone()),
                _ => None,
            })
            .unwrap()
    };
    assert_eq!(labels(&ingest, "group"), labels(&frame, "group"));
    assert_eq!(labels(&ingest, "lung"), labels(&frame, "lung"));
    let lung = labels(&ingest, "lung");
    assert!(lung.contains(&1) && lung.contains(&2) && lung.iter().all(|&l| l == 1 || l == 2));
    let group = labels(&ingest, "group");
    for code in 0..=5u8 {
        assert!(group.contains(&code), "no node of group {code}");
    }
    assert!(group.iter().all(|&g| g <= 5));
    // The surface: group per face (cell data) and per node (point data).
    let surface = read_vtp_surface(&out.join("ingest/surface.vtp")).unwrap();
    let (pd, cd) = (arrays(&surface.point_data), arrays(&surface.cell_data));
    let (sp, sq) = (surface.points_lps_mm.len(), surface.quads.len());
    assert!(has(&cd, "group", "UInt8", sq), "{cd:?}");
    assert!(
        has(&pd, "group", "UInt8", sp) && has(&pd, "node_id", "Int32", sp),
        "{pd:?}"
    );
}

/// meshio's view of a VTK file: for each array, "point|cell name dtype shape".
fn meshio_arrays(path: &Path) -> Vec<String> {
    let script = r#"
import sys, meshio
m = meshio.read(sys.argv[1])
print("points", m.points.shape[0])
for name, a in m.point_data.items():
    print("point", name, a.dtype, "x".join(map(str, a.shape)))
for name, blocks in m.cell_data.items():
    for a in blocks:
        print("cell", name, a.dtype, "x".join(map(str, a.shape)))
"#;
    let output = std::process::Command::new("python3")
        .args(["-c", script])
        .arg(path)
        .output()
        .expect("python3 is needed (with meshio: pip install meshio)");
    assert!(
        output.status.success(),
        "meshio could not read {}: {} (pip install meshio)",
        path.display(),
        String::from_utf8_lossy(&output.stderr)
    );
    String::from_utf8_lossy(&output.stdout)
        .lines()
        .map(str::to_string)
        .collect()
}

#[test]
#[cfg_attr(
    not(feature = "slow-tests"),
    ignore = "needs python3 with meshio (pip install meshio; .ci/run installs it): \
              cargo test --features slow-tests --test run_outputs"
)]
fn meshio_reads_the_same_arrays_from_the_meshes() {
    let (out, _) = both_ways();
    let ours = read_vtu(&out.join("frames/1/mesh.vtu")).unwrap();
    let (points, cells) = (ours.points_lps_mm.len(), ours.cells.len());
    for file in ["ingest/mesh.vtu", "frames/1/mesh.vtu"] {
        let lines = meshio_arrays(&out.join(file));
        for expected in [
            format!("points {points}"),
            format!("point displacement_mm float32 {points}x3"),
            format!("point group uint8 {points}x1"),
            format!("cell lung uint8 {cells}x1"),
            format!("cell material_class int32 {cells}x1"),
        ] {
            assert!(
                lines.contains(&expected),
                "{file}: {expected:?} not in {lines:?}"
            );
        }
    }
}

/// The PNG's tEXt value for `key`.
fn text_of(path: &Path, key: &str) -> String {
    read_png_text(path)
        .unwrap()
        .into_iter()
        .find(|(k, _)| k == key)
        .unwrap_or_else(|| panic!("{}: no tEXt {key}", path.display()))
        .1
}

fn rect_of(path: &Path, key: &str) -> [usize; 4] {
    let v: Vec<usize> = text_of(path, key)
        .split(',')
        .map(|x| x.parse().unwrap())
        .collect();
    [v[0], v[1], v[2], v[3]]
}

/// Pixels of `colour` and near-black pixels in a rectangle of the image.
fn count_in(img: &RgbImage, r: [usize; 4], colour: [u8; 3]) -> (usize, usize) {
    let (mut exact, mut dark) = (0, 0);
    for row in r[1]..(r[1] + r[3]).min(img.height) {
        for col in r[0]..(r[0] + r[2]).min(img.width) {
            let p = img.pixel(col, row);
            exact += usize::from(p == colour);
            dark += usize::from(p.iter().all(|&c| c < 40));
        }
    }
    (exact, dark)
}

#[test]
fn ingest_quick_looks_have_a_title_orientation_letters_a_legend_and_a_sagittal_slice_through_a_lung(
) {
    let (out, _) = both_ways();
    let lungs = read_nifti_labels(&out.join("ingest/lung-mask.nii.gz")).unwrap();
    for plane in ["axial", "coronal", "sagittal"] {
        let path = out.join(format!("ingest/quicklook-{plane}.png"));
        let img = read_png(&path).unwrap();
        assert_eq!(text_of(&path, "lungmotion:plane"), plane);
        assert!(text_of(&path, "Title").contains(plane));
        let slice = rect_of(&path, "lungmotion:slice_px");
        let legend = rect_of(&path, "lungmotion:legend_px");
        // Title band above the slice: text.
        let (_, title_dark) = count_in(&img, [0, 0, img.width, slice[1] - 24], [0; 3]);
        assert!(
            title_dark > 200,
            "{plane}: title band has {title_dark} dark pixels"
        );
        // Orientation letters in the white margins left and right of the slice.
        let (_, left_dark) = count_in(&img, [0, slice[1], slice[0], slice[3]], [0; 3]);
        let right_margin = [slice[0] + slice[2], slice[1], 30, slice[3]];
        let (_, right_dark) = count_in(&img, right_margin, [0; 3]);
        assert!(
            left_dark > 20 && right_dark > 20,
            "{plane}: {left_dark} / {right_dark}"
        );
        // Every group's colour as a swatch in the legend, with its label's text.
        let (_, legend_dark) = count_in(&img, legend, [0; 3]);
        assert!(
            legend_dark > 500,
            "{plane}: legend has {legend_dark} dark pixels"
        );
        for (code, colour) in group_palette() {
            let (swatch, _) = count_in(&img, legend, colour);
            assert!(
                swatch >= 14 * 14,
                "{plane}: group {code} swatch {swatch} px"
            );
        }
    }
    // The sagittal slice lies in the larger lung, well off the midline.
    let path = out.join("ingest/quicklook-sagittal.png");
    let x_mm: f64 = text_of(&path, "lungmotion:position_lps_mm")
        .parse()
        .unwrap();
    let through = text_of(&path, "lungmotion:through");
    let (larger, counts, extent) = lung_extents_x(&lungs);
    let name = if larger == 1 { "right" } else { "left" };
    assert_eq!(through, format!("the {name} lung's centroid"));
    let [lo, hi] = extent[larger as usize];
    assert!(
        lo < x_mm && x_mm < hi,
        "x = {x_mm} mm outside the {name} lung ({lo}..{hi} mm)"
    );
    let [olo, ohi] = extent[3 - larger as usize];
    assert!(
        !(olo..=ohi).contains(&x_mm),
        "x = {x_mm} mm also cuts the other lung"
    );
    assert!(counts[1] > 0 && counts[2] > 0);
}

/// The larger lung label, voxel counts per label and each lung's LPS x extent, mm.
fn lung_extents_x(lungs: &Volume<u8>) -> (u8, [usize; 3], [[f64; 2]; 3]) {
    let g = lungs.geometry;
    let mut counts = [0usize; 3];
    let mut extent = [[f64::MAX, f64::MIN]; 3];
    for k in 0..g.dims[2] {
        for j in 0..g.dims[1] {
            for i in 0..g.dims[0] {
                let l = lungs.get(i, j, k) as usize;
                if l == 1 || l == 2 {
                    let x = g
                        .voxel_to_lps_mm(Vector3::new(i as f64, j as f64, k as f64))
                        .x;
                    counts[l] += 1;
                    extent[l] = [extent[l][0].min(x), extent[l][1].max(x)];
                }
            }
        }
    }
    let larger = if counts[2] > counts[1] { 2 } else { 1 };
    (larger, counts, extent)
}
