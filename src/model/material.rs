//! Material parameters of a tissue: small-strain moduli, density and the springs' law.

use serde::{Deserialize, Serialize};

pub use super::hourglass::HourglassLaw;
pub use super::spring_law::{ContinuumLaw, SpringLaw};
use crate::{Error, Result};

/// Isotropic material: Young's modulus, Poisson's ratio and density, in SI units.
///
/// Read from a configuration (`[material]`, or the API's `material`), every key is optional and
/// a missing key takes [`Material::default`]'s value, with one exception: a table that names a
/// `volumetric_law` and no `continuum_correction` gets no correction (the two exclude each
/// other). `continuum_correction = "none"` (or JSON `null`) asks for the springs' own response.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(from = "MaterialTable")]
pub struct Material {
    /// Young's modulus E in pascals.
    pub youngs_modulus_pa: f64,
    /// Poisson's ratio ν (dimensionless, 0 ≤ ν < 0.5 for this element).
    pub poisson_ratio: f64,
    /// Mass density ρ in kg/m³.
    pub density_kg_per_m3: f64,
    /// How each spring's tension grows with its elongation beyond the small-strain slope.
    pub spring_law: SpringLaw,
    /// A continuum law the elements' hydrostatic response follows through a volumetric
    /// correction pressure ([`super::volumetric`]); `None`: the springs' own response.
    pub volumetric_law: Option<ContinuumLaw>,
    /// A continuum law the elements' whole response to homogeneous deformation follows
    /// (deviatoric and hydrostatic) through corner forces at the centre-point deformation
    /// gradient ([`super::continuum_correction`]); `None`: the springs' own response.
    /// Excludes [`Material::volumetric_law`], whose pressure it already contains.
    #[serde(serialize_with = "serialize_correction")]
    pub continuum_correction: Option<ContinuumLaw>,
    /// Where the elements' hourglass (bending, twist) response comes from: the springs' or a
    /// continuum finite element's ([`super::hourglass`]).
    pub hourglass: HourglassLaw,
}

impl Default for Material {
    /// [`Material::LUNG_CONTINUUM`]: what a run uses unless told otherwise. Against CalculiX
    /// (C3D8, `NEO HOOKE`) on the CIP lungs at 500 mL it is 0.03 mm mean, it completes the
    /// deflations below the scan and the large breaths the springs alone do not, and its
    /// Newton–Krylov solves take fewer iterations (README, "The default element").
    fn default() -> Self {
        Material::LUNG_CONTINUUM
    }
}

/// `None` is written as `"none"`, so that a configuration written out and read back keeps the
/// springs' own response rather than falling back to the default correction.
fn serialize_correction<S: serde::Serializer>(
    law: &Option<ContinuumLaw>,
    serializer: S,
) -> std::result::Result<S::Ok, S::Error> {
    match law {
        Some(law) => law.serialize(serializer),
        None => serializer.serialize_str("none"),
    }
}

/// A `continuum_correction` value as written: a law, or `"none"`.
#[derive(Debug, Clone, Copy, Deserialize)]
#[serde(rename_all = "snake_case")]
enum CorrectionName {
    None,
    NeoHookean,
    Hyperfoam,
    LungBirzle,
}

impl From<CorrectionName> for Option<ContinuumLaw> {
    fn from(name: CorrectionName) -> Self {
        match name {
            CorrectionName::None => None,
            CorrectionName::NeoHookean => Some(ContinuumLaw::NeoHookean),
            CorrectionName::Hyperfoam => Some(ContinuumLaw::Hyperfoam),
            CorrectionName::LungBirzle => Some(ContinuumLaw::LungBirzle),
        }
    }
}

/// [`Material`] as a configuration writes it: every key optional, and a missing
/// `continuum_correction` told apart from an explicit `"none"` or `null`.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
struct MaterialTable {
    youngs_modulus_pa: Option<f64>,
    poisson_ratio: Option<f64>,
    density_kg_per_m3: Option<f64>,
    spring_law: Option<SpringLaw>,
    volumetric_law: Option<ContinuumLaw>,
    #[serde(default, deserialize_with = "present")]
    continuum_correction: Option<Option<CorrectionName>>,
    hourglass: Option<HourglassLaw>,
}

