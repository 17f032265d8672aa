//! The ingest stage end to end: CT in HU → lung segmentation → cubic elements and
//! constraint groups, with the summary `ingest.json` reports.

use std::collections::BTreeMap;
use std::time::Instant;

use serde::Serialize;

use super::lung_model::{
    build_lung_model_with, ConstraintGroup, LungModel, LungModelReport, LungModelSettings,
    PrebuiltWall,
};
use super::scan::LoadedScan;
use super::segmentation::{
    segment_lungs_cancellable, LungSegmentation, SegmentationReport, SegmentationSettings,
};
use super::Cancel;
use crate::volume::VolumeGeometry;
use crate::{Error, Result};

/// Plausible volume of both lungs in the segmentation, mL: adult total lung capacity is
/// about 6 L (4–8 L), residual volume above 1 L, and hyperinflated emphysema stays under
/// 10 L; outside, the scan's geometry or the segmentation is wrong.
pub const PLAUSIBLE_LUNG_ML: std::ops::RangeInclusive<f64> = 1000.0..=10_000.0;

/// Everything ingest can be told.
#[derive(Debug, Clone, Default)]
pub struct IngestSettings {
    /// Lung segmentation thresholds.
    pub segmentation: SegmentationSettings,
    /// Element size, material and constraint-group overrides.
    pub model: LungModelSettings,
}

/// The result of ingest: the masks on the CT grid, the mechanical model and its summary.
pub struct IngestOutcome {
    /// Lungs (1 right, 2 left), airways and body on the CT grid.
    pub segmentation: LungSegmentation,
    /// Cubic elements, constraint groups and the cavity wall.
    pub model: LungModel,
    /// What `ingest.json` holds.
    pub summary: IngestSummary,
}

/// The machine-readable ingest summary (`ingest.json`); other tools script against its fields.
#[derive(Debug, Clone, Serialize)]
pub struct IngestSummary {
    /// lungmotion version that produced it.
    pub software_version: &'static str,
    /// Both lungs in the segmentation, mL.
    pub lung_volume_ml: f64,
    /// Right lung, mL.
    pub right_volume_ml: f64,
    /// Left lung, mL.
    pub left_volume_ml: f64,
    /// Edge of the cubic elements, mm.
    pub element_size_mm: f64,
    /// Number of elements.
    pub elements: usize,
    /// Number of nodes.
    pub nodes: usize,
    /// Nodes in each constraint group, by group name.
    pub group_nodes: BTreeMap<String, usize>,
    /// The code of each group in `groups.nii.gz`, with its mechanical role.
    pub group_codes: BTreeMap<u8, GroupCode>,
    /// Where the CT came from and its grid.
    pub source: ScanSummary,
    /// Segmentation details.
    pub segmentation: SegmentationReport,
    /// Meshing details.
    pub model: LungModelReport,
    /// Stage wall times in seconds.
    pub timings_s: BTreeMap<String, f64>,
    /// Everything the user should know (skipped files, removed elements …).
    pub warnings: Vec<String>,
}

/// One entry of the group legend.
#[derive(Debug, Clone, Serialize)]
pub struct GroupCode {
    /// Short name (`hilum`, `costal`, …).
    pub name: String,
    /// How the simulation treats these nodes.
    pub role: String,
}

/// The input scan, without anything that identifies the patient.
#[derive(Debug, Clone, Serialize)]
pub struct ScanSummary {
    /// Container format.
    pub format: super::scan::ScanFormat,
    /// Grid and LPS placement of the CT.
    pub geometry: VolumeGeometry,
    /// DICOM series description (no patient data).
    pub series: Option<crate::formats::dicom::SeriesInfo>,
}

/// Segments the lungs of a loaded CT and builds its mechanical model.
///
/// # Examples
///
/// ```
/// use lungmotion::ingest::pipeline::{ingest_scan, IngestSettings};
/// use lungmotion::ingest::scan::load_ct;
///
/// let path = concat!(env!("CARGO_MANIFEST_DIR"), "/sample-volumes/phantom-ct.nii.gz");
/// let scan = load_ct(std::path::Path::new(path))?;
/// let mut settings = IngestSettings::default();
/// settings.model.element_size_mm = 12.0; // coarse, so the example runs in a second
/// let outcome = ingest_scan(&scan, &settings)?;
/// assert!(outcome.summary.elements > 0);
/// assert!(outcome.summary.lung_volume_ml > 1000.0);
/// # Ok::<(), lungmotion::Error>(())
/// ```
pub fn ingest_scan(scan: &LoadedScan, settings: &IngestSettings) -> Result<IngestOutcome> {
    ingest_scan_cancellable(scan, settings, Cancel::NEVER)
}

/// [`ingest_scan`], stopped with [`Error::Cancelled`] once `cancel` is raised (looked at
/// between the steps of the segmentation and of the model and inside their long loops).
pub fn ingest_scan_cancellable(
    scan: &LoadedScan,
    settings: &IngestSettings,
    cancel: Cancel<'_>,
) -> Result<IngestOutcome> {
    ingest_from_parts(scan, settings, None, None, cancel)
}

