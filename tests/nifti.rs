//! NIfTI reading and writing: round trips, hand-built NIfTI-1/NIfTI-2 headers checked against
//! the standard's formulas, an independent reader (the `nifti` crate), real data and bad input.

use std::io::{Read, Write};
use std::path::{Path, PathBuf};
use std::time::Instant;

use lungmotion::datasets::{cip_chest_ct64, totalseg_abdomen_ct};
use lungmotion::formats::nifti::{
    read_nifti, read_nifti_bytes, read_nifti_labels, read_nifti_vector_field, write_nifti_ct,
    write_nifti_labels, write_nifti_vector_field,
};
use lungmotion::formats::nrrd::read_nrrd;
use lungmotion::volume::{Volume, VolumeGeometry};
use nalgebra::{Matrix3, Rotation3, Vector3};

// ---------------------------------------------------------------------------------------
// Helpers
// ---------------------------------------------------------------------------------------

fn scratch_dir(test: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("lungmotion-nifti-{}-{test}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

fn columns(m: Matrix3<f64>) -> [[f64; 3]; 3] {
    std::array::from_fn(|c| m.column(c).into_owned().into())
}

/// An oblique right-handed grid (a rotation about a tilted axis).
fn oblique_geometry() -> VolumeGeometry {
    VolumeGeometry {
        dims: [7, 5, 4],
        spacing_mm: [0.8, 1.25, 2.5],
        origin_lps_mm: [-60.5, 35.25, 80.75],
        direction_lps: columns(Rotation3::from_euler_angles(0.3, -0.5, 1.1).into_inner()),
    }
}

/// A left-handed grid: an oblique rotation with its j axis reflected.
fn reflected_geometry() -> VolumeGeometry {
    let mut d = Rotation3::from_euler_angles(-0.2, 0.4, 2.2).into_inner();
    let j = -d.column(1);
    d.set_column(1, &j);
    assert!(d.determinant() < 0.0);
    VolumeGeometry {
        dims: [6, 5, 3],
        spacing_mm: [1.5, 0.7, 3.0],
        origin_lps_mm: [42.0, -75.5, -20.25],
        direction_lps: columns(d),
    }
}

/// Largest distance between the two grids' voxel centres over the 8 corners, and the
/// largest spacing and direction differences.
fn geometry_error_mm(a: &VolumeGeometry, b: &VolumeGeometry) -> f64 {
    assert_eq!(a.dims, b.dims);
    let mut worst = 0.0f64;
    for corner in 0..8 {
        let ijk = Vector3::from(std::array::from_fn(|axis| {
            if corner & (1 << axis) != 0 {
                (a.dims[axis] - 1) as f64
            } else {
                0.0
            }
        }));
        worst = worst.max((a.voxel_to_lps_mm(ijk) - b.voxel_to_lps_mm(ijk)).norm());
    }
    for axis in 0..3 {
        worst = worst.max((a.spacing_mm[axis] - b.spacing_mm[axis]).abs());
    }
    worst.max((a.direction() - b.direction()).abs().max())
}

fn ct_values(g: &VolumeGeometry, fractional: bool) -> Vec<f32> {
    (0..g.voxel_count())
        .map(|v| {
            let hu = ((v * 7919) % 3000) as f32 - 1024.0;
            if fractional {
                hu + 0.375
            } else {
                hu
            }
        })
        .collect()
}

/// Decompressed bytes of a file written by us (gzip or raw).
fn file_bytes(path: &Path) -> Vec<u8> {
    let raw = std::fs::read(path).unwrap();
    if raw.starts_with(&[0x1f, 0x8b]) {
        let mut out = Vec::new();
        flate2::read::GzDecoder::new(&raw[..])
            .read_to_end(&mut out)
            .unwrap();
        out
    } else {
        raw
    }
}

fn le_i16(b: &[u8], o: usize) -> i16 {
    i16::from_le_bytes([b[o], b[o + 1]])
}
fn le_f32(b: &[u8], o: usize) -> f32 {
    f32::from_le_bytes([b[o], b[o + 1], b[o + 2], b[o + 3]])
}

fn gzip(bytes: &[u8]) -> Vec<u8> {
    let mut e = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::default());
    e.write_all(bytes).unwrap();
    e.finish().unwrap()
}

/// A hand-built NIfTI-1 header (little-endian, single file), fields per `nifti1.h`.
#[derive(Clone)]
struct Nifti1 {
    sizeof_hdr: i32,
    dim: [i16; 8],
    intent_code: i16,
    datatype: i16,
    bitpix: i16,
    pixdim: [f32; 8],
    vox_offset: f32,
    scl_slope: f32,
    scl_inter: f32,
    xyzt_units: u8,
    qform_code: i16,
    sform_code: i16,
    quatern: [f32; 3],
    qoffset: [f32; 3],
    srow: [[f32; 4]; 3],
    magic: [u8; 4],
}

impl Nifti1 {
    fn new(dims: [i16; 3], datatype: i16, bitpix: i16) -> Self {
        Nifti1 {
            sizeof_hdr: 348,
            dim: [3, dims[0], dims[1], dims[2], 1, 1, 1, 1],
            intent_code: 0,
            datatype,
            bitpix,
            pixdim: [1.0; 8],
            vox_offset: 352.0,
            scl_slope: 0.0,
            scl_inter: 0.0,
            xyzt_units: 2,
            qform_code: 0,
            sform_code: 0,
            quatern: [0.0; 3],
            qoffset: [0.0; 3],
            srow: [[0.0; 4]; 3],
            magic: *b"n+1\0",
        }
    }

    fn bytes(&self) -> Vec<u8> {
        let mut h = vec![0u8; 352];
        let mut put = |o: usize, b: &[u8]| h[o..o + b.len()].copy_from_slice(b);
        put(0, &self.sizeof_hdr.to_le_bytes());
        for (a, d) in self.dim.iter().enumerate() {
            put(40 + 2 * a, &d.to_le_bytes());
        }
        put(68, &self.intent_code.to_le_bytes());
        put(70, &self.datatype.to_le_bytes());
        put(72, &self.bitpix.to_le_bytes());
        for (a, p) in self.pixdim.iter().enumerate() {
            put(76 + 4 * a, &p.to_le_bytes());
        }
        put(108, &self.vox_offset.to_le_bytes());
        put(112, &self.scl_slope.to_le_bytes());
        put(116, &self.scl_inter.to_le_bytes());
        put(123, &[self.xyzt_units]);
        put(252, &self.qform_code.to_le_bytes());
        put(254, &self.sform_code.to_le_bytes());
        for (a, v) in self.quatern.iter().chain(&self.qoffset).enumerate() {
            put(256 + 4 * a, &v.to_le_bytes());
        }
        for r in 0..3 {
            for c in 0..4 {
                put(280 + 16 * r + 4 * c, &self.srow[r][c].to_le_bytes());
            }
        }
        put(344, &self.magic);
        h
    }

    fn with_i16_voxels(&self, voxels: &[i16]) -> Vec<u8> {
        let mut b = self.bytes();
        b.extend(voxels.iter().flat_map(|v| v.to_le_bytes()));
        b
    }
}

fn ramp_i16(n: usize) -> Vec<i16> {
    (0..n).map(|v| (v as i16) * 3 - 20).collect()
}

// ---------------------------------------------------------------------------------------
// Round trips
// ---------------------------------------------------------------------------------------

#[test]
fn ct_round_trips_through_nii_and_nii_gz_on_oblique_and_reflected_grids() {
    let dir = scratch_dir("ct-round-trip");
    for (name, geometry) in [
        ("oblique", oblique_geometry()),
        ("reflected", reflected_geometry()),
    ] {
        for fractional in [false, true] {
            let ct = Volume::from_data(geometry, ct_values(&geometry, fractional)).unwrap();
            for file in ["ct.nii", "ct.nii.gz"] {
                let path = dir.join(format!("{name}-{fractional}-{file}"));
                write_nifti_ct(&path, &ct).unwrap();
                let raw = std::fs::read(&path).unwrap();
                assert_eq!(raw.starts_with(&[0x1f, 0x8b]), file.ends_with(".gz"));
                let header = file_bytes(&path);
                // Integer HU are stored losslessly as int16, others as float32.
                let expected_type = if fractional { 16 } else { 4 };
                assert_eq!(le_i16(&header, 70), expected_type, "{path:?}");
                let back = read_nifti(&path).unwrap();
                assert_eq!(back.as_slice(), ct.as_slice(), "{path:?}");
                let err = geometry_error_mm(&back.geometry, &geometry);
                assert!(err < 1e-5, "{path:?}: geometry off by {err:.2e} mm");
            }
        }
    }
    std::fs::remove_dir_all(dir).unwrap();
}

#[test]
fn labels_round_trip_through_nii_and_nii_gz_on_oblique_and_reflected_grids() {
    let dir = scratch_dir("labels-round-trip");
    for (name, geometry) in [
        ("oblique", oblique_geometry()),
        ("reflected", reflected_geometry()),
    ] {
        let labels: Vec<u8> = (0..geometry.voxel_count())
            .map(|v| ((v * 37) % 256) as u8)
            .collect();
        let volume = Volume::from_data(geometry, labels).unwrap();
        for file in ["lm.nii", "lm.nii.gz"] {
            let path = dir.join(format!("{name}-{file}"));
            write_nifti_labels(&path, &volume).unwrap();
            let header = file_bytes(&path);
            assert_eq!(le_i16(&header, 70), 2, "uint8");
            assert_eq!(le_i16(&header, 68), 1002, "label intent");
            let back = read_nifti_labels(&path).unwrap();
            assert_eq!(back.as_slice(), volume.as_slice());
            let err = geometry_error_mm(&back.geometry, &geometry);
            assert!(err < 1e-5, "{path:?}: geometry off by {err:.2e} mm");
        }
    }
    std::fs::remove_dir_all(dir).unwrap();
}

#[test]
fn vector_field_round_trips_with_lps_components_in_component_planes() {
    let dir = scratch_dir("vector-field");
    let geometry = reflected_geometry();
    let n = geometry.voxel_count();
    let vectors: Vec<[f32; 3]> = (0..n)
        .map(|v| {
            let t = v as f32;
            [0.5 * t - 3.0, -0.25 * t + 1.0, (t * 0.37).sin() * 20.0]
        })
        .collect();
    for file in ["u.nii", "u.nii.gz"] {
        let path = dir.join(file);
        write_nifti_vector_field(&path, &geometry, &vectors, "inspiration, phase 3 of 10").unwrap();
        let bytes = file_bytes(&path);
        let dim: Vec<i16> = (0..8).map(|a| le_i16(&bytes, 40 + 2 * a)).collect();
        assert_eq!(dim, [5, 6, 5, 3, 1, 3, 1, 1]);
        assert_eq!(le_i16(&bytes, 68), 1007, "NIFTI_INTENT_VECTOR");
        assert_eq!(le_i16(&bytes, 70), 16, "float32");
        let descrip = String::from_utf8_lossy(&bytes[148..228]);
        assert!(
            descrip.contains("LPS mm") && descrip.contains("inspiration"),
            "{descrip}"
        );
        // Components are stored as given (LPS), x plane first: not flipped to RAS.
        let vox = le_f32(&bytes, 108) as usize;
        for v in [0, 17, n - 1] {
            for (c, &component) in vectors[v].iter().enumerate() {
                let stored = le_f32(&bytes, vox + 4 * (c * n + v));
                assert_eq!(stored, component, "voxel {v} component {c}");
            }
        }
        let (g, back) = read_nifti_vector_field(&path).unwrap();
        assert_eq!(back, vectors);
        let err = geometry_error_mm(&g, &geometry);
        assert!(err < 1e-5, "geometry off by {err:.2e} mm");
        // A displacement field is not a CT.
        let e = read_nifti(&path).unwrap_err().to_string();
        assert!(e.contains("values per voxel"), "{e}");
    }
    std::fs::remove_dir_all(dir).unwrap();
}

#[test]
fn independent_reader_sees_scanner_codes_and_the_ras_affine() {
    use nifti::{IntoNdArray, NiftiObject, ReaderOptions};
    let dir = scratch_dir("independent");
    let geometry = reflected_geometry();
    let ct = Volume::from_data(geometry, ct_values(&geometry, true)).unwrap();
    let path = dir.join("ct.nii.gz");
    write_nifti_ct(&path, &ct).unwrap();

    let object = ReaderOptions::new().read_file(&path).unwrap();
    let header = object.header();
    assert_eq!((header.sform_code, header.qform_code), (1, 1));
    assert_eq!(header.xyzt_units & 7, 2, "millimetres");
    let lps = geometry.voxel_to_lps();
    let flip = [-1.0, -1.0, 1.0];
    for (r, row) in [header.srow_x, header.srow_y, header.srow_z]
        .iter()
        .enumerate()
    {
        for c in 0..4 {
            let expected = flip[r] * lps[(r, c)];
            assert!(
                (row[c] as f64 - expected).abs() < 1e-4,
                "srow[{r}][{c}] = {} vs {expected}",
                row[c]
            );
        }
    }
    assert_eq!(header.pixdim[0], -1.0, "left-handed grid: qfac = -1");
    let array = object.into_volume().into_ndarray::<f32>().unwrap();
    assert_eq!(array.shape(), &geometry.dims[..]);
    for k in 0..geometry.dims[2] {
        for j in 0..geometry.dims[1] {
            for i in 0..geometry.dims[0] {
                assert_eq!(array[[i, j, k]], ct.get(i, j, k));
            }
        }
    }
    std::fs::remove_dir_all(dir).unwrap();
}

#[test]
fn written_qform_alone_gives_the_same_grid_as_the_sform() {
    let dir = scratch_dir("qform-consistent");
    for geometry in [oblique_geometry(), reflected_geometry()] {
        let ct = Volume::from_data(geometry, ct_values(&geometry, false)).unwrap();
        let path = dir.join("ct.nii");
        write_nifti_ct(&path, &ct).unwrap();
        let mut bytes = std::fs::read(&path).unwrap();
        bytes[348] = 0; // extension flag off: the exact-geometry comment is not consulted
        let sform = read_nifti_bytes(&bytes, "sform").unwrap().geometry;
        let err = geometry_error_mm(&sform, &geometry);
        assert!(err < 3e-5, "float32 sform off by {err:.2e} mm");
        bytes[254..256].copy_from_slice(&0i16.to_le_bytes()); // sform_code = 0
        let qform = read_nifti_bytes(&bytes, "qform only").unwrap().geometry;
        let err = geometry_error_mm(&qform, &geometry);
        assert!(err < 1e-4, "qform differs from the sform by {err:.2e} mm");
    }
    std::fs::remove_dir_all(dir).unwrap();
}

#[test]
fn exact_geometry_extension_yields_to_an_edited_affine() {
    let dir = scratch_dir("extension");
    let geometry = oblique_geometry();
    let ct = Volume::from_data(geometry, ct_values(&geometry, false)).unwrap();
    let path = dir.join("ct.nii");
    write_nifti_ct(&path, &ct).unwrap();
    let mut bytes = std::fs::read(&path).unwrap();
    let comment = String::from_utf8_lossy(&bytes[360..le_f32(&bytes, 108) as usize]);
    assert!(
        comment.starts_with("lungmotion exact geometry, LPS mm"),
        "{comment}"
    );
    assert_eq!(
        read_nifti_bytes(&bytes, "exact").unwrap().geometry,
        geometry
    );
    // Another tool moved the image 5 mm to the right (RAS x + 5): the header wins.
    let moved = le_f32(&bytes, 280 + 12) + 5.0;
    bytes[292..296].copy_from_slice(&moved.to_le_bytes());
    let g = read_nifti_bytes(&bytes, "moved").unwrap().geometry;
    let shift = Vector3::from(g.origin_lps_mm) - Vector3::from(geometry.origin_lps_mm);
    assert!(
        (shift - Vector3::new(-5.0, 0.0, 0.0)).norm() < 1e-4,
        "{shift}"
    );
    std::fs::remove_dir_all(dir).unwrap();
}

// ---------------------------------------------------------------------------------------
// Hand-built headers: the standard's formulas
// ---------------------------------------------------------------------------------------

#[test]
fn qform_with_qfac_minus_one_follows_the_standard() {
    // Quaternion (b, c, d) = (0, 0, sin 45°): 90° about z, so R = [[0,-1,0],[1,0,0],[0,0,1]].
    // qfac = -1 reflects the third column. RAS columns: i → +y (A), j → −x (L), k → −z (I);
    // in LPS: i → (0, −1, 0), j → (1, 0, 0), k → (0, 0, −1).
    let mut h = Nifti1::new([3, 4, 2], 4, 16);
    h.qform_code = 1;
    h.quatern = [0.0, 0.0, std::f32::consts::FRAC_1_SQRT_2];
    h.qoffset = [10.0, -20.0, 30.0];
    h.pixdim = [-1.0, 0.5, 2.0, 4.0, 1.0, 1.0, 1.0, 1.0];
    let voxels = ramp_i16(24);
    let v = read_nifti_bytes(&h.with_i16_voxels(&voxels), "qfac").unwrap();
    let g = v.geometry;
    assert_eq!(g.dims, [3, 4, 2]);
    assert!((Vector3::from(g.spacing_mm) - Vector3::new(0.5, 2.0, 4.0)).norm() < 1e-6);
    let expected = Matrix3::new(0.0, 1.0, 0.0, -1.0, 0.0, 0.0, 0.0, 0.0, -1.0);
    assert!(
        (g.direction() - expected).abs().max() < 1e-6,
        "{}",
        g.direction()
    );
    assert!((g.origin() - Vector3::new(-10.0, 20.0, 30.0)).norm() < 1e-6);
    // Voxel (1, 1, 1) in RAS: offset + (0, 0.5, 0) + (−2, 0, 0) + (0, 0, −4) = (8, −19.5, 26).
    let p = g.voxel_to_lps_mm(Vector3::new(1.0, 1.0, 1.0));
    assert!((p - Vector3::new(-8.0, 19.5, 26.0)).norm() < 1e-5, "{p}");
    assert_eq!(
        v.as_slice(),
        voxels.iter().map(|&x| x as f32).collect::<Vec<_>>()
    );

    // The same header with qfac = +1 keeps k superior.
    h.pixdim[0] = 1.0;
    let g = read_nifti_bytes(&h.with_i16_voxels(&voxels), "qfac+1")
        .unwrap()
        .geometry;
    assert!((Vector3::from(g.direction_lps[2]) - Vector3::z()).norm() < 1e-6);
}

#[test]
fn qform_half_turn_and_sform_precedence() {
    // (b, c, d) = (1, 0, 0): a = 0, 180° about x: R = diag(1, −1, −1) in RAS.
    let mut h = Nifti1::new([2, 2, 2], 4, 16);
    h.qform_code = 1;
    h.quatern = [1.0, 0.0, 0.0];
    let voxels = ramp_i16(8);
    let g = read_nifti_bytes(&h.with_i16_voxels(&voxels), "half turn")
        .unwrap()
        .geometry;
    let expected_lps = Matrix3::from_diagonal(&Vector3::new(-1.0, 1.0, -1.0));
    assert!((g.direction() - expected_lps).abs().max() < 1e-6);

    // With sform_code > 0 the sform wins: axes along R, A, S scaled 2, 3, 5.
    h.sform_code = 2;
    h.srow = [
        [2.0, 0.0, 0.0, -5.0],
        [0.0, 3.0, 0.0, 6.0],
        [0.0, 0.0, 5.0, 7.0],
    ];
    let g = read_nifti_bytes(&h.with_i16_voxels(&voxels), "sform")
        .unwrap()
        .geometry;
    assert_eq!(g.spacing_mm, [2.0, 3.0, 5.0]);
    let expected_lps = Matrix3::from_diagonal(&Vector3::new(-1.0, -1.0, 1.0));
    assert!((g.direction() - expected_lps).abs().max() < 1e-12);
    assert_eq!(g.origin_lps_mm, [5.0, -6.0, 7.0]);
}

#[test]
fn analyze_fallback_units_and_scaling() {
    let voxels = ramp_i16(8);
    // No transform at all: pixdim along R, A, S from the origin.
    let mut h = Nifti1::new([2, 2, 2], 4, 16);
    h.pixdim[1..4].copy_from_slice(&[1.5, 2.5, 3.5]);
    let g = read_nifti_bytes(&h.with_i16_voxels(&voxels), "analyze")
        .unwrap()
        .geometry;
    assert_eq!(g.spacing_mm, [1.5, 2.5, 3.5]);
    assert_eq!(g.origin_lps_mm, [0.0; 3]);
    assert_eq!(g.direction_lps[0], [-1.0, 0.0, 0.0]);

    // Metres and micrometres become millimetres, in spacing and origin alike.
    for (units, mm_per_unit) in [(1u8, 1000.0), (3u8, 1e-3)] {
        let mut h = Nifti1::new([2, 2, 2], 4, 16);
        h.xyzt_units = units | 8; // spatial unit plus seconds
        let s = (2.0 / mm_per_unit) as f32;
        h.pixdim[1..4].copy_from_slice(&[s; 3]);
        h.sform_code = 1;
        h.srow = [[s, 0.0, 0.0, s], [0.0, s, 0.0, 0.0], [0.0, 0.0, s, 0.0]];
        let g = read_nifti_bytes(&h.with_i16_voxels(&voxels), "units")
            .unwrap()
            .geometry;
        for axis in 0..3 {
            assert!((g.spacing_mm[axis] - 2.0).abs() < 1e-5, "{units}: {g:?}");
        }
        assert!((g.origin_lps_mm[0] + 2.0).abs() < 1e-5, "{units}: {g:?}");
    }

    // scl_slope / scl_inter apply when the slope is non-zero.
    let mut h = Nifti1::new([2, 2, 2], 4, 16);
    h.scl_slope = 2.0;
    h.scl_inter = -1024.0;
    let v = read_nifti_bytes(&h.with_i16_voxels(&voxels), "scaled").unwrap();
    let expected: Vec<f32> = voxels.iter().map(|&x| 2.0 * x as f32 - 1024.0).collect();
    assert_eq!(v.as_slice(), expected);
}

/// A NIfTI-2 file per `nifti2.h`: 540-byte header, 64-bit dims, double affine.
fn nifti2_file(
    dims: [i64; 3],
    srow: [[f64; 4]; 3],
    pixdim: [f64; 3],
    extra: &[i64],
    voxels: &[i16],
) -> Vec<u8> {
    let mut h = vec![0u8; 544];
    let mut put = |o: usize, b: &[u8]| h[o..o + b.len()].copy_from_slice(b);
    put(0, &540i32.to_le_bytes());
    put(4, b"n+2\0\r\n\x1a\n");
    put(12, &4i16.to_le_bytes()); // int16
    put(14, &16i16.to_le_bytes());
    let mut dim = [1i64; 8];
    dim[0] = 3 + extra.len() as i64;
    dim[1..4].copy_from_slice(&dims);
    dim[4..4 + extra.len()].copy_from_slice(extra);
    for (a, d) in dim.iter().enumerate() {
        put(16 + 8 * a, &d.to_le_bytes());
    }
    let mut pd = [1.0f64; 8];
    pd[1..4].copy_from_slice(&pixdim);
    for (a, p) in pd.iter().enumerate() {
        put(104 + 8 * a, &p.to_le_bytes());
    }
    put(168, &544i64.to_le_bytes());
    put(348, &1i32.to_le_bytes()); // sform_code
    for (r, row) in srow.iter().enumerate() {
        for (c, v) in row.iter().enumerate() {
            put(400 + 32 * r + 8 * c, &v.to_le_bytes());
        }
    }
    put(500, &2i32.to_le_bytes()); // mm
    h.extend(voxels.iter().flat_map(|v| v.to_le_bytes()));
    h
}

#[test]
fn nifti2_is_read_with_its_double_precision_geometry() {
    let g = oblique_geometry();
    let lps = g.voxel_to_lps();
    let flip = [-1.0, -1.0, 1.0];
    let srow: [[f64; 4]; 3] =
        std::array::from_fn(|r| std::array::from_fn(|c| flip[r] * lps[(r, c)]));
    let dims = g.dims.map(|n| n as i64);
    let voxels = ramp_i16(g.voxel_count());
    for gz in [false, true] {
        let mut bytes = nifti2_file(dims, srow, g.spacing_mm, &[], &voxels);
        if gz {
            bytes = gzip(&bytes);
        }
        let v = read_nifti_bytes(&bytes, "nifti2").unwrap();
        let err = geometry_error_mm(&v.geometry, &g);
        assert!(err < 1e-9, "NIfTI-2 geometry off by {err:.2e} mm");
        assert_eq!(
            v.as_slice(),
            voxels.iter().map(|&x| x as f32).collect::<Vec<_>>()
        );
    }
}

// ---------------------------------------------------------------------------------------
// Real data
// ---------------------------------------------------------------------------------------

#[test]
#[cfg_attr(
    not(shared_data),
    ignore = "needs the shared CT data (../shared/data or LUNGMOTION_SHARED_DATA; see README)"
)]
fn totalsegmentator_ct_reads_with_ras_axes_and_round_trips() {
    let Some(dir) = totalseg_abdomen_ct() else {
        println!("skipped: shared data not found");
        return;
    };
    let ct = read_nifti(&dir.join("ct.nii.gz")).unwrap();
    let g = ct.geometry;
    assert_eq!(g.dims, [122, 101, 112]);
    for s in g.spacing_mm {
        assert!((s - 3.0).abs() < 1e-3, "{g:?}");
    }
    // Voxel axes point R, A, S: in LPS that is diag(−1, −1, 1).
    let expected = Matrix3::from_diagonal(&Vector3::new(-1.0, -1.0, 1.0));
    assert!((g.direction() - expected).abs().max() < 1e-6, "{g:?}");
    let min = ct.as_slice().iter().copied().fold(f32::INFINITY, f32::min);
    let max = ct
        .as_slice()
        .iter()
        .copied()
        .fold(f32::NEG_INFINITY, f32::max);
    println!(
        "totalseg ct: origin {:?} mm, HU {min} .. {max}",
        g.origin_lps_mm
    );
    // Air is about −1024 HU; resampling left 124 voxels below it (the file's own minimum
    // is −1207, checked by unpacking it with Python's struct module).
    assert!((-1300.0..=-1000.0).contains(&min), "min {min} HU");
    assert!(max > 1000.0, "max {max} HU");
    // An independent reader (the `nifti` crate) sees the same voxels at the same indices.
    use nifti::{IntoNdArray, NiftiObject, ReaderOptions};
    let object = ReaderOptions::new()
        .read_file(dir.join("ct.nii.gz"))
        .unwrap();
    let array = object.into_volume().into_ndarray::<f32>().unwrap();
    for k in 0..g.dims[2] {
        for j in 0..g.dims[1] {
            for i in 0..g.dims[0] {
                assert_eq!(array[[i, j, k]], ct.get(i, j, k), "voxel ({i}, {j}, {k})");
            }
        }
    }

    let out = scratch_dir("totalseg");
    let path = out.join("ct.nii.gz");
    write_nifti_ct(&path, &ct).unwrap();
    let back = read_nifti(&path).unwrap();
    assert_eq!(back.as_slice(), ct.as_slice());
    let err = geometry_error_mm(&back.geometry, &g);
    println!("totalseg round trip: geometry error {err:.2e} mm");
    assert!(err < 1e-5, "geometry off by {err:.2e} mm");
    std::fs::remove_dir_all(out).unwrap();
}

