//! Lung model building: cubic elements, cleanup of mechanisms, constraint groups and the wall,
//! on synthetic masks with known geometry and on the CIP expert label map, solved end to end.

use std::collections::{HashMap, HashSet};
use std::time::Instant;

use nalgebra::Vector3;

use lungmotion::ingest::lung_model::{
    build_lung_model, ConstraintGroup, LungModel, LungModelSettings, LEFT_LUNG, RIGHT_LUNG,
};
use lungmotion::model::{Loads, NodeConstraint, SurfacePressure};
use lungmotion::simulation::{QuasiStaticSettings, QuasiStaticSolver, Scene};
use lungmotion::volume::{Volume, VolumeGeometry};
use lungmotion::Error;

/// Lungs: ellipsoids of semi-axes (50, 70, 100) mm centred at x = ∓70 mm, each with an
/// anterior medial tongue reaching x = 0 so the two lungs touch there. Box faces not on the
/// lattice cut cells at 25 %, never at exactly the 50 % threshold (a tie a rotated grid breaks
/// differently).
const LUNG_CENTRE_X_MM: f64 = 70.0;
const SEMI_AXES_MM: [f64; 3] = [50.0, 70.0, 100.0];
/// Where the bronchus tube (y = 0, z = 16 mm, radius 8 mm) meets each lung's medial surface.
const BRONCHUS_Z_MM: f64 = 16.0;

fn in_ellipsoid(p: Vector3<f64>, centre_x: f64) -> bool {
    let d = [
        (p.x - centre_x) / SEMI_AXES_MM[0],
        p.y / SEMI_AXES_MM[1],
        p.z / SEMI_AXES_MM[2],
    ];
    d.iter().map(|v| v * v).sum::<f64>() <= 1.0
}

fn in_box(p: Vector3<f64>, lo: [f64; 3], hi: [f64; 3]) -> bool {
    (0..3).all(|a| p[a] >= lo[a] && p[a] < hi[a])
}

/// Lung label (0, 1, 2) and airway flag of an LPS point.
fn anatomy(p: Vector3<f64>) -> (u8, bool) {
    let right =
        in_ellipsoid(p, -LUNG_CENTRE_X_MM) || in_box(p, [-40.0, -62.0, -22.0], [0.0, -30.0, 40.0]);
    let left = in_ellipsoid(p, LUNG_CENTRE_X_MM)
        || in_box(p, [0.0, -62.0, -22.0], [40.0, -30.0, 40.0])
        // A one-element-thick finger (8 mm lattice) and a cube hanging from its tip by a corner.
        || in_box(p, [112.0, 0.0, 0.0], [160.0, 8.0, 8.0])
        || in_box(p, [160.0, 8.0, 8.0], [176.0, 24.0, 24.0]);
    let lung = if right {
        RIGHT_LUNG
    } else if left {
        LEFT_LUNG
    } else {
        0
    };
    let bronchus = p.x.abs() < 24.0 && (p.y.powi(2) + (p.z - BRONCHUS_Z_MM).powi(2)) < 64.0;
    let trachea = p.x.powi(2) + p.y.powi(2) < 64.0 && p.z > BRONCHUS_Z_MM && p.z < 120.0;
    (lung, lung == 0 && (bronchus || trachea))
}

fn synthetic_masks(geometry: VolumeGeometry) -> (Volume<u8>, Volume<u8>) {
    let n = geometry.voxel_count();
    let mut lungs = vec![0u8; n];
    let mut airways = vec![0u8; n];
    let [nx, ny, nz] = geometry.dims;
    for k in 0..nz {
        for j in 0..ny {
            for i in 0..nx {
                let p = geometry.voxel_to_lps_mm(Vector3::new(i as f64, j as f64, k as f64));
                let (lung, airway) = anatomy(p);
                let idx = geometry.index(i, j, k);
                lungs[idx] = lung;
                airways[idx] = airway as u8;
            }
        }
    }
    (
        Volume::from_data(geometry, lungs).unwrap(),
        Volume::from_data(geometry, airways).unwrap(),
    )
}

/// Axis-aligned 2 mm grid whose voxel centres sit at odd millimetres (never on a cell face).
fn axis_aligned_geometry() -> VolumeGeometry {
    VolumeGeometry::axis_aligned([160, 90, 125], [2.0; 3], [-139.0, -89.0, -119.0])
}

