//! RT Structure Sets: our writer's output read back by pydicom (references and the mask,
//! rasterised by the script's own even-odd fill), and our reader on structure sets pydicom
//! wrote, with every refusal named (missing ROI, other frame of reference, contours off the
//! CT's slices, not a structure set). Needs python3 with pydicom and numpy; the tests say so
//! and return when they are missing.

use std::path::{Path, PathBuf};
use std::process::Command;

use lungmotion::formats::dicom::{read_dicom_series, DicomSeries};
use lungmotion::outputs::radiotherapy::rtstruct::{read_roi_mask, write_rtstruct, RoiContours};
use lungmotion::outputs::radiotherapy::target::TargetSpec;
use lungmotion::volume::Volume;

fn phantom_dicom() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("sample-volumes/phantom-dicom")
}

fn scratch(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("lm-rtstruct-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

/// Whether python3 with pydicom and numpy is there (a skipped test says so on stderr).
fn pydicom_available() -> bool {
    let ok = Command::new("python3")
        .args(["-c", "import pydicom, numpy"])
        .output()
        .map(|o| o.status.success())
        .unwrap_or(false);
    if !ok {
        eprintln!("skipped: needs python3 with pydicom and numpy (pip install pydicom numpy)");
    }
    ok
}

/// Runs a python script with arguments; panics with its stderr when it fails.
fn python(script: &str, args: &[&Path]) -> String {
    let out = Command::new("python3")
        .arg("-c")
        .arg(script)
        .args(args)
        .output()
        .expect("python3 runs");
    assert!(
        out.status.success(),
        "python failed: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8_lossy(&out.stdout).into_owned()
}

/// A mask on the phantom's grid holding the voxels where `inside(lps)` holds.
fn mask_of(series: &DicomSeries, inside: impl Fn([f64; 3]) -> bool) -> Volume<u8> {
    let g = series.volume.geometry;
    let mut mask = Volume::filled(g, 0u8).unwrap();
    let [ni, nj, nk] = g.dims;
    for k in 0..nk {
        for j in 0..nj {
            for i in 0..ni {
                let p = g.voxel_to_lps_mm(nalgebra::Vector3::new(i as f64, j as f64, k as f64));
                if inside([p[0], p[1], p[2]]) {
                    mask.as_slice_mut()[g.index(i, j, k)] = 1;
                }
            }
        }
    }
    mask
}

/// pydicom reads the structure set and the CT files on its own, checks the references and
/// rasterises each ROI on the CT's slices by an even-odd fill; prints `name dice` per ROI.
const READ_BACK: &str = r#"
import sys, glob, numpy as np, pydicom
rs_path, ct_dir, masks_path = sys.argv[1], sys.argv[2], sys.argv[3]
rs = pydicom.dcmread(rs_path)
cts = [pydicom.dcmread(f) for f in sorted(glob.glob(ct_dir + "/*.dcm"))]
normal = np.cross(np.array(cts[0].ImageOrientationPatient[:3], float),
                  np.array(cts[0].ImageOrientationPatient[3:], float))
cts.sort(key=lambda d: float(np.dot(normal, np.array(d.ImagePositionPatient, float))))
ct = cts[0]
assert rs.SOPClassUID == "1.2.840.10008.5.1.4.1.1.481.3", rs.SOPClassUID
assert rs.Modality == "RTSTRUCT"
assert rs.StudyInstanceUID == ct.StudyInstanceUID
assert rs.PatientID == ct.PatientID and str(rs.PatientName) == str(ct.PatientName)
assert rs.SeriesInstanceUID != ct.SeriesInstanceUID
ref = rs.ReferencedFrameOfReferenceSequence[0]
assert ref.FrameOfReferenceUID == ct.FrameOfReferenceUID
study = ref.RTReferencedStudySequence[0]
assert study.ReferencedSOPInstanceUID == ct.StudyInstanceUID
series = study.RTReferencedSeriesSequence[0]
assert series.SeriesInstanceUID == ct.SeriesInstanceUID
ct_uids = {d.SOPInstanceUID for d in cts}
listed = {i.ReferencedSOPInstanceUID for i in series.ContourImageSequence}
assert listed == ct_uids, "every CT slice listed once"
rows, cols = int(ct.Rows), int(ct.Columns)
ni, nj, nk = cols, rows, len(cts)
origin = np.array(ct.ImagePositionPatient, float)
row_dir = np.array(ct.ImageOrientationPatient[:3], float)
col_dir = np.array(ct.ImageOrientationPatient[3:], float)
dx, dy = float(ct.PixelSpacing[1]), float(ct.PixelSpacing[0])
z_of = [float(np.dot(normal, np.array(d.ImagePositionPatient, float))) for d in cts]
uid_of = [d.SOPInstanceUID for d in cts]
masks = np.fromfile(masks_path, dtype=np.uint8).reshape(-1, nk, nj, ni)
names = {r.ROINumber: r.ROIName for r in rs.StructureSetROISequence}
types = {o.ReferencedROINumber: o.RTROIInterpretedType for o in rs.RTROIObservationsSequence}
for roi in rs.StructureSetROISequence:
    assert roi.ReferencedFrameOfReferenceUID == ct.FrameOfReferenceUID
jj, ii = np.mgrid[0:nj, 0:ni]
for n, item in enumerate(rs.ROIContourSequence):
    got = np.zeros((nk, nj, ni), bool)
    for c in item.ContourSequence:
        assert c.ContourGeometricType == "CLOSED_PLANAR"
        pts = np.array(c.ContourData, float).reshape(-1, 3)
        assert len(pts) == int(c.NumberOfContourPoints)
        z = float(np.dot(normal, pts[0]))
        k = int(np.argmin([abs(z - zk) for zk in z_of]))
        assert abs(z - z_of[k]) < 1e-3, "contour on a CT slice"
        assert c.ContourImageSequence[0].ReferencedSOPInstanceUID == uid_of[k], "references its slice"
        rel = pts - np.array(cts[k].ImagePositionPatient, float)
        x, y = rel @ row_dir / dx, rel @ col_dir / dy
        inside = np.zeros((nj, ni), bool)
        for a in range(len(x)):
            b = (a + 1) % len(x)
            cross = (y[a] > jj) != (y[b] > jj)
            with np.errstate(divide="ignore", invalid="ignore"):
                xc = x[a] + (jj - y[a]) * (x[b] - x[a]) / (y[b] - y[a])
            inside ^= cross & (ii < xc)
        got[k] ^= inside
    want = masks[n].astype(bool)
    dice = 2 * (got & want).sum() / (got.sum() + want.sum())
    print(names[item.ReferencedROINumber], types[item.ReferencedROINumber], len(item.ContourSequence), dice)
"#;

#[test]
fn our_rtstruct_read_by_pydicom_recovers_a_sphere_and_a_ring_with_a_hole_and_its_references() {
    if !pydicom_available() {
        return;
    }
    let series = read_dicom_series(&phantom_dicom()).unwrap();
    let sphere = mask_of(&series, |p| {
        let d = [p[0] + 95.0, p[1] - 20.0, p[2] + 80.0];
        (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt() <= 30.0
    });
    // A thick-walled tube along z: an outer boundary and a hole on every slice it crosses.
    let ring = mask_of(&series, |p| {
        let r = ((p[0] - 80.0).powi(2) + (p[1] - 10.0).powi(2)).sqrt();
        (12.0..=40.0).contains(&r) && (-60.0..=20.0).contains(&p[2])
    });
    let rois = [
        RoiContours::of_mask("GTV sphere", "GTV", [255, 0, 0], &sphere),
        RoiContours::of_mask("ITV ring", "ITV", [0, 255, 0], &ring),
    ];
    assert!(
        rois[1].slices.iter().all(|(_, c)| c.iter().any(|c| c.hole)),
        "the ring has a hole on each slice"
    );
    let dir = scratch("readback");
    let rs = dir.join("rs.dcm");
    let g = series.volume.geometry;
    write_rtstruct(&rs, &series.study, &g, &rois, "test").unwrap();
    let masks = dir.join("masks.u8");
    let mut bytes = sphere.as_slice().to_vec();
    bytes.extend_from_slice(ring.as_slice());
    std::fs::write(&masks, bytes).unwrap();
    let out = python(READ_BACK, &[&rs, &phantom_dicom(), &masks]);
    let lines: Vec<Vec<&str>> = out
        .lines()
        .map(|l| l.split_whitespace().collect())
        .collect();
    assert_eq!(lines.len(), 2, "{out}");
    for (line, (name, kind)) in lines
        .iter()
        .zip([("GTV sphere", "GTV"), ("ITV ring", "ITV")])
    {
        let dice: f64 = line.last().unwrap().parse().unwrap();
        assert!(
            line.join(" ").starts_with(&format!("{name} {kind}")),
            "{out}"
        );
        assert!(dice >= 0.95, "{name}: Dice {dice} ({out})");
        // Marching squares at the voxel midpoints give the mask back exactly.
        assert_eq!(dice, 1.0, "{name}: {out}");
    }
    // Our own reader agrees.
    let back = read_roi_mask(
        &rs,
        "ITV ring",
        &g,
        Some(&series.study.frame_of_reference_uid),
    )
    .unwrap();
    assert_eq!(back.as_slice(), ring.as_slice());
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn an_rtstruct_without_the_cts_images_is_refused_with_the_reason() {
    let series = read_dicom_series(&phantom_dicom()).unwrap();
    let g = series.volume.geometry;
    let generated = lungmotion::formats::dicom::DicomStudyContext::generated(7);
    let mask = mask_of(&series, |p| {
        p[0].abs() < 20.0 && p[1].abs() < 20.0 && p[2].abs() < 20.0
    });
    let rois = [RoiContours::of_mask("GTV", "GTV", [255, 0, 0], &mask)];
    let dir = scratch("nifti-ct");
    let e = write_rtstruct(&dir.join("rs.dcm"), &generated, &g, &rois, "t")
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("not read from DICOM (a NIfTI or NRRD input)"),
        "{e}"
    );
    assert!(!dir.join("rs.dcm").exists());
}

/// Writes structure sets with pydicom on the phantom CT's frame of reference: `rs.dcm` with a
/// sphere of radius 20 mm at (−95, 20, −80) as 64-gons ("GTV") and a ring with a hole
/// ("Ring": outer radius 40, inner 15 mm around (80, 10), slices −60…20); `other-for.dcm`
/// the same GTV in another frame of reference; `off-slice.dcm` a contour 2.5 mm off a slice.
const WRITE_RS: &str = r#"
import sys, glob, math, numpy as np, pydicom
from pydicom.dataset import Dataset, FileMetaDataset
from pydicom.sequence import Sequence
from pydicom.uid import ExplicitVRLittleEndian, generate_uid
ct_dir, out_dir = sys.argv[1], sys.argv[2]
cts = [pydicom.dcmread(f) for f in sorted(glob.glob(ct_dir + "/*.dcm"))]
cts.sort(key=lambda d: float(d.ImagePositionPatient[2]))
ct = cts[0]
def circle(cx, cy, z, r, n=64, clockwise=False):
    pts = []
    for a in range(n):
        t = 2 * math.pi * a / n * (-1 if clockwise else 1)
        pts += [cx + r * math.cos(t), cy + r * math.sin(t), z]
    return pts
def write(path, rois, frame_uid, z_shift=0.0):
    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID = "1.2.840.10008.5.1.4.1.1.481.3"
    meta.MediaStorageSOPInstanceUID = generate_uid()
    meta.TransferSyntaxUID = ExplicitVRLittleEndian
    ds = Dataset()
    ds.file_meta = meta
    ds.SOPClassUID = meta.MediaStorageSOPClassUID
    ds.SOPInstanceUID = meta.MediaStorageSOPInstanceUID
    ds.Modality = "RTSTRUCT"
    ds.PatientName, ds.PatientID = ct.PatientName, ct.PatientID
    ds.StudyInstanceUID, ds.SeriesInstanceUID = ct.StudyInstanceUID, generate_uid()
    ds.StructureSetLabel = "pydicom"
    fr = Dataset(); fr.FrameOfReferenceUID = frame_uid
    ds.ReferencedFrameOfReferenceSequence = Sequence([fr])
    ds.StructureSetROISequence = Sequence()
    ds.ROIContourSequence = Sequence()
    for number, (name, contours) in enumerate(rois, start=1):
        r = Dataset(); r.ROINumber = number; r.ROIName = name
        r.ReferencedFrameOfReferenceUID = frame_uid; r.ROIGenerationAlgorithm = "MANUAL"
        ds.StructureSetROISequence.append(r)
        item = Dataset(); item.ReferencedROINumber = number; item.ROIDisplayColor = [255, 0, 0]
        item.ContourSequence = Sequence()
        for pts in contours:
            c = Dataset(); c.ContourGeometricType = "CLOSED_PLANAR"
            pts = [v + (z_shift if i % 3 == 2 else 0.0) for i, v in enumerate(pts)]
            c.NumberOfContourPoints = len(pts) // 3
            c.ContourData = [round(v, 4) for v in pts]
            item.ContourSequence.append(c)
        ds.ROIContourSequence.append(item)
    ds.save_as(path, enforce_file_format=True)
zs = [float(d.ImagePositionPatient[2]) for d in cts]
gtv = [circle(-95, 20, z, math.sqrt(400 - (z + 80) ** 2)) for z in zs if abs(z + 80) < 20]
ring = []
for z in zs:
    if -60 <= z <= 20:
        ring.append(circle(80, 10, z, 40))
        ring.append(circle(80, 10, z, 15, clockwise=True))
write(out_dir + "/rs.dcm", [("GTV", gtv), ("Ring", ring)], ct.FrameOfReferenceUID)
write(out_dir + "/other-for.dcm", [("GTV", gtv)], generate_uid())
write(out_dir + "/off-slice.dcm", [("GTV", gtv)], ct.FrameOfReferenceUID, z_shift=2.5)
"#;

/// Voxels of the phantom grid whose centre is inside (true) or outside (false) the disc of
/// radius `r(z)` around (cx, cy) in its slice, leaving out those within `band` mm of the edge.
fn disc_mismatches(
    mask: &Volume<u8>,
    centre: [f64; 2],
    radius_at: impl Fn(f64) -> Option<(f64, f64)>,
    band_mm: f64,
) -> usize {
    let g = mask.geometry;
    let [ni, nj, nk] = g.dims;
    let mut wrong = 0;
    for k in 0..nk {
        for j in 0..nj {
            for i in 0..ni {
                let p = g.voxel_to_lps_mm(nalgebra::Vector3::new(i as f64, j as f64, k as f64));
                let r = ((p[0] - centre[0]).powi(2) + (p[1] - centre[1]).powi(2)).sqrt();
                let (expected, edge_distance) = match radius_at(p[2]) {
                    Some((outer, inner)) => (
                        r < outer && r > inner,
                        (r - outer).abs().min((r - inner).abs()),
                    ),
                    None => (false, f64::INFINITY),
                };
                let got = mask.as_slice()[g.index(i, j, k)] != 0;
                if got != expected && edge_distance > band_mm {
                    wrong += 1;
                }
            }
        }
    }
    wrong
}

#[test]
fn our_reader_rasterises_pydicom_structure_sets_and_names_every_refusal() {
    if !pydicom_available() {
        return;
    }
    let dir = scratch("import");
    python(WRITE_RS, &[&phantom_dicom(), &dir]);
    let series = read_dicom_series(&phantom_dicom()).unwrap();
    let g = series.volume.geometry;
    let frame = series.study.frame_of_reference_uid.clone();
    let rs = dir.join("rs.dcm");

    // The 64-gons lie within 0.03 mm of their circles; voxels closer than that may go either way.
    let gtv = read_roi_mask(&rs, "GTV", &g, Some(&frame)).unwrap();
    let count = gtv.as_slice().iter().filter(|&&v| v != 0).count();
    let wrong = disc_mismatches(
        &gtv,
        [-95.0, 20.0],
        |z| {
            let h = 400.0 - (z + 80.0) * (z + 80.0);
            (h > 0.0).then(|| (h.sqrt(), -1.0))
        },
        0.05,
    );
    assert_eq!(wrong, 0, "GTV voxels off the sphere ({count} voxels)");
    assert!(count > 100, "{count}");
    // ROI names are matched ignoring case when no exact match exists.
    let ring = read_roi_mask(&rs, "ring", &g, Some(&frame)).unwrap();
    let wrong = disc_mismatches(
        &ring,
        [80.0, 10.0],
        |z| (-60.0..=20.0).contains(&z).then_some((40.0, 15.0)),
        0.05,
    );
    assert_eq!(wrong, 0, "ring voxels: the inner contour is a hole");
    assert!(
        ring.as_slice()[g.index(
            ((80.0 - g.origin_lps_mm[0]) / 5.0) as usize,
            ((10.0 - g.origin_lps_mm[1]) / 5.0) as usize,
            ((-20.0 - g.origin_lps_mm[2]) / 5.0) as usize
        )] == 0
    );

    // Through --target's parser and resolution, with the CT's study.
    let spec: TargetSpec = format!("{}:GTV", rs.display()).parse().unwrap();
    let resolved = spec.resolve(&g, Some(&series.study)).unwrap();
    assert_eq!(resolved.mask.as_slice(), gtv.as_slice());

    let refusal = |path: &Path, roi: &str| {
        read_roi_mask(path, roi, &g, Some(&frame))
            .unwrap_err()
            .to_string()
    };
    let e = refusal(&rs, "PTV");
    assert!(
        e.contains("no ROI named `PTV`") && e.contains("ROIs present: GTV, Ring"),
        "{e}"
    );
    let e = refusal(&dir.join("other-for.dcm"), "GTV");
    assert!(
        e.contains("frame of reference") && e.contains(&frame) && e.contains("another scan"),
        "{e}"
    );
    let e = refusal(&dir.join("off-slice.dcm"), "GTV");
    assert!(
        e.contains("contour 1") && e.contains("2.50 mm off the CT's slices"),
        "{e}"
    );
    let ct_file = phantom_dicom().join("IMG0001.dcm");
    let e = refusal(&ct_file, "GTV");
    assert!(e.contains("not an RT Structure Set"), "{e}");
    let e = format!("{}", rs.display())
        .parse::<TargetSpec>()
        .unwrap_err()
        .to_string();
    assert!(e.contains("name the ROI after a colon"), "{e}");
    let _ = std::fs::remove_dir_all(&dir);
}
