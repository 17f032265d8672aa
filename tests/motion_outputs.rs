//! Breathing-pipeline outputs: curve and displacement PNGs (decoded back and checked pixel by
//! pixel where the data say things are), tracked-point files, field sampling.

use std::path::PathBuf;

use lungmotion::datasets::cip_chest_ct64;
use lungmotion::formats::nrrd::read_nrrd;
use lungmotion::model::{Material, VoxelGrid};
use lungmotion::outputs::displacement_field::{FieldGrid, FieldSampler};
use lungmotion::outputs::plots::{
    lung_centroid_lps_mm, render_breathing_curve, render_displacement_look, viridis, Arrow,
    BreathingCurve, DisplacementLook, DisplacementLookInput, ARROW_COLOUR, OVERLAY_OPACITY,
    SIMULATED_COLOUR, TARGET_COLOUR, TRACE_COLOUR,
};
use lungmotion::outputs::quicklook::{read_png, write_png, HuWindow, RgbImage};
use lungmotion::outputs::trajectories::{
    read_points, read_trajectories, TrackedPoint, TrajectoryFile, TRAJECTORY_HEADER,
};
use lungmotion::volume::{Volume, VolumeGeometry};
use nalgebra::Vector3;

fn scratch_dir(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!(
        "lungmotion-motion-outputs-{name}-{}",
        std::process::id()
    ));
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// Writes and decodes the image, checking the PNG round trip keeps size and pixels.
fn through_png(image: &RgbImage, path: &std::path::Path) -> RgbImage {
    write_png(path, image).unwrap();
    let back = read_png(path).unwrap();
    assert_eq!((back.width, back.height), (image.width, image.height));
    assert!(back == *image, "PNG round trip changed pixels");
    back
}

fn pixel_at(image: &RgbImage, p: [f64; 2]) -> [u8; 3] {
    image.pixel(p[0].round() as usize, p[1].round() as usize)
}

fn has_black_in(
    image: &RgbImage,
    cols: std::ops::Range<usize>,
    rows: std::ops::Range<usize>,
) -> bool {
    rows.into_iter()
        .any(|r| cols.clone().any(|c| image.pixel(c, r) == [0, 0, 0]))
}

/// A CIP-sized field (64×64×79 grid, ≈55 000 lung voxels) sampled repeatedly: prints the rate
/// and checks a rigid shift comes out exactly on every lung voxel and zero elsewhere.
#[test]
fn sampling_a_field_is_fast_and_exact() {
    let gm = VoxelGrid::filled_box(
        [16, 20, 24],
        [0.008; 3],
        Vector3::new(-0.064, -0.08, -0.096),
    )
    .to_mesh(Material::LUNG)
    .unwrap();
    let mesh = gm.mesh;
    let g =
        VolumeGeometry::axis_aligned([64, 64, 79], [4.17, 4.17, 3.99], [-131.0, -131.0, -157.0]);
    let mut lungs = Volume::filled(g, 0u8).unwrap();
    for k in 0..79 {
        for j in 0..64 {
            for i in 0..64 {
                let p = g.voxel_to_lps_mm(Vector3::new(i as f64, j as f64, k as f64));
                if p.x.abs() < 60.0 && p.y.abs() < 75.0 && p.z.abs() < 90.0 {
                    lungs.as_slice_mut()[g.index(i, j, k)] = 1;
                }
            }
        }
    }
    let sampler =
        FieldSampler::new(&lungs, &mesh, &vec![1; mesh.elements.len()], FieldGrid::Ct).unwrap();
    let shift = Vector3::new(0.001, -0.002, -0.012);
    let moved: Vec<_> = mesh.rest_positions_m.iter().map(|x| x + shift).collect();
    let mut field = vec![[f32::NAN; 3]; g.voxel_count()];
    let frames = 50;
    let start = std::time::Instant::now();
    for _ in 0..frames {
        sampler.sample_mm(&mesh, &moved, &mut field);
    }
    let per_field_ms = start.elapsed().as_secs_f64() * 1e3 / frames as f64;
    println!(
        "sample_mm: {:.3} ms per field ({} lung voxels of {})",
        per_field_ms,
        sampler.sampled_voxels(),
        g.voxel_count()
    );
    for (idx, u) in field.iter().enumerate() {
        let expected: [f32; 3] = if lungs.as_slice()[idx] != 0 {
            [1.0, -2.0, -12.0]
        } else {
            [0.0; 3]
        };
        for c in 0..3 {
            assert!((u[c] - expected[c]).abs() < 1e-4, "voxel {idx}: {u:?}");
        }
    }
}