/// The same voxel centres, stored with i → −x, j → +z, k → +y.
fn flipped_geometry() -> VolumeGeometry {
    VolumeGeometry {
        dims: [160, 125, 90],
        spacing_mm: [2.0; 3],
        origin_lps_mm: [179.0, -89.0, -119.0],
        direction_lps: [[-1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, 1.0, 0.0]],
    }
}

/// A grid rotated 25° about z then 10° about x, covering the same anatomy.
fn oblique_geometry() -> VolumeGeometry {
    let rot = nalgebra::Rotation3::from_axis_angle(&Vector3::x_axis(), 10f64.to_radians())
        * nalgebra::Rotation3::from_axis_angle(&Vector3::z_axis(), 25f64.to_radians());
    let m = rot.matrix();
    let dims = [200usize, 170, 150];
    let spacing = 2.0;
    let centre = Vector3::new(20.0, 0.0, 5.0);
    let half = Vector3::from(dims.map(|d| (d - 1) as f64 * spacing / 2.0));
    let origin = centre - m * half;
    VolumeGeometry {
        dims,
        spacing_mm: [spacing; 3],
        origin_lps_mm: [origin.x, origin.y, origin.z],
        direction_lps: [
            [m[(0, 0)], m[(1, 0)], m[(2, 0)]],
            [m[(0, 1)], m[(1, 1)], m[(2, 1)]],
            [m[(0, 2)], m[(1, 2)], m[(2, 2)]],
        ],
    }
}

fn settings(element_size_mm: f64) -> LungModelSettings {
    LungModelSettings {
        element_size_mm,
        ..LungModelSettings::default()
    }
}

fn mask_volume_ml(lungs: &Volume<u8>) -> f64 {
    lungs.as_slice().iter().filter(|&&v| v != 0).count() as f64
        * lungs.geometry.voxel_volume_mm3()
        * 1e-3
}

fn node_lungs(model: &LungModel) -> Vec<HashSet<u8>> {
    let mut lungs = vec![HashSet::new(); model.mesh.mesh.node_count()];
    for (corners, &l) in model.mesh.mesh.elements.iter().zip(&model.element_lung) {
        for &c in corners {
            lungs[c as usize].insert(l);
        }
    }
    lungs
}

fn position_mm(model: &LungModel, n: u32) -> Vector3<f64> {
    model.mesh.mesh.rest_positions_m[n as usize] * 1e3
}