/// Marks a key that is present (even as `null`) as `Some`, so a missing key stays `None`.
fn present<'de, D: serde::Deserializer<'de>>(
    deserializer: D,
) -> std::result::Result<Option<Option<CorrectionName>>, D::Error> {
    Option::<CorrectionName>::deserialize(deserializer).map(Some)
}

impl From<MaterialTable> for Material {
    fn from(t: MaterialTable) -> Self {
        let d = Material::default();
        let continuum_correction = match t.continuum_correction {
            Some(written) => written.and_then(Option::from),
            None if t.volumetric_law.is_some() => None,
            None => d.continuum_correction,
        };
        Material {
            youngs_modulus_pa: t.youngs_modulus_pa.unwrap_or(d.youngs_modulus_pa),
            poisson_ratio: t.poisson_ratio.unwrap_or(d.poisson_ratio),
            density_kg_per_m3: t.density_kg_per_m3.unwrap_or(d.density_kg_per_m3),
            spring_law: t.spring_law.unwrap_or(d.spring_law),
            volumetric_law: t.volumetric_law,
            continuum_correction,
            hourglass: t.hourglass.unwrap_or(d.hourglass),
        }
    }
}

impl Material {
    /// Lung parenchyma at rest as used by Baudet: E = 390 Pa (Gefen), ν = 0.3, ρ ≈ 700 kg/m³
    /// (inflated lung tissue is mostly air; 1250 g over ≈ 1.8 L of tissue-filled volume).
    pub const LUNG: Material = Material {
        youngs_modulus_pa: 390.0,
        poisson_ratio: 0.3,
        density_kg_per_m3: 700.0,
        spring_law: SpringLaw::Linear,
        volumetric_law: None,
        continuum_correction: None,
        hourglass: HourglassLaw::Springs,
    };

    /// [`Material::LUNG`] whose elements follow compressible neo-Hookean under any homogeneous
    /// deformation (the continuum correction). Against CalculiX on the CIP lung it is a third
    /// of the springs' error, and it keeps elements from inverting in the large breaths where
    /// the springs alone fail (README, "The continuum correction").
    pub const LUNG_CORRECTED: Material = Material {
        continuum_correction: Some(ContinuumLaw::NeoHookean),
        ..Material::LUNG
    };

    /// [`Material::LUNG_CORRECTED`] whose bending and twist (hourglass) modes also resist like
    /// a fully integrated trilinear brick's (CalculiX C3D8) instead of the springs': the
    /// element is then C3D8 with the neo-Hookean law at small strain, and the twist modes the
    /// springs leave without stiffness (which buckle a compressed lattice) are held.
    pub const LUNG_CONTINUUM: Material = Material {
        hourglass: HourglassLaw::FullIntegration,
        ..Material::LUNG_CORRECTED
    };

    /// Builds a material after checking every parameter.
    pub fn new(youngs_modulus_pa: f64, poisson_ratio: f64, density_kg_per_m3: f64) -> Result<Self> {
        let m = Material {
            youngs_modulus_pa,
            poisson_ratio,
            density_kg_per_m3,
            spring_law: SpringLaw::Linear,
            volumetric_law: None,
            continuum_correction: None,
            hourglass: HourglassLaw::Springs,
        };
        m.validate()?;
        Ok(m)
    }

    /// Refuses non-finite values, E ≤ 0, ν outside [0, 0.5) and ρ ≤ 0.
    pub fn validate(&self) -> Result<()> {
        let Material {
            youngs_modulus_pa: e,
            poisson_ratio: nu,
            density_kg_per_m3: rho,
            spring_law,
            volumetric_law,
            continuum_correction,
            hourglass: _,
        } = *self;
        if !e.is_finite() || e <= 0.0 {
            return Err(Error::InvalidMaterial(format!(
                "Young's modulus must be a positive finite number of pascals, got {e}"
            )));
        }
        if !nu.is_finite() || !(0.0..0.5).contains(&nu) {
            return Err(Error::InvalidMaterial(format!(
                "Poisson's ratio must be in [0, 0.5) (0.5 is incompressible, which a mass–spring \
                 element cannot represent), got {nu}"
            )));
        }
        if !rho.is_finite() || rho <= 0.0 {
            return Err(Error::InvalidMaterial(format!(
                "density must be a positive finite number of kg/m³, got {rho}"
            )));
        }
        if let (Some(volumetric), Some(continuum)) = (volumetric_law, continuum_correction) {
            return Err(Error::InvalidMaterial(format!(
                "continuum_correction = {continuum:?} already gives the elements its law's \
                 hydrostatic response; volumetric_law = {volumetric:?} would add a second \
                 pressure on top: set only one of them"
            )));
        }
        spring_law.validate(nu)
    }

