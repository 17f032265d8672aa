//! The radiotherapy deliverables over HTTP: a job on an uploaded DICOM series asks for the
//! virtual 4D-CT (NIfTI and DICOM), the registrations and a target, and a client fetches
//! each through the files and archives routes; the DICOM objects are read back by dicom-rs
//! (not the project's reader) and sit in the planning CT's study and frame of reference.

mod service_support;

use std::io::Read;
use std::time::Duration;

use dicom_dictionary_std::tags;
use dicom_object::{from_reader, open_file, DefaultDicomObject};
use serde_json::json;
use service_support::{
    accepted_job_id, breathing_trace, sample, zip_dicom_series, Scratch, ServerProcess,
};

/// An element of `obj` as text, without DICOM padding.
fn text(obj: &DefaultDicomObject, tag: dicom_core::Tag) -> String {
    obj.element(tag)
        .unwrap_or_else(|_| panic!("{tag} missing"))
        .to_str()
        .unwrap()
        .trim_end_matches(['\0', ' '])
        .to_string()
}

/// A DICOM file's bytes parsed by dicom-rs.
fn parse(bytes: &[u8]) -> DefaultDicomObject {
    // A Part 10 file: 128-byte preamble, then "DICM".
    assert_eq!(&bytes[128..132], b"DICM");
    from_reader(&bytes[128..]).unwrap()
}