#[test]
fn synthetic_lungs_give_clean_cubic_elements_and_anatomical_groups() {
    let (lungs, airways) = synthetic_masks(axis_aligned_geometry());
    let h = 8.0;
    let t = Instant::now();
    let model = build_lung_model(&lungs, &airways, &settings(h)).unwrap();
    let r = &model.report;
    println!(
        "built in {:.2} s: {}",
        t.elapsed().as_secs_f64(),
        serde_json::to_string_pretty(r).unwrap()
    );
    let mesh = &model.mesh.mesh;

    // Element count and volume against the mask.
    let mask_ml = mask_volume_ml(&lungs);
    let expected_elements = mask_ml * 1e3 / h.powi(3);
    let count_error = (mesh.element_count() as f64 - expected_elements) / expected_elements;
    assert!(
        count_error.abs() < 0.03,
        "elements {} vs {expected_elements:.0}",
        mesh.element_count()
    );
    let mesh_ml = mesh.enclosed_volume_m3(&mesh.rest_positions_m) * 1e6;
    assert!(
        ((mesh_ml - mask_ml) / mask_ml).abs() < 0.05,
        "mesh {mesh_ml} mL vs mask {mask_ml} mL"
    );
    assert!((r.mesh_volume_ml - mesh_ml).abs() < 1e-6 && (r.mask_volume_ml - mask_ml).abs() < 1e-6);

    // Cubes of the requested size, placed in LPS.
    for e in &mesh.elements {
        let p = e.map(|n| mesh.rest_positions_m[n as usize]);
        for (a, b) in [(0, 1), (0, 3), (0, 4)] {
            assert!(((p[b] - p[a]).norm() - h * 1e-3).abs() < 1e-9);
        }
    }

    // The lungs touch at x = 0, yet share no node.
    let lungs_of = node_lungs(&model);
    assert!(
        lungs_of.iter().all(|s| s.len() == 1),
        "a node belongs to both lungs"
    );
    let mut by_position: HashMap<[i64; 3], HashSet<u8>> = HashMap::new();
    for (n, s) in lungs_of.iter().enumerate() {
        let p = position_mm(&model, n as u32).map(|v| (v * 1000.0).round() as i64);
        by_position.entry([p.x, p.y, p.z]).or_default().extend(s);
    }
    let coincident = by_position.values().filter(|s| s.len() == 2).count();
    assert!(
        coincident > 0,
        "the synthetic lungs should touch, making coincident node pairs"
    );
    assert!(r.wall_contact_voxels > 0);

    // No mechanism: every element is in a fully occupied 2×2×2 block of its lung, and each
    // lung is one face-connected piece.
    let cells: HashMap<[u32; 3], u8> = model
        .mesh
        .element_cell
        .iter()
        .zip(&model.element_lung)
        .map(|(c, &l)| (*c, l))
        .collect();
    for (c, &l) in &cells {
        let in_block = (0..8).any(|o| {
            let base: [i64; 3] = std::array::from_fn(|a| c[a] as i64 - ((o >> a) & 1) as i64);
            (0..8).all(|q| {
                let cell: [i64; 3] = std::array::from_fn(|a| base[a] + ((q >> a) & 1) as i64);
                cell.iter().all(|&v| v >= 0) && cells.get(&cell.map(|v| v as u32)) == Some(&l)
            })
        });
        assert!(
            in_block,
            "element at cell {c:?} is part of a one-element-thick piece"
        );
    }
    for lung in [RIGHT_LUNG, LEFT_LUNG] {
        let mine: Vec<[u32; 3]> = cells
            .iter()
            .filter(|(_, &l)| l == lung)
            .map(|(c, _)| *c)
            .collect();
        let mut seen = HashSet::from([mine[0]]);
        let mut stack = vec![mine[0]];
        while let Some(c) = stack.pop() {
            for a in 0..3 {
                for d in [-1i64, 1] {
                    let mut q = c.map(|v| v as i64);
                    q[a] += d;
                    if q[a] < 0 {
                        continue;
                    }
                    let q = q.map(|v| v as u32);
                    if cells.get(&q) == Some(&lung) && seen.insert(q) {
                        stack.push(q);
                    }
                }
            }
        }
        assert_eq!(
            seen.len(),
            mine.len(),
            "lung {lung} is not one face-connected piece"
        );
    }
    // The finger (5 cells) and the corner-hanging cube (8 cells) are gone.
    assert!(r.removed_thin_elements >= 5, "{}", r.removed_thin_elements);
    assert!(
        r.removed_detached_elements >= 8,
        "{}",
        r.removed_detached_elements
    );
    let max_x = mesh
        .rest_positions_m
        .iter()
        .map(|p| p.x * 1e3)
        .fold(f64::MIN, f64::max);
    assert!(
        max_x < LUNG_CENTRE_X_MM + SEMI_AXES_MM[0] + h,
        "max x {max_x} mm"
    );

    // Groups: all present in each lung, where anatomy puts them.
    let node_lung: Vec<u8> = lungs_of.iter().map(|s| *s.iter().next().unwrap()).collect();
    for lung in [RIGHT_LUNG, LEFT_LUNG] {
        let side = if lung == RIGHT_LUNG { -1.0 } else { 1.0 };
        let of = |g: ConstraintGroup| -> Vec<Vector3<f64>> {
            model
                .group_nodes(g)
                .into_iter()
                .filter(|&n| node_lung[n as usize] == lung)
                .map(|n| position_mm(&model, n))
                .collect()
        };
        let mean_z = |v: &[Vector3<f64>]| v.iter().map(|p| p.z).sum::<f64>() / v.len() as f64;
        for g in ConstraintGroup::ALL {
            assert!(
                !of(g).is_empty(),
                "lung {lung}: group {} is empty",
                g.name()
            );
        }
        // Hilum around where the bronchus tube meets the lung's medial surface.
        let entry = Vector3::new(
            side * (LUNG_CENTRE_X_MM - SEMI_AXES_MM[0]),
            0.0,
            BRONCHUS_Z_MM,
        );
        let hilum = of(ConstraintGroup::Hilum);
        let centroid = hilum.iter().sum::<Vector3<f64>>() / hilum.len() as f64;
        assert!(
            (centroid - entry).norm() < 1.5 * h,
            "lung {lung}: hilum centroid {centroid:?}, entry {entry:?}"
        );
        for p in &hilum {
            assert!(
                (p - entry).norm() < r.hilum_radius_mm + 1.5 * h,
                "hilum node {p:?} far from {entry:?}"
            );
        }
        assert!(
            r.hilum_source[if lung == RIGHT_LUNG { "right" } else { "left" }].starts_with("airway")
        );
        // Apex near the top (z = 100), base near the bottom (z = −100).
        let apex = of(ConstraintGroup::Apex);
        assert!(apex
            .iter()
            .all(|p| p.z > SEMI_AXES_MM[2] - 0.1 * 2.0 * SEMI_AXES_MM[2] - 2.0 * h));
        assert!(
            mean_z(&apex) > 0.8 * SEMI_AXES_MM[2] - h,
            "apex mean z {}",
            mean_z(&apex)
        );
        // The base takes every downward-facing node below the hilum (n_z ≤ −0.1: dome and
        // zone of apposition), which on this tall ellipsoid reaches well up its lower half.
        let base = of(ConstraintGroup::Diaphragmatic);
        assert!(
            mean_z(&base) < -0.5 * SEMI_AXES_MM[2],
            "base mean z {}",
            mean_z(&base)
        );
        assert!(base.iter().all(|p| p.z < BRONCHUS_Z_MM));
        // Mediastinal nodes on the medial side.
        let med = of(ConstraintGroup::Mediastinal);
        assert!(
            med.iter().all(|p| p.x * side < LUNG_CENTRE_X_MM),
            "mediastinal node lateral"
        );
        let costal = of(ConstraintGroup::Costal);
        let lateral_costal = costal
            .iter()
            .filter(|p| p.x * side > LUNG_CENTRE_X_MM)
            .count();
        assert!(lateral_costal > costal.len() / 3);
    }

    // Constraints: hilum fixed, sliding groups on the wall's tangent plane through the rest
    // position, base on a cranio-caudal line through its rest position.
    let cs = &model.constraints;
    for n in 0..mesh.node_count() as u32 {
        let c = cs.get(n);
        let rest = mesh.rest_positions_m[n as usize];
        match ConstraintGroup::from_code(model.node_group[n as usize]) {
            Some(ConstraintGroup::Hilum) => {
                assert!(matches!(c, Some(NodeConstraint::Fixed { target_m }) if *target_m == rest))
            }
            Some(ConstraintGroup::Diaphragmatic) => assert!(
                matches!(c, Some(NodeConstraint::Line { point_m, direction })
                    if *point_m == rest && *direction == Vector3::z()),
                "{c:?}"
            ),
            None => assert!(c.is_none()),
            Some(g) => {
                let Some(NodeConstraint::Plane { point_m, normal }) = c else {
                    panic!("{} node {n} is not sliding: {c:?}", g.name());
                };
                assert_eq!(*point_m, rest);
                assert!((normal - model.wall.normal(rest)).norm() < 1e-12);
            }
        }
    }
    // Staircase nodes lie near the smooth CT wall (further only where the cleanup removed
    // mask, e.g. at the finger's root).
    assert!(
        r.wall_rest_offset_mean_mm < 0.5 * h,
        "sliding nodes are {:.2} mm off the wall on average",
        r.wall_rest_offset_mean_mm
    );
    // The wall's inside is the lungs: a point deep in each lung is inside, the midline gap outside.
    assert!(model.wall.evaluate(Vector3::new(-0.07, 0.0, 0.0)).0 < -0.02);
    assert!(model.wall.evaluate(Vector3::new(0.07, 0.0, 0.0)).0 < -0.02);
    assert!(model.wall.evaluate(Vector3::new(0.0, 0.0, -0.05)).0 > 0.005);

    // groups_volume: only lung-surface voxels, every code present, interior voxels 0.
    let gv = &model.groups_volume;
    assert_eq!(gv.geometry, lungs.geometry);
    for (&g, &l) in gv.as_slice().iter().zip(lungs.as_slice()) {
        assert!(g == 0 || l != 0, "a background voxel has a group");
    }
    for g in ConstraintGroup::ALL {
        assert!(
            gv.as_slice().contains(&g.code()),
            "no voxel painted {}",
            g.name()
        );
    }
    let centre = lungs
        .geometry
        .lps_mm_to_voxel(Vector3::new(-70.0, 0.0, 0.0))
        .map(|v| v.round() as usize);
    assert_eq!(
        gv.get(centre.x, centre.y, centre.z),
        0,
        "an interior voxel has a group"
    );
    let surface_voxels = (0..lungs.as_slice().len())
        .filter(|&i| lungs.as_slice()[i] != 0 && gv.as_slice()[i] != 0)
        .count();
    assert!(surface_voxels > 1000);
}

