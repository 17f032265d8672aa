//! The procedural thorax phantom against anatomy: sizes, sides, heights, HU per tissue, airway
//! connectivity, determinism, and a quick-look picture to check by eye.

use std::collections::VecDeque;

use lungmotion::phantom::{
    generate_thorax_phantom, Phantom, PhantomSettings, Tissue, Tumour, AIR_HU, BONE_HU, LIVER_HU,
    LUNG_HU, TUMOUR_HU,
};
use lungmotion::volume::Volume;
use nalgebra::Vector3;

fn default_phantom() -> Phantom {
    generate_thorax_phantom(&PhantomSettings::default()).expect("default phantom")
}

fn label_at(truth: &Volume<u8>, p_lps_mm: [f64; 3]) -> u8 {
    let ijk = truth.geometry.lps_mm_to_voxel(Vector3::from(p_lps_mm));
    let [nx, ny, nz] = truth.dims();
    let idx = [ijk.x, ijk.y, ijk.z].map(|v| v.round());
    assert!(
        idx.iter()
            .zip([nx, ny, nz])
            .all(|(&v, n)| v >= 0.0 && v < n as f64),
        "{p_lps_mm:?} is outside the grid"
    );
    truth.get(idx[0] as usize, idx[1] as usize, idx[2] as usize)
}

/// LPS centroid of the voxels with `code`.
fn centroid_lps_mm(truth: &Volume<u8>, code: u8) -> [f64; 3] {
    let [nx, ny, _] = truth.dims();
    let mut sum = Vector3::zeros();
    let mut n = 0usize;
    for (index, _) in truth
        .as_slice()
        .iter()
        .enumerate()
        .filter(|(_, &l)| l == code)
    {
        let ijk = Vector3::new(
            (index % nx) as f64,
            ((index / nx) % ny) as f64,
            (index / (nx * ny)) as f64,
        );
        sum += truth.geometry.voxel_to_lps_mm(ijk);
        n += 1;
    }
    assert!(n > 0, "no voxel with label {code}");
    (sum / n as f64).into()
}

/// The 6-neighbours of voxel `index` inside the grid.
fn neighbours(dims: [usize; 3], index: usize) -> impl Iterator<Item = usize> {
    let [nx, ny, nz] = dims;
    let (i, j, k) = (index % nx, (index / nx) % ny, index / (nx * ny));
    let steps: [(bool, isize); 6] = [
        (i > 0, -1),
        (i + 1 < nx, 1),
        (j > 0, -(nx as isize)),
        (j + 1 < ny, nx as isize),
        (k > 0, -((nx * ny) as isize)),
        (k + 1 < nz, (nx * ny) as isize),
    ];
    steps
        .into_iter()
        .filter(|(ok, _)| *ok)
        .map(move |(_, s)| (index as isize + s) as usize)
}

fn mean(values: impl Iterator<Item = f64>) -> f64 {
    let (s, n) = values.fold((0.0, 0usize), |(s, n), v| (s + v, n + 1));
    assert!(n > 0, "mean of nothing");
    s / n as f64
}

#[test]
fn default_phantom_is_small_enough_to_commit() {
    let started = std::time::Instant::now();
    let p = default_phantom();
    println!(
        "generated in {:.1} ms",
        started.elapsed().as_secs_f64() * 1e3
    );
    let count = p.ct.geometry.voxel_count();
    println!(
        "default phantom: grid {:?}, {count} voxels, {:.2} MB as int16",
        p.ct.dims(),
        count as f64 * 2.0 / 1e6
    );
    assert!(count <= 450_000, "{count} voxels");
    assert_eq!(p.ct.geometry, p.truth.geometry);
    assert_eq!(
        p.ct.geometry.direction_lps,
        [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]
    );
    let counted: usize = p.description.label_counts.iter().map(|c| c.voxels).sum();
    assert_eq!(counted, count);
    for c in &p.description.label_counts {
        let actual = p.truth.as_slice().iter().filter(|&&l| l == c.code).count();
        assert_eq!(actual, c.voxels, "label {}", c.name);
        assert!(
            c.voxels > 0,
            "label {} is absent from the default phantom",
            c.name
        );
    }
    let json = serde_json::to_string(&p.description).unwrap();
    assert!(json.contains("right_lung_volume_ml") && json.contains("carina_lps_mm"));
}

