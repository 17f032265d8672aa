//! The PACS round trip against a real DICOMweb server: Debian's Orthanc with its DICOMweb
//! plugin (`.ci/run` installs both), started here on loopback ports of its own. Push the
//! bundled CT, pull it back by study, run on it straight from the PACS and push the outputs;
//! a repeated push stores nothing twice; a server that is down, an unknown study and a study
//! without a CT are refused by name.

mod common;
mod orthanc_support;

use std::process::Output;

use common::{absent_temp_dir, bin, sample, write_breaths};
use dicom_dictionary_std::tags;
use dicom_object::open_file;
use lungmotion::formats::dicom::read_dicom_series;
use orthanc_support::{free_port, Orthanc};

fn lungmotion(args: &[&str]) -> Output {
    bin().args(args).output().unwrap()
}

fn text(o: &Output) -> String {
    format!(
        "{}{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    )
}

use orthanc_support::study_uid_of as study_uid;

#[test]
#[cfg_attr(
    not(feature = "slow-tests"),
    ignore = "needs Orthanc with its DICOMweb plugin (.ci/run installs it): cargo test --features slow-tests --test pacs_orthanc"
)]
fn push_pull_run_and_push_back_through_a_real_dicomweb_server() {
    let orthanc = Orthanc::start("roundtrip");
    let root = orthanc.root();
    let ct_dir = sample("phantom-dicom");
    let study = study_uid(&ct_dir);
    let scratch = absent_temp_dir("pacs-roundtrip");
    std::fs::create_dir_all(&scratch).unwrap();

    // Push the planning CT; again: nothing stored twice.
    let o = lungmotion(&["pacs", "push", "--to", &root, ct_dir.to_str().unwrap()]);
    assert!(o.status.success(), "{}", text(&o));
    assert!(text(&o).contains("stored 68 instances"), "{}", text(&o));
    let o = lungmotion(&["pacs", "push", "--to", &root, ct_dir.to_str().unwrap()]);
    assert!(
        text(&o).contains("stored 0 instances; 68 already on the server"),
        "{}",
        text(&o)
    );

    // Pull it back by study: the same volume as the files pushed.
    let pulled = scratch.join("pulled");
    let from = format!("{root}/studies/{study}");
    let o = lungmotion(&[
        "pacs",
        "pull",
        "--from",
        &from,
        "--out",
        pulled.to_str().unwrap(),
    ]);
    assert!(o.status.success(), "{}", text(&o));
    let original = read_dicom_series(&ct_dir).unwrap();
    let back = read_dicom_series(&pulled).unwrap();
    assert_eq!(back.volume.geometry, original.volume.geometry);
    assert_eq!(back.volume.as_slice(), original.volume.as_slice());
    assert_eq!(back.study.study_instance_uid, study);

    // Run straight from the PACS and push the outputs back into the CT's study.
    let trace = scratch.join("trace.csv");
    write_breaths(&trace, 300.0, 0.2, 4.0);
    let out = scratch.join("run");
    let o = lungmotion(&[
        "run",
        "--ct",
        &from,
        "--trace",
        trace.to_str().unwrap(),
        "--element-size",
        "12",
        "--out",
        out.to_str().unwrap(),
        "--quiet",
        "--virtual-ct",
        "dicom",
        "--registration-spacing",
        "6",
        "--target",
        "point:-95,20,-80:r=12",
        "--push",
        &root,
    ]);
    assert!(o.status.success(), "{}", text(&o));
    assert!(out.join("summary.json").is_file());
    assert!(text(&o).contains("pushed to"), "{}", text(&o));
    // Everything a planner loads is in the CT's study on the PACS: the planning CT, one
    // virtual phase series per frame, MIP and AIP, a REG per frame and the RTSTRUCT.
    let summary: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("summary.json")).unwrap()).unwrap();
    let frames = summary["frames"].as_array().unwrap().len();
    let series = orthanc.series_of(&study);
    let count = |modality: &str| series.iter().filter(|(m, _)| m == modality).count();
    assert_eq!(count("CT"), 1 + frames + 2, "{series:?}");
    assert_eq!(count("REG"), frames, "{series:?}");
    assert_eq!(count("RTSTRUCT"), 1, "{series:?}");
    let (_, reg_series) = series.iter().find(|(m, _)| m == "REG").unwrap();
    let metadata = orthanc.metadata(&study, reg_series);
    assert_eq!(
        metadata[0]["00080016"]["Value"][0], "1.2.840.10008.5.1.4.1.1.66.3",
        "the stored REG read back is a Deformable Spatial Registration"
    );
    std::fs::remove_dir_all(&scratch).unwrap();
}