#[test]
fn painted_groups_read_back_as_overrides_give_the_same_node_groups() {
    let (lungs, airways) = synthetic_masks(axis_aligned_geometry());
    let auto = build_lung_model(&lungs, &airways, &settings(8.0)).unwrap();
    let overridden = build_lung_model(
        &lungs,
        &airways,
        &LungModelSettings {
            group_overrides: Some(auto.groups_volume.clone()),
            ..settings(8.0)
        },
    )
    .unwrap();
    assert!(overridden.report.groups_from_overrides);
    let surface = auto.mesh.mesh.surface_nodes();
    let agree = surface
        .iter()
        .filter(|&&n| auto.node_group[n as usize] == overridden.node_group[n as usize])
        .count();
    let fraction = agree as f64 / surface.len() as f64;
    println!(
        "override round trip: {agree} of {} surface nodes agree",
        surface.len()
    );
    assert!(
        fraction > 0.9,
        "only {:.1} % of node groups survive the round trip",
        fraction * 100.0
    );
}

fn sorted_positions(model: &LungModel) -> Vec<[i64; 4]> {
    let lungs = node_lungs(model);
    let mut v: Vec<[i64; 4]> = model
        .mesh
        .mesh
        .rest_positions_m
        .iter()
        .zip(&lungs)
        .map(|(p, l)| {
            let q = p.map(|v| (v * 1e6).round() as i64);
            [q.x, q.y, q.z, *l.iter().next().unwrap() as i64]
        })
        .collect();
    v.sort_unstable();
    v
}