/// Tidal breathing, 500 mL peak-to-peak every 4 s, sampled at 25 Hz for 8 s.
fn tidal_trace() -> (Vec<f64>, Vec<f64>) {
    let t: Vec<f64> = (0..=200).map(|i| i as f64 * 0.04).collect();
    let v = t
        .iter()
        .map(|t| 250.0 * (1.0 - (2.0 * std::f64::consts::PI * t / 4.0).cos()))
        .collect();
    (t, v)
}

#[test]
fn the_breathing_curve_shows_trace_targets_and_simulated_volumes_where_the_data_are() {
    let (trace_t, trace_v) = tidal_trace();
    let volume_at = |t: f64| 250.0 * (1.0 - (2.0 * std::f64::consts::PI * t / 4.0).cos());
    let frame_t: Vec<f64> = (0..8).map(|i| 0.5 + i as f64).collect();
    let target: Vec<f64> = frame_t.iter().map(|&t| volume_at(t)).collect();
    // The simulation falls 40 mL short: dot and ring are apart.
    let simulated: Vec<f64> = target.iter().map(|v| v - 40.0).collect();
    let curve = BreathingCurve {
        trace_time_s: &trace_t,
        trace_volume_ml: &trace_v,
        frame_time_s: &frame_t,
        frame_target_ml: &target,
        frame_simulated_ml: &simulated,
        title: "Breathing trace and frames",
    };
    let plot = render_breathing_curve(&curve).unwrap();
    let dir = scratch_dir("curve");
    let image = through_png(&plot.image, &dir.join("breathing-curve.png"));
    let axes = plot.axes;
    assert!(
        axes.volume_range_ml[0] < 0.0 && axes.volume_range_ml[1] > 500.0,
        "{axes:?}"
    );

    // Trace samples between frames lie on the blue line.
    for t in [1.0, 2.0, 4.04, 6.96] {
        assert_eq!(
            pixel_at(&image, axes.to_pixel(t, volume_at(t))),
            TRACE_COLOUR,
            "t = {t}"
        );
    }
    for (i, (&t, &v)) in frame_t.iter().zip(&target).enumerate() {
        let [x, y] = axes.to_pixel(t, v);
        // The ring's band (radii 4.5–7 px) on its four sides; the trace may cross one or two.
        let on_ring = [[5.75, 0.0], [-5.75, 0.0], [0.0, 5.75], [0.0, -5.75]]
            .iter()
            .filter(|d| pixel_at(&image, [x + d[0], y + d[1]]) == TARGET_COLOUR)
            .count();
        assert!(on_ring >= 2, "frame {i}: {on_ring} ring sides in orange");
        assert_eq!(
            pixel_at(&image, axes.to_pixel(t, simulated[i])),
            SIMULATED_COLOUR,
            "frame {i}"
        );
        // 150 mL above the target nothing is drawn but the background or a grid line.
        let empty = pixel_at(&image, axes.to_pixel(t, v + 150.0));
        assert!(
            empty == [255, 255, 255] || empty == [225, 225, 225],
            "frame {i}: {empty:?}"
        );
    }
    // Title, tick labels and axis labels are drawn (black glyph pixels where text goes).
    assert!(has_black_in(&image, 300..660, 8..26), "no title");
    let left = axes.left_px as usize;
    assert!(
        has_black_in(
            &image,
            30..left - 8,
            axes.top_px as usize..axes.bottom_px as usize
        ),
        "no volume ticks"
    );
    assert!(has_black_in(&image, 0..30, 100..400), "no volume label");
    assert!(
        has_black_in(
            &image,
            left..axes.right_px as usize,
            axes.bottom_px as usize + 8..image.height
        ),
        "no time ticks"
    );

    // Without simulated volumes the plot still draws; inconsistent inputs are refused.
    assert!(render_breathing_curve(&BreathingCurve {
        frame_simulated_ml: &[],
        ..curve
    })
    .is_ok());
    let e = render_breathing_curve(&BreathingCurve {
        frame_target_ml: &target[1..],
        ..curve
    })
    .unwrap_err();
    assert!(
        e.to_string().contains("8 frame times for 7 frame targets"),
        "{e}"
    );
    let mut backwards = trace_t.clone();
    backwards.swap(3, 4);
    let e = render_breathing_curve(&BreathingCurve {
        trace_time_s: &backwards,
        ..curve
    })
    .unwrap_err();
    assert!(e.to_string().contains("trace times must increase"), "{e}");
}