#[test]
#[cfg_attr(
    not(shared_data),
    ignore = "needs the shared CT data (../shared/data or LUNGMOTION_SHARED_DATA; see README)"
)]
fn cip_nrrd_written_as_nifti_reads_back_identical() {
    let Some(dir) = cip_chest_ct64() else {
        println!("skipped: shared data not found");
        return;
    };
    let ct = read_nrrd(&dir.join("ct-64.nrrd")).unwrap();
    let out = scratch_dir("cip");
    for file in ["ct.nii", "ct.nii.gz"] {
        let path = out.join(file);
        write_nifti_ct(&path, &ct).unwrap();
        let back = read_nifti(&path).unwrap();
        assert_eq!(back.as_slice(), ct.as_slice());
        println!(
            "cip {file}: geometry error {:.2e} mm",
            geometry_error_mm(&back.geometry, &ct.geometry)
        );
        // Bit-identical thanks to the exact-geometry extension (float32 alone: 2.7e-5 mm).
        assert_eq!(back.geometry, ct.geometry);
    }
    std::fs::remove_dir_all(out).unwrap();
}

// ---------------------------------------------------------------------------------------
// Bad input
// ---------------------------------------------------------------------------------------

fn error_of(bytes: &[u8]) -> String {
    read_nifti_bytes(bytes, "upload.nii")
        .unwrap_err()
        .to_string()
}