#[test]
fn same_seed_is_bit_identical_and_another_seed_changes_only_the_noise() {
    let settings = PhantomSettings::default();
    let a = generate_thorax_phantom(&settings).unwrap();
    let b = generate_thorax_phantom(&settings).unwrap();
    assert!(a
        .ct
        .as_slice()
        .iter()
        .zip(b.ct.as_slice())
        .all(|(x, y)| x.to_bits() == y.to_bits()));
    assert_eq!(a.truth, b.truth);
    // The thread count does not matter either.
    let single = rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .build()
        .unwrap()
        .install(|| generate_thorax_phantom(&settings).unwrap());
    assert!(a
        .ct
        .as_slice()
        .iter()
        .zip(single.ct.as_slice())
        .all(|(x, y)| x.to_bits() == y.to_bits()));
    assert_eq!(a.truth, single.truth);

    let other = generate_thorax_phantom(&PhantomSettings {
        seed: settings.seed + 1,
        ..settings.clone()
    })
    .unwrap();
    assert_eq!(a.truth, other.truth, "the seed must not move anatomy");
    // Away from the −1024 clamp in air, the difference is two independent noises.
    let diffs: Vec<f64> =
        a.ct.as_slice()
            .iter()
            .zip(other.ct.as_slice())
            .filter(|(x, y)| x.min(**y) > AIR_HU + 100.0)
            .map(|(x, y)| (x - y) as f64)
            .collect();
    let changed = diffs.iter().filter(|d| d.abs() > 0.0).count();
    assert!(
        changed > diffs.len() / 2,
        "another seed changed only {changed} voxels"
    );
    let m = mean(diffs.iter().copied());
    let sd = mean(diffs.iter().map(|d| (d - m).powi(2))).sqrt();
    let expected_sd = std::f64::consts::SQRT_2 * settings.noise_hu as f64;
    println!("seed difference: mean {m:.3} HU, sd {sd:.2} HU (expected {expected_sd:.2})");
    assert!(m.abs() < 0.5, "mean difference {m}");
    assert!((sd - expected_sd).abs() < 0.05 * expected_sd, "sd {sd}");

    // Without noise, the seed changes nothing at all.
    let quiet = |seed| {
        generate_thorax_phantom(&PhantomSettings {
            noise_hu: 0.0,
            seed,
            ..settings.clone()
        })
        .unwrap()
    };
    assert_eq!(quiet(3).ct, quiet(4).ct);
}

#[test]
fn lungs_have_plausible_volumes_sides_and_heights() {
    let p = default_phantom();
    let d = &p.description;
    println!(
        "lung volumes: right {:.0} mL, left {:.0} mL",
        d.right_lung_volume_ml, d.left_lung_volume_ml
    );
    for v in [d.right_lung_volume_ml, d.left_lung_volume_ml] {
        assert!((1500.0..=3500.0).contains(&v), "lung volume {v} mL");
    }
    assert!(d.right_lung_volume_ml > d.left_lung_volume_ml);

    let right = centroid_lps_mm(&p.truth, Tissue::RightLung.code());
    let left = centroid_lps_mm(&p.truth, Tissue::LeftLung.code());
    println!("centroids: right {right:.1?}, left {left:.1?}");
    assert!(right[0] < -40.0, "right lung centroid at x = {}", right[0]);
    assert!(left[0] > 40.0, "left lung centroid at x = {}", left[0]);

    let l = &d.landmarks;
    for (apex, base) in [
        (l.right_lung_apex_lps_mm, l.right_lung_base_lps_mm),
        (l.left_lung_apex_lps_mm, l.left_lung_base_lps_mm),
    ] {
        let height = apex[2] - base[2];
        assert!(
            (150.0..=260.0).contains(&height),
            "apex {apex:?} base {base:?}"
        );
    }
    // The right dome stands higher than the left.
    assert!(l.right_lung_base_lps_mm[2] > l.left_lung_base_lps_mm[2]);
    let carina = l.carina_lps_mm;
    assert!(carina[2] > l.right_lung_base_lps_mm[2] && carina[2] > l.left_lung_base_lps_mm[2]);
    assert!(carina[2] < l.right_lung_apex_lps_mm[2] && carina[2] < l.left_lung_apex_lps_mm[2]);
    assert!(right[0] < carina[0] && carina[0] < left[0]);
}

