//! Loading a CT from whatever the user hands us: a DICOM directory, a zip of a DICOM series,
//! a single DICOM file, a NIfTI (`.nii`, `.nii.gz`) or a NRRD file, told apart by content,
//! never by file name alone.

use std::io::Read;
use std::path::Path;

use serde::Serialize;

use crate::formats::{dicom, nifti, nrrd};
use crate::volume::Volume;
use crate::{Error, IoContext, IoOp, Result};

/// The container a scan arrived in.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum ScanFormat {
    /// A directory of DICOM files (searched recursively).
    DicomDirectory,
    /// A zip archive holding a DICOM series.
    DicomZip,
    /// One DICOM file (a multi-slice series needs the others: pass the directory).
    DicomFile,
    /// NIfTI-1 or NIfTI-2, plain or gzip-compressed.
    Nifti,
    /// NRRD with attached data.
    Nrrd,
}

/// A CT in Hounsfield units on its own grid, with where it came from.
#[derive(Debug, Clone)]
pub struct LoadedScan {
    /// The CT in HU, LPS geometry.
    pub ct: Volume<f32>,
    /// What the input was.
    pub format: ScanFormat,
    /// The DICOM series' non-identifying description, when the input was DICOM.
    pub series: Option<dicom::SeriesInfo>,
    /// The DICOM series' patient, study and frame of reference (identifying: never logged
    /// or serialized), when the input was DICOM.
    pub study: Option<dicom::DicomStudyContext>,
    /// Files skipped and other things the user should know.
    pub warnings: Vec<String>,
}

/// Tells the format of `path` from its content (magic numbers, header sizes).
pub fn detect_scan_format(path: &Path) -> Result<ScanFormat> {
    let meta = std::fs::metadata(path).at(IoOp::Open, path)?;
    if meta.is_dir() {
        return Ok(ScanFormat::DicomDirectory);
    }
    let mut head = Vec::with_capacity(544);
    std::fs::File::open(path)
        .and_then(|f| f.take(544).read_to_end(&mut head))
        .at(IoOp::Read, path)?;
    classify_header(&head).ok_or_else(|| {
        Error::scan(
            path,
            format!(
                "not a DICOM directory, zip, DICOM, NIfTI or NRRD file (first bytes {:02x?})",
                &head[..head.len().min(8)]
            ),
        )
    })
}

/// Recognises a format from the first bytes of a file.
pub fn classify_header(head: &[u8]) -> Option<ScanFormat> {
    let nifti_size = |b: &[u8]| {
        b.len() >= 4 && {
            let le = i32::from_le_bytes([b[0], b[1], b[2], b[3]]);
            let be = i32::from_be_bytes([b[0], b[1], b[2], b[3]]);
            [348, 540].contains(&le) || [348, 540].contains(&be)
        }
    };
    if head.starts_with(b"PK\x03\x04") || head.starts_with(b"PK\x05\x06") {
        Some(ScanFormat::DicomZip)
    } else if head.starts_with(&[0x1f, 0x8b]) {
        // Gzip: we only read gzip-compressed NIfTI (a gzip NRRD would start with "NRRD").
        Some(ScanFormat::Nifti)
    } else if head.starts_with(b"NRRD000") {
        Some(ScanFormat::Nrrd)
    } else if head.len() >= 132 && &head[128..132] == b"DICM" {
        Some(ScanFormat::DicomFile)
    } else if nifti_size(head) {
        Some(ScanFormat::Nifti)
    } else {
        None
    }
}

/// Reads a CT from a DICOM directory, zip or file, a NIfTI or a NRRD file.
///
/// # Examples
///
/// ```
/// use lungmotion::ingest::scan::{load_ct, ScanFormat};
///
/// let path = concat!(env!("CARGO_MANIFEST_DIR"), "/sample-volumes/phantom-ct.nii.gz");
/// let scan = load_ct(std::path::Path::new(path))?;
/// assert_eq!(scan.format, ScanFormat::Nifti);
/// // Voxels are in Hounsfield units on a grid placed in LPS millimetres.
/// let g = scan.ct.geometry;
/// assert_eq!(scan.ct.as_slice().len(), g.dims[0] * g.dims[1] * g.dims[2]);
/// # Ok::<(), lungmotion::Error>(())
/// ```
pub fn load_ct(path: &Path) -> Result<LoadedScan> {
    load_ct_with(path, &dicom::DicomReadOptions::default())
}

/// [`load_ct`] with DICOM options (which series of several to read).
pub fn load_ct_with(path: &Path, dicom_options: &dicom::DicomReadOptions) -> Result<LoadedScan> {
    load_ct_cancellable(path, dicom_options, None)
}