#[test]
#[cfg_attr(
    not(feature = "slow-tests"),
    ignore = "needs Orthanc with its DICOMweb plugin (.ci/run installs it): cargo test --features slow-tests --test pacs_orthanc"
)]
fn a_server_down_an_unknown_study_and_a_study_without_ct_are_refused_by_name() {
    let scratch = absent_temp_dir("pacs-refusals");
    std::fs::create_dir_all(&scratch).unwrap();
    let out = scratch.join("pulled");
    let out_arg = out.to_str().unwrap();

    // Nothing listens on that port: a failure while working (exit 1), named.
    let down = format!(
        "dicomweb://127.0.0.1:{}/dicom-web/studies/1.2.3",
        free_port()
    );
    let o = lungmotion(&["pacs", "pull", "--from", &down, "--out", out_arg]);
    assert_eq!(o.status.code(), Some(1), "{}", text(&o));
    assert!(text(&o).contains("cannot connect"), "{}", text(&o));

    let orthanc = Orthanc::start("refusals");
    let root = orthanc.root();
    // A study the server does not hold: refused (exit 2), named.
    let o = lungmotion(&[
        "pacs",
        "pull",
        "--from",
        &format!("{root}/studies/1.2.3.4"),
        "--out",
        out_arg,
    ]);
    assert_eq!(o.status.code(), Some(2), "{}", text(&o));
    assert!(text(&o).contains("holds no study 1.2.3.4"), "{}", text(&o));

    // A study holding an MR image only.
    let mr = scratch.join("mr.dcm");
    let first = std::fs::read_dir(sample("phantom-dicom"))
        .unwrap()
        .next()
        .unwrap()
        .unwrap()
        .path();
    let mut obj = open_file(first).unwrap();
    for (tag, value) in [
        (tags::MODALITY, "MR"),
        (tags::SOP_CLASS_UID, "1.2.840.10008.5.1.4.1.1.4"),
        (tags::STUDY_INSTANCE_UID, "1.2.826.0.1.3680043.2.1125.77.1"),
        (tags::SERIES_INSTANCE_UID, "1.2.826.0.1.3680043.2.1125.77.2"),
        (tags::SOP_INSTANCE_UID, "1.2.826.0.1.3680043.2.1125.77.3"),
    ] {
        obj.put(dicom_core::DataElement::new(
            tag,
            if tag == tags::MODALITY {
                dicom_core::VR::CS
            } else {
                dicom_core::VR::UI
            },
            dicom_core::PrimitiveValue::from(value),
        ));
    }
    obj.meta_mut().media_storage_sop_class_uid = "1.2.840.10008.5.1.4.1.1.4".into();
    obj.meta_mut().media_storage_sop_instance_uid = "1.2.826.0.1.3680043.2.1125.77.3".into();
    obj.write_to_file(&mr).unwrap();
    let o = lungmotion(&["pacs", "push", "--to", &root, mr.to_str().unwrap()]);
    assert!(text(&o).contains("stored 1 instances"), "{}", text(&o));
    let from = format!("{root}/studies/1.2.826.0.1.3680043.2.1125.77.1");
    let o = lungmotion(&["pacs", "pull", "--from", &from, "--out", out_arg]);
    assert_eq!(o.status.code(), Some(2), "{}", text(&o));
    assert!(
        text(&o).contains("holds no CT series (it holds: MR"),
        "{}",
        text(&o)
    );
    assert!(!out.exists() || std::fs::read_dir(&out).unwrap().next().is_none());

    // A malformed address is refused before any request.
    let o = lungmotion(&[
        "pacs",
        "pull",
        "--from",
        "http://example.org/x",
        "--out",
        out_arg,
    ]);
    assert_eq!(o.status.code(), Some(2), "{}", text(&o));
    assert!(text(&o).contains("not a DICOMweb address"), "{}", text(&o));
    std::fs::remove_dir_all(&scratch).unwrap();
}

#[test]
#[cfg_attr(
    not(feature = "slow-tests"),
    ignore = "needs Orthanc with its DICOMweb plugin (.ci/run installs it): cargo test --features slow-tests --test pacs_orthanc"
)]
fn credentials_come_from_the_environment_and_a_401_is_refused_by_name() {
    let orthanc = Orthanc::start_with("auth", Some(("lungmotion", "cli-pass-5678")));
    let root = orthanc.root();
    let ct_dir = sample("phantom-dicom");
    let push = |env: &[(&str, &str)]| {
        let mut cmd = bin();
        cmd.args(["pacs", "push", "--to", &root, ct_dir.to_str().unwrap()]);
        for name in [
            "LUNGMOTION_PACS_USERNAME",
            "LUNGMOTION_PACS_PASSWORD",
            "LUNGMOTION_PACS_TOKEN",
        ] {
            cmd.env_remove(name);
        }
        cmd.envs(env.iter().copied()).output().unwrap()
    };
    let o = push(&[]);
    assert_eq!(o.status.code(), Some(2), "{}", text(&o));
    assert!(text(&o).contains("answered HTTP 401"), "{}", text(&o));
    let o = push(&[
        ("LUNGMOTION_PACS_USERNAME", "lungmotion"),
        ("LUNGMOTION_PACS_PASSWORD", "wrong"),
    ]);
    assert!(text(&o).contains("answered HTTP 401"), "{}", text(&o));
    assert!(!text(&o).contains("wrong"), "{}", text(&o));
    let o = push(&[
        ("LUNGMOTION_PACS_USERNAME", "lungmotion"),
        ("LUNGMOTION_PACS_PASSWORD", "cli-pass-5678"),
    ]);
    assert!(text(&o).contains("stored 68 instances"), "{}", text(&o));
}