#[test]
fn landmarks_sit_on_the_labelled_anatomy() {
    let p = default_phantom();
    let l = &p.description.landmarks;
    let s = p.truth.geometry.spacing_mm[2];
    let (rl, ll) = (Tissue::RightLung.code(), Tissue::LeftLung.code());
    for (apex, base, lung) in [
        (l.right_lung_apex_lps_mm, l.right_lung_base_lps_mm, rl),
        (l.left_lung_apex_lps_mm, l.left_lung_base_lps_mm, ll),
    ] {
        let below_apex = label_at(&p.truth, [apex[0], apex[1], apex[2] - 1.5 * s]);
        let above_apex = label_at(&p.truth, [apex[0], apex[1], apex[2] + 1.5 * s]);
        assert_eq!(below_apex, lung, "just below the apex {apex:?}");
        assert_ne!(above_apex, lung, "above the apex {apex:?}");
        let above_base = label_at(&p.truth, [base[0], base[1], base[2] + 1.5 * s]);
        let below_base = label_at(&p.truth, [base[0], base[1], base[2] - 1.5 * s]);
        assert_eq!(above_base, lung, "just above the base {base:?}");
        assert_eq!(
            below_base,
            Tissue::Abdomen.code(),
            "below the base {base:?}"
        );
        // Nothing of this lung lies above its apex.
        let top = p
            .truth
            .as_slice()
            .iter()
            .enumerate()
            .filter(|(_, &c)| c == lung)
            .map(|(i, _)| i / (p.truth.dims()[0] * p.truth.dims()[1]))
            .max()
            .unwrap();
        let top_z = p.truth.geometry.origin_lps_mm[2] + top as f64 * s;
        assert!(
            top_z <= apex[2] && top_z > apex[2] - 2.0 * s,
            "top slice {top_z} vs apex {apex:?}"
        );
    }
    assert_eq!(label_at(&p.truth, l.carina_lps_mm), Tissue::Airway.code());
}

#[test]
fn tumour_lies_inside_the_right_lung() {
    let p = default_phantom();
    let code = Tissue::Tumour.code();
    let centre = p
        .description
        .landmarks
        .tumour_centre_lps_mm
        .expect("default tumour");
    assert_eq!(label_at(&p.truth, centre), code);
    let dims = p.truth.dims();
    let mut touching = [0usize; 9];
    let mut tumour_voxels = 0;
    for (i, _) in p
        .truth
        .as_slice()
        .iter()
        .enumerate()
        .filter(|(_, &l)| l == code)
    {
        tumour_voxels += 1;
        for n in neighbours(dims, i) {
            touching[p.truth.as_slice()[n] as usize] += 1;
        }
    }
    let radius = PhantomSettings::default().tumour.unwrap().radius_mm;
    let sphere_voxels =
        4.0 / 3.0 * std::f64::consts::PI * radius.powi(3) / p.truth.geometry.voxel_volume_mm3();
    println!("tumour: {tumour_voxels} voxels (sphere {sphere_voxels:.1}), neighbours {touching:?}");
    assert!((tumour_voxels as f64 - sphere_voxels).abs() < 0.3 * sphere_voxels);
    let outside: usize = touching
        .iter()
        .enumerate()
        .filter(|(c, _)| *c as u8 != code && *c as u8 != Tissue::RightLung.code())
        .map(|(_, n)| n)
        .sum();
    assert_eq!(
        outside, 0,
        "the tumour touches something other than the right lung"
    );
    assert!(touching[Tissue::RightLung as usize] > 0);

    // Tumour CT numbers match its label.
    let hu = mean(
        p.truth
            .as_slice()
            .iter()
            .zip(p.ct.as_slice())
            .filter(|(&l, _)| l == code)
            .map(|(_, &h)| h as f64),
    );
    assert!(
        hu > (LUNG_HU + TUMOUR_HU) as f64 / 2.0,
        "tumour mean {hu} HU"
    );

    // No tumour requested, none drawn; the lung takes its place.
    let none = generate_thorax_phantom(&PhantomSettings {
        tumour: None,
        ..PhantomSettings::default()
    })
    .unwrap();
    assert!(!none.truth.as_slice().contains(&code));
    assert_eq!(label_at(&none.truth, centre), Tissue::RightLung.code());
    assert!(none.description.landmarks.tumour_centre_lps_mm.is_none());
}