#[test]
fn the_same_anatomy_on_flipped_and_oblique_grids_gives_the_same_model() {
    let h = 8.0;
    let (lungs, airways) = synthetic_masks(axis_aligned_geometry());
    let reference = build_lung_model(&lungs, &airways, &settings(h)).unwrap();

    let (lungs_f, airways_f) = synthetic_masks(flipped_geometry());
    assert_eq!(
        lungs_f.as_slice().iter().filter(|&&v| v != 0).count(),
        lungs.as_slice().iter().filter(|&&v| v != 0).count()
    );
    let flipped = build_lung_model(&lungs_f, &airways_f, &settings(h)).unwrap();
    assert_eq!(
        flipped.mesh.mesh.element_count(),
        reference.mesh.mesh.element_count()
    );
    assert_eq!(sorted_positions(&flipped), sorted_positions(&reference));
    // Groups may differ where a normal sits on a threshold to rounding (sums taken in a
    // different axis order): allow a handful of nodes.
    for g in ConstraintGroup::ALL {
        let (a, b) = (
            reference.report.group_nodes[g.name()],
            flipped.report.group_nodes[g.name()],
        );
        assert!(a.abs_diff(b) <= 3, "{}: {a} vs {b}", g.name());
    }

    let (lungs_o, airways_o) = synthetic_masks(oblique_geometry());
    let oblique = build_lung_model(&lungs_o, &airways_o, &settings(h)).unwrap();
    let (ne, no) = (
        reference.mesh.mesh.element_count(),
        oblique.mesh.mesh.element_count(),
    );
    let (ve, vo) = (
        reference.report.mesh_volume_ml,
        oblique.report.mesh_volume_ml,
    );
    println!("axis-aligned {ne} elements {ve:.1} mL; oblique {no} elements {vo:.1} mL");
    assert!(
        (no as f64 - ne as f64).abs() / (ne as f64) < 0.01,
        "{ne} vs {no}"
    );
    assert!(((vo - ve) / ve).abs() < 0.01);
    // The same lattice in LPS: every oblique node is a lattice point of the reference frame.
    for p in &oblique.mesh.mesh.rest_positions_m {
        let u = p * 1e3 / h;
        assert!((u - u.map(|v| v.round())).norm() < 1e-6);
    }
    // The hilum is a ball around one node, so its count jumps with that node; compare
    // centres, and the other groups by count.
    for side in ["right", "left"] {
        let (a, b) = (
            Vector3::from(reference.report.hilum_centre_mm[side]),
            Vector3::from(oblique.report.hilum_centre_mm[side]),
        );
        assert!(
            (a - b).norm() <= h * 1.01,
            "{side} hilum centre {a:?} vs {b:?}"
        );
    }
    for g in ConstraintGroup::ALL.into_iter().skip(1) {
        let (a, b) = (
            reference.report.group_nodes[g.name()],
            oblique.report.group_nodes[g.name()],
        );
        assert!(
            (a as f64 - b as f64).abs() <= 0.1 * a as f64 + 4.0,
            "{}: {a} vs {b}",
            g.name()
        );
    }
}

