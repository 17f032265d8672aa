//! Lung segmentation: accuracy on the real CIP chest CT against its expert label map, and
//! anatomy-following labels on synthetic thoraxes stored on flipped and oblique grids.

use lungmotion::datasets::{cip_chest_ct64, cip_expert_labels, CIP_AIRWAY_LABEL};
use lungmotion::formats::nrrd::read_nrrd;
use lungmotion::ingest::segmentation::{
    dice, segment_lungs, SegmentationSettings, ThresholdMethod, LEFT_LUNG, RIGHT_LUNG,
};
use lungmotion::volume::{Volume, VolumeGeometry};
use lungmotion::Error;
use nalgebra::Vector3;

fn union(v: &Volume<u8>) -> Volume<u8> {
    v.map(|l| (l == RIGHT_LUNG || l == LEFT_LUNG) as u8)
}

#[test]
#[cfg_attr(
    not(shared_data),
    ignore = "needs the shared CT data (../shared/data or LUNGMOTION_SHARED_DATA; see README)"
)]
fn cip_case_matches_the_expert_lung_map() {
    let Some(dir) = cip_chest_ct64() else {
        println!("skipped: shared data not found");
        return;
    };
    let ct = read_nrrd(&dir.join("ct-64.nrrd")).unwrap();
    let expert = cip_expert_labels(&read_nrrd(&dir.join("lm-64.nrrd")).unwrap());
    let voxel_ml = ct.geometry.voxel_volume_mm3() / 1000.0;
    let count = |v: &Volume<u8>, l: u8| v.as_slice().iter().filter(|&&x| x == l).count() as f64;
    let expert_right_ml = count(&expert, RIGHT_LUNG) * voxel_ml;
    let expert_left_ml = count(&expert, LEFT_LUNG) * voxel_ml;
    let expert_airway_ml = count(&expert, CIP_AIRWAY_LABEL) * voxel_ml;

    for method in [ThresholdMethod::Fixed, ThresholdMethod::Otsu] {
        let settings = SegmentationSettings {
            threshold_method: method,
            ..SegmentationSettings::default()
        };
        let seg = segment_lungs(&ct, &settings).unwrap();
        let r = &seg.report;
        let both = dice(&union(&seg.lungs), 1, &union(&expert), 1).unwrap();
        let right = dice(&seg.lungs, RIGHT_LUNG, &expert, RIGHT_LUNG).unwrap();
        let left = dice(&seg.lungs, LEFT_LUNG, &expert, LEFT_LUNG).unwrap();
        let swapped_right = dice(&seg.lungs, RIGHT_LUNG, &expert, LEFT_LUNG).unwrap();
        let swapped_left = dice(&seg.lungs, LEFT_LUNG, &expert, RIGHT_LUNG).unwrap();
        let airway = dice(&seg.airways, 1, &expert, CIP_AIRWAY_LABEL).unwrap();
        println!(
            "CIP ct-64, {method:?} threshold {:.0} HU: Dice both {both:.4}, right {right:.4}, \
             left {left:.4} (swapped: {swapped_right:.4} / {swapped_left:.4}); airways Dice \
             {airway:.3}",
            r.threshold_hu
        );
        println!(
            "  volumes mL: right {:.0} (expert {expert_right_ml:.0}), left {:.0} (expert \
             {expert_left_ml:.0}), both {:.0} (expert {:.0}); airways {:.1} (expert \
             {expert_airway_ml:.1}); cutoff {:?} HU, separation {:?} mm, removed {} ({:.1} mL), \
             {:.3} s; warnings {:?}",
            r.right_volume_ml,
            r.left_volume_ml,
            r.lung_volume_ml,
            expert_right_ml + expert_left_ml,
            r.airway_volume_ml,
            r.airway_cutoff_hu,
            r.separation_depth_mm,
            r.components_removed,
            r.components_removed_ml,
            r.wall_time_s,
            r.warnings
        );
        println!("  airway growth: {:?}", r.airway_growth);
        assert!(both >= 0.97, "Dice of both lungs {both:.4} < 0.97");
        assert!(right >= 0.95, "Dice of the right lung {right:.4} < 0.95");
        assert!(left >= 0.95, "Dice of the left lung {left:.4} < 0.95");
        assert!(
            swapped_right < 0.05 && swapped_left < 0.05,
            "left and right swapped"
        );
        let total_err = (r.lung_volume_ml / (expert_right_ml + expert_left_ml) - 1.0).abs();
        assert!(
            total_err < 0.05,
            "lung volume off by {:.1} %",
            100.0 * total_err
        );
        assert!(r.airway_seed_lps_mm.is_some(), "trachea not found");
        // Masks on the CT grid, body containing the lungs.
        assert!(seg.lungs.geometry.same_grid(&ct.geometry, 1e-9));
        let outside_body = seg
            .lungs
            .as_slice()
            .iter()
            .zip(seg.body.as_slice())
            .filter(|(&l, &b)| l != 0 && b == 0)
            .count();
        assert_eq!(outside_body, 0);
    }
}

