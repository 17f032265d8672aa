//! The target through analytic motions (a translation, a stretch): warped masks, centroids,
//! peak-to-peak motion, ITV and the files; `--target` masks checked against the CT's grid;
//! and the demo's phantom tumour followed through a real run.

use std::path::PathBuf;

use lungmotion::formats::nifti::{read_nifti_labels, write_nifti_labels};
use lungmotion::outputs::radiotherapy::target::TargetSpec;
use lungmotion::outputs::radiotherapy::target_motion::{frame_names, TargetTracker};
use lungmotion::outputs::radiotherapy::PhaseMotion;
use lungmotion::volume::{Volume, VolumeGeometry};

fn scratch(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("lm-target-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// Every point moves by `t_mm`.
struct Translation {
    t_mm: [f64; 3],
}

impl PhaseMotion for Translation {
    fn moved_lps_mm(&self, p: [f64; 3]) -> [f64; 3] {
        [0, 1, 2].map(|a| p[a] + self.t_mm[a])
    }
    fn source_lps_mm(&self, p: [f64; 3]) -> [f64; 3] {
        [0, 1, 2].map(|a| p[a] - self.t_mm[a])
    }
}

/// z scaled by `factor` about `z0_mm` (a diaphragm-like stretch along SI).
struct Stretch {
    factor: f64,
    z0_mm: f64,
}

impl PhaseMotion for Stretch {
    fn moved_lps_mm(&self, p: [f64; 3]) -> [f64; 3] {
        [p[0], p[1], self.z0_mm + self.factor * (p[2] - self.z0_mm)]
    }
    fn source_lps_mm(&self, p: [f64; 3]) -> [f64; 3] {
        [p[0], p[1], self.z0_mm + (p[2] - self.z0_mm) / self.factor]
    }
}

fn grid() -> VolumeGeometry {
    VolumeGeometry::axis_aligned([40, 36, 30], [2.0, 2.5, 3.0], [-40.0, -45.0, -45.0])
}

/// A target on `grid()`: a ball of radius 9 mm at (0, 0, 0) written as a label map with
/// label 8 (and label 3 elsewhere, not the target).
fn labelled_ball(path: &std::path::Path) -> Volume<u8> {
    let g = grid();
    let mut labels = Volume::filled(g, 0u8).unwrap();
    let [ni, nj, nk] = g.dims;
    for k in 0..nk {
        for j in 0..nj {
            for i in 0..ni {
                let p = g.voxel_to_lps_mm(nalgebra::Vector3::new(i as f64, j as f64, k as f64));
                let label = if p.norm() <= 9.0 {
                    8
                } else if p[0] > 30.0 {
                    3
                } else {
                    0
                };
                labels.as_slice_mut()[g.index(i, j, k)] = label;
            }
        }
    }
    write_nifti_labels(path, &labels).unwrap();
    labels
}

#[test]
fn a_translation_moves_the_mask_exactly_and_the_centroid_by_t_with_the_itv_the_union() {
    let dir = scratch("translation");
    let labels = labelled_ball(&dir.join("labels.nii.gz"));
    let spec: TargetSpec = format!("{}:label=8", dir.join("labels.nii.gz").display())
        .parse()
        .unwrap();
    let g = grid();
    let target = spec.resolve(&g, None).unwrap();
    let planning = target.voxel_count();
    assert_eq!(
        planning,
        labels.as_slice().iter().filter(|&&v| v == 8).count()
    );
    let out = dir.join("run");
    let instants = lungmotion::breathing::OutputInstants::Phases { count: 3 };
    let mut tracker = TargetTracker::new(target, &out, frame_names(&instants, 3), None).unwrap();
    // Whole voxels: (3, −2, 2) voxels at the end, half of it in the middle frame.
    let t_mm = [12.0, -10.0, 12.0];
    let shifts = [0.0, 0.5, 1.0];
    for (k, s) in shifts.iter().enumerate() {
        let motion = Translation {
            t_mm: t_mm.map(|v| v * s),
        };
        tracker.frame(k, k as f64, &motion).unwrap();
    }
    let summary = tracker.finish().unwrap();
    let shift_voxels = |s: f64| [0, 1, 2].map(|a| (t_mm[a] * s / g.spacing_mm[a]).round() as i64);
    let mut union = vec![0u8; g.voxel_count()];
    for (k, &s) in shifts.iter().enumerate() {
        let frame = read_nifti_labels(&out.join(format!("frames/{k}/target.nii.gz"))).unwrap();
        assert!(frame.geometry.same_grid(&g, 1e-4));
        let d = shift_voxels(s);
        let [ni, nj, nk] = g.dims.map(|n| n as i64);
        let mut expected = vec![0u8; g.voxel_count()];
        for kk in 0..nk {
            for j in 0..nj {
                for i in 0..ni {
                    let (si, sj, sk) = (i - d[0], j - d[1], kk - d[2]);
                    let inside =
                        (0..ni).contains(&si) && (0..nj).contains(&sj) && (0..nk).contains(&sk);
                    if inside
                        && labels.as_slice()[g.index(si as usize, sj as usize, sk as usize)] == 8
                    {
                        expected[g.index(i as usize, j as usize, kk as usize)] = 1;
                    }
                }
            }
        }
        assert_eq!(
            frame.as_slice(),
            &expected[..],
            "frame {k}: the mask shifted by {d:?}"
        );
        union.iter_mut().zip(&expected).for_each(|(u, e)| *u |= e);
        let f = &summary.frames[k];
        let c0 = summary.planning_centroid_lps_mm;
        for a in 0..3 {
            assert!(
                (f.centroid_lps_mm[a] - (c0[a] + s * t_mm[a])).abs() < 1e-9,
                "frame {k} centroid {:?}",
                f.centroid_lps_mm
            );
        }
        assert!((f.volume_cc - summary.planning_volume_cc).abs() < 1e-12);
    }
    let itv = read_nifti_labels(&out.join("target/itv.nii.gz")).unwrap();
    assert_eq!(
        itv.as_slice(),
        &union[..],
        "the ITV is the union of the frames"
    );
    let itv_cc = union.iter().filter(|&&v| v != 0).count() as f64 * 15.0 / 1000.0;
    assert!((summary.itv_volume_cc - itv_cc).abs() < 1e-9);
    let p = summary.peak_to_peak_mm;
    assert!((p.lr - 12.0).abs() < 1e-9 && (p.ap - 10.0).abs() < 1e-9 && (p.si - 12.0).abs() < 1e-9);
    assert!(summary.tg76_motion_management_advised);
    assert_eq!(summary.frames[1].name, "phase 33%");
    assert!(summary.files.rtstruct.is_none());
    assert!(
        summary.notes.iter().any(|n| n.contains("no RTSTRUCT")),
        "{:?}",
        summary.notes
    );
    let csv = std::fs::read_to_string(out.join("target-motion.csv")).unwrap();
    let lines: Vec<&str> = csv.lines().collect();
    assert!(lines[0].starts_with("frame,time_s,name,volume_cc,centroid_x_lps_mm"));
    assert!(lines[0].ends_with("lr_mm_plus_left,ap_mm_plus_posterior,si_mm_plus_superior"));
    assert_eq!(lines.len(), 4);
    assert!(
        lines[3].ends_with(",12.0000,-10.0000,12.0000"),
        "{}",
        lines[3]
    );
    let json = serde_json::to_value(&summary).unwrap();
    assert_eq!(json["peak_to_peak_mm"]["si"], 12.0);
    assert!(json["source"]
        .as_str()
        .unwrap()
        .ends_with("labels.nii.gz:label=8"));
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_stretch_scales_the_volume_and_a_small_motion_stays_under_tg76() {
    let dir = scratch("stretch");
    let g = grid();
    let spec: TargetSpec = "point:0,0,0:r=9".parse().unwrap();
    let target = spec.resolve(&g, None).unwrap();
    let planning_cc = target.voxel_count() as f64 * 15.0 / 1000.0;
    let mut tracker = TargetTracker::new(target, &dir, Vec::new(), None).unwrap();
    // Stretched by 1.3 along SI about z = −30 mm: the centroid goes up by 0.3 × 30 mm = 9 mm…
    tracker
        .frame(
            0,
            0.0,
            &Stretch {
                factor: 1.0,
                z0_mm: -30.0,
            },
        )
        .unwrap();
    tracker
        .frame(
            1,
            1.0,
            &Stretch {
                factor: 1.3,
                z0_mm: -30.0,
            },
        )
        .unwrap();
    let s = tracker.finish().unwrap();
    assert_eq!(s.frames[1].name, "frame 1");
    assert!(
        (s.frames[1].displacement_mm.si - 9.0).abs() < 1e-9,
        "{:?}",
        s.frames[1]
    );
    assert!(s.frames[1].displacement_mm.lr.abs() < 1e-12);
    // …and its volume grows by 1.3 within the voxelisation of a 9 mm ball on 3 mm slices.
    let ratio = s.frames[1].volume_cc / planning_cc;
    assert!((ratio - 1.3).abs() < 0.1, "volume ratio {ratio}");
    assert!(s.tg76_motion_management_advised);

    // A 3 mm translation along LR only: under TG-76's 5 mm.
    let target = spec.resolve(&g, None).unwrap();
    let mut tracker = TargetTracker::new(target, &dir.join("small"), Vec::new(), None).unwrap();
    tracker
        .frame(0, 0.0, &Translation { t_mm: [0.0; 3] })
        .unwrap();
    tracker
        .frame(
            1,
            1.0,
            &Translation {
                t_mm: [3.0, 0.0, 0.0],
            },
        )
        .unwrap();
    let s = tracker.finish().unwrap();
    assert!((s.peak_to_peak_mm.lr - 3.0).abs() < 1e-9);
    assert!(!s.tg76_motion_management_advised);
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn masks_off_the_cts_grid_and_bad_target_texts_are_refused_with_their_reason() {
    let dir = scratch("refusals");
    let path = dir.join("labels.nii.gz");
    labelled_ball(&path);
    let g = grid();
    // Another grid: shifted by a voxel.
    let other = VolumeGeometry {
        origin_lps_mm: [-38.0, -45.0, -45.0],
        ..g
    };
    let e = format!("{}:label=8", path.display())
        .parse::<TargetSpec>()
        .unwrap()
        .resolve(&other, None)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("not on the CT's grid")
            && e.contains("first voxel at (-40, -45, -45) mm")
            && e.contains("first voxel at (-38, -45, -45) mm"),
        "names both grids: {e}"
    );
    let e = format!("{}:label=9", path.display())
        .parse::<TargetSpec>()
        .unwrap()
        .resolve(&g, None)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("label 9 is not in the mask; labels present: 3, 8"),
        "{e}"
    );
    for (text, says) in [
        (
            format!("{}:GTV", path.display()),
            "only `:label=<n>` may follow",
        ),
        (
            format!("{}:label=0", path.display()),
            "not a whole number from 1 to 255",
        ),
        (format!("{}:label=x", path.display()), "label `x`"),
        (dir.display().to_string(), "no such file"),
        ("point:1,2,3:r=-4".to_string(), "radius -4 mm is outside"),
    ] {
        let e = text.parse::<TargetSpec>().unwrap_err().to_string();
        assert!(
            e.contains(says) && e.contains("invalid target"),
            "{text}: {e}"
        );
    }
    // A sphere outside the CT holds none of its voxels.
    let e = "point:500,0,0:r=10"
        .parse::<TargetSpec>()
        .unwrap()
        .resolve(&g, None)
        .unwrap_err()
        .to_string();
    assert!(e.contains("holds no voxel of the CT's grid"), "{e}");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn the_demo_follows_the_phantom_tumour_into_the_summary_the_masks_and_the_rtstruct() {
    use lungmotion::run::demo::{demo_inputs, sample_volumes_dir};
    use lungmotion::run::{run_breathing, RunConfig, SilentObserver};
    let out = scratch("demo");
    let inputs = demo_inputs(&sample_volumes_dir()).unwrap();
    let config = RunConfig {
        element_size_mm: 12.0,
        ..RunConfig::default()
    };
    let summary = run_breathing(&inputs, &config, &out, &mut SilentObserver).unwrap();
    let target = summary.target.as_ref().expect("the demo has a target");
    assert!(target.source.ends_with("phantom-truth.nii.gz:label=8"));
    assert_eq!(target.frames.len(), summary.frames.len());
    // The tumour's centroid follows the tracked point at its centre (both from the model:
    // the mesh at the point, the sampled field over the tumour's voxels).
    let tumour = summary.points.iter().find(|p| p.name == "tumour").unwrap();
    for (f, d) in target.frames.iter().zip(&tumour.displacement_mm) {
        let c = f.displacement_mm;
        let gap = ((c.lr - d[0]).powi(2) + (c.ap - d[1]).powi(2) + (c.si - d[2]).powi(2)).sqrt();
        assert!(
            gap < 1.0,
            "frame {}: centroid {c:?} vs point {d:?}",
            f.frame
        );
    }
    assert!(
        target.peak_to_peak_mm.si > 5.0,
        "{:?}",
        target.peak_to_peak_mm
    );
    assert!(target.itv_volume_cc > target.planning_volume_cc);
    let rtstruct = out.join(
        target
            .files
            .rtstruct
            .as_ref()
            .expect("a DICOM CT gets an RTSTRUCT"),
    );
    let itv = read_nifti_labels(&out.join(&target.files.itv_nifti)).unwrap();
    let study = lungmotion::formats::dicom::read_dicom_series(&inputs.ct_path)
        .unwrap()
        .study;
    let back = lungmotion::outputs::radiotherapy::rtstruct::read_roi_mask(
        &rtstruct,
        "ITV",
        &itv.geometry,
        Some(&study.frame_of_reference_uid),
    )
    .unwrap();
    assert_eq!(
        back.as_slice(),
        itv.as_slice(),
        "the RTSTRUCT's ITV is the ITV mask"
    );
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("summary.json")).unwrap()).unwrap();
    assert!(json["target"]["peak_to_peak_mm"]["si"].as_f64().unwrap() > 5.0);
    assert!(out.join("target-motion.csv").is_file());
    let _ = std::fs::remove_dir_all(&out);
}

#[test]
fn the_cli_refuses_a_target_it_cannot_use_with_exit_status_2() {
    let out = std::env::temp_dir().join(format!("lm-target-cli-{}", std::process::id()));
    let run = |target: &str| {
        std::process::Command::new(env!("CARGO_BIN_EXE_lungmotion"))
            .args(["run", "--ct"])
            .arg(PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("sample-volumes/phantom-ct.nii.gz"))
            .args(["--trace", "/dev/null", "--out"])
            .arg(&out)
            .args(["--target", target, "--quiet"])
            .output()
            .unwrap()
    };
    let o = run("point:1,2:r=5");
    assert_eq!(o.status.code(), Some(2));
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        err.contains("the point has 2 coordinate(s), not 3"),
        "{err}"
    );
    assert!(!out.exists());
}