/// A small synthetic chest: 40 HU body, two −800 HU lung boxes either side of x = 0, a
/// 1000 HU ball (outside the lungs) to locate the slice, and lung labels 1 (right, −x) and
/// 2 (left, +x).
fn synthetic_chest() -> (Volume<f32>, Volume<u8>, [f64; 3]) {
    let g = VolumeGeometry::axis_aligned([40, 12, 44], [4.0, 5.0, 4.0], [-78.0, -10.0, -186.0]);
    let ball = [0.0, 17.5, -60.0];
    let mut ct = Volume::filled(g, 40.0f32).unwrap();
    let mut lungs = Volume::filled(g, 0u8).unwrap();
    for k in 0..44 {
        for j in 0..12 {
            for i in 0..40 {
                let p = g.voxel_to_lps_mm(Vector3::new(i as f64, j as f64, k as f64));
                let idx = g.index(i, j, k);
                if (12.0..70.0).contains(&p.x.abs()) && (-170.0..-30.0).contains(&p.z) {
                    ct.as_slice_mut()[idx] = -800.0;
                    lungs.as_slice_mut()[idx] = if p.x < 0.0 { 1 } else { 2 };
                }
                if (p - Vector3::from(ball)).norm() < 7.0 {
                    ct.as_slice_mut()[idx] = 1000.0;
                }
            }
        }
    }
    (ct, lungs, ball)
}

fn field_of(lungs: &Volume<u8>, right_mm: [f32; 3], left_mm: [f32; 3]) -> Vec<[f32; 3]> {
    lungs
        .as_slice()
        .iter()
        .map(|&l| match l {
            1 => right_mm,
            2 => left_mm,
            _ => [0.0; 3],
        })
        .collect()
}

/// Arrow pixels are drawn from the tail to the head, with barbs at the head only.
fn assert_arrow_drawn(image: &RgbImage, a: &Arrow) {
    let (dx, dy) = (a.head_px[0] - a.tail_px[0], a.head_px[1] - a.tail_px[1]);
    let len = dx.hypot(dy);
    let (ux, uy) = (dx / len, dy / len);
    let at = |along: f64, across: f64| {
        pixel_at(
            image,
            [
                a.tail_px[0] + along * ux - across * uy,
                a.tail_px[1] + along * uy + across * ux,
            ],
        )
    };
    assert_eq!(at(0.5 * len, 0.0), ARROW_COLOUR, "{a:?}: shaft");
    assert_ne!(at(-3.0, 0.0), ARROW_COLOUR, "{a:?}: behind the tail");
    let barb = (0.35 * len).clamp(3.0, 8.0);
    let (back, side) = (0.8 * barb * 30f64.to_radians().cos(), 0.8 * barb * 0.5);
    for s in [-1.0, 1.0] {
        assert_eq!(
            at(len - back, s * side),
            ARROW_COLOUR,
            "{a:?}: barb at the head"
        );
        assert_ne!(at(back, s * side), ARROW_COLOUR, "{a:?}: barb at the tail");
    }
}