    /// The same material with another spring law.
    pub fn with_spring_law(mut self, law: SpringLaw) -> Result<Self> {
        self.spring_law = law;
        self.validate()?;
        Ok(self)
    }

    /// The same material with its hydrostatic response following `law` (or the springs').
    pub fn with_volumetric_law(mut self, law: Option<ContinuumLaw>) -> Self {
        self.volumetric_law = law;
        self
    }

    /// The same material with its whole homogeneous response following `law` (or the
    /// springs'); refused beside a volumetric law.
    pub fn with_continuum_correction(mut self, law: Option<ContinuumLaw>) -> Result<Self> {
        self.continuum_correction = law;
        self.validate()?;
        Ok(self)
    }

    /// The same material with its hourglass response taken from `law`.
    pub fn with_hourglass(mut self, law: HourglassLaw) -> Self {
        self.hourglass = law;
        self
    }

    /// Shear modulus G = E / (2(1+ν)) in pascals.
    pub fn shear_modulus_pa(&self) -> f64 {
        self.youngs_modulus_pa / (2.0 * (1.0 + self.poisson_ratio))
    }

    /// Bulk modulus K = E / (3(1−2ν)) in pascals.
    pub fn bulk_modulus_pa(&self) -> f64 {
        self.youngs_modulus_pa / (3.0 * (1.0 - 2.0 * self.poisson_ratio))
    }

    /// Longitudinal (P-wave) modulus λ + 2μ in pascals; sets the fastest wave speed.
    pub fn p_wave_modulus_pa(&self) -> f64 {
        let (e, nu) = (self.youngs_modulus_pa, self.poisson_ratio);
        e * (1.0 - nu) / ((1.0 + nu) * (1.0 - 2.0 * nu))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn refuses_unphysical_parameters() {
        assert!(Material::new(0.0, 0.3, 1.0).is_err());
        assert!(Material::new(-5.0, 0.3, 1.0).is_err());
        assert!(Material::new(f64::NAN, 0.3, 1.0).is_err());
        assert!(Material::new(1.0, 0.5, 1.0).is_err());
        assert!(Material::new(1.0, -0.1, 1.0).is_err());
        assert!(Material::new(1.0, 0.3, 0.0).is_err());
        assert!(Material::new(1.0, 0.3, f64::INFINITY).is_err());
        let msg = Material::new(1.0, 0.5, 1.0).unwrap_err().to_string();
        assert!(msg.contains("Poisson"), "{msg}");
        assert!(Material::new(390.0, 0.3, 700.0).is_ok());
        let both = Material::LUNG
            .with_volumetric_law(Some(ContinuumLaw::Hyperfoam))
            .with_continuum_correction(Some(ContinuumLaw::NeoHookean))
            .unwrap_err()
            .to_string();
        assert!(
            both.contains("continuum_correction = NeoHookean")
                && both.contains("volumetric_law = Hyperfoam"),
            "{both}"
        );
        assert!(Material::LUNG
            .with_continuum_correction(Some(ContinuumLaw::LungBirzle))
            .is_ok());
    }

    #[test]
    fn moduli_relations_hold() {
        let m = Material::new(1000.0, 0.3, 1.0).unwrap();
        let (e, g, k) = (
            m.youngs_modulus_pa,
            m.shear_modulus_pa(),
            m.bulk_modulus_pa(),
        );
        // E = 9KG / (3K + G)
        assert!((9.0 * k * g / (3.0 * k + g) - e).abs() < 1e-9);
    }
}
