//! Tissue that varies with the CT (`[tissue]`): the phantom's elements take their moduli from
//! its Hounsfield units and its tumour (label 8 of the truth labels) can be made stiffer;
//! a stiffer tumour must strain less under the same breath, and the mapping must sit the
//! material's modulus on the phantom's parenchyma (−850 HU by construction).

use std::path::{Path, PathBuf};

use lungmotion::breathing::{BreathingTrace, OutputInstants};
use lungmotion::ingest::lung_model::{sample_element_density, LungModel};
use lungmotion::ingest::pipeline::{ingest_scan, IngestOutcome};
use lungmotion::ingest::scan::{load_ct, LoadedScan};
use lungmotion::math::V3;
use lungmotion::model::tissue::{map_element_tissue, ElementDensity, TissueSettings};
use lungmotion::model::Material;
use lungmotion::motion::{
    run_motion, run_scene, run_scene_with_tissue, MotionSettings, WallMotion,
};
use lungmotion::outputs::radiotherapy::target::TargetSpec;
use lungmotion::run::RunConfig;
use lungmotion::simulation::Scene;

fn sample(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("sample-volumes")
        .join(name)
}

/// The phantom at 8 mm, its ingest and what the CT says of each element, with the tumour as
/// the target.
fn phantom() -> (LoadedScan, IngestOutcome, ElementDensity, f64) {
    let scan = load_ct(&sample("phantom-ct.nii.gz")).unwrap();
    let config = RunConfig::from_toml("element_size_mm = 8.0").unwrap();
    let outcome = ingest_scan(&scan, &config.ingest_settings()).unwrap();
    let tumour = TargetSpec::Mask {
        path: sample("phantom-truth.nii.gz"),
        label: Some(8),
    }
    .resolve(&scan.ct.geometry, None)
    .unwrap();
    let density = sample_element_density(
        &outcome.model,
        &scan.ct,
        &outcome.segmentation.lungs,
        Some(&tumour.mask),
    )
    .unwrap();
    let voxel_cc = scan.ct.geometry.spacing_mm.iter().product::<f64>() * 1e-3;
    let tumour_cc = tumour.voxel_count() as f64 * voxel_cc;
    (scan, outcome, density, tumour_cc)
}

/// End-inhale node positions of `scene` after a 400 mL breath in.
fn end_inhale(scene: &Scene) -> Vec<V3> {
    let times: Vec<f64> = (0..=4).map(|i| i as f64 * 0.5).collect();
    let volumes = times
        .iter()
        .map(|t| 200.0 * (1.0 - (std::f64::consts::PI * t / 2.0).cos()))
        .collect();
    let trace = BreathingTrace::new(times, volumes).unwrap();
    let settings = MotionSettings {
        instants: OutputInstants::EverySample,
        rib_cage_share: WallMotion::default().rib_cage_share,
        ..MotionSettings::default()
    };
    let mut last = Vec::new();
    run_motion(scene, &Material::LUNG, &trace, &settings, &mut |_, x| {
        last = x.to_vec();
        Ok(())
    })
    .unwrap();
    last
}

/// Mean |ℓ/ℓ₀ − 1| over the 12 edges of each of `elements`.
fn mean_edge_strain(model: &LungModel, x: &[V3], elements: &[usize]) -> f64 {
    use lungmotion::model::mesh::HEX_EDGES;
    let mesh = &model.mesh.mesh;
    let mut sum = 0.0;
    for &e in elements {
        let c = mesh.elements[e];
        for (a, b) in HEX_EDGES {
            let (a, b) = (c[a] as usize, c[b] as usize);
            let rest = (mesh.rest_positions_m[a] - mesh.rest_positions_m[b]).norm();
            sum += ((x[a] - x[b]).norm() / rest - 1.0).abs();
        }
    }
    sum / (12 * elements.len()) as f64
}

#[test]
fn a_stiffer_tumour_strains_less_than_the_same_tissue_and_barely_moves_its_centre() {
    let (_, outcome, density, tumour_cc) = phantom();
    let model = &outcome.model;
    let settings = TissueSettings {
        target_stiffness_ratio: 10.0,
        ..TissueSettings::default()
    };
    let (tissue, report) = map_element_tissue(&density, &settings, 390.0).unwrap();
    // The elements hold the mask's volume (a 15 mm sphere on 5 mm voxels: 17 cc).
    let held = report.target_element_volumes * 0.512;
    assert!(
        (held - tumour_cc).abs() < 0.05 * tumour_cc,
        "target volume in the elements {held:.2} cc, in the mask {tumour_cc:.2} cc"
    );
    let inside: Vec<usize> = (0..model.mesh.mesh.element_count())
        .filter(|&e| density.target_fraction[e] > 0.9)
        .collect();
    assert!(
        inside.len() >= 8,
        "{} elements inside the tumour",
        inside.len()
    );
    assert!(inside.iter().all(|&e| tissue.stiffness_ratio[e] > 9.0));

    let walls = WallMotion::default();
    let plain = end_inhale(&run_scene(model, &walls).unwrap());
    let stiff_scene =
        run_scene_with_tissue(model, &walls, &tissue, settings.stiffness_step).unwrap();
    assert!(stiff_scene.mesh.classes.len() > 1);
    let stiff = end_inhale(&stiff_scene);
    let (strain_plain, strain_stiff) = (
        mean_edge_strain(model, &plain, &inside),
        mean_edge_strain(model, &stiff, &inside),
    );
    let centre = |x: &[V3]| {
        let mut sum = V3::zeros();
        let mut n = 0.0;
        for &e in &inside {
            for c in model.mesh.mesh.elements[e] {
                sum += x[c as usize] - model.mesh.mesh.rest_positions_m[c as usize];
                n += 1.0;
            }
        }
        sum / n * 1e3
    };
    let (moved_plain, moved_stiff) = (centre(&plain), centre(&stiff));
    eprintln!(
        "tumour edge strain {:.4} → {:.4} with 10× stiffness; centre motion {:.2} mm, \
         changed by {:.2} mm",
        strain_plain,
        strain_stiff,
        moved_plain.norm(),
        (moved_stiff - moved_plain).norm()
    );
    assert!(
        strain_plain > 0.005,
        "the breath strains the tumour's tissue: {strain_plain}"
    );
    assert!(
        strain_stiff < 0.5 * strain_plain,
        "a 10× stiffer tumour strains {strain_stiff:.4} against {strain_plain:.4}"
    );
    assert!(moved_plain.norm() > 3.0);
    assert!((moved_stiff - moved_plain).norm() < 0.2 * moved_plain.norm());
}