#[test]
fn bad_inputs_are_refused_with_the_reason() {
    let geometry = VolumeGeometry::axis_aligned([40, 40, 40], [2.0; 3], [0.0; 3]);
    let mut data = vec![0u8; geometry.voxel_count()];
    for k in 5..35 {
        for j in 5..35 {
            for i in 5..35 {
                data[geometry.index(i, j, k)] = if i < 20 { RIGHT_LUNG } else { LEFT_LUNG };
            }
        }
    }
    let lungs = Volume::from_data(geometry, data).unwrap();
    let airways = Volume::filled(geometry, 0u8).unwrap();
    // The good case builds, with no airway: geometric hilum.
    let ok = build_lung_model(&lungs, &airways, &settings(6.0)).unwrap();
    assert!(ok.report.hilum_source["right"].starts_with("geometric"));

    let message = |r: lungmotion::Result<LungModel>| match r {
        Err(e @ (Error::Config { .. } | Error::Argument { .. })) => e.to_string(),
        Err(other) => panic!("expected Config or Argument, got {other}"),
        Ok(_) => panic!("expected an error"),
    };
    for bad in [1.9, 16.5, 0.0, -4.0, f64::NAN] {
        let m = message(build_lung_model(&lungs, &airways, &settings(bad)));
        assert!(m.contains("element size"), "{m}");
    }
    let empty = Volume::filled(geometry, 0u8).unwrap();
    let m = message(build_lung_model(&empty, &airways, &settings(6.0)));
    assert!(m.contains("empty"), "{m}");

    let shifted = VolumeGeometry::axis_aligned([40, 40, 40], [2.0; 3], [1.0, 0.0, 0.0]);
    let other_grid = Volume::filled(shifted, 0u8).unwrap();
    let m = message(build_lung_model(&lungs, &other_grid, &settings(6.0)));
    assert!(
        m.contains("airway mask") && m.contains("different grid"),
        "{m}"
    );
    let smaller = Volume::filled(
        VolumeGeometry::axis_aligned([40, 40, 39], [2.0; 3], [0.0; 3]),
        0u8,
    )
    .unwrap();
    let m = message(build_lung_model(&lungs, &smaller, &settings(6.0)));
    assert!(m.contains("different grid"), "{m}");

    let mut bad_labels = lungs.clone();
    bad_labels.as_slice_mut()[geometry.index(10, 10, 10)] = 7;
    let m = message(build_lung_model(&bad_labels, &airways, &settings(6.0)));
    assert!(m.contains("label 7"), "{m}");

    let mut overrides = Volume::filled(geometry, 0u8).unwrap();
    overrides.as_slice_mut()[0] = 9;
    let m = message(build_lung_model(
        &lungs,
        &airways,
        &LungModelSettings {
            group_overrides: Some(overrides),
            ..settings(6.0)
        },
    ));
    assert!(m.contains("code 9"), "{m}");

    // A lung too thin for the elements is an ingest failure, not a panic.
    let mut sheet = vec![0u8; geometry.voxel_count()];
    for j in 5..35 {
        for i in 5..35 {
            sheet[geometry.index(i, j, 20)] = RIGHT_LUNG;
        }
    }
    let sheet = Volume::from_data(geometry, sheet).unwrap();
    match build_lung_model(&sheet, &airways, &settings(8.0)) {
        Err(Error::Ingest(m)) => assert!(m.contains("too small or thin"), "{m}"),
        other => panic!(
            "expected an ingest error, got {:?}",
            other.map(|m| m.report)
        ),
    }
}

