//! VTK XML meshes: round trips of every array, the lung-mesh helpers (metres → LPS mm,
//! external surface) and refusal of files the reader does not understand.

use std::path::PathBuf;

use lungmotion::formats::vtk::{
    read_vtp_surface, read_vtu, surface_from_hex_mesh, vtu_from_hex_mesh, write_vtp_surface,
    write_vtu, DataArray, VtpSurface, VtuMesh,
};
use lungmotion::model::{Material, VoxelGrid};
use lungmotion::Error;
use nalgebra::Vector3;

fn scratch(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("lungmotion-vtk-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir.join(name)
}

/// Deterministic values in [−½, ½) (xorshift64*), so failures reproduce.
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> f64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        (self.0.wrapping_mul(0x2545_f491_4f6c_dd1d) >> 11) as f64 / (1u64 << 53) as f64 - 0.5
    }
}

/// Two hexahedra sharing a face, with values that are not exactly representable in short
/// decimal form (so a lossy text path would show).
fn two_hexes() -> VtuMesh {
    let mut rng = Rng(0x1234_5678_9abc_def1);
    let points: Vec<[f64; 3]> = (0..12)
        .map(|n| {
            let (i, j, k) = (n % 3, (n / 3) % 2, n / 6);
            [
                -128.414 + 10.0 * i as f64 + rng.next() * 1e-3,
                -264.414 + 10.0 * j as f64 + rng.next() * 1e-3,
                -360.256 + 10.0 * k as f64 + rng.next() * 1e-3,
            ]
        })
        .collect();
    let cells = vec![[0, 1, 4, 3, 6, 7, 10, 9], [1, 2, 5, 4, 7, 8, 11, 10]];
    let disp: Vec<[f32; 3]> = (0..12)
        .map(|_| {
            [
                rng.next() as f32,
                rng.next() as f32 * 1e-7,
                -rng.next() as f32 * 1e6,
            ]
        })
        .collect();
    VtuMesh {
        points_lps_mm: points,
        cells,
        point_data: vec![
            ("displacement_mm".into(), DataArray::VectorsF32(disp)),
            (
                "stress_pa".into(),
                DataArray::ScalarsF32((0..12).map(|n| n as f32 * 0.1 - 0.55).collect()),
            ),
        ],
        cell_data: vec![
            ("group".into(), DataArray::ScalarsU8(vec![3, 255])),
            (
                "material_class".into(),
                DataArray::ScalarsI32(vec![-7, 1 << 30]),
            ),
        ],
    }
}

#[test]
fn vtu_round_trip_keeps_points_cells_and_every_array_bit_exact() {
    let mesh = two_hexes();
    let path = scratch("two.vtu");
    write_vtu(&path, &mesh).unwrap();
    let back = read_vtu(&path).unwrap();
    // Float64 points and f32 arrays go through binary: exact, not approximately equal.
    assert_eq!(back, mesh);
    let text = std::fs::read_to_string(&path).unwrap();
    assert!(text.contains("type=\"UnstructuredGrid\"") && text.contains("LPS millimetres"));
    assert!(text.contains("format=\"binary\""));
}

#[test]
fn vtp_round_trip_keeps_quads_and_arrays() {
    let hexes = two_hexes();
    let surface = VtpSurface {
        points_lps_mm: hexes.points_lps_mm.clone(),
        quads: vec![[0, 3, 4, 1], [6, 7, 10, 9], [1, 4, 5, 2]],
        point_data: hexes.point_data.clone(),
        cell_data: vec![("group".into(), DataArray::ScalarsU8(vec![1, 2, 3]))],
    };
    let path = scratch("quads.vtp");
    write_vtp_surface(&path, &surface).unwrap();
    assert_eq!(read_vtp_surface(&path).unwrap(), surface);
    // A PolyData file is not an UnstructuredGrid.
    let e = read_vtu(&path).unwrap_err().to_string();
    assert!(
        e.contains("quads.vtp") && e.contains("UnstructuredGrid"),
        "{e}"
    );
}

