//! `lungmotion phantom`: the procedural thorax phantom written to disk.

use std::path::PathBuf;

use lungmotion::phantom::{
    write_four_dct_phantom, write_phantom_files, FourDctPhantomSettings, PhantomSettings,
};

use super::prepare_out;

/// Options of `lungmotion phantom`.
#[derive(clap::Args)]
pub struct PhantomArgs {
    /// Directory for the phantom files.
    #[arg(long, default_value = "sample-volumes")]
    out: PathBuf,
    /// Random seed of the noise (same seed, same bytes).
    #[arg(long)]
    seed: Option<u64>,
    /// Leave the tumour out.
    #[arg(long)]
    no_tumour: bool,
    /// Instead: a 4D-CT of the phantom, the same anatomy at several breathing states moved
    /// by an analytic field (not the model): phases/<T..>.nii.gz, DIR-Lab landmark files in
    /// landmarks/, landmarks.csv (LPS mm) and phantom-4d.json.
    #[arg(long = "4dct")]
    four_dct: bool,
    /// With --4dct: number of phases over one breathing cycle (phase 0 end-inhale).
    #[arg(long, default_value_t = 10, requires = "four_dct")]
    phases: usize,
    /// Voxel spacing in mm (all three axes; default 5).
    #[arg(long, value_name = "MM")]
    spacing: Option<f64>,
}

impl PhantomArgs {
    /// Writes the phantom's files and names them on stderr.
    pub fn execute(self) -> anyhow::Result<()> {
        prepare_out(&self.out)?;
        let mut settings = PhantomSettings::default();
        if let Some(seed) = self.seed {
            settings.seed = seed;
        }
        if self.no_tumour {
            settings.tumour = None;
        }
        if let Some(spacing) = self.spacing {
            settings.spacing_mm = [spacing; 3];
        }
        if self.four_dct {
            let four_dct = FourDctPhantomSettings::with_phases(settings, self.phases);
            let written = write_four_dct_phantom(&four_dct, &self.out)?;
            for phase in &written.phases {
                eprintln!(
                    "lungmotion: phase {} (amplitude {:.2}): lungs {:.0} mL",
                    phase.name,
                    phase.amplitude,
                    phase.right_lung_volume_ml + phase.left_lung_volume_ml
                );
            }
            eprintln!(
                "lungmotion: wrote {} phases and {} landmarks per phase into {}",
                written.phases.len(),
                written.lung_landmarks_lps_mm[0].len(),
                self.out.display()
            );
            return Ok(());
        }
        for p in write_phantom_files(&settings, &self.out)? {
            eprintln!("lungmotion: wrote {}", p.display());
        }
        Ok(())
    }
}