/// [`load_ct_with`], stopped with [`Error::Cancelled`] once `cancel` is raised (a DICOM
/// series is checked before each slice; a NIfTI or NRRD file is one read).
pub fn load_ct_cancellable(
    path: &Path,
    dicom_options: &dicom::DicomReadOptions,
    cancel: Option<&std::sync::atomic::AtomicBool>,
) -> Result<LoadedScan> {
    let start = std::time::Instant::now();
    let format = detect_scan_format(path)?;
    let (ct, series, study, warnings) = match format {
        ScanFormat::DicomDirectory | ScanFormat::DicomZip | ScanFormat::DicomFile => {
            let s = dicom::read_dicom_series_cancellable(path, dicom_options, cancel)?;
            (s.volume, Some(s.info), Some(s.study), s.warnings)
        }
        ScanFormat::Nifti => (nifti::read_nifti(path)?, None, None, Vec::new()),
        ScanFormat::Nrrd => (nrrd::read_nrrd(path)?, None, None, Vec::new()),
    };
    let read_s = start.elapsed().as_secs_f64();
    check_spacing_for_lung_model(&ct.geometry.spacing_mm, path)?;
    let mut warnings = warnings;
    warnings.extend(check_hounsfield(&ct, path)?);
    tracing::info!(
        read_s,
        checks_s = start.elapsed().as_secs_f64() - read_s,
        dims = ?ct.geometry.dims,
        "CT loaded"
    );
    Ok(LoadedScan {
        ct,
        format,
        series,
        study,
        warnings,
    })
}

/// Refuses volumes that cannot be a CT in Hounsfield units (non-finite values, no air at all)
/// and warns about unusual ranges, so a mislabelled MR or a raw-count image fails here, by name.
pub fn check_hounsfield(ct: &Volume<f32>, path: &Path) -> Result<Vec<String>> {
    use rayon::prelude::*;
    let (non_finite, below_air, min, max) = ct
        .as_slice()
        .par_iter()
        .fold(
            || (0usize, 0usize, f32::INFINITY, f32::NEG_INFINITY),
            |(n, b, lo, hi), &v| {
                if !v.is_finite() {
                    (n + 1, b, lo, hi)
                } else {
                    (n, b + usize::from(v < AIR_LIKE_HU), lo.min(v), hi.max(v))
                }
            },
        )
        .reduce(
            || (0, 0, f32::INFINITY, f32::NEG_INFINITY),
            |a, b| (a.0 + b.0, a.1 + b.1, a.2.min(b.2), a.3.max(b.3)),
        );
    let name = path;
    if non_finite > 0 {
        return Err(Error::scan(
            name,
            format!("{non_finite} voxels are NaN or infinite"),
        ));
    }
    let fraction = below_air as f64 / ct.as_slice().len() as f64;
    if fraction < MIN_AIR_FRACTION {
        return Err(Error::scan(
            name,
            format!(
                "not a chest CT in Hounsfield units: only {:.2} % of voxels are below \
             {AIR_LIKE_HU} HU (values {min} … {max}); lungs and outside air should be near −1000 \
             HU (an MR, or raw detector counts without the rescale?)",
                100.0 * fraction
            ),
        ));
    }
    let mut warnings = Vec::new();
    if max > 5000.0 {
        warnings.push(format!(
            "{}: maximum {max} HU is far above bone (≈ 1000–2000 HU): metal, or an unusual rescale",
            name.display()
        ));
    }
    Ok(warnings)
}

/// Refuses voxel spacings too coarse for a lung model, whatever the format: the coarsest axis
/// (the slices, in a CT) above [`MAX_SLICE_SPACING_MM`] or another axis above
/// [`MAX_IN_PLANE_SPACING_MM`].
pub fn check_spacing_for_lung_model(spacing_mm: &[f64; 3], path: &Path) -> Result<()> {
    let mut axes = [0usize, 1, 2];
    axes.sort_by(|&a, &b| spacing_mm[a].total_cmp(&spacing_mm[b]));
    let [_, in_plane, slices] = axes;
    let shown = format!(
        "{} × {} × {} mm",
        round_mm(spacing_mm[0]),
        round_mm(spacing_mm[1]),
        round_mm(spacing_mm[2])
    );
    let fault = if spacing_mm[slices] > MAX_SLICE_SPACING_MM {
        Some(format!(
            "its slices are {} mm apart (axis {}), above the {MAX_SLICE_SPACING_MM} mm a lung \
             model needs: the lung is about 20 cm tall and its base moves 10–30 mm in a breath, \
             so coarser slices cannot place the diaphragm to within the motion being predicted",
            round_mm(spacing_mm[slices]),
            slices
        ))
    } else if spacing_mm[in_plane] > MAX_IN_PLANE_SPACING_MM {
        Some(format!(
            "its in-plane pixels are {} mm (axis {}), above the {MAX_IN_PLANE_SPACING_MM} mm \
             a lung model needs: each lung is about 10 cm wide and the trachea 15–20 mm, so \
             coarser pixels cannot separate the lungs or find the airways",
            round_mm(spacing_mm[in_plane]),
            in_plane
        ))
    } else {
        None
    };
    match fault {
        Some(why) => Err(Error::scan(
            path,
            format!("voxel spacing {shown} is too coarse for a lung model: {why}"),
        )),
        None => Ok(()),
    }
}