#[test]
fn hex_mesh_goes_to_millimetres_with_its_displacement() {
    let origin_m = Vector3::new(-0.12, -0.25, -0.36);
    let grid = VoxelGrid::filled_box([3, 2, 4], [0.004, 0.005, 0.006], origin_m);
    let mesh = grid.to_mesh(Material::LUNG).unwrap().mesh;
    // Deformed state: a uniform 2 % stretch about the origin plus a 3 mm inferior shift.
    let shift_m = Vector3::new(0.0, 0.0, -0.003);
    let positions_m: Vec<Vector3<f64>> = mesh
        .rest_positions_m
        .iter()
        .map(|p| origin_m + (p - origin_m) * 1.02 + shift_m)
        .collect();
    let vtu = vtu_from_hex_mesh(&mesh, &positions_m).unwrap();
    let path = scratch("box.vtu");
    write_vtu(&path, &vtu).unwrap();
    let back = read_vtu(&path).unwrap();
    assert_eq!(back.cells, mesh.elements);
    assert_eq!(back.points_lps_mm.len(), mesh.node_count());
    for (n, p) in back.points_lps_mm.iter().enumerate() {
        let want = positions_m[n] * 1000.0;
        for a in 0..3 {
            assert!((p[a] - want[a]).abs() < 1e-9, "node {n}: {p:?} vs {want}");
        }
    }
    let Some((_, DataArray::VectorsF32(d))) =
        back.point_data.iter().find(|(n, _)| n == "displacement_mm")
    else {
        panic!("no displacement_mm vectors in {:?}", back.point_data);
    };
    for (n, v) in d.iter().enumerate() {
        let rest_mm = (mesh.rest_positions_m[n] - origin_m) * 1000.0;
        let want = rest_mm * 0.02 + Vector3::new(0.0, 0.0, -3.0);
        for a in 0..3 {
            assert!(
                (v[a] as f64 - want[a]).abs() < 1e-4,
                "node {n}: {v:?} vs {want}"
            );
        }
    }
    // Cell corners in VTK order: corner 6 is opposite corner 0 along +i+j+k.
    for c in &back.cells {
        let (p0, p6) = (
            back.points_lps_mm[c[0] as usize],
            back.points_lps_mm[c[6] as usize],
        );
        assert!(p6[0] > p0[0] && p6[1] > p0[1] && p6[2] > p0[2]);
    }
    assert!(vtu_from_hex_mesh(&mesh, &positions_m[1..]).is_err());
}

#[test]
fn surface_of_a_2x2x2_box_has_24_outward_quads_and_its_groups() {
    let mesh = VoxelGrid::filled_box([2, 2, 2], [0.01; 3], Vector3::zeros())
        .to_mesh(Material::LUNG)
        .unwrap()
        .mesh;
    let groups: Vec<u8> = (0..mesh.external_faces.len())
        .map(|f| (f % 5) as u8)
        .collect();
    let surface =
        surface_from_hex_mesh(&mesh, &mesh.rest_positions_m, Some(groups.as_slice())).unwrap();
    assert_eq!(surface.quads.len(), 24);
    // 27 lattice nodes, only the centre one is interior.
    assert_eq!(surface.points_lps_mm.len(), 26);
    let path = scratch("box.vtp");
    write_vtp_surface(&path, &surface).unwrap();
    let back = read_vtp_surface(&path).unwrap();
    assert_eq!(back, surface);
    assert_eq!(
        back.cell_data,
        vec![("group".to_string(), DataArray::ScalarsU8(groups))]
    );
    // Right-hand normals point away from the box centre (10, 10, 10) mm.
    for q in &back.quads {
        let p = q.map(|n| Vector3::from(back.points_lps_mm[n as usize]));
        let normal = (p[2] - p[0]).cross(&(p[3] - p[1]));
        let centroid = (p[0] + p[1] + p[2] + p[3]) / 4.0;
        assert!(normal.dot(&(centroid - Vector3::new(10.0, 10.0, 10.0))) > 0.0);
    }
    // node_id maps surface points back to mesh nodes (positions in mm).
    let Some((_, DataArray::ScalarsI32(ids))) =
        back.point_data.iter().find(|(n, _)| n == "node_id")
    else {
        panic!("no node_id");
    };
    for (s, &id) in ids.iter().enumerate() {
        let want = mesh.rest_positions_m[id as usize] * 1000.0;
        assert!((Vector3::from(back.points_lps_mm[s]) - want).norm() < 1e-12);
    }
    assert!(surface_from_hex_mesh(&mesh, &mesh.rest_positions_m, Some(&[1u8; 23])).is_err());
}

#[test]
fn writer_refuses_inconsistent_meshes() {
    let mut mesh = two_hexes();
    mesh.cells[1][3] = 12;
    let path = scratch("bad.vtu");
    let e = write_vtu(&path, &mesh).unwrap_err().to_string();
    assert!(e.contains("point 12"), "{e}");
    let mut mesh = two_hexes();
    mesh.cell_data[0].1 = DataArray::ScalarsU8(vec![1]);
    let e = write_vtu(&path, &mesh).unwrap_err().to_string();
    assert!(e.contains("group") && e.contains("1 items"), "{e}");
    let mut mesh = two_hexes();
    mesh.point_data[1].0 = "a\"b".into();
    assert!(write_vtu(&path, &mesh).is_err());
    assert!(
        !path.exists(),
        "nothing is written when the mesh is refused"
    );
}