fn assert_mentions(message: &str, words: &[&str]) {
    for w in words {
        assert!(message.contains(w), "'{w}' missing from: {message}");
    }
}

#[test]
fn non_finite_voxels_are_refused_with_count_and_first_voxel() {
    let h = Nifti1::new([4, 3, 2], 16, 32);
    let mut values = [1.0f32; 24];
    values[1 + 4 * 2] = f32::NAN; // voxel (1, 2, 0)
    values[3 + 4 * (1 + 3)] = f32::INFINITY;
    let mut bytes = h.bytes();
    bytes.extend(values.iter().flat_map(|v| v.to_le_bytes()));
    let e = error_of(&bytes);
    assert_mentions(&e, &["upload.nii", "2 voxels", "NaN", "(1, 2, 0)"]);

    let g = oblique_geometry();
    let mut ct = Volume::filled(g, 0.0f32).unwrap();
    ct.as_slice_mut()[5] = f32::NAN;
    let path = scratch_dir("nan-write").join("ct.nii");
    let e = write_nifti_ct(&path, &ct).unwrap_err().to_string();
    assert_mentions(&e, &["1 voxels", "NaN"]);
    assert!(!path.exists());
}

#[test]
fn label_reader_refuses_fractions_and_values_above_255() {
    let mut h = Nifti1::new([2, 2, 2], 4, 16);
    let mut voxels = vec![0i16, 1, 2, 3, 4, 5, 6, 7];
    voxels[6] = 300;
    let dir = scratch_dir("labels-bad");
    let path = dir.join("lm.nii");
    std::fs::write(&path, h.with_i16_voxels(&voxels)).unwrap();
    let e = read_nifti_labels(&path).unwrap_err().to_string();
    assert_mentions(&e, &["lm.nii", "0..=255", "(0, 1, 1)", "300"]);

    voxels[6] = 6;
    h.scl_slope = 0.5; // 7 × 0.5 = 3.5 and friends are not labels
    std::fs::write(&path, h.with_i16_voxels(&voxels)).unwrap();
    let e = read_nifti_labels(&path).unwrap_err().to_string();
    assert_mentions(&e, &["4 voxels", "(1, 0, 0) = 0.5"]);
    std::fs::remove_dir_all(dir).unwrap();
}

