//! The bundled phantom: current with its generator, identical in its two formats, and
//! segmented as its exact labels say.

use std::path::PathBuf;

use lungmotion::formats::{dicom, nifti};
use lungmotion::ingest::segmentation::{dice, segment_lungs, SegmentationSettings};
use lungmotion::phantom::{generate_thorax_phantom, PhantomSettings, Tissue};
use lungmotion::volume::Volume;

fn sample(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("sample-volumes")
        .join(name)
}

#[test]
fn committed_sample_is_what_the_generator_makes_in_both_formats() {
    let fresh = generate_thorax_phantom(&PhantomSettings::default()).unwrap();
    let nii = nifti::read_nifti(&sample("phantom-ct.nii.gz")).unwrap();
    assert!(nii.geometry.same_grid(&fresh.ct.geometry, 1e-4));
    assert_eq!(
        nii.as_slice(),
        fresh.ct.as_slice(),
        "sample-volumes/ is stale: run `cargo run --release -- phantom`"
    );
    let truth = nifti::read_nifti_labels(&sample("phantom-truth.nii.gz")).unwrap();
    assert_eq!(truth.as_slice(), fresh.truth.as_slice());
    let series = dicom::read_dicom_series(&sample("phantom-dicom")).unwrap();
    assert!(series.volume.geometry.same_grid(&nii.geometry, 1e-3));
    assert_eq!(series.volume.as_slice(), nii.as_slice());
    assert_eq!(series.info.modality, "CT");
}

#[test]
fn phantom_lungs_are_segmented_as_its_truth_says() {
    let phantom = generate_thorax_phantom(&PhantomSettings::default()).unwrap();
    let seg = segment_lungs(&phantom.ct, &SegmentationSettings::default()).unwrap();
    // The tumour sits inside the right lung: the lung mask should enclose it, as the expert
    // CIP map encloses vessels and nodules.
    let truth: Volume<u8> = phantom.truth.map(|t| match Tissue::from_code(t) {
        Some(Tissue::RightLung | Tissue::Tumour) => 1,
        Some(Tissue::LeftLung) => 2,
        _ => 0,
    });
    let both = |v: &Volume<u8>| v.map(|l| u8::from(l != 0));
    let d_all = dice(&both(&seg.lungs), 1, &both(&truth), 1).unwrap();
    let d_right = dice(&seg.lungs, 1, &truth, 1).unwrap();
    let d_left = dice(&seg.lungs, 2, &truth, 2).unwrap();
    println!(
        "phantom Dice: both {d_all:.4}, right {d_right:.4}, left {d_left:.4}; volumes {:.0} / {:.0} mL",
        seg.report.right_volume_ml, seg.report.left_volume_ml
    );
    assert!(d_all >= 0.97 && d_right >= 0.97 && d_left >= 0.97);
    assert!(
        dice(&seg.lungs, 1, &truth, 2).unwrap() < 0.01,
        "left and right swapped"
    );
    // The trachea above the carina is airway, not lung: a lung mask that kept it would put
    // the trachea into the mechanical model. (Bronchi inside the lungs belong to the lung
    // mask, as in the expert CIP map.)
    let airway = Tissue::Airway.code();
    let carina_z = phantom.description.landmarks.carina_lps_mm[2];
    let g = phantom.truth.geometry;
    let (mut trachea, mut in_lungs) = (0, 0);
    for (idx, (&t, &l)) in phantom
        .truth
        .as_slice()
        .iter()
        .zip(seg.lungs.as_slice())
        .enumerate()
    {
        let k = idx / (g.dims[0] * g.dims[1]);
        let z = g
            .voxel_to_lps_mm(nalgebra::Vector3::new(0.0, 0.0, k as f64))
            .z;
        if t == airway && z > carina_z + 10.0 {
            trachea += 1;
            in_lungs += usize::from(l != 0);
        }
    }
    println!("trachea voxels in the lung mask: {in_lungs} of {trachea}");
    assert!(
        trachea > 50 && in_lungs * 20 < trachea,
        "{in_lungs} of {trachea}"
    );
}
