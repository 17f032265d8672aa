//! The treatment target a run follows (`--target`): parsed and checked once from its text,
//! then made into a mask on the planning CT's grid from a mask file, an RTSTRUCT ROI or a
//! sphere around a point.
//!
//! Syntax, one of:
//! * `<mask.nii[.gz] | mask.nrrd>[:label=<n>]`: a label map on the CT's grid; nonzero voxels
//!   (or those equal to `n`) are the target;
//! * `<rtstruct.dcm>:<ROI name>`: the ROI's closed planar contours, rasterised on the CT's
//!   slices (even-odd rule, so a contour inside another is a hole);
//! * `point:<x>,<y>,<z>:r=<radius>`: the CT voxels whose centres lie within `radius` mm of
//!   the point (LPS millimetres, as a planning system shows them).

use std::fmt;
use std::path::{Path, PathBuf};
use std::str::FromStr;

use serde::{Serialize, Serializer};

use crate::formats::budget::{ScanBudget, MAX_VOLUME_BYTES};
use crate::formats::dicom::DicomStudyContext;
use crate::formats::{nifti, nrrd};
use crate::ingest::scan::{detect_scan_format, ScanFormat};
use crate::volume::{Volume, VolumeGeometry};
use crate::{Error, IoContext, IoOp, Result};

/// How far a mask's grid may lie from the CT's and still be the CT's grid, mm (float32
/// affines and DS rounding stay far below it; a resampled grid is off by far more).
pub const TARGET_GRID_TOLERANCE_MM: f64 = 0.01;
/// Largest radius of a point target, mm (a sphere wider than a lung is a typing error).
pub const MAX_TARGET_RADIUS_MM: f64 = 150.0;

/// Where the target comes from, as `--target` (or the run inputs' `target`) names it.
#[derive(Debug, Clone, PartialEq)]
pub enum TargetSpec {
    /// A label map on the CT's grid.
    Mask {
        /// NIfTI or NRRD file.
        path: PathBuf,
        /// Only this label is the target (else every nonzero voxel).
        label: Option<u8>,
    },
    /// An ROI of a DICOM RT Structure Set.
    Rtstruct {
        /// The RTSTRUCT file.
        path: PathBuf,
        /// ROIName (3006,0026) of the ROI, as stored (compared ignoring case when no exact
        /// match exists).
        roi: String,
    },
    /// A sphere around a point.
    Sphere {
        /// Centre, LPS mm.
        centre_lps_mm: [f64; 3],
        /// Radius, mm.
        radius_mm: f64,
    },
}

impl fmt::Display for TargetSpec {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            TargetSpec::Mask { path, label: None } => write!(f, "{}", path.display()),
            TargetSpec::Mask {
                path,
                label: Some(l),
            } => write!(f, "{}:label={l}", path.display()),
            TargetSpec::Rtstruct { path, roi } => write!(f, "{}:{roi}", path.display()),
            TargetSpec::Sphere {
                centre_lps_mm: c,
                radius_mm,
            } => write!(f, "point:{},{},{}:r={radius_mm}", c[0], c[1], c[2]),
        }
    }
}

impl Serialize for TargetSpec {
    fn serialize<S: Serializer>(&self, s: S) -> std::result::Result<S::Ok, S::Error> {
        s.collect_str(self)
    }
}

impl FromStr for TargetSpec {
    type Err = Error;

    /// Parses the text and checks what can be checked without the CT: the numbers, that the
    /// file exists and is a mask (NIfTI, NRRD) or a DICOM file, and that a DICOM file comes
    /// with an ROI name and a mask with nothing but `label=<n>`.
    fn from_str(text: &str) -> Result<Self> {
        let bad = |reason: String| Error::argument(format!("target `{text}`"), reason);
        if let Some(rest) = text.strip_prefix("point:") {
            return parse_point(rest).map_err(bad);
        }
        let (path, qualifier) = split_file(text).map_err(bad)?;
        let format = detect_scan_format(&path).map_err(|e| bad(e.to_string()))?;
        match (format, qualifier) {
            (ScanFormat::Nifti | ScanFormat::Nrrd, None) => {
                Ok(TargetSpec::Mask { path, label: None })
            }
            (ScanFormat::Nifti | ScanFormat::Nrrd, Some(q)) => {
                let label = q.strip_prefix("label=").ok_or_else(|| {
                    bad(format!(
                        "after a mask file only `:label=<n>` may follow, not `:{q}` (an ROI \
                         name goes with an RTSTRUCT file)"
                    ))
                })?;
                let label: u8 = label
                    .trim()
                    .parse()
                    .ok()
                    .filter(|&l| l > 0)
                    .ok_or_else(|| {
                        bad(format!(
                            "label `{label}` is not a whole number from 1 to 255"
                        ))
                    })?;
                Ok(TargetSpec::Mask {
                    path,
                    label: Some(label),
                })
            }
            (ScanFormat::DicomFile, Some(roi)) if !roi.trim().is_empty() => {
                Ok(TargetSpec::Rtstruct {
                    path,
                    roi: roi.to_string(),
                })
            }
            (ScanFormat::DicomFile, _) => Err(bad(format!(
                "{} is a DICOM file: name the ROI after a colon, e.g. `{}:GTV`",
                path.display(),
                path.display()
            ))),
            (ScanFormat::DicomDirectory | ScanFormat::DicomZip, _) => Err(bad(format!(
                "{} is a directory or zip; the target is one mask file (NIfTI, NRRD) or one \
                 RTSTRUCT file",
                path.display()
            ))),
        }
    }
}