#[test]
fn truncated_files_are_refused_as_truncated() {
    let g = oblique_geometry();
    let ct = Volume::from_data(g, ct_values(&g, true)).unwrap();
    let dir = scratch_dir("truncated");
    for file in ["ct.nii", "ct.nii.gz"] {
        let path = dir.join(file);
        write_nifti_ct(&path, &ct).unwrap();
        let full = std::fs::read(&path).unwrap();
        for keep in [full.len() - 9, full.len() / 2, 200] {
            std::fs::write(&path, &full[..keep]).unwrap();
            let e = read_nifti(&path).unwrap_err().to_string();
            assert_mentions(&e, &[file, "truncated"]);
        }
    }
    std::fs::remove_dir_all(dir).unwrap();
}

#[test]
fn absurd_dims_are_refused_before_allocating() {
    let mut h = Nifti1::new([30_000, 30_000, 30_000], 4, 16);
    h.sform_code = 1;
    h.srow = [
        [1.0, 0.0, 0.0, 0.0],
        [0.0, 1.0, 0.0, 0.0],
        [0.0, 0.0, 1.0, 0.0],
    ];
    let start = Instant::now();
    let e = error_of(&h.with_i16_voxels(&[0; 16]));
    assert_mentions(&e, &["absurd"]);
    let e = error_of(&gzip(&h.with_i16_voxels(&[0; 16])));
    assert_mentions(&e, &["absurd"]);

    // 100000³ needs NIfTI-2's 64-bit dims.
    let srow = [
        [1.0, 0.0, 0.0, 0.0],
        [0.0, 1.0, 0.0, 0.0],
        [0.0, 0.0, 1.0, 0.0],
    ];
    let big = nifti2_file([100_000; 3], srow, [1.0; 3], &[], &[0; 16]);
    assert_mentions(&error_of(&big), &["absurd", "100000"]);
    // Under the per-axis limit but 4·10¹² voxels in all.
    let big = nifti2_file([16_000; 3], srow, [1.0; 3], &[], &[0; 16]);
    assert_mentions(&error_of(&gzip(&big)), &["absurd"]);
    // Within the format's limits but over the memory budget: refused before inflating.
    let big = nifti2_file([2048, 2048, 512], srow, [1.0; 3], &[], &[0; 16]);
    assert_mentions(&error_of(&gzip(&big)), &["over the budget", "8.0 GiB"]);
    // Within the budget, its voxels missing: truncated (raw) or over the ratio cap (gzip,
    // decided from the header before inflating), never allocated.
    let big = nifti2_file([512, 512, 512], srow, [1.0; 3], &[], &[0; 16]);
    assert_mentions(&error_of(&big), &["truncated"]);
    assert_mentions(&error_of(&gzip(&big)), &["cap of 250×"]);
    let elapsed = start.elapsed();
    assert!(elapsed.as_millis() < 500, "took {elapsed:?}");
}