#[test]
fn labels_agree_with_ct_numbers() {
    let p = default_phantom();
    let dims = p.truth.dims();
    // Interior voxels (all 6 neighbours share the label) carry the tissue's nominal CT number.
    let interior_mean = |code: u8| {
        mean(
            p.truth
                .as_slice()
                .iter()
                .enumerate()
                .filter(|&(i, &l)| {
                    l == code && neighbours(dims, i).all(|n| p.truth.as_slice()[n] == code)
                })
                .map(|(i, _)| p.ct.as_slice()[i] as f64),
        )
    };
    for (tissue, nominal, tolerance) in [
        (Tissue::RightLung, LUNG_HU, 40.0),
        (Tissue::LeftLung, LUNG_HU, 40.0),
        (Tissue::Abdomen, LIVER_HU, 10.0),
        (Tissue::OutsideAir, AIR_HU, 10.0),
        (Tissue::Bone, BONE_HU, 60.0),
    ] {
        let m = interior_mean(tissue.code());
        println!(
            "{}: interior mean {m:.1} HU (nominal {nominal})",
            tissue.name()
        );
        assert!(
            (m - nominal as f64).abs() < tolerance,
            "{}: {m} HU",
            tissue.name()
        );
    }
    // Every bone voxel is bright, every lung and airway voxel dark.
    let all_mean = |code: u8| {
        mean(
            p.truth
                .as_slice()
                .iter()
                .zip(p.ct.as_slice())
                .filter(|(&l, _)| l == code)
                .map(|(_, &h)| h as f64),
        )
    };
    let bone = all_mean(Tissue::Bone.code());
    let airway = all_mean(Tissue::Airway.code());
    println!("all bone voxels {bone:.0} HU, all airway voxels {airway:.0} HU");
    assert!(bone > 300.0);
    assert!(airway < -700.0);
    for lung in [Tissue::RightLung, Tissue::LeftLung] {
        let m = all_mean(lung.code());
        assert!((-900.0..-650.0).contains(&m), "{}: {m} HU", lung.name());
    }
}

#[test]
fn trachea_reaches_both_lungs_through_the_bronchi() {
    let p = default_phantom();
    let dims = p.truth.dims();
    let [nx, ny, nz] = dims;
    let airway = Tissue::Airway.code();
    // Seeds: airway voxels in the top slice (the trachea leaves the field of view there).
    let top = (nz - 1) * nx * ny;
    let seeds: Vec<usize> = (top..top + nx * ny)
        .filter(|&i| p.truth.as_slice()[i] == airway)
        .collect();
    assert!(!seeds.is_empty(), "no trachea in the top slice");
    let mut seen = vec![false; p.truth.as_slice().len()];
    let mut queue: VecDeque<usize> = seeds.into_iter().collect();
    for &s in &queue {
        seen[s] = true;
    }
    let mut reached = [false; 9];
    while let Some(v) = queue.pop_front() {
        for n in neighbours(dims, v) {
            let l = p.truth.as_slice()[n];
            reached[l as usize] = true;
            if l == airway && !seen[n] {
                seen[n] = true;
                queue.push_back(n);
            }
        }
    }
    let trachea_voxels = seen.iter().filter(|&&s| s).count();
    println!("airway tree from the top: {trachea_voxels} voxels");
    assert!(
        reached[Tissue::RightLung as usize],
        "the airway does not reach the right lung"
    );
    assert!(
        reached[Tissue::LeftLung as usize],
        "the airway does not reach the left lung"
    );
    // The lungs are separate: no lung voxel touches the other lung.
    let touching = p
        .truth
        .as_slice()
        .iter()
        .enumerate()
        .filter(|(_, &l)| l == Tissue::RightLung.code())
        .any(|(i, _)| {
            neighbours(dims, i).any(|n| p.truth.as_slice()[n] == Tissue::LeftLung.code())
        });
    assert!(!touching, "the lungs touch each other");
}