/// The ingest of `scan`, with its segmentation and wall taken from `segmentation` and
/// `wall` when given (an earlier ingest of the same CT and settings: see
/// [`super::stored`]) and computed otherwise.
pub(crate) fn ingest_from_parts(
    scan: &LoadedScan,
    settings: &IngestSettings,
    segmentation: Option<LungSegmentation>,
    wall: Option<PrebuiltWall>,
    cancel: Cancel<'_>,
) -> Result<IngestOutcome> {
    let t0 = Instant::now();
    let segmentation = match segmentation {
        Some(stored) => stored,
        None => segment_lungs_cancellable(&scan.ct, &settings.segmentation, cancel)?,
    };
    let report = &segmentation.report;
    check_lung_volume(
        report.right_volume_ml,
        report.left_volume_ml,
        &scan.ct.geometry,
    )?;
    let t_seg = t0.elapsed().as_secs_f64();
    let t1 = Instant::now();
    let model = build_lung_model_with(
        &segmentation.lungs,
        &segmentation.airways,
        &settings.model,
        wall,
        cancel,
    )?;
    let t_model = t1.elapsed().as_secs_f64();

    let mut warnings = scan.warnings.clone();
    warnings.extend(segmentation.report.warnings.iter().cloned());
    let group_codes = ConstraintGroup::ALL
        .iter()
        .map(|g| {
            (
                g.code(),
                GroupCode {
                    name: g.name().to_string(),
                    role: g.mechanical_role().to_string(),
                },
            )
        })
        .collect();
    let summary = IngestSummary {
        software_version: env!("CARGO_PKG_VERSION"),
        lung_volume_ml: segmentation.report.lung_volume_ml,
        right_volume_ml: segmentation.report.right_volume_ml,
        left_volume_ml: segmentation.report.left_volume_ml,
        element_size_mm: model.report.element_size_mm,
        elements: model.report.elements,
        nodes: model.report.nodes,
        group_nodes: model.report.group_nodes.clone(),
        group_codes,
        source: ScanSummary {
            format: scan.format,
            geometry: scan.ct.geometry,
            series: scan.series.clone(),
        },
        segmentation: segmentation.report.clone(),
        model: model.report.clone(),
        timings_s: BTreeMap::from([
            ("segmentation".to_string(), t_seg),
            ("model".to_string(), t_model),
        ]),
        warnings,
    };
    Ok(IngestOutcome {
        segmentation,
        model,
        summary,
    })
}

/// Refuses a segmentation whose lungs are outside [`PLAUSIBLE_LUNG_ML`], naming the volumes
/// and the spacing they were computed with.
fn check_lung_volume(right_ml: f64, left_ml: f64, geometry: &VolumeGeometry) -> Result<()> {
    let total_ml = right_ml + left_ml;
    if PLAUSIBLE_LUNG_ML.contains(&total_ml) {
        return Ok(());
    }
    let [sx, sy, sz] = geometry.spacing_mm;
    Err(Error::scan(
        "CT for segmentation",
        format!(
            "the segmented lungs hold {:.1} L (right {:.1} L, left {:.1} L), outside the \
             {:.0}–{:.0} L of adult lungs: the voxel spacing ({sx:.2} × {sy:.2} × {sz:.2} mm) \
             is wrong, the scan does not cover the lungs, or it is not a chest CT",
            total_ml / 1000.0,
            right_ml / 1000.0,
            left_ml / 1000.0,
            PLAUSIBLE_LUNG_ML.start() / 1000.0,
            PLAUSIBLE_LUNG_ML.end() / 1000.0,
        ),
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ingest_gives_the_same_masks_mesh_wall_and_groups_on_one_and_two_threads() {
        let path = concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/sample-volumes/phantom-ct.nii.gz"
        );
        let scan = super::super::scan::load_ct(std::path::Path::new(path)).unwrap();
        let mut settings = IngestSettings::default();
        settings.model.element_size_mm = 8.0;
        let on = |threads: usize| {
            rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap()
                .install(|| ingest_scan(&scan, &settings).unwrap())
        };
        let (one, two) = (on(1), on(2));
        let (s1, s2) = (&one.segmentation, &two.segmentation);
        assert_eq!(s1.lungs.as_slice(), s2.lungs.as_slice());
        assert_eq!(s1.airways.as_slice(), s2.airways.as_slice());
        assert_eq!(s1.body.as_slice(), s2.body.as_slice());
        let (m1, m2) = (&one.model, &two.model);
        assert!(m1.mesh.mesh.element_count() > 1000);
        assert_eq!(m1.mesh.mesh.elements, m2.mesh.mesh.elements);
        assert_eq!(m1.mesh.mesh.rest_positions_m, m2.mesh.mesh.rest_positions_m);
        assert_eq!(m1.node_group, m2.node_group);
        assert!(m1.wall.same_samples(&m2.wall));
        assert_eq!(m1.groups_volume.as_slice(), m2.groups_volume.as_slice());
        assert_eq!(
            serde_json::to_value(&m1.report.group_nodes).unwrap(),
            serde_json::to_value(&m2.report.group_nodes).unwrap()
        );
    }

    #[test]
    fn lung_volumes_outside_adult_lungs_are_refused_naming_the_litres() {
        let g = VolumeGeometry::axis_aligned([10, 10, 10], [4.17, 4.17, 39.87], [0.0; 3]);
        let e = check_lung_volume(24_000.0, 21_900.0, &g)
            .unwrap_err()
            .to_string();
        for part in ["45.9 L", "right 24.0 L", "1–10 L", "39.87 mm"] {
            assert!(e.contains(part), "{part}: {e}");
        }
        let e = check_lung_volume(450.0, 0.0, &g).unwrap_err().to_string();
        assert!(e.contains("hold 0.5 L"), "{e}");
        check_lung_volume(2_400.0, 2_190.0, &g).unwrap();
    }
}