/// The CIP expert lungs and airways.
fn cip_masks() -> Option<(Volume<u8>, Volume<u8>)> {
    lungmotion::datasets::cip_expert_lung_masks().map(|m| m.unwrap())
}

fn real_case(h: f64, pressure_pa: f64, solve: bool) {
    let Some((lungs, airways)) = cip_masks() else {
        println!("skipped: shared data not found");
        return;
    };
    let t = Instant::now();
    let model = build_lung_model(&lungs, &airways, &settings(h)).unwrap();
    let build_s = t.elapsed().as_secs_f64();
    println!(
        "CIP lm-64 at {h} mm: built in {build_s:.2} s\n{}",
        serde_json::to_string_pretty(&model.report).unwrap()
    );
    let r = &model.report;
    assert!(((r.mesh_volume_ml - r.mask_volume_ml) / r.mask_volume_ml).abs() < 0.05);
    for g in ConstraintGroup::ALL {
        assert!(r.group_nodes[g.name()] > 0, "group {} empty", g.name());
    }
    assert!(
        r.hilum_source.values().all(|s| s.starts_with("airway")),
        "{:?}",
        r.hilum_source
    );

    if !solve {
        return;
    }
    let mesh = model.mesh.mesh.clone();
    let loads = Loads {
        pressures: vec![SurfacePressure {
            faces: mesh.external_faces.clone(),
            pressure_pa,
            follows_deformation: true,
        }],
        ..Loads::default()
    };
    let scene = Scene::new(mesh, model.constraints.clone(), loads).unwrap();
    // The solver projects constrained nodes onto their constraint first: a no-op at rest.
    let snap_mm = scene
        .initial_positions()
        .iter()
        .zip(&scene.mesh.rest_positions_m)
        .map(|(a, b)| (a - b).norm() * 1e3)
        .fold(0.0, f64::max);
    assert!(snap_mm < 1e-9, "a node moved {snap_mm} mm with no load");
    let t = Instant::now();
    let mut solver = QuasiStaticSolver::new(&scene, QuasiStaticSettings::default()).unwrap();
    let (x, solve) = solver.solve(None).unwrap();
    println!(
        "solve at {pressure_pa} Pa: {:.2} s in all (set-up {:.2} s), {} Newton, {} Krylov, {} pseudo-time, \
         {} relaxation steps, {} multigrid levels, residual {:.2e}",
        t.elapsed().as_secs_f64(),
        solve.setup_time_s,
        solve.newton_iterations,
        solve.linear_iterations,
        solve.pseudo_time_steps,
        solve.relaxation_steps,
        solve.multigrid_levels,
        solve.residual
    );
    assert!(solve.residual <= QuasiStaticSettings::default().tolerance);
    let rest = &scene.mesh.rest_positions_m;
    let u: Vec<Vector3<f64>> = x.iter().zip(rest).map(|(a, b)| a - b).collect();
    assert!(u.iter().all(|d| d.iter().all(|v| v.is_finite())));
    let v0 = scene.mesh.enclosed_volume_m3(rest);
    let v1 = scene.mesh.enclosed_volume_m3(&x);
    let max_u_mm = u.iter().map(|d| d.norm() * 1e3).fold(0.0, f64::max);
    println!(
        "volume {:.1} → {:.1} mL (ΔV = {:+.1} mL), max displacement {max_u_mm:.2} mm",
        v0 * 1e6,
        v1 * 1e6,
        (v1 - v0) * 1e6
    );
    assert!(v1 > v0, "the lung did not inflate");

    // Base (lowest 10 % of nodes) moves down more than the apex (highest 10 %).
    let mut order: Vec<usize> = (0..rest.len()).collect();
    order.sort_by(|&a, &b| rest[a].z.total_cmp(&rest[b].z));
    let tenth = order.len() / 10;
    let mean_dz = |ids: &[usize]| ids.iter().map(|&i| u[i].z).sum::<f64>() / ids.len() as f64;
    let (base_dz, apex_dz) = (
        mean_dz(&order[..tenth]),
        mean_dz(&order[order.len() - tenth..]),
    );
    println!(
        "mean Δz: base {:.2} mm, apex {:.2} mm",
        base_dz * 1e3,
        apex_dz * 1e3
    );
    assert!(base_dz < 0.0 && base_dz < apex_dz);

    let hilum_max = model
        .group_nodes(ConstraintGroup::Hilum)
        .iter()
        .map(|&n| u[n as usize].norm())
        .fold(0.0, f64::max);
    assert!(hilum_max < 1e-9, "hilum moved {hilum_max} m");
    // Sliding nodes stay exactly on their tangent plane; the plane departs from the curved
    // wall as they slide (d²/2R), so report how far their distance to the wall changed.
    let wall = &model.wall;
    let mut off_plane_mm: f64 = 0.0;
    let mut wall_change_mm = Vec::new();
    for (n, c) in &scene.constraints.entries {
        if let NodeConstraint::Plane { point_m, normal } = c {
            let (x1, x0) = (x[*n as usize], rest[*n as usize]);
            off_plane_mm = off_plane_mm.max(normal.dot(&(x1 - point_m)).abs() * 1e3);
            wall_change_mm.push((wall.evaluate(x1).0 - wall.evaluate(x0).0).abs() * 1e3);
        }
    }
    wall_change_mm.sort_by(f64::total_cmp);
    let pct = |q: f64| wall_change_mm[((wall_change_mm.len() - 1) as f64 * q) as usize];
    println!(
        "{} sliding nodes: off their plane ≤ {off_plane_mm:.2e} mm; change of wall distance \
         median {:.3} mm, 95 % {:.3} mm, max {:.3} mm",
        wall_change_mm.len(),
        pct(0.5),
        pct(0.95),
        pct(1.0)
    );
    assert!(!wall_change_mm.is_empty() && off_plane_mm < 1e-6);
    assert!(
        pct(0.5) < 0.5,
        "half the sliding nodes left the wall by 0.5 mm"
    );
    assert!(
        pct(1.0) < h,
        "a sliding node left the wall by more than an element"
    );
}

