//! PNG quick looks: the radiological display convention on straight, flipped and oblique
//! scans, the HU window, overlays, PNG round trip, and the real CIP chest case.

use std::path::PathBuf;

use lungmotion::formats::nrrd::read_nrrd;
use lungmotion::outputs::quicklook::{
    read_png, render_slice, write_overview, write_png, HuWindow, Overlay, RgbImage, SlicePlane,
};
use lungmotion::volume::{Volume, VolumeGeometry};
use nalgebra::{Rotation3, Vector3};

fn scratch_dir() -> PathBuf {
    let dir = std::env::temp_dir().join(format!("lungmotion-quicklook-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// Centre of every test volume, LPS mm.
const CENTRE: [f64; 3] = [-20.0, 35.0, -150.0];
/// Marker offset from the centre: patient right (−x), anterior (−y), superior (+z).
const MARKER_OFFSET: [f64; 3] = [-30.0, -25.0, 28.0];

/// A geometry with the given direction whose voxel-grid centre sits at [`CENTRE`].
fn centred_geometry(direction_lps: [[f64; 3]; 3]) -> VolumeGeometry {
    let dims = [40, 44, 36];
    let spacing_mm = [2.0, 2.2, 2.5];
    let mut g = VolumeGeometry {
        dims,
        spacing_mm,
        origin_lps_mm: [0.0; 3],
        direction_lps,
    };
    let half = Vector3::from_fn(|a, _| (dims[a] - 1) as f64 / 2.0);
    let offset = g.voxel_to_lps_mm(half);
    g.origin_lps_mm = (Vector3::from(CENTRE) - offset).into();
    g
}

/// −1000 HU everywhere except a 7 mm ball of +1000 HU at `marker_lps_mm`, placed by each
/// voxel's own LPS position (independently of the renderer).
fn marker_ct(g: VolumeGeometry, marker_lps_mm: Vector3<f64>) -> Volume<f32> {
    let mut data = vec![-1000.0f32; g.voxel_count()];
    for k in 0..g.dims[2] {
        for j in 0..g.dims[1] {
            for i in 0..g.dims[0] {
                let p = g.voxel_to_lps_mm(Vector3::new(i as f64, j as f64, k as f64));
                if (p - marker_lps_mm).norm() < 7.0 {
                    data[g.index(i, j, k)] = 1000.0;
                }
            }
        }
    }
    Volume::from_data(g, data).unwrap()
}

/// Centroid (column, row) and count of pixels brighter than mid-grey.
fn bright_centroid(img: &RgbImage) -> ([f64; 2], usize) {
    let (mut sum, mut n) = ([0.0; 2], 0);
    for row in 0..img.height {
        for col in 0..img.width {
            if img.pixel(col, row)[0] > 200 {
                sum[0] += col as f64;
                sum[1] += row as f64;
                n += 1;
            }
        }
    }
    ([sum[0] / n.max(1) as f64, sum[1] / n.max(1) as f64], n)
}

#[test]
fn marker_lands_where_the_radiological_convention_puts_it_on_any_grid() {
    let identity = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
    let flipped_x = [[-1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
    // Feet-first-like storage: j runs anterior and k inferior (still a rotation).
    let flipped_yz = [[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]];
    let r = Rotation3::from_euler_angles(0.25, -0.2, 0.45);
    let m = r.matrix();
    let oblique = [
        [m[(0, 0)], m[(1, 0)], m[(2, 0)]],
        [m[(0, 1)], m[(1, 1)], m[(2, 1)]],
        [m[(0, 2)], m[(1, 2)], m[(2, 2)]],
    ];
    let marker = Vector3::from(CENTRE) + Vector3::from(MARKER_OFFSET);
    for (name, dir) in [
        ("identity", identity),
        ("flipped x", flipped_x),
        ("flipped y z", flipped_yz),
        ("oblique", oblique),
    ] {
        let ct = marker_ct(centred_geometry(dir), marker);
        let px = 2.0; // the smallest spacing
        let [dx, dy, dz] = MARKER_OFFSET;
        // (plane, slice position, expected column and row offsets from the image centre, mm):
        // the image is centred on the scan, whose box is centred on CENTRE.
        let expect = [
            (SlicePlane::Axial, marker.z, dx, dy),
            (SlicePlane::Coronal, marker.y, dx, -dz),
            (SlicePlane::Sagittal, marker.x, dy, -dz),
        ];
        for (plane, position, col_mm, row_mm) in expect {
            let img = render_slice(&ct, &[], plane, position, HuWindow::LUNG).unwrap();
            let ([col, row], n) = bright_centroid(&img);
            assert!(n >= 20, "{name} {plane:?}: marker not visible ({n} px)");
            // Patient right / anterior / superior all land in the top-left quadrant.
            assert!(
                col < img.width as f64 / 2.0 && row < img.height as f64 / 2.0,
                "{name} {plane:?}: marker at ({col:.1}, {row:.1}) in {}×{}",
                img.width,
                img.height
            );
            let want_col = img.width as f64 / 2.0 - 0.5 + col_mm / px;
            let want_row = img.height as f64 / 2.0 - 0.5 + row_mm / px;
            assert!(
                (col - want_col).abs() < 1.0 && (row - want_row).abs() < 1.0,
                "{name} {plane:?}: marker at ({col:.2}, {row:.2}), expected ({want_col:.2}, {want_row:.2})"
            );
        }
    }
}

#[test]
fn lung_window_maps_minus_1350_to_black_and_150_to_white() {
    let g = VolumeGeometry::axis_aligned([5, 5, 5], [1.0; 3], [0.0; 3]);
    for (hu, grey) in [
        (-1350.0, 0u8),
        (-2000.0, 0),
        (150.0, 255),
        (3000.0, 255),
        (-600.0, 128),
        (-975.0, 64),
    ] {
        let ct = Volume::filled(g, hu).unwrap();
        let img = render_slice(&ct, &[], SlicePlane::Axial, 2.0, HuWindow::default()).unwrap();
        assert_eq!((img.width, img.height), (5, 5));
        assert!(
            img.pixels.iter().all(|&p| p == grey),
            "{hu} HU: {:?}",
            &img.pixels[..6]
        );
    }
    assert_eq!(HuWindow::MEDIASTINUM.grey(240.0), 255);
}

#[test]
fn overlay_colours_exactly_the_labelled_voxels() {
    // Patient's right half (x < 0, i < 10) labelled 3, on a grid coarser than the CT.
    let ct_g = VolumeGeometry::axis_aligned([20, 20, 10], [1.0; 3], [-9.5, -9.5, 0.0]);
    let ct = Volume::filled(ct_g, -600.0f32).unwrap();
    let lab_g = VolumeGeometry::axis_aligned([10, 10, 5], [2.0; 3], [-9.0, -9.0, 0.5]);
    let mut labels = Volume::filled(lab_g, 0u8).unwrap();
    for k in 0..5 {
        for j in 0..10 {
            for i in 0..5 {
                let n = lab_g.index(i, j, k);
                labels.as_slice_mut()[n] = 3;
            }
        }
    }
    let palette = [(3u8, [255u8, 0, 0]), (7, [0, 255, 0])];
    let overlay = |opacity: f32, outline_only: bool| Overlay {
        labels: &labels,
        palette: &palette,
        opacity,
        outline_only,
    };
    let img = render_slice(
        &ct,
        &[overlay(1.0, false)],
        SlicePlane::Axial,
        4.0,
        HuWindow::LUNG,
    )
    .unwrap();
    assert_eq!(img.width, 20);
    for row in 0..img.height {
        for col in 0..img.width {
            let want = if col < 10 { [255, 0, 0] } else { [128; 3] };
            assert_eq!(img.pixel(col, row), want, "pixel ({col}, {row})");
        }
    }
    let half = render_slice(
        &ct,
        &[overlay(0.5, false)],
        SlicePlane::Axial,
        4.0,
        HuWindow::LUNG,
    )
    .unwrap();
    assert_eq!(half.pixel(3, 7), [192, 64, 64]);
    assert_eq!(half.pixel(15, 7), [128; 3]);
    let outline = render_slice(
        &ct,
        &[overlay(1.0, true)],
        SlicePlane::Axial,
        4.0,
        HuWindow::LUNG,
    )
    .unwrap();
    assert_eq!(outline.pixel(9, 7), [255, 0, 0], "the boundary is drawn");
    assert_eq!(outline.pixel(5, 7), [128; 3], "the interior is not");
    // In the coronal plane the label still sits on the image's left (patient right).
    let coronal = render_slice(
        &ct,
        &[overlay(1.0, false)],
        SlicePlane::Coronal,
        0.0,
        HuWindow::LUNG,
    )
    .unwrap();
    assert_eq!(coronal.pixel(2, 3), [255, 0, 0]);
    assert_eq!(coronal.pixel(17, 3), [128; 3]);
}

#[test]
fn bad_requests_are_refused_with_the_reason() {
    let g = VolumeGeometry::axis_aligned([8, 8, 8], [1.0; 3], [0.0; 3]);
    let ct = Volume::filled(g, 0.0f32).unwrap();
    let e = render_slice(&ct, &[], SlicePlane::Axial, 50.0, HuWindow::LUNG)
        .unwrap_err()
        .to_string();
    assert!(e.contains("outside the scan"), "{e}");
    let labels = Volume::filled(g, 1u8).unwrap();
    let o = Overlay {
        labels: &labels,
        palette: &[(1, [0, 0, 255])],
        opacity: 1.5,
        outline_only: false,
    };
    let e = render_slice(&ct, &[o], SlicePlane::Axial, 3.0, HuWindow::LUNG)
        .unwrap_err()
        .to_string();
    assert!(e.contains("opacity"), "{e}");
    let flat = HuWindow {
        width_hu: 0.0,
        level_hu: 0.0,
    };
    assert!(render_slice(&ct, &[], SlicePlane::Axial, 3.0, flat).is_err());
}

#[test]
fn png_round_trip_is_exact_and_garbage_is_refused() {
    let (width, height) = (7, 5);
    let pixels: Vec<u8> = (0..3 * width * height)
        .map(|n| (n * 37 % 251) as u8)
        .collect();
    let img = RgbImage {
        width,
        height,
        pixels,
    };
    let path = scratch_dir().join("roundtrip.png");
    write_png(&path, &img).unwrap();
    assert_eq!(read_png(&path).unwrap(), img);
    std::fs::write(&path, b"not a png").unwrap();
    let e = read_png(&path).unwrap_err().to_string();
    assert!(e.contains("roundtrip.png"), "{e}");
    let wrong = RgbImage {
        width: 3,
        height: 3,
        pixels: vec![0; 10],
    };
    assert!(write_png(&scratch_dir().join("wrong.png"), &wrong).is_err());
}

#[test]
#[cfg_attr(
    not(shared_data),
    ignore = "needs the shared CT data (../shared/data or LUNGMOTION_SHARED_DATA; see README)"
)]
fn overview_of_the_cip_chest_shows_the_right_lung_on_the_image_left() {
    let Some(dir) = lungmotion::datasets::cip_chest_ct64() else {
        println!("skipped: shared data not found");
        return;
    };
    let ct = read_nrrd(&dir.join("ct-64.nrrd")).unwrap();
    let lm = read_nrrd(&dir.join("lm-64.nrrd")).unwrap();
    // 1 = left lung (regions 9–11), 2 = right lung (12–14), 3 = trachea outside the lungs.
    let labels = lm.map(|v| match (v as u32 & 0xFF, v as u32) {
        (9..=11, _) => 1u8,
        (12..=14, _) => 2,
        (_, 512) => 3,
        _ => 0,
    });
    let g = labels.geometry;
    let (mut sum, mut n) = (Vector3::zeros(), 0.0);
    for k in 0..g.dims[2] {
        for j in 0..g.dims[1] {
            for i in 0..g.dims[0] {
                if matches!(labels.get(i, j, k), 1 | 2) {
                    sum += g.voxel_to_lps_mm(Vector3::new(i as f64, j as f64, k as f64));
                    n += 1.0;
                }
            }
        }
    }
    let centre: [f64; 3] = (sum / n).into();
    let palette = [(1, [0, 160, 255]), (2, [255, 160, 0]), (3, [0, 255, 0])];
    let overlay = Overlay {
        labels: &labels,
        palette: &palette,
        opacity: 0.35,
        outline_only: false,
    };
    let out = std::env::var_os("LUNGMOTION_QUICKLOOK_DIR")
        .map(PathBuf::from)
        .unwrap_or_else(scratch_dir);
    let t = std::time::Instant::now();
    let paths = write_overview(&ct, &[overlay], centre, &out, "cip-ct64").unwrap();
    println!(
        "quick looks in {:.3} s: {paths:?}",
        t.elapsed().as_secs_f64()
    );
    assert_eq!(paths.len(), 3);
    let is_orange = |p: [u8; 3]| i32::from(p[0]) > i32::from(p[2]) + 60;
    let is_blue = |p: [u8; 3]| i32::from(p[2]) > i32::from(p[0]) + 60;
    for (path, plane) in paths.iter().zip(SlicePlane::ALL).take(2) {
        assert!(path.ends_with(format!("cip-ct64-{}.png", plane.name())));
        let img = read_png(path).unwrap();
        let (mut right, mut left) = ((0.0, 0.0), (0.0, 0.0));
        for row in 0..img.height {
            for col in 0..img.width {
                let p = img.pixel(col, row);
                if is_orange(p) {
                    right = (right.0 + col as f64, right.1 + 1.0);
                } else if is_blue(p) {
                    left = (left.0 + col as f64, left.1 + 1.0);
                }
            }
        }
        assert!(
            right.1 > 1000.0 && left.1 > 1000.0,
            "{plane:?}: {right:?} {left:?}"
        );
        let (right_col, left_col) = (right.0 / right.1, left.0 / left.1);
        assert!(
            right_col < img.width as f64 / 2.0 && left_col > img.width as f64 / 2.0,
            "{plane:?}: right lung at column {right_col:.0}, left at {left_col:.0} of {}",
            img.width
        );
    }
}

/// The font pixels (dark) of the `w` × `h` box at (`left`, `top`).
fn dark_mask(img: &RgbImage, left: usize, top: usize, w: usize, h: usize) -> Vec<bool> {
    let mut mask = Vec::with_capacity(w * h);
    for row in top..top + h {
        for col in left..left + w {
            mask.push(img.pixel(col, row).iter().all(|&c| c < 40));
        }
    }
    mask
}

#[test]
fn a_labelled_slice_names_its_edges_by_the_lps_convention_and_shows_its_legend() {
    use lungmotion::outputs::plots::{render_labelled_slice, LabelledSliceInput, LegendEntry};
    use lungmotion::outputs::raster_text::draw_text;
    let identity = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
    let marker = Vector3::from(CENTRE) + Vector3::from(MARKER_OFFSET);
    let ct = marker_ct(centred_geometry(identity), marker);
    let legend = [
        LegendEntry {
            label: "costal (slides on wall)".into(),
            colour: [40, 200, 80],
            outline: false,
        },
        LegendEntry {
            label: "right lung (outline)".into(),
            colour: [70, 150, 255],
            outline: true,
        },
    ];
    for (plane, letters) in [
        (SlicePlane::Axial, ['R', 'L', 'A', 'P']),
        (SlicePlane::Coronal, ['R', 'L', 'S', 'I']),
        (SlicePlane::Sagittal, ['A', 'P', 'S', 'I']),
    ] {
        let look = render_labelled_slice(&LabelledSliceInput {
            ct: &ct,
            overlays: &[],
            plane,
            position_lps_mm: marker[plane.normal_axis()],
            pixel_mm: 2.0,
            title: "A title",
            subtitle: "where",
            legend: &legend,
        })
        .unwrap();
        let img = through_png_file(&look.image, plane.name());
        // Each edge's letter, pixel for pixel as the font draws it.
        for ((letter, b), want) in look.orientation.iter().zip(letters) {
            assert_eq!(*letter, want, "{plane:?}");
            let mut glyph = RgbImage {
                width: b.width,
                height: b.height,
                pixels: vec![255; 3 * b.width * b.height],
            };
            draw_text(&mut glyph, &want.to_string(), 0, 0, 2, [0, 0, 0]);
            assert_eq!(
                dark_mask(&img, b.left, b.top, b.width, b.height),
                dark_mask(&glyph, 0, 0, b.width, b.height),
                "{plane:?}: letter {want} at {b:?}"
            );
        }
        // The marker (patient right, anterior, superior) sits on the side its letters say.
        let p = look.panel;
        let ([col, row], n) = bright_centroid(&crop(&img, p.left, p.top, p.width, p.height));
        assert!(n > 10, "{plane:?}: marker not drawn");
        assert!(
            col < p.width as f64 / 2.0 && row < p.height as f64 / 2.0,
            "{plane:?}: the marker (right, anterior, superior) is at ({col:.0}, {row:.0}) of \
             {}×{}, not on the {} and {} sides",
            p.width,
            p.height,
            letters[0],
            letters[2]
        );
        // The legend: a filled swatch, an outlined one, and text beside each.
        let l = look.legend;
        let legend_img = crop(&img, l.left, l.top, l.width, l.height);
        let count = |c: [u8; 3]| legend_img.pixels.chunks(3).filter(|p| **p == c).count();
        assert!(count([40, 200, 80]) >= 14 * 14, "{plane:?}: filled swatch");
        let outline = count([70, 150, 255]);
        assert!(
            (100..16 * 16).contains(&outline),
            "{plane:?}: outline swatch {outline}"
        );
        assert!(count([0, 0, 0]) > 300, "{plane:?}: legend text");
    }
}

fn through_png_file(image: &RgbImage, name: &str) -> RgbImage {
    let path = scratch_dir().join(format!("labelled-{name}.png"));
    write_png(&path, image).unwrap();
    read_png(&path).unwrap()
}

fn crop(img: &RgbImage, left: usize, top: usize, w: usize, h: usize) -> RgbImage {
    let mut pixels = Vec::with_capacity(3 * w * h);
    for row in top..top + h {
        pixels.extend_from_slice(
            &img.pixels[3 * (row * img.width + left)..3 * (row * img.width + left + w)],
        );
    }
    RgbImage {
        width: w,
        height: h,
        pixels,
    }
}