#[test]
fn a_job_serves_the_virtual_4dct_registrations_and_target_as_files_and_zips() {
    let scratch = Scratch::new("deliverables");
    let server = ServerProcess::start(&scratch.join("data"), &["--workers", "1"]);
    let zip_path = scratch.join("series.zip");
    zip_dicom_series(&zip_path);
    let resp = server.post_scan_bytes(std::fs::read(&zip_path).unwrap(), "application/zip");
    assert_eq!(resp.status(), 201);
    let scan: serde_json::Value = resp.json().unwrap();
    let scan_id = scan["scan_id"].as_str().unwrap();
    let ct_slices = std::fs::read_dir(sample("phantom-dicom")).unwrap().count();
    let ct = open_file(
        std::fs::read_dir(sample("phantom-dicom"))
            .unwrap()
            .next()
            .unwrap()
            .unwrap()
            .path(),
    )
    .unwrap();

    let (time_s, volume_ml) = breathing_trace(2);
    let request = json!({
        "trace": {"time_s": time_s, "volume_ml": volume_ml},
        "element_size_mm": 12,
        "motion": {"instants": {"kind": "phases", "count": 2}},
        "outputs": {"quicklooks": false, "virtual_ct": "both", "registration": true,
                    "registration_spacing_mm": 8},
        "target": "point:-95,20,-80:r=12",
    });
    let job = accepted_job_id(server.post_simulation(scan_id, &request));
    server.wait_for_state(&job, &["done"], Duration::from_secs(900));
    let summary = server.get_json(&format!("/v1/jobs/{job}/summary"));
    let frames = summary["frames"].as_array().unwrap().len();
    assert_eq!(frames, 2, "{summary:#}");

    // Every phase's DICOM series as one zip: one image per CT slice, in the CT's study and
    // frame of reference, a series of its own carrying its respiratory phase.
    let mut phase_series = Vec::new();
    let mut positions = std::collections::BTreeSet::new();
    for dir in (0..frames)
        .map(|k| format!("frames/{k}/virtual-ct-dicom"))
        .chain(["mip-ct-dicom".into(), "aip-ct-dicom".into()])
    {
        let resp = server.get(&format!("/v1/jobs/{job}/archives/{dir}"));
        assert_eq!(resp.status(), 200, "{dir}");
        assert_eq!(resp.headers()["content-type"], "application/zip");
        let mut zip = zip::ZipArchive::new(std::io::Cursor::new(resp.bytes().unwrap())).unwrap();
        assert_eq!(zip.len(), ct_slices, "{dir}");
        let mut series = std::collections::BTreeSet::new();
        for n in 0..zip.len() {
            let mut bytes = Vec::new();
            zip.by_index(n).unwrap().read_to_end(&mut bytes).unwrap();
            let obj = parse(&bytes);
            assert_eq!(text(&obj, tags::MODALITY), "CT", "{dir}");
            for tag in [tags::STUDY_INSTANCE_UID, tags::FRAME_OF_REFERENCE_UID] {
                assert_eq!(text(&obj, tag), text(&ct, tag), "{dir} {tag}");
            }
            series.insert(text(&obj, tags::SERIES_INSTANCE_UID));
            if dir.starts_with("frames/") {
                assert_eq!(
                    text(&obj, tags::RESPIRATORY_MOTION_COMPENSATION_TECHNIQUE),
                    "RETROSPECTIVE",
                    "{dir}"
                );
                positions.insert(text(&obj, tags::TEMPORAL_POSITION_IDENTIFIER));
            }
        }
        assert_eq!(series.len(), 1, "{dir}: one series");
        let uid = series.into_iter().next().unwrap();
        assert_ne!(uid, text(&ct, tags::SERIES_INSTANCE_UID), "{dir}");
        phase_series.push(uid);
    }
    let distinct: std::collections::BTreeSet<&String> = phase_series.iter().collect();
    assert_eq!(distinct.len(), phase_series.len(), "{phase_series:?}");
    // Each phase at its own temporal position, the same on all its images.
    assert_eq!(positions.len(), frames, "{positions:?}");

    // The NIfTI phases and projections, the ITV and per-phase target masks (gzip).
    let gzip = |path: &str| {
        let resp = server.get(&format!("/v1/jobs/{job}/files/{path}"));
        assert_eq!(resp.status(), 200, "{path}");
        let bytes = resp.bytes().unwrap();
        assert_eq!(&bytes[..2], &[0x1f, 0x8b], "{path} is gzip");
        bytes.len()
    };
    for k in 0..frames {
        gzip(&format!("frames/{k}/virtual-ct.nii.gz"));
        gzip(&format!("frames/{k}/target.nii.gz"));
    }
    for path in ["mip-ct.nii.gz", "aip-ct.nii.gz", "target/itv.nii.gz"] {
        gzip(path);
    }

    // A REG per frame and the structure set, as DICOM files.
    let dicom = |path: &str| {
        let resp = server.get(&format!("/v1/jobs/{job}/files/{path}"));
        assert_eq!(resp.status(), 200, "{path}");
        assert_eq!(
            resp.headers()["content-type"],
            "application/dicom",
            "{path}"
        );
        parse(&resp.bytes().unwrap())
    };
    for k in 0..frames {
        let reg = dicom(&format!("frames/{k}/registration.dcm"));
        assert_eq!(
            text(&reg, tags::SOP_CLASS_UID),
            "1.2.840.10008.5.1.4.1.1.66.3"
        );
        assert_eq!(
            text(&reg, tags::FRAME_OF_REFERENCE_UID),
            text(&ct, tags::FRAME_OF_REFERENCE_UID)
        );
    }
    let rtstruct = dicom("target/rtstruct.dcm");
    assert_eq!(
        text(&rtstruct, tags::SOP_CLASS_UID),
        "1.2.840.10008.5.1.4.1.1.481.3"
    );
    let names: Vec<String> = rtstruct
        .element(tags::STRUCTURE_SET_ROI_SEQUENCE)
        .unwrap()
        .items()
        .unwrap()
        .iter()
        .map(|item| {
            item.element(tags::ROI_NAME)
                .unwrap()
                .to_str()
                .unwrap()
                .trim_end_matches(['\0', ' '])
                .to_string()
        })
        .collect();
    assert!(names.iter().any(|n| n == "ITV"), "{names:?}");
    // The ITV, the planning target and one ROI per phase.
    assert_eq!(names.len(), 2 + frames, "{names:?}");

    // The target's motion: the CSV a row per frame, the summary's ITV no smaller than the
    // planning target.
    let csv = server
        .get(&format!("/v1/jobs/{job}/files/target-motion.csv"))
        .text()
        .unwrap();
    assert_eq!(csv.lines().count(), 1 + frames, "{csv}");
    let target = &summary["target"];
    assert!(
        target["itv_volume_cc"].as_f64().unwrap() >= target["planning_volume_cc"].as_f64().unwrap(),
        "{target:#}"
    );
}