/// A synthetic thorax in LPS mm: body ellipse (40 HU) in air (−1000 HU), two ellipsoid lungs
/// (−850 HU) touching at the midline, a trachea joined to both by main bronchi, and vessels.
struct Thorax {
    /// Half-distance between the lung centres in x, mm (less than the x semi-axis: touching).
    lung_offset_mm: f64,
    /// Whether the left lung exists.
    left_lung: bool,
}

const LUNG_AXES_MM: [f64; 3] = [60.0, 70.0, 100.0];
const VESSEL_RADIUS_MM: f64 = 6.0;

impl Thorax {
    fn in_lung(&self, p: Vector3<f64>, side: f64) -> bool {
        let c = Vector3::new(side * self.lung_offset_mm, 0.0, 0.0);
        let q = p - c;
        (q.x / LUNG_AXES_MM[0]).powi(2)
            + (q.y / LUNG_AXES_MM[1]).powi(2)
            + (q.z / LUNG_AXES_MM[2]).powi(2)
            <= 1.0
    }

    /// Truth: 1 right (x < 0), 2 left, 0 elsewhere (the trachea outside the lungs included).
    fn label(&self, p: Vector3<f64>) -> u8 {
        if self.in_lung(p, -1.0) && (p.x < 0.0 || !self.left_lung || !self.in_lung(p, 1.0)) {
            RIGHT_LUNG
        } else if self.left_lung && self.in_lung(p, 1.0) {
            LEFT_LUNG
        } else {
            0
        }
    }

    fn in_airway(p: Vector3<f64>) -> bool {
        let carina = Vector3::new(0.0, -10.0, 55.0);
        let trachea = p.z >= carina.z && (p.x.powi(2) + (p.y - carina.y).powi(2)) <= 81.0;
        let bronchus = |end: Vector3<f64>| {
            let axis = end - carina;
            let t = ((p - carina).dot(&axis) / axis.norm_squared()).clamp(0.0, 1.0);
            (p - (carina + axis * t)).norm() <= 6.0
        };
        trachea
            || bronchus(Vector3::new(-45.0, -5.0, 25.0))
            || bronchus(Vector3::new(45.0, -5.0, 25.0))
    }

    fn hu(&self, p: Vector3<f64>) -> f32 {
        let in_body = (p.x / 160.0).powi(2) + (p.y / 110.0).powi(2) <= 1.0;
        if !in_body {
            return -1000.0;
        }
        if Self::in_airway(p) {
            return -1000.0;
        }
        let lung = self.in_lung(p, -1.0) || (self.left_lung && self.in_lung(p, 1.0));
        if lung {
            // Vessels inside each lung, enclosed by parenchyma.
            for c in [
                Vector3::new(-70.0, 10.0, -20.0),
                Vector3::new(70.0, -15.0, 0.0),
                Vector3::new(-60.0, 0.0, 30.0),
            ] {
                if (p - c).norm() <= VESSEL_RADIUS_MM {
                    return 40.0;
                }
            }
            return -850.0;
        }
        40.0
    }