#[test]
fn the_displacement_look_colours_the_lungs_and_points_arrows_the_way_the_field_goes() {
    let (ct, lungs, ball) = synthetic_chest();
    let y = 17.5;
    let dir = scratch_dir("look");
    // Everything moves inferiorly (−z): right lung 4 mm, left lung 8 mm.
    let field = field_of(&lungs, [0.0, 0.0, -4.0], [0.0, 0.0, -8.0]);
    let input = DisplacementLookInput {
        ct: &ct,
        lungs: &lungs,
        displacement_mm: &field,
        coronal_y_mm: y,
        colour_max_mm: Some(10.0),
        title: "End-inhale displacement",
    };
    let look: DisplacementLook = render_displacement_look(&input).unwrap();
    let image = through_png(&look.image, &dir.join("displacement-down.png"));
    let panel = look.panel;
    // The 4 mm CT is refined 8 times (0.5 mm pixels) so arrows have room.
    assert_eq!(
        (panel.pixel_mm, panel.width_px, panel.height_px),
        (0.5, 320, 352)
    );

    // The panel sits on the CT exactly as the ingest quick look: the bone ball is white.
    assert_eq!(pixel_at(&image, panel.image_px_of_lps(ball)), [255; 3]);
    // Radiological convention: the patient's right (−x) on the image's left, superior up.
    let right = panel.image_px_of_lps([-40.0, y, -100.0]);
    let left = panel.image_px_of_lps([40.0, y, -100.0]);
    let top = panel.image_px_of_lps([-40.0, y, -40.0]);
    assert!(right[0] < left[0] && top[1] < right[1]);

    // Lung pixels blend the viridis colour of |u| over the −800 HU grey; the most common
    // colour of each lung is exactly that blend.
    let blend = |u_mm: f32| {
        let grey = HuWindow::LUNG.grey(-800.0) as f32;
        viridis(u_mm / 10.0)
            .map(|c| (grey * (1.0 - OVERLAY_OPACITY) + c as f32 * OVERLAY_OPACITY).round() as u8)
    };
    for (x_lo, x_hi, u_mm) in [(-66.0, -16.0, 4.0), (16.0, 66.0, 8.0)] {
        let a = panel.image_px_of_lps([x_lo, y, -166.0]);
        let b = panel.image_px_of_lps([x_hi, y, -34.0]);
        let mut counts = std::collections::HashMap::new();
        for row in b[1] as usize..a[1] as usize {
            for col in a[0] as usize..b[0] as usize {
                *counts.entry(image.pixel(col, row)).or_insert(0usize) += 1;
            }
        }
        let (&common, _) = counts.iter().max_by_key(|(_, &n)| n).unwrap();
        assert_eq!(common, blend(u_mm), "lung at x {x_lo}..{x_hi}");
    }
    // Between the lungs (40 HU, no field) the CT grey shows through.
    let grey = HuWindow::LUNG.grey(40.0);
    assert_eq!(
        pixel_at(&image, panel.image_px_of_lps([0.0, y, -120.0])),
        [grey; 3]
    );

    // Arrows point down the image, with the length the scale states, and are drawn so.
    assert!(look.arrows.len() > 20, "{} arrows", look.arrows.len());
    for a in &look.arrows {
        let u = -a.displacement_mm[2] as f64;
        assert!((a.head_px[0] - a.tail_px[0]).abs() < 1e-9, "{a:?}");
        assert!(
            (a.head_px[1] - a.tail_px[1] - u * look.arrow_px_per_mm).abs() < 1e-9,
            "{a:?}"
        );
        assert_arrow_drawn(&image, a);
    }
    // The colour bar and the labels are there.
    let bar_top = viridis(1.0);
    assert!(
        image.pixels.chunks_exact(3).any(|p| p == bar_top),
        "no colour bar"
    );
    assert!(has_black_in(&image, 40..400, 8..24), "no title");

    // Towards the patient's left (+x): arrows point right on the image.
    let field = field_of(&lungs, [5.0, 0.0, 0.0], [5.0, 0.0, 0.0]);
    let look = render_displacement_look(&DisplacementLookInput {
        displacement_mm: &field,
        ..input
    })
    .unwrap();
    let image = through_png(&look.image, &dir.join("displacement-left.png"));
    assert!(!look.arrows.is_empty());
    for a in &look.arrows {
        assert!(
            a.head_px[0] - a.tail_px[0] > 2.0 && (a.head_px[1] - a.tail_px[1]).abs() < 1e-9,
            "{a:?}"
        );
        assert_arrow_drawn(&image, a);
    }

    // Mismatched inputs are refused with the reason.
    let e = render_displacement_look(&DisplacementLookInput {
        displacement_mm: &field[1..],
        ..input
    })
    .unwrap_err();
    assert!(e.to_string().contains("displacements for"), "{e}");
    let mut nan_field = field.clone();
    nan_field[7] = [f32::NAN, 0.0, 0.0];
    let e = render_displacement_look(&DisplacementLookInput {
        displacement_mm: &nan_field,
        ..input
    })
    .unwrap_err();
    assert!(e.to_string().contains("voxel 7"), "{e}");
    let e = render_displacement_look(&DisplacementLookInput {
        coronal_y_mm: 500.0,
        ..input
    })
    .unwrap_err();
    assert!(e.to_string().contains("outside the scan"), "{e}");
}