#[test]
fn zero_or_negative_pixdim_is_refused() {
    for bad in [0.0f32, -1.5] {
        let mut h = Nifti1::new([2, 2, 2], 4, 16);
        h.qform_code = 1;
        h.pixdim[2] = bad;
        let e = error_of(&h.with_i16_voxels(&ramp_i16(8)));
        assert_mentions(&e, &["upload.nii", "pixdim[2]", "positive"]);
    }
}

#[test]
fn time_series_are_refused() {
    let mut h = Nifti1::new([2, 2, 2], 4, 16);
    h.dim[0] = 4;
    h.dim[4] = 5;
    let e = error_of(&h.with_i16_voxels(&ramp_i16(40)));
    assert_mentions(&e, &["4-D", "5 volumes"]);
    // A 4-D header with a single time point is one 3-D CT.
    h.dim[4] = 1;
    let v = read_nifti_bytes(&h.with_i16_voxels(&ramp_i16(8)), "nt1").unwrap();
    assert_eq!(v.dims(), [2, 2, 2]);
}

#[test]
fn files_that_are_not_nifti_are_refused() {
    let good = Nifti1::new([2, 2, 2], 4, 16);
    let mut h = good.clone();
    h.sizeof_hdr = 352;
    assert_mentions(
        &error_of(&h.with_i16_voxels(&ramp_i16(8))),
        &["not a NIfTI", "352"],
    );
    let mut h = good.clone();
    h.magic = *b"abc\0";
    assert_mentions(&error_of(&h.with_i16_voxels(&ramp_i16(8))), &["magic"]);
    let mut h = good.clone();
    h.magic = *b"ni1\0";
    assert_mentions(&error_of(&h.with_i16_voxels(&ramp_i16(8))), &[".hdr/.img"]);
    let mut h = good;
    h.datatype = 32; // complex64
    h.bitpix = 64;
    assert_mentions(
        &error_of(&h.with_i16_voxels(&ramp_i16(32))),
        &["datatype code 32"],
    );
    assert_mentions(&error_of(b"NRRD0004\nhello"), &["not a NIfTI"]);
    assert_mentions(&error_of(b"ab"), &["not a NIfTI"]);
}