#[test]
fn bad_settings_are_refused_with_the_reason() {
    let ok = PhantomSettings::default();
    let cases = [
        (
            PhantomSettings {
                spacing_mm: [0.0, 5.0, 5.0],
                ..ok.clone()
            },
            "spacing",
        ),
        (
            PhantomSettings {
                field_of_view_mm: [f64::NAN, 5.0, 5.0],
                ..ok.clone()
            },
            "field of view",
        ),
        (
            PhantomSettings {
                spacing_mm: [0.01; 3],
                ..ok.clone()
            },
            "voxels",
        ),
        (
            PhantomSettings {
                noise_hu: -1.0,
                ..ok.clone()
            },
            "noise",
        ),
        (
            PhantomSettings {
                tumour: Some(Tumour {
                    centre_lps_mm: [0.0; 3],
                    radius_mm: 0.0,
                }),
                ..ok.clone()
            },
            "tumour",
        ),
    ];
    for (settings, word) in cases {
        let e = generate_thorax_phantom(&settings).unwrap_err().to_string();
        assert!(e.contains(word), "{e}");
    }
}

/// Writes the mid-coronal, mid-sagittal, carina-level and heart-level axial slices as 8-bit PNG (window
/// −1000…+400 HU) into a temporary directory, for a look by eye.
#[test]
fn quick_look_slices_are_written() {
    let p = default_phantom();
    let dir = std::env::temp_dir().join("lungmotion-phantom-quicklook");
    std::fs::create_dir_all(&dir).unwrap();
    let g = p.ct.geometry;
    let [nx, ny, nz] = g.dims;
    let centre = g.lps_mm_to_voxel(Vector3::new(-70.0, 20.0, 0.0));
    let (ci, cj, ck) = (
        (centre.x.round() as usize).min(nx - 1),
        (g.lps_mm_to_voxel(Vector3::new(0.0, 20.0, 0.0)).y.round() as usize).min(ny - 1),
        (centre.z.round() as usize).min(nz - 1),
    );
    let grey = |hu: f32| (((hu + 1000.0) / 1400.0).clamp(0.0, 1.0) * 255.0) as u8;
    // Superior at the top, patient right on the image left (radiological display).
    let coronal: Vec<u8> = (0..nz)
        .rev()
        .flat_map(|k| (0..nx).map(move |i| (i, k)))
        .map(|(i, k)| grey(p.ct.get(i, cj, k)))
        .collect();
    let sagittal: Vec<u8> = (0..nz)
        .rev()
        .flat_map(|k| (0..ny).map(move |j| (j, k)))
        .map(|(j, k)| grey(p.ct.get(ci, j, k)))
        .collect();
    let axial = |k: usize| -> Vec<u8> {
        (0..ny)
            .flat_map(|j| (0..nx).map(move |i| (i, j)))
            .map(|(i, j)| grey(p.ct.get(i, j, k)))
            .collect()
    };
    let heart_k = (g.lps_mm_to_voxel(Vector3::new(0.0, 0.0, -80.0)).z.round() as usize).min(nz - 1);
    for (name, w, h, pixels) in [
        ("coronal.png", nx, nz, coronal),
        ("sagittal_right.png", ny, nz, sagittal),
        ("axial_carina.png", nx, ny, axial(ck)),
        ("axial_heart.png", nx, ny, axial(heart_k)),
    ] {
        // Upscaled ×4 (nearest) so 5 mm voxels are visible.
        let (w, h, pixels) = upscale(w, h, &pixels, 4);
        let path = dir.join(name);
        let file = std::io::BufWriter::new(std::fs::File::create(&path).unwrap());
        let mut enc = png::Encoder::new(file, w as u32, h as u32);
        enc.set_color(png::ColorType::Grayscale);
        enc.set_depth(png::BitDepth::Eight);
        enc.write_header()
            .unwrap()
            .write_image_data(&pixels)
            .unwrap();
        println!("wrote {}", path.display());
        assert!(std::fs::metadata(&path).unwrap().len() > 100);
    }
}

fn upscale(w: usize, h: usize, pixels: &[u8], f: usize) -> (usize, usize, Vec<u8>) {
    let out = (0..h * f)
        .flat_map(|y| (0..w * f).map(move |x| pixels[(y / f) * w + x / f]))
        .collect();
    (w * f, h * f, out)
}