/// `x,y,z:r=R` after `point:`.
fn parse_point(rest: &str) -> std::result::Result<TargetSpec, String> {
    let syntax = "write a point target as point:<x>,<y>,<z>:r=<radius mm> (LPS mm), e.g. \
                  point:-95,20,-80:r=15";
    let (xyz, radius) = rest
        .split_once(':')
        .ok_or_else(|| format!("no radius: {syntax}"))?;
    let number = |what: &str, s: &str| -> std::result::Result<f64, String> {
        s.trim()
            .parse::<f64>()
            .ok()
            .filter(|v| v.is_finite() && v.abs() <= 1e5)
            .ok_or_else(|| format!("{what} `{s}` is not a finite number of millimetres; {syntax}"))
    };
    let parts: Vec<&str> = xyz.split(',').collect();
    let [x, y, z] = parts[..] else {
        return Err(format!(
            "the point has {} coordinate(s), not 3; {syntax}",
            parts.len()
        ));
    };
    let centre_lps_mm = [number("x", x)?, number("y", y)?, number("z", z)?];
    let radius = radius
        .trim()
        .strip_prefix("r=")
        .ok_or_else(|| format!("`{radius}` is not r=<radius mm>; {syntax}"))?;
    let radius_mm = number("radius", radius)?;
    if radius_mm <= 0.0 || radius_mm > MAX_TARGET_RADIUS_MM {
        return Err(format!(
            "radius {radius_mm} mm is outside 0–{MAX_TARGET_RADIUS_MM} mm"
        ));
    }
    Ok(TargetSpec::Sphere {
        centre_lps_mm,
        radius_mm,
    })
}

/// The file and the text after it: the whole text when it names an existing file, else the
/// longest prefix before a colon that does (file names may hold colons, ROI names too).
fn split_file(text: &str) -> std::result::Result<(PathBuf, Option<&str>), String> {
    if Path::new(text).is_file() {
        return Ok((text.into(), None));
    }
    let found = text
        .char_indices()
        .filter(|&(_, c)| c == ':')
        .map(|(at, _)| at)
        .rev()
        .find(|&at| Path::new(&text[..at]).is_file());
    match found {
        Some(at) => Ok((text[..at].into(), Some(&text[at + 1..]))),
        None => {
            let file = text.split(':').next().unwrap_or(text);
            Err(format!(
                "no such file: {file} (expected a mask file, mask:label=<n>, rtstruct:<ROI \
                 name> or point:<x>,<y>,<z>:r=<mm>)"
            ))
        }
    }
}

/// The target as a mask on the planning CT's grid.
#[derive(Debug, Clone)]
pub struct TargetMask {
    /// 1 inside the target, 0 outside, on the CT's grid.
    pub mask: Volume<u8>,
    /// What it was made from (the spec as given).
    pub source: String,
    /// Things the user should know (an RTSTRUCT placed without a frame of reference check).
    pub notes: Vec<String>,
}

impl TargetMask {
    /// Number of target voxels.
    pub fn voxel_count(&self) -> usize {
        self.mask.as_slice().iter().filter(|&&v| v != 0).count()
    }
}