/// A moderate inflation (≈ 215 mL at 8 mm); the breathing tests drive the full 500 mL.
const CIP_PRESSURE_PA: f64 = -30.0;

#[test]
#[cfg_attr(
    not(shared_data),
    ignore = "needs the shared CT data (../shared/data or LUNGMOTION_SHARED_DATA; see README)"
)]
fn cip_lungs_at_8_mm_inflate_downwards_with_the_hilum_held() {
    real_case(8.0, CIP_PRESSURE_PA, true);
}

/// At 4 mm the model is built and checked; its solve (minutes with block Jacobi on this
/// machine) belongs to the breathing benchmark, not the test suite.
#[test]
#[cfg_attr(
    not(shared_data),
    ignore = "needs the shared CT data (../shared/data or LUNGMOTION_SHARED_DATA; see README)"
)]
fn cip_lungs_at_4_mm_give_a_clean_model() {
    real_case(4.0, CIP_PRESSURE_PA, false);
}

/// The solver's default settings on the lungs. Multigrid glued the two lungs where they
/// touch (coarse levels identify nodes by lattice point) and stalled at residual 0.45 with
/// the sliding planes; such meshes now take block Jacobi, which converges.
#[test]
#[cfg_attr(
    not(shared_data),
    ignore = "needs the shared CT data (../shared/data or LUNGMOTION_SHARED_DATA; see README)"
)]
fn default_solver_settings_converge_on_both_lungs() {
    let Some((lungs, airways)) = cip_masks() else {
        println!("skipped: shared data not found");
        return;
    };
    let model = build_lung_model(&lungs, &airways, &settings(8.0)).unwrap();
    let mesh = model.mesh.mesh.clone();
    let loads = Loads {
        pressures: vec![SurfacePressure {
            faces: mesh.external_faces.clone(),
            pressure_pa: -10.0,
            follows_deformation: true,
        }],
        ..Loads::default()
    };
    let scene = Scene::new(mesh, model.constraints.clone(), loads).unwrap();
    let settings = QuasiStaticSettings {
        relaxation_max_steps: 0,
        ..QuasiStaticSettings::default()
    };
    let mut solver = QuasiStaticSolver::new(&scene, settings).unwrap();
    let (_, report) = solver.solve(None).unwrap();
    println!("default settings on the CIP lungs at 8 mm: {report:?}");
    assert!(report.residual <= 1e-6);
}
