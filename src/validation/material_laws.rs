//! How closely one cube of each material variant (Baudet's linear springs, Boux de Casson's
//! cubic springs, a volumetric law) follows the continuum laws lung models use, and which cubic
//! ratio a least-squares fit to each law asks for.

use serde::Serialize;

use crate::model::spring_law::{cube_response, fit_cubic_ratio, CubeResponse, FitSweeps};
use crate::model::{ContinuumLaw, Material, SpringLaw};
use crate::Result;

/// Poisson's ratio of the study (the lung's default).
const POISSON_RATIO: f64 = 0.3;
/// The cubic ratio shown beside the linear springs: stiff enough to matter at 25 % strain.
pub const SHOWN_CUBIC_RATIO: f64 = 3.0;

/// One element variant against one law along the report's sweeps.
#[derive(Debug, Clone, Serialize)]
pub struct LawComparison {
    /// What the element is, in words.
    pub variant: String,
    /// The response.
    pub response: CubeResponse,
}

/// The study's result.
#[derive(Debug, Clone, Serialize)]
pub struct MaterialLawReport {
    /// Poisson's ratio used.
    pub poisson_ratio: f64,
    /// Every (law, variant) along the wide sweeps (to 50 % stretch, J from 0.3 to 2).
    pub comparisons: Vec<LawComparison>,
    /// Per law: the cubic ratio minimising the RMS stress error over the fit sweeps
    /// (0–25 % stretch, ±20 % volume), with its response there.
    pub fits: Vec<CubeResponse>,
    /// Per law: linear springs on the fit sweeps, for the fit's gain.
    pub linear_on_fit_sweeps: Vec<CubeResponse>,
}

/// The report's wide sweeps: where the variants differ (the fit sweeps are too gentle for the
/// cubic term: a spring of a cube at J = 0.8 is only 7 % short).
fn wide_sweeps() -> FitSweeps {
    FitSweeps {
        uniaxial_stretches: vec![1.1, 1.25, 1.5],
        volume_ratios: vec![0.3, 0.5, 0.8, 1.2, 1.5, 2.0],
    }
}

/// Runs the study.
pub fn run_material_law_study() -> Result<MaterialLawReport> {
    let base = Material::new(1.0, POISSON_RATIO, 1.0)?;
    let laws = [
        ContinuumLaw::NeoHookean,
        ContinuumLaw::Hyperfoam,
        ContinuumLaw::LungBirzle,
    ];
    let mut comparisons = Vec::new();
    let mut fits = Vec::new();
    let mut linear_on_fit_sweeps = Vec::new();
    for law in laws {
        let variants = [
            ("linear springs".to_string(), base),
            (
                format!("cubic springs, c = {SHOWN_CUBIC_RATIO}"),
                base.with_spring_law(SpringLaw::Cubic(SHOWN_CUBIC_RATIO))?,
            ),
            (
                format!("linear springs + volumetric {law:?}"),
                base.with_volumetric_law(Some(law)),
            ),
        ];
        for (variant, material) in variants {
            comparisons.push(LawComparison {
                variant,
                response: cube_response(law, material, &wide_sweeps())?,
            });
        }
        fits.push(fit_cubic_ratio(law, POISSON_RATIO)?);
        linear_on_fit_sweeps.push(cube_response(law, base, &FitSweeps::default())?);
    }
    Ok(MaterialLawReport {
        poisson_ratio: POISSON_RATIO,
        comparisons,
        fits,
        linear_on_fit_sweeps,
    })
}

impl MaterialLawReport {
    /// The study as a markdown section.
    pub fn to_markdown(&self) -> String {
        let mut s = format!(
            "## Spring and volumetric laws against continuum laws (one cube, ν = {})\n\n\
             Relative stress error (element / law − 1): nominal axial stress under uniaxial \
             stress at the given stretch, Cauchy pressure at the given volume ratio J.\n\n",
            self.poisson_ratio
        );
        let sweeps = wide_sweeps();
        s.push_str("| law | element | ");
        for l in &sweeps.uniaxial_stretches {
            s.push_str(&format!("stretch {l} | "));
        }
        for j in &sweeps.volume_ratios {
            s.push_str(&format!("J {j} | "));
        }
        s.push('\n');
        s.push_str(
            &"|---".repeat(2 + sweeps.uniaxial_stretches.len() + sweeps.volume_ratios.len()),
        );
        s.push_str("|\n");
        for c in &self.comparisons {
            s.push_str(&format!("| {:?} | {} |", c.response.law, c.variant));
            for p in c.response.uniaxial.iter().chain(&c.response.hydrostatic) {
                s.push_str(&format!(" {:+.1} % |", 100.0 * p.stress_error()));
            }
            s.push('\n');
        }
        s.push_str(
            "\nCubic ratio c = λ₁/λ₂ fitted to each law over 0–25 % stretch and ±20 % volume \
             (admissible c ≥ −1/3):\n\n| law | fitted c | RMS error, fitted | RMS error, linear | max error, fitted | max error, linear |\n|---|---|---|---|---|---|\n",
        );
        for (f, l) in self.fits.iter().zip(&self.linear_on_fit_sweeps) {
            s.push_str(&format!(
                "| {:?} | {:.3} | {:.1} % | {:.1} % | {:.1} % | {:.1} % |\n",
                f.law,
                f.spring_law.cubic_ratio(),
                100.0 * f.rms_stress_error(),
                100.0 * l.rms_stress_error(),
                100.0 * f.max_stress_error(),
                100.0 * l.max_stress_error()
            ));
        }
        s
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn volumetric_laws_make_the_hydrostatic_response_exact_and_fits_stay_admissible() {
        let r = run_material_law_study().unwrap();
        for c in r
            .comparisons
            .iter()
            .filter(|c| c.response.volumetric_law.is_some())
        {
            for p in &c.response.hydrostatic {
                assert!(p.stress_error().abs() < 1e-3, "{}: {p:?}", c.variant);
            }
        }
        for f in &r.fits {
            let c = f.spring_law.cubic_ratio();
            assert!((-1.0 / 3.0 - 1e-9..=10.0).contains(&c), "{:?}: {c}", f.law);
        }
        let md = r.to_markdown();
        assert!(md.contains("LungBirzle") && md.contains("fitted c"), "{md}");
    }
}