#[test]
fn sheared_sform_is_refused() {
    let mut h = Nifti1::new([2, 2, 2], 4, 16);
    h.sform_code = 1;
    h.srow = [
        [1.0, 0.3, 0.0, 0.0],
        [0.0, 1.0, 0.0, 0.0],
        [0.0, 0.0, 1.0, 0.0],
    ];
    let e = error_of(&h.with_i16_voxels(&ramp_i16(8)));
    assert_mentions(&e, &["upload.nii", "sheared", "not orthogonal"]);
}

#[test]
fn degenerate_qform_quaternion_is_refused_naming_it() {
    // The file: qform_code 1, b = c = d = 5 (nifti1_io would renormalise it into
    // some half-turn; nibabel refuses it).
    let mut h = Nifti1::new([2, 2, 2], 4, 16);
    h.qform_code = 1;
    h.quatern = [5.0, 5.0, 5.0];
    let e = error_of(&h.with_i16_voxels(&ramp_i16(8)));
    assert_mentions(
        &e,
        &[
            "upload.nii",
            "degenerate qform",
            "(5, 5, 5)",
            "b²+c²+d² = 75",
            "more than 1: not a rotation",
        ],
    );
    h.quatern = [f32::NAN, 0.0, 0.0];
    assert_mentions(
        &error_of(&h.with_i16_voxels(&ramp_i16(8))),
        &["degenerate qform", "NaN"],
    );
    h.quatern = [0.0; 3];
    h.qoffset = [f32::INFINITY, 0.0, 0.0];
    assert_mentions(
        &error_of(&h.with_i16_voxels(&ramp_i16(8))),
        &["qoffset", "not finite"],
    );
    // A float32-rounded half-turn (b² + c² + d² a hair above 1) still reads.
    let third = (1.0f32 / 3.0).sqrt() * (1.0 + 1e-7);
    h.qoffset = [0.0; 3];
    h.quatern = [third; 3];
    read_nifti_bytes(&h.with_i16_voxels(&ramp_i16(8)), "half-turn").unwrap();
}

