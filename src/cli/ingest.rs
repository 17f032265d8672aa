//! `lungmotion ingest`: a CT turned into the mechanical model, its files written.

use std::path::PathBuf;

use anyhow::Context;
use lungmotion::formats::dicom::DicomReadOptions;
use lungmotion::ingest::{load_ct_with, IngestSettings};
use lungmotion::outputs::ingest_files::write_ingest_outputs;

use super::prepare_out;

/// Options of `lungmotion ingest`.
#[derive(clap::Args)]
pub struct IngestArgs {
    /// The CT: a DICOM directory, a zip of one DICOM series, a NIfTI (.nii, .nii.gz) or a
    /// NRRD file (told apart by content).
    #[arg(long)]
    ct: PathBuf,
    /// Directory for the outputs (created if missing; files in it are replaced atomically).
    #[arg(long)]
    out: PathBuf,
    /// Edge of the cubic elements in millimetres (2–16).
    #[arg(long)]
    element_size: Option<f64>,
    /// The DICOM series to read when the CT folder or zip holds several: uid:<UID>,
    /// number:<N>, description:<text>, or the bare value (default: the only CT series that
    /// is not a scout).
    #[arg(long)]
    series: Option<lungmotion::formats::dicom::SeriesChoice>,
    /// Your own constraint groups: a label map on the CT's grid with the codes listed in
    /// ingest.json (1 hilum, 2 mediastinal, 3 costal, 4 diaphragmatic, 5 apex).
    #[arg(long)]
    groups: Option<PathBuf>,
}

impl IngestArgs {
    /// Segments the lungs, builds the model, writes its files and prints what was built.
    pub fn execute(self) -> anyhow::Result<()> {
        prepare_out(&self.out)?;
        let settings = self.settings()?;
        eprintln!("lungmotion: reading {}", self.ct.display());
        let dicom_options = DicomReadOptions {
            series: self.series.clone(),
            ..DicomReadOptions::default()
        };
        let scan = load_ct_with(&self.ct, &dicom_options)?;
        for w in &scan.warnings {
            eprintln!("lungmotion: warning: {w}");
        }
        let g = scan.ct.geometry;
        eprintln!(
            "lungmotion: CT {}×{}×{} voxels of {:.3}×{:.3}×{:.3} mm; segmenting the lungs",
            g.dims[0], g.dims[1], g.dims[2], g.spacing_mm[0], g.spacing_mm[1], g.spacing_mm[2]
        );
        let outcome = lungmotion::ingest::ingest_scan(&scan, &settings)?;
        let s = &outcome.summary;
        for w in s.warnings.iter().skip(scan.warnings.len()) {
            eprintln!("lungmotion: warning: {w}");
        }
        let writing = std::time::Instant::now();
        let written = write_ingest_outputs(&self.out, &scan.ct, &outcome)
            .with_context(|| format!("writing the ingest outputs into {}", self.out.display()))?;
        tracing::info!(
            seconds = writing.elapsed().as_secs_f64(),
            "ingest outputs written"
        );
        print_model(s);
        for p in written {
            eprintln!("lungmotion: wrote {}", p.display());
        }
        Ok(())
    }

    /// The ingest settings: defaults, the element size and the user's constraint groups.
    fn settings(&self) -> anyhow::Result<IngestSettings> {
        let mut settings = IngestSettings::default();
        if let Some(mm) = self.element_size {
            settings.model.element_size_mm = mm;
        }
        if let Some(path) = &self.groups {
            let labels = lungmotion::formats::nifti::read_nifti_labels(path)
                .with_context(|| format!("reading the constraint groups {}", path.display()))?;
            settings.model.group_overrides = Some(labels);
        }
        Ok(settings)
    }
}

/// The lungs and the model on stdout.
fn print_model(s: &lungmotion::ingest::IngestSummary) {
    println!(
        "lungs {:.0} mL (right {:.0} mL, left {:.0} mL); {} elements of {} mm, {} nodes",
        s.lung_volume_ml,
        s.right_volume_ml,
        s.left_volume_ml,
        s.elements,
        s.element_size_mm,
        s.nodes
    );
    let groups: Vec<String> = s
        .group_nodes
        .iter()
        .map(|(name, n)| format!("{name} {n}"))
        .collect();
    println!("constraint groups (nodes): {}", groups.join(", "));
}