/// Frame number, time (s), displacement of each of two points (mm), inside-lung flags.
type Frame = (usize, f64, [[f64; 3]; 2], [bool; 2]);

#[test]
fn trajectories_round_trip_through_a_file_written_frame_by_frame() {
    let dir = scratch_dir("trajectories");
    let points_path = dir.join("points.csv");
    std::fs::write(
        &points_path,
        "name,x_mm,y_mm,z_mm\ntumour,-42.5,10.25,-120\ncarina,1.5,-20,-60\n",
    )
    .unwrap();
    let points = read_points(&points_path).unwrap();
    assert_eq!(points.len(), 2);

    let path = dir.join("trajectories.csv");
    let mut file = TrajectoryFile::create(&path, &points).unwrap();
    let frames: Vec<Frame> = (0..5)
        .map(|f| {
            let t = 0.4 * f as f64 + 0.123_456;
            let s = (t * 1.3).sin();
            (
                2 * f,
                t,
                [[0.5 * s, 1.25 * s, -12.345_67 * s], [0.0, 0.1 * s, -s]],
                [true, f % 2 == 0],
            )
        })
        .collect();
    for (f, t, d, inside) in &frames {
        file.write_frame(*f, *t, d, inside).unwrap();
        // Until finished only the partial file exists.
        assert!(!path.exists());
    }
    assert_eq!(file.finish().unwrap(), path);
    let mut partial = path.as_os_str().to_owned();
    partial.push(".partial");
    assert!(!PathBuf::from(partial).exists());

    let text = std::fs::read_to_string(&path).unwrap();
    assert_eq!(text.lines().next(), Some(TRAJECTORY_HEADER));
    let samples = read_trajectories(&path).unwrap();
    assert_eq!(samples.len(), 10);
    for (n, s) in samples.iter().enumerate() {
        let (f, t, d, inside) = &frames[n / 2];
        let p: &TrackedPoint = &points[n % 2];
        assert_eq!(
            (s.frame, s.point.as_str(), s.inside_lung),
            (*f, p.name.as_str(), inside[n % 2])
        );
        assert!((s.time_s - t).abs() < 1e-6);
        for (a, d) in d[n % 2].iter().enumerate() {
            assert!((s.displacement_mm[a] - d).abs() <= 5e-5, "{s:?}");
            assert!(
                (s.position_lps_mm[a] - (p.rest_lps_mm[a] + d)).abs() <= 5e-5,
                "{s:?}"
            );
        }
    }

    // Damaged files are refused naming file and line.
    let bad = dir.join("bad.csv");
    std::fs::write(&bad, text.replacen(",true", ",maybe", 1)).unwrap();
    let e = read_trajectories(&bad).unwrap_err().to_string();
    assert!(
        e.contains("bad.csv") && e.contains("line 2: inside_lung \"maybe\""),
        "{e}"
    );
    std::fs::write(&bad, "name,x_mm,y_mm,z_mm\ntumour,1,2,3\ntumour,4,5,6\n").unwrap();
    let e = read_points(&bad).unwrap_err().to_string();
    assert!(
        e.contains("bad.csv: line 3: point name \"tumour\" already used on line 2"),
        "{e}"
    );
    std::fs::write(&bad, "x,y,z\n1,2,3\n").unwrap();
    let e = read_points(&bad).unwrap_err().to_string();
    assert!(
        e.contains("line 1: header `name,x_mm,y_mm,z_mm` required"),
        "{e}"
    );
}