    fn sample(&self, g: VolumeGeometry) -> (Volume<f32>, Volume<u8>) {
        let [nx, ny, nz] = g.dims;
        let mut ct = Vec::with_capacity(nx * ny * nz);
        let mut truth = Vec::with_capacity(nx * ny * nz);
        for k in 0..nz {
            for j in 0..ny {
                for i in 0..nx {
                    let p = g.voxel_to_lps_mm(Vector3::new(i as f64, j as f64, k as f64));
                    ct.push(self.hu(p));
                    truth.push(self.label(p));
                }
            }
        }
        (
            Volume::from_data(g, ct).unwrap(),
            Volume::from_data(g, truth).unwrap(),
        )
    }
}

/// A grid covering x ±180, y ±130, z −120…+170 mm at `spacing` mm with the given axes.
fn grid(spacing: f64, direction: [[f64; 3]; 3]) -> VolumeGeometry {
    let extent = [360.0, 260.0, 290.0];
    let dims = extent.map(|e| (e / spacing) as usize + 1);
    let centre = Vector3::new(0.0, 0.0, 25.0);
    let mut g = VolumeGeometry {
        dims,
        spacing_mm: [spacing; 3],
        origin_lps_mm: [0.0; 3],
        direction_lps: direction,
    };
    // Put the grid centre at `centre` whatever the axes.
    let half = Vector3::from(dims.map(|n| (n - 1) as f64 * 0.5));
    let offset = g.voxel_to_lps_mm(half);
    g.origin_lps_mm = (centre - offset).into();
    g
}

const IDENTITY: [[f64; 3]; 3] = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];

fn check_synthetic(direction: [[f64; 3]; 3], name: &str) {
    let thorax = Thorax {
        lung_offset_mm: 58.0,
        left_lung: true,
    };
    let (ct, truth) = thorax.sample(grid(4.0, direction));
    let on = |threads: usize| {
        rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap()
            .install(|| segment_lungs(&ct, &SegmentationSettings::default()).unwrap())
    };
    let (seg, single) = (on(2), on(1));
    // The per-slice closing, the distance maps and the split of touching lungs run on all
    // cores: one core must give the same voxels and the same report, timings aside.
    assert_eq!(seg.lungs.as_slice(), single.lungs.as_slice(), "{name}");
    assert_eq!(seg.airways.as_slice(), single.airways.as_slice(), "{name}");
    assert_eq!(seg.body.as_slice(), single.body.as_slice(), "{name}");
    let untimed = |r: &lungmotion::ingest::segmentation::SegmentationReport| {
        let mut v = serde_json::to_value(r).unwrap();
        v["wall_time_s"] = serde_json::Value::Null;
        v["step_times_s"] = serde_json::Value::Null;
        v
    };
    assert_eq!(untimed(&seg.report), untimed(&single.report), "{name}");
    let r = &seg.report;
    let right = dice(&seg.lungs, RIGHT_LUNG, &truth, RIGHT_LUNG).unwrap();
    let left = dice(&seg.lungs, LEFT_LUNG, &truth, LEFT_LUNG).unwrap();
    println!(
        "synthetic {name}: Dice right {right:.4}, left {left:.4}; volumes {:.0} / {:.0} mL; \
         separation {:?} mm; airways {:.1} mL; warnings {:?}",
        r.right_volume_ml, r.left_volume_ml, r.separation_depth_mm, r.airway_volume_ml, r.warnings
    );
    assert!(right >= 0.93 && left >= 0.93, "{name}: {right} {left}");
    // The lungs touch, so they must have been separated by erosion.
    assert!(
        r.separation_depth_mm.is_some(),
        "{name}: lungs did not touch?"
    );
    assert!(r.airway_seed_lps_mm.is_some(), "{name}: no trachea seed");
    // The trachea above the lungs is airway, not lung.
    let probe = Vector3::new(0.0, -10.0, 120.0);
    let ijk = ct
        .geometry
        .lps_mm_to_voxel(probe)
        .map(|v| v.round() as usize);
    assert_eq!(
        seg.lungs.get(ijk.x, ijk.y, ijk.z),
        0,
        "{name}: trachea in lung"
    );
    assert_eq!(
        seg.airways.get(ijk.x, ijk.y, ijk.z),
        1,
        "{name}: trachea missed"
    );
    // Enclosed vessels are lung.
    let vessel = Vector3::new(-70.0, 10.0, -20.0);
    let ijk = ct
        .geometry
        .lps_mm_to_voxel(vessel)
        .map(|v| v.round() as usize);
    assert_eq!(
        seg.lungs.get(ijk.x, ijk.y, ijk.z),
        RIGHT_LUNG,
        "{name}: vessel left out"
    );
}