impl TargetSpec {
    /// The target on the CT grid `ct`: the mask file read and checked against that grid, the
    /// RTSTRUCT's ROI rasterised on its slices (its frame of reference checked against
    /// `study`'s when the CT came from DICOM), or the sphere's voxels. Refuses a target that
    /// holds no CT voxel.
    pub fn resolve(
        &self,
        ct: &VolumeGeometry,
        study: Option<&DicomStudyContext>,
    ) -> Result<TargetMask> {
        let mut notes = Vec::new();
        let mask = match self {
            TargetSpec::Mask { path, label } => read_mask(path, *label, ct)?,
            TargetSpec::Rtstruct { path, roi } => {
                let frame_of_reference = study
                    .filter(|s| s.from_input)
                    .map(|s| s.frame_of_reference_uid.as_str());
                if frame_of_reference.is_none() {
                    notes.push(format!(
                        "the CT carries no DICOM frame of reference (NIfTI or NRRD): ROI \
                         {roi} of {} is placed by its patient coordinates alone",
                        path.display()
                    ));
                }
                super::rtstruct::read_roi_mask(path, roi, ct, frame_of_reference)?
            }
            TargetSpec::Sphere {
                centre_lps_mm,
                radius_mm,
            } => sphere_mask(ct, *centre_lps_mm, *radius_mm)?,
        };
        let target = TargetMask {
            mask,
            source: self.to_string(),
            notes,
        };
        if target.voxel_count() == 0 {
            return Err(Error::argument(
                format!("target `{self}`"),
                format!("it holds no voxel of the CT's grid ({})", describe_grid(ct)),
            ));
        }
        Ok(target)
    }
}

/// The grid in words: voxels, spacing, origin, and the direction when it is not the identity.
pub fn describe_grid(g: &VolumeGeometry) -> String {
    let [a, b, c] = g.dims;
    let [sx, sy, sz] = g.spacing_mm;
    let [ox, oy, oz] = g.origin_lps_mm;
    let identity = (g.direction() - nalgebra::Matrix3::identity()).abs().max() < 1e-6;
    let direction = if identity {
        String::new()
    } else {
        format!(", axes {:?}", g.direction_lps)
    };
    format!(
        "{a}×{b}×{c} voxels of {sx}×{sy}×{sz} mm, first voxel at ({ox}, {oy}, {oz}) mm LPS{direction}"
    )
}

/// The voxels of each label (1–255) of the NIfTI or NRRD label map at `path`, checked to lie
/// on `ct` as a `--target` mask must; labels with no voxel are left out. What an uploaded
/// mask is checked with before a request names one of its labels.
pub fn mask_label_counts(path: &Path, ct: &VolumeGeometry) -> Result<Vec<(u8, usize)>> {
    let labels = read_label_map(path, ct)?;
    let mut counts = [0usize; 256];
    labels
        .as_slice()
        .iter()
        .for_each(|&v| counts[v as usize] += 1);
    Ok((1..=255u8)
        .filter(|&l| counts[l as usize] > 0)
        .map(|l| (l, counts[l as usize]))
        .collect())
}

/// Reads a NIfTI or NRRD label map and checks it lies on `ct`.
fn read_label_map(path: &Path, ct: &VolumeGeometry) -> Result<Volume<u8>> {
    let labels = match detect_scan_format(path)? {
        ScanFormat::Nrrd => {
            let size = std::fs::metadata(path).at(IoOp::Metadata, path)?.len();
            if size > MAX_VOLUME_BYTES {
                return Err(Error::scan(
                    path,
                    format!("{size} bytes is more than a mask of any CT grid needs"),
                ));
            }
            let bytes = std::fs::read(path).at(IoOp::Read, path)?;
            // A mostly empty mask compresses far beyond the CT readers' ratio cap.
            let budget = ScanBudget::for_this_machine().without_ratio_cap();
            let values = nrrd::parse_nrrd_within(&bytes, &path.display().to_string(), &budget)?;
            let codes: Vec<u8> = values
                .as_slice()
                .iter()
                .map(|&v| {
                    if v == 0.0 {
                        0
                    } else if v.fract() == 0.0 && (1.0..=255.0).contains(&v) {
                        v as u8
                    } else {
                        255
                    }
                })
                .collect();
            Volume::from_data(values.geometry, codes)?
        }
        _ => nifti::read_nifti_labels(path)?,
    };
    if !labels.geometry.same_grid(ct, TARGET_GRID_TOLERANCE_MM) {
        return Err(Error::scan(
            path,
            format!(
                "the target mask is not on the CT's grid: the mask has {}, the CT {}; \
                 resample the mask onto the CT (nearest neighbour) first",
                describe_grid(&labels.geometry),
                describe_grid(ct)
            ),
        ));
    }
    Ok(labels)
}

/// Reads a NIfTI or NRRD label map, checks it lies on `ct`, and keeps `label` (or nonzero).
fn read_mask(path: &Path, label: Option<u8>, ct: &VolumeGeometry) -> Result<Volume<u8>> {
    let labels = read_label_map(path, ct)?;
    let keep = |v: u8| match label {
        Some(l) => v == l,
        None => v != 0,
    };
    if let Some(l) = label {
        if !labels.as_slice().contains(&l) {
            let mut present = [false; 256];
            labels
                .as_slice()
                .iter()
                .for_each(|&v| present[v as usize] = true);
            let list: Vec<String> = (1..256)
                .filter(|&v| present[v])
                .map(|v| v.to_string())
                .collect();
            return Err(Error::scan(
                path,
                format!(
                    "label {l} is not in the mask; labels present: {}",
                    if list.is_empty() {
                        "none (the mask is empty)".to_string()
                    } else {
                        list.join(", ")
                    }
                ),
            ));
        }
    }
    let data = labels
        .as_slice()
        .iter()
        .map(|&v| u8::from(keep(v)))
        .collect();
    // The CT's own geometry, so later grid comparisons are exact.
    Volume::from_data(*ct, data)
}