#[test]
fn malformed_files_are_refused_with_the_file_and_the_problem() {
    let good_path = scratch("good.vtu");
    write_vtu(&good_path, &two_hexes()).unwrap();
    let good = std::fs::read_to_string(&good_path).unwrap();
    let cases: Vec<(String, &str)> = vec![
        ("hello".into(), "no VTKFile"),
        (good[..good.len() / 2].into(), "truncated"),
        (
            good.replace("header_type=\"UInt64\"", "header_type=\"UInt32\""),
            "header_type",
        ),
        (
            good.replace("format=\"binary\"", "format=\"ascii\""),
            "ascii",
        ),
        // Corrupt one base64 character of the first array's data.
        (good.replacen("AAAAAAA", "AAA!AAA", 1), "base64"),
        (
            good.replacen("NumberOfPoints=\"12\"", "NumberOfPoints=\"13\"", 1),
            "13",
        ),
        (
            good.replacen("NumberOfCells=\"2\"", "NumberOfCells=\"3\"", 1),
            "3 cells",
        ),
        (good.replace("</Cells>", ""), "closes"),
        (
            good.replace("vtkZLibDataCompressor", "vtkLZ4DataCompressor"),
            "vtkLZ4DataCompressor",
        ),
    ];
    for (n, (text, word)) in cases.into_iter().enumerate() {
        let path = scratch(&format!("bad{n}.vtu"));
        std::fs::write(&path, text).unwrap();
        match read_vtu(&path) {
            Err(e @ Error::Format { .. }) => {
                let m = e.to_string();
                assert!(
                    m.contains(&format!("bad{n}.vtu")) && m.contains(word),
                    "case {n}: {m}"
                )
            }
            other => panic!("case {n}: expected Format, got {other:?}"),
        }
    }
    assert!(read_vtu(&scratch("missing.vtu")).is_err());
}

#[test]
fn lung_sized_mesh_compresses_to_under_a_third_of_its_raw_bytes() {
    let mesh = VoxelGrid::filled_box([40, 40, 60], [0.004; 3], Vector3::zeros())
        .to_mesh(Material::LUNG)
        .unwrap()
        .mesh;
    let vtu = vtu_from_hex_mesh(&mesh, &mesh.rest_positions_m).unwrap();
    let path = scratch("lung-sized.vtu");
    let t = std::time::Instant::now();
    write_vtu(&path, &vtu).unwrap();
    let write_s = t.elapsed().as_secs_f64();
    let t = std::time::Instant::now();
    let back = read_vtu(&path).unwrap();
    let read_s = t.elapsed().as_secs_f64();
    assert_eq!(back.cells.len(), 96_000);
    // Per node: 3 f64 points + 3 f32 displacements; per cell: 8 i64 corners, an i64 offset,
    // a u8 type and an i32 class.
    let raw = mesh.node_count() * (24 + 12) + mesh.element_count() * (64 + 8 + 1 + 4);
    let size = std::fs::metadata(&path).unwrap().len() as f64;
    println!(
        "{} elements, {} nodes: {:.1} MB (raw {:.1} MB), write {write_s:.3} s, read {read_s:.3} s",
        mesh.element_count(),
        mesh.node_count(),
        size / 1e6,
        raw as f64 / 1e6
    );
    assert!(size < raw as f64 / 3.0, "{size} bytes");
}

#[test]
fn lung_meshes_carry_lung_per_cell_and_group_per_node_and_refuse_mismatched_labels() {
    use lungmotion::outputs::ingest_files::lung_mesh_vtu;
    let mesh = VoxelGrid::filled_box([2, 1, 1], [0.01; 3], Vector3::zeros())
        .to_mesh(Material::LUNG)
        .unwrap()
        .mesh;
    let (cells, nodes) = (mesh.element_count(), mesh.node_count());
    let lung: Vec<u8> = (0..cells).map(|c| 1 + (c % 2) as u8).collect();
    let group: Vec<u8> = (0..nodes).map(|n| (n % 6) as u8).collect();
    let vtu = lung_mesh_vtu(&mesh, &mesh.rest_positions_m, &lung, &group).unwrap();
    let path = scratch("lung-labels.vtu");
    write_vtu(&path, &vtu).unwrap();
    let back = read_vtu(&path).unwrap();
    let find = |data: &[(String, DataArray)], name: &str| {
        data.iter().find(|(n, _)| n == name).map(|(_, a)| a.clone())
    };
    assert_eq!(
        find(&back.cell_data, "lung"),
        Some(DataArray::ScalarsU8(lung.clone()))
    );
    assert_eq!(
        find(&back.point_data, "group"),
        Some(DataArray::ScalarsU8(group.clone()))
    );
    assert!(matches!(
        find(&back.point_data, "displacement_mm"),
        Some(DataArray::VectorsF32(v)) if v.len() == nodes
    ));
    assert!(
        find(&back.cell_data, "group").is_none(),
        "group is point data"
    );
    let e = lung_mesh_vtu(&mesh, &mesh.rest_positions_m, &lung[1..], &group)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains(&format!("{} lung labels for {cells} elements", cells - 1)),
        "{e}"
    );
}