#[test]
fn the_ct_mapping_puts_the_material_on_the_parenchyma_and_stiffens_vessel_elements() {
    let (scan, outcome, density, _) = phantom();
    let settings = TissueSettings {
        from_ct: true,
        ..TissueSettings::default()
    };
    let (tissue, report) = map_element_tissue(&density, &settings, 390.0).unwrap();
    // The phantom's parenchyma is drawn at −850 HU with zero-mean noise.
    assert!(
        (report.reference_hu + 850.0).abs() < 10.0,
        "reference {} HU",
        report.reference_hu
    );
    assert_eq!(report.stiffness_ratio_quantiles[2], 1.0);
    // Elements holding a vessel (+40 HU) are stiffer; none is softer than air-only tissue
    // allows (the clamp).
    let lung_hu = scan.ct.as_slice();
    assert!(lung_hu.len() > 1);
    assert!(report.stiffness_ratio_quantiles[4] > 2.0, "{report:?}");
    assert!(tissue
        .stiffness_ratio
        .iter()
        .all(|&r| (0.1..=10.0).contains(&r)));
    let n = tissue.stiffness_ratio.len();
    let vessel_rich = (0..n)
        .filter(|&e| density.parenchyma_fraction[e] > 0.25 && density.target_fraction[e] == 0.0)
        .collect::<Vec<_>>();
    assert!(!vessel_rich.is_empty());
    for &e in &vessel_rich {
        let want = (density.parenchyma_fraction[e] / report.reference_tissue_fraction)
            .powi(2)
            .min(10.0);
        assert!((tissue.stiffness_ratio[e] - want).abs() < 1e-9);
    }
    let scene = run_scene_with_tissue(
        &outcome.model,
        &WallMotion {
            rib_cage_share: 0.0,
            ..WallMotion::default()
        },
        &tissue,
        settings.stiffness_step,
    )
    .unwrap();
    assert_eq!(scene.mesh.classes.len(), report.classes);
    // Node masses follow the densities: ρ·φ/φ_ref summed over the elements.
    let want_mass: f64 = tissue.density_ratio.iter().sum::<f64>()
        * scene.mesh.classes[0].shape.volume_m3()
        * Material::LUNG.density_kg_per_m3;
    let got = scene.mesh.total_mass_kg();
    assert!((got / want_mass - 1.0).abs() < 0.03, "{got} vs {want_mass}");
}

/// The `lungmotion` binary.
fn bin() -> std::process::Command {
    std::process::Command::new(env!("CARGO_BIN_EXE_lungmotion"))
}

/// The stderr of a run of the phantom with `config`, which must be refused (exit status 2)
/// without writing its output.
fn refused(dir: &Path, config: &str) -> String {
    let toml = dir.join("tissue.toml");
    std::fs::write(&toml, config).unwrap();
    let o = bin()
        .arg("run")
        .arg("--ct")
        .arg(sample("phantom-ct.nii.gz"))
        .arg("--trace")
        .arg(dir.join("trace.csv"))
        .arg("--out")
        .arg(dir.join("out"))
        .arg("--config")
        .arg(&toml)
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&o.stderr).to_string();
    assert_eq!(o.status.code(), Some(2), "{config}: {stderr}");
    assert!(!dir.join("out").exists(), "a refused run wrote its output");
    stderr
}

#[test]
fn tissue_settings_no_run_can_use_are_refused_with_the_key_and_the_value() {
    let dir = std::env::temp_dir().join(format!("lungmotion-tissue-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    std::fs::write(dir.join("trace.csv"), "time_s,volume_ml\n0,0\n1,300\n2,0\n").unwrap();
    let cases = [
        (
            "[tissue]\ntarget_stiffness_ratio = 4.0\n",
            "tissue.target_stiffness_ratio",
            "--target",
        ),
        (
            "[tissue]\ntarget_stiffness_ratio = -3.0\n",
            "tissue.target_stiffness_ratio",
            "-3",
        ),
        (
            "[tissue]\nfrom_ct = true\nhu_to_youngs_modulus_pa = [[-950, 100], [-850, -5]]\n",
            "tissue.hu_to_youngs_modulus_pa",
            "-5 Pa at -850 HU is not a positive stiffness",
        ),
        (
            "[tissue]\nfrom_ct = true\nstiffness_exponent = 9\n",
            "tissue.stiffness_exponent",
            "9",
        ),
        ("[tissue]\nfrom_cT = true\n", "from_cT", "unknown field"),
        (
            "[motion.dynamic]\nsurface_damping_ratio = -0.1\n",
            "surface damping ratio",
            "-0.1",
        ),
    ];
    for (config, key, value) in cases {
        let stderr = refused(&dir, config);
        assert!(
            stderr.contains(key) && stderr.contains(value),
            "{config}: {stderr}"
        );
    }
    std::fs::remove_dir_all(&dir).unwrap();
}