#[test]
fn non_finite_or_singular_sform_is_refused_naming_the_rows() {
    let mut h = Nifti1::new([2, 2, 2], 4, 16);
    h.sform_code = 1;
    h.srow = [
        [1.0, 0.0, 0.0, 0.0],
        [0.0, f32::NAN, 0.0, 0.0],
        [0.0, 0.0, 1.0, 0.0],
    ];
    let e = error_of(&h.with_i16_voxels(&ramp_i16(8)));
    assert_mentions(&e, &["upload.nii", "non-finite", "srow_y"]);
    // Two parallel axes: no grid.
    h.srow = [
        [1.0, 2.0, 0.0, 0.0],
        [1.0, 2.0, 0.0, 0.0],
        [0.0, 0.0, 1.0, 0.0],
    ];
    let e = error_of(&h.with_i16_voxels(&ramp_i16(8)));
    assert_mentions(&e, &["singular sform", "srow_x = [1.0, 2.0, 0.0, 0.0]"]);
    // An all-zero sform (a writer that set the code but not the rows).
    h.srow = [[0.0; 4]; 3];
    let e = error_of(&h.with_i16_voxels(&ramp_i16(8)));
    assert_mentions(&e, &["singular sform"]);
}

/// Throughput on a clinical-size grid; run with `--ignored --nocapture`.
#[test]
#[ignore]
fn timing_on_a_512_by_512_by_256_ct() {
    let geometry = VolumeGeometry {
        dims: [512, 512, 256],
        ..oblique_geometry()
    };
    let ct = Volume::from_data(geometry, ct_values(&geometry, false)).unwrap();
    let dir = scratch_dir("timing");
    for file in ["ct.nii", "ct.nii.gz"] {
        let path = dir.join(file);
        let t = Instant::now();
        write_nifti_ct(&path, &ct).unwrap();
        let written = t.elapsed();
        let t = Instant::now();
        let back = read_nifti(&path).unwrap();
        let read = t.elapsed();
        let size = std::fs::metadata(&path).unwrap().len();
        println!("{file}: write {written:?}, read {read:?}, {size} bytes");
        assert_eq!(back.as_slice(), ct.as_slice());
    }
    std::fs::remove_dir_all(dir).unwrap();
}