/// The CIP chest CT with a synthetic end-inhale field (the base descends up to 15 mm,
/// the apex stays): a picture to look at, and its basic facts checked.
#[test]
#[cfg_attr(
    not(shared_data),
    ignore = "needs the shared CT data (../shared/data or LUNGMOTION_SHARED_DATA; see README)"
)]
fn the_cip_chest_displacement_look_renders() {
    let Some(dir) = cip_chest_ct64() else {
        println!("skipped: shared data not found");
        return;
    };
    let ct = read_nrrd(&dir.join("ct-64.nrrd")).unwrap();
    let lungs = read_nrrd(&dir.join("wholeLung-64.nrrd"))
        .unwrap()
        .map(|v| u8::from(v > 0.0));
    let g = lungs.geometry;
    let centroid = lung_centroid_lps_mm(&lungs).unwrap();
    let (z_lo, z_hi) = lungs
        .as_slice()
        .iter()
        .enumerate()
        .filter(|(_, &l)| l != 0)
        .map(|(idx, _)| {
            g.origin_lps_mm[2] + (idx / (g.dims[0] * g.dims[1])) as f64 * g.spacing_mm[2]
        })
        .fold((f64::MAX, f64::MIN), |(a, b), z| (a.min(z), b.max(z)));
    let field: Vec<[f32; 3]> = lungs
        .as_slice()
        .iter()
        .enumerate()
        .map(|(idx, &l)| {
            if l == 0 {
                return [0.0; 3];
            }
            let (i, k) = (idx % g.dims[0], idx / (g.dims[0] * g.dims[1]));
            let p = g.voxel_to_lps_mm(Vector3::new(i as f64, 0.0, k as f64));
            let depth = ((z_hi - p.z) / (z_hi - z_lo)) as f32;
            let lateral = ((p.x - centroid[0]) / 150.0) as f32;
            [4.0 * lateral * depth, -2.0 * depth, -15.0 * depth * depth]
        })
        .collect();
    let look = render_displacement_look(&DisplacementLookInput {
        ct: &ct,
        lungs: &lungs,
        displacement_mm: &field,
        coronal_y_mm: centroid[1],
        colour_max_mm: None,
        title: "CIP chest: synthetic end-inhale displacement",
    })
    .unwrap();
    let out = scratch_dir("cip").join("cip-displacement.png");
    let image = through_png(&look.image, &out);
    println!(
        "wrote {} ({}×{}, {} arrows)",
        out.display(),
        image.width,
        image.height,
        look.arrows.len()
    );
    assert!(
        look.colour_max_mm >= 15.0 && look.colour_max_mm <= 20.0,
        "{}",
        look.colour_max_mm
    );
    assert!(look.arrows.len() > 50);
    // Arrows near the base point down more than those near the apex.
    let (mut low, mut high) = (0.0, 0.0);
    for a in &look.arrows {
        let dz = a.head_px[1] - a.tail_px[1];
        if a.tail_px[1] > (look.panel.top_px + look.panel.height_px / 2) as f64 {
            low += dz;
        } else {
            high += dz;
        }
    }
    assert!(low > high && low > 0.0, "{low} vs {high}");
}