/// Millimetres to 2 decimals, for messages.
fn round_mm(mm: f64) -> f64 {
    (mm * 100.0).round() / 100.0
}

/// Largest spacing along the coarsest axis (slice spacing): clinical chest CTs are
/// reconstructed at 0.5–5 mm, legacy thick-slice series at up to 10 mm.
pub const MAX_SLICE_SPACING_MM: f64 = 10.0;
/// Largest spacing along the two other axes: clinical in-plane pixels are 0.5–1 mm; the
/// bundled phantom uses 5 mm and the CIP test CT 4.17 mm, both still segment correctly.
pub const MAX_IN_PLANE_SPACING_MM: f64 = 5.0;

/// Below this, a voxel holds air or lung (lung parenchyma is ≈ −850 HU).
const AIR_LIKE_HU: f32 = -500.0;
/// A chest CT is at least this fraction air or lung; a few percent would already be a small lung.
const MIN_AIR_FRACTION: f64 = 0.01;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn formats_are_told_apart_by_content() {
        let mut dicom = vec![0u8; 132];
        dicom[128..132].copy_from_slice(b"DICM");
        assert_eq!(classify_header(&dicom), Some(ScanFormat::DicomFile));
        assert_eq!(
            classify_header(b"PK\x03\x04rest"),
            Some(ScanFormat::DicomZip)
        );
        assert_eq!(
            classify_header(&[0x1f, 0x8b, 8, 0]),
            Some(ScanFormat::Nifti)
        );
        assert_eq!(classify_header(b"NRRD0004\n"), Some(ScanFormat::Nrrd));
        assert_eq!(
            classify_header(&348i32.to_le_bytes()),
            Some(ScanFormat::Nifti)
        );
        assert_eq!(
            classify_header(&540i32.to_be_bytes()),
            Some(ScanFormat::Nifti)
        );
        assert_eq!(classify_header(b"hello world"), None);
        assert_eq!(classify_header(b""), None);
    }

    #[test]
    fn spacings_too_coarse_for_a_lung_model_are_refused_naming_the_axis() {
        let ok = |s: [f64; 3]| check_spacing_for_lung_model(&s, Path::new("ct.nrrd"));
        ok([0.7, 0.7, 2.5]).unwrap();
        ok([5.0, 5.0, 5.0]).unwrap();
        ok([4.17, 4.17, 10.0]).unwrap();
        let e = ok([4.171872, 4.171872, 39.873]).unwrap_err().to_string();
        for part in [
            "ct.nrrd",
            "4.17 × 4.17 × 39.87 mm",
            "39.87 mm apart (axis 2)",
            "10 mm",
        ] {
            assert!(e.contains(part), "{part}: {e}");
        }
        // The slice axis is the coarsest, whichever it is.
        let e = ok([12.0, 1.0, 1.0]).unwrap_err().to_string();
        assert!(e.contains("12 mm apart (axis 0)"), "{e}");
        let e = ok([0.8, 6.0, 8.0]).unwrap_err().to_string();
        assert!(
            e.contains("in-plane pixels are 6 mm (axis 1)") && e.contains("5 mm"),
            "{e}"
        );
    }

    #[test]
    fn images_that_are_not_ct_in_hu_are_refused() {
        use crate::volume::VolumeGeometry;
        let g = VolumeGeometry::axis_aligned([8, 8, 8], [2.0; 3], [0.0; 3]);
        let mut ct = Volume::filled(g, 40.0f32).unwrap();
        let e = check_hounsfield(&ct, Path::new("mr.nii"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("mr.nii") && e.contains("Hounsfield"), "{e}");
        for v in ct.as_slice_mut().iter_mut().take(100) {
            *v = -1000.0;
        }
        assert!(check_hounsfield(&ct, Path::new("ct.nii"))
            .unwrap()
            .is_empty());
        ct.as_slice_mut()[200] = f32::NAN;
        let e = check_hounsfield(&ct, Path::new("ct.nii"))
            .unwrap_err()
            .to_string();
        assert!(e.contains("NaN"), "{e}");
    }
}