#[test]
fn synthetic_touching_lungs_are_split_and_labelled_by_anatomy() {
    check_synthetic(IDENTITY, "identity axes");
}

#[test]
fn labels_follow_anatomy_when_x_is_stored_flipped() {
    check_synthetic(
        [[-1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]],
        "flipped x (left-handed)",
    );
}

#[test]
fn labels_follow_anatomy_on_an_oblique_grid_stored_upside_down() {
    let (s, c) = (0.4f64.sin(), 0.4f64.cos());
    check_synthetic(
        [[c, s, 0.0], [s, -c, 0.0], [0.0, 0.0, -1.0]],
        "oblique, z reversed",
    );
}

#[test]
fn a_scan_without_lungs_is_refused_with_the_reason() {
    let g = grid(8.0, IDENTITY);
    // Solid body in air: no lung.
    let ct = Volume::filled(g, 40.0f32).unwrap();
    match segment_lungs(&ct, &SegmentationSettings::default()) {
        Err(Error::Ingest(m)) => assert!(m.contains("no lung found"), "{m}"),
        other => panic!("expected 'no lung found', got {other:?}"),
    }
    // Air only.
    let ct = Volume::filled(g, -1000.0f32).unwrap();
    match segment_lungs(&ct, &SegmentationSettings::default()) {
        Err(Error::Ingest(m)) => assert!(m.contains("no lung found"), "{m}"),
        other => panic!("expected 'no lung found', got {other:?}"),
    }
}

#[test]
fn a_single_lung_is_refused_or_kept_with_a_warning() {
    let thorax = Thorax {
        lung_offset_mm: 70.0,
        left_lung: false,
    };
    let (ct, truth) = thorax.sample(grid(5.0, IDENTITY));
    match segment_lungs(&ct, &SegmentationSettings::default()) {
        Err(Error::Ingest(m)) => assert!(m.contains("only one lung found"), "{m}"),
        other => panic!("expected 'only one lung found', got {other:?}"),
    }
    let settings = SegmentationSettings {
        allow_single_lung: true,
        ..SegmentationSettings::default()
    };
    let seg = segment_lungs(&ct, &settings).unwrap();
    assert!(seg
        .report
        .warnings
        .iter()
        .any(|w| w.contains("only one lung")));
    assert_eq!(seg.report.left_volume_ml, 0.0);
    assert!(dice(&seg.lungs, RIGHT_LUNG, &truth, RIGHT_LUNG).unwrap() > 0.9);
}

#[test]
fn bad_settings_and_mismatched_grids_are_refused() {
    let settings = SegmentationSettings {
        air_threshold_hu: f32::NAN,
        ..SegmentationSettings::default()
    };
    let ct = Volume::filled(grid(8.0, IDENTITY), 0.0f32).unwrap();
    assert!(matches!(
        segment_lungs(&ct, &settings),
        Err(Error::Config { .. })
    ));
    let a = Volume::filled(
        VolumeGeometry::axis_aligned([4, 4, 4], [1.0; 3], [0.0; 3]),
        1u8,
    )
    .unwrap();
    let b = Volume::filled(
        VolumeGeometry::axis_aligned([4, 4, 5], [1.0; 3], [0.0; 3]),
        1u8,
    )
    .unwrap();
    assert!(dice(&a, 1, &b, 1).is_err());
    let mut c = a.clone();
    c.as_slice_mut()[..32].fill(0);
    // 32 common voxels of 64 and 32: 2·32/96.
    assert!((dice(&a, 1, &c, 1).unwrap() - 64.0 / 96.0).abs() < 1e-12);
}