/// The voxels of `ct` whose centres lie within `radius_mm` of `centre_lps_mm`.
fn sphere_mask(ct: &VolumeGeometry, centre_lps_mm: [f64; 3], radius_mm: f64) -> Result<Volume<u8>> {
    let mut mask = Volume::filled(*ct, 0u8)?;
    let centre = ct.lps_mm_to_voxel(centre_lps_mm.into());
    // The sphere's box in voxel indices (any direction: a sphere's box is the same in every
    // orthonormal frame, scaled per axis by the spacing).
    let range = |axis: usize| {
        let reach = radius_mm / ct.spacing_mm[axis];
        let lo = (centre[axis] - reach).floor().max(0.0);
        let hi = (centre[axis] + reach)
            .ceil()
            .min(ct.dims[axis] as f64 - 1.0);
        (lo as usize, hi)
    };
    let ranges = [range(0), range(1), range(2)];
    if ranges.iter().any(|&(lo, hi)| hi < lo as f64) {
        return Ok(mask);
    }
    let centre_mm = nalgebra::Vector3::from(centre_lps_mm);
    let g = *ct;
    let data = mask.as_slice_mut();
    for k in ranges[2].0..=ranges[2].1 as usize {
        for j in ranges[1].0..=ranges[1].1 as usize {
            for i in ranges[0].0..=ranges[0].1 as usize {
                let p = g.voxel_to_lps_mm(nalgebra::Vector3::new(i as f64, j as f64, k as f64));
                if (p - centre_mm).norm() <= radius_mm {
                    data[g.index(i, j, k)] = 1;
                }
            }
        }
    }
    Ok(mask)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn point_targets_parse_and_print_back() {
        let t: TargetSpec = "point:-95,20,-80:r=15".parse().unwrap();
        assert_eq!(
            t,
            TargetSpec::Sphere {
                centre_lps_mm: [-95.0, 20.0, -80.0],
                radius_mm: 15.0
            }
        );
        assert_eq!(t.to_string(), "point:-95,20,-80:r=15");
        let t: TargetSpec = "point: -95.5, 20 ,-80 : r= 7.5".parse().unwrap();
        assert!(matches!(t, TargetSpec::Sphere { radius_mm, .. } if radius_mm == 7.5));
    }

    #[test]
    fn bad_point_syntax_is_refused_with_the_part_at_fault() {
        for (text, says) in [
            ("point:-95,20:r=15", "2 coordinate(s), not 3"),
            ("point:-95,20,-80", "no radius"),
            ("point:-95,20,-80:15", "is not r=<radius mm>"),
            ("point:-95,abc,-80:r=15", "y `abc` is not a finite number"),
            ("point:-95,20,-80:r=0", "radius 0 mm is outside"),
            ("point:-95,20,-80:r=NaN", "radius `NaN`"),
            ("point:-95,20,-80:r=500", "radius 500 mm is outside"),
        ] {
            let e = text.parse::<TargetSpec>().unwrap_err();
            let shown = e.to_string();
            assert!(shown.contains(says), "{text}: {shown}");
            assert!(shown.contains(text), "names the value: {shown}");
        }
    }

    #[test]
    fn a_missing_file_is_named() {
        let e = "/no/such/mask.nii.gz:label=8"
            .parse::<TargetSpec>()
            .unwrap_err()
            .to_string();
        assert!(e.contains("no such file: /no/such/mask.nii.gz"), "{e}");
    }

    #[test]
    fn a_sphere_holds_the_voxels_within_its_radius() {
        let g = VolumeGeometry::axis_aligned([20, 20, 20], [2.0, 2.0, 2.0], [0.0, 0.0, 0.0]);
        let m = sphere_mask(&g, [20.0, 20.0, 20.0], 6.0).unwrap();
        let count = m.as_slice().iter().filter(|&&v| v == 1).count();
        // Points of the integer lattice within radius 3: 123.
        assert_eq!(count, 123);
        let outside = sphere_mask(&g, [500.0, 20.0, 20.0], 6.0).unwrap();
        assert!(outside.as_slice().iter().all(|&v| v == 0));
    }
}
