//! The springs' force law (Baudet's linear springs or Boux de Casson's cubic ones) and the fit
//! of the cubic term to a named continuum law on one cube.
//!
//! A spring of rest length ℓ₀ and Baudet stiffness k pulls with T = λ₂·d + λ₁·d³, d = (ℓ − ℓ₀)/ℓ₀
//! its relative elongation and λ₂ = k·ℓ₀ (Boux de Casson 2000, §2.5 and §4.5). The cubic term
//! vanishes at small strain, so E, ν and K stay exactly Baudet's there; c = λ₁/λ₂ sets how the
//! element departs from linearity at large strain.

use serde::{Deserialize, Serialize};

use super::element::{BrickCoefficients, BrickShape};
use super::material::Material;
use crate::{Error, Result};

/// Largest |d| a spring is expected to reach (from collapse to twice its length): the tangent
/// λ₂·(1 + 3c·d²) must stay positive over it, so c ≥ −1/3.
pub const ADMISSIBLE_RELATIVE_ELONGATION: f64 = 1.0;
/// Largest cubic ratio accepted: beyond it the tangent at 25 % elongation exceeds 20× the
/// small-strain one, which no tissue law fitted here asks for and which shrinks explicit steps.
pub const MAX_CUBIC_RATIO: f64 = 100.0;

/// How each spring's tension grows with its relative elongation beyond the small-strain slope.
///
/// In a configuration: `"linear"`, `"cubic"` (the ratio fitted to the compressible neo-Hookean
/// law at the material's ν) or `{ cubic = c }` (an explicit ratio).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub enum SpringLaw {
    /// λ₁ = 0: Baudet's element as published.
    #[default]
    Linear,
    /// λ₁ = c·λ₂ with the given dimensionless c (Boux de Casson's cubic springs).
    Cubic(f64),
    /// λ₁ = c·λ₂ with c fitted by [`fit_cubic_ratio`] to the compressible neo-Hookean law
    /// W = (G/2)(Ī₁ − 3) + (K/2)(J − 1)² (G, K the material's small-strain moduli) over
    /// 0–25 % uniaxial stretch and ±20 % volume, at the material's Poisson's ratio.
    CubicNeoHookean,
}

/// The configuration name of [`SpringLaw::CubicNeoHookean`].
const CUBIC_NEO_HOOKEAN_NAME: &str = "cubic";

impl SpringLaw {
    /// The ratio c = λ₁/λ₂ of this law for a material of Poisson's ratio `poisson_ratio`
    /// (NaN when a fit is asked for an inadmissible ν, which [`Material::validate`] refuses).
    pub fn cubic_ratio(&self, poisson_ratio: f64) -> f64 {
        match *self {
            SpringLaw::Linear => 0.0,
            SpringLaw::Cubic(c) => c,
            SpringLaw::CubicNeoHookean => {
                fitted_cubic_ratio(ContinuumLaw::NeoHookean, poisson_ratio).unwrap_or(f64::NAN)
            }
        }
    }

    /// Refuses a cubic ratio that makes a spring's tangent stiffness non-positive within the
    /// admissible elongations, or that is not finite or absurdly large (for a fitted ratio,
    /// the ratio the fit gives at `poisson_ratio`).
    pub fn validate(&self, poisson_ratio: f64) -> Result<()> {
        let c = match *self {
            SpringLaw::Linear => return Ok(()),
            SpringLaw::Cubic(c) => c,
            SpringLaw::CubicNeoHookean => {
                fitted_cubic_ratio(ContinuumLaw::NeoHookean, poisson_ratio)?
            }
        };
        let floor = -1.0 / (3.0 * ADMISSIBLE_RELATIVE_ELONGATION.powi(2));
        if !c.is_finite() || c < floor || c > MAX_CUBIC_RATIO {
            return Err(Error::InvalidMaterial(format!(
                "spring_law cubic ratio λ₁/λ₂ = {c} is outside [{floor:.4}, {MAX_CUBIC_RATIO}]: \
                 below −1/3 a spring's stiffness λ₂·(1 + 3c·d²) turns negative before it \
                 doubles or collapses (|d| ≤ {ADMISSIBLE_RELATIVE_ELONGATION}); above \
                 {MAX_CUBIC_RATIO} its tangent at 25 % elongation passes 20× the one at rest"
            )));
        }
        Ok(())
    }
}

impl Serialize for SpringLaw {
    fn serialize<S: serde::Serializer>(&self, s: S) -> std::result::Result<S::Ok, S::Error> {
        use serde::ser::SerializeMap;
        match *self {
            SpringLaw::Linear => s.serialize_str("linear"),
            SpringLaw::CubicNeoHookean => s.serialize_str(CUBIC_NEO_HOOKEAN_NAME),
            SpringLaw::Cubic(c) => {
                let mut m = s.serialize_map(Some(1))?;
                m.serialize_entry("cubic", &c)?;
                m.end()
            }
        }
    }
}

impl<'de> Deserialize<'de> for SpringLaw {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> std::result::Result<Self, D::Error> {
        struct Visitor;
        impl<'de> serde::de::Visitor<'de> for Visitor {
            type Value = SpringLaw;
            fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
                f.write_str(
                    "\"linear\", \"cubic\" (fitted to compressible neo-Hookean) or \
                     { cubic = <λ₁/λ₂> }",
                )
            }
            fn visit_str<E: serde::de::Error>(self, v: &str) -> std::result::Result<SpringLaw, E> {
                match v {
                    "linear" => Ok(SpringLaw::Linear),
                    CUBIC_NEO_HOOKEAN_NAME => Ok(SpringLaw::CubicNeoHookean),
                    other => Err(E::custom(format!(
                        "unknown spring_law `{other}`: expected \"linear\", \"cubic\" (the \
                         cubic ratio fitted to compressible neo-Hookean) or {{ cubic = <λ₁/λ₂> }}"
                    ))),
                }
            }
            fn visit_map<A: serde::de::MapAccess<'de>>(
                self,
                mut map: A,
            ) -> std::result::Result<SpringLaw, A::Error> {
                use serde::de::Error as _;
                let key: String = map
                    .next_key()?
                    .ok_or_else(|| A::Error::custom("spring_law table is empty: { cubic = c }"))?;
                if key != "cubic" {
                    return Err(A::Error::custom(format!(
                        "unknown spring_law key `{key}`: the only one is `cubic` (λ₁/λ₂)"
                    )));
                }
                let c: f64 = map.next_value()?;
                if let Some(extra) = map.next_key::<String>()? {
                    return Err(A::Error::custom(format!(
                        "unknown spring_law key `{extra}`: the only one is `cubic` (λ₁/λ₂)"
                    )));
                }
                Ok(SpringLaw::Cubic(c))
            }
        }
        d.deserialize_any(Visitor)
    }
}

impl std::str::FromStr for SpringLaw {
    type Err = String;

    /// `linear`, `cubic` (fitted to compressible neo-Hookean) or `cubic:<λ₁/λ₂>`.
    fn from_str(text: &str) -> std::result::Result<Self, String> {
        match text.trim() {
            "linear" => Ok(SpringLaw::Linear),
            CUBIC_NEO_HOOKEAN_NAME => Ok(SpringLaw::CubicNeoHookean),
            other => match other.strip_prefix("cubic:") {
                Some(c) => c.trim().parse().map(SpringLaw::Cubic).map_err(|_| {
                    format!("`{c}` is not a number (the cubic ratio λ₁/λ₂ of `cubic:<c>`)")
                }),
                None => Err(format!(
                    "unknown spring law `{other}`: expected linear, cubic (fitted to \
                     compressible neo-Hookean) or cubic:<λ₁/λ₂>"
                )),
            },
        }
    }
}

/// Fitted ratios already computed, by law and the bits of ν: a fit costs tens of
/// milliseconds and every element class of every mesh asks for it.
static FITTED_RATIOS: std::sync::Mutex<Vec<(ContinuumLaw, u64, f64)>> =
    std::sync::Mutex::new(Vec::new());

/// The cubic ratio [`fit_cubic_ratio`] gives for `law` at `poisson_ratio`, memoised.
pub fn fitted_cubic_ratio(law: ContinuumLaw, poisson_ratio: f64) -> Result<f64> {
    let key = (law, poisson_ratio.to_bits());
    let cached = |fits: &Vec<(ContinuumLaw, u64, f64)>| {
        fits.iter()
            .find(|(l, nu, _)| (*l, *nu) == key)
            .map(|&(_, _, c)| c)
    };
    if let Some(c) = cached(&FITTED_RATIOS.lock().unwrap_or_else(|e| e.into_inner())) {
        return Ok(c);
    }
    let c = fit_cubic_ratio(law, poisson_ratio)?
        .spring_law
        .cubic_ratio(poisson_ratio);
    let mut fits = FITTED_RATIOS.lock().unwrap_or_else(|e| e.into_inner());
    if cached(&fits).is_none() {
        fits.push((key.0, key.1, c));
    }
    Ok(c)
}

/// Continuum laws the cubic term can be fitted to, each with the small-strain moduli G and K
/// of the material (from E and ν).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ContinuumLaw {
    /// W = (G/2)(Ī₁ − 3) + (K/2)(J − 1)²: CalculiX `*HYPERELASTIC, NEO HOOKE`.
    NeoHookean,
    /// Storåkers' compressible foam with α = 2: W = (G/2)[I₁ − 3 + (J^(−2β) − 1)/β],
    /// β = ν/(1 − 2ν): CalculiX `*HYPERFOAM, N=1` (μ₁ = G, α₁ = 2, ν₁ = ν), and the first two
    /// terms of Birzle's lung law.
    Hyperfoam,
    /// Birzle et al. (2019), lung parenchyma from rat lungs (J. Mech. Behav. Biomed. Mater. 94,
    /// 126–143; FEBio's `lung` material): the hyperfoam plus c₁(Ī₁ − 3)³ + c₃(J^(2/3) − 1)⁶,
    /// with c₁/c = 278.2/356.7 and c₃/c = 5.766/356.7 kept from the paper (c = G/2), so the
    /// curve keeps its measured shape while E and ν are the material's.
    LungBirzle,
}

impl ContinuumLaw {
    /// Principal Cauchy stresses (Pa, tension positive) at principal stretches `stretch` for
    /// shear modulus `g_pa` and bulk modulus `k_pa`.
    pub fn principal_cauchy_stress_pa(&self, stretch: [f64; 3], g_pa: f64, k_pa: f64) -> [f64; 3] {
        let j = stretch.iter().product::<f64>();
        match self {
            ContinuumLaw::NeoHookean => {
                let b = stretch.map(|l| (j.powf(-1.0 / 3.0) * l).powi(2));
                let i1 = b.iter().sum::<f64>();
                b.map(|bi| g_pa / j * (bi - i1 / 3.0) + k_pa * (j - 1.0))
            }
            ContinuumLaw::Hyperfoam | ContinuumLaw::LungBirzle => {
                // σ_i = (2/J)(λ_i²·∂W/∂I₁ + I₃·∂W/∂I₃) for W(I₁, I₃).
                let c = g_pa / 2.0;
                // ν from G and K: β = ν/(1 − 2ν) = (3K − 2G)/(6G)... written through K/G.
                let beta = (3.0 * k_pa - 2.0 * g_pa) / (6.0 * g_pa);
                let (c1, c3) = match self {
                    ContinuumLaw::LungBirzle => (c * 278.2 / 356.7, c * 5.766 / 356.7),
                    _ => (0.0, 0.0),
                };
                let i1 = stretch.iter().map(|l| l * l).sum::<f64>();
                let i3 = j * j;
                let i1_bar = i3.powf(-1.0 / 3.0) * i1;
                let shear = 3.0 * c1 * (i1_bar - 3.0).powi(2);
                let w1 = c + shear * i3.powf(-1.0 / 3.0);
                let w3 = -c * i3.powf(-beta - 1.0) - shear * i1 * i3.powf(-4.0 / 3.0) / 3.0
                    + 2.0 * c3 * (i3.cbrt() - 1.0).powi(5) * i3.powf(-2.0 / 3.0);
                stretch.map(|l| 2.0 / j * (l * l * w1 + i3 * w3))
            }
        }
    }

    /// Principal nominal (first Piola–Kirchhoff) stresses: the force on each positive face of
    /// a cube stretched by `stretch`, per m² of rest face, in pascals.
    pub fn nominal_stress_pa(&self, stretch: [f64; 3], g_pa: f64, k_pa: f64) -> [f64; 3] {
        let s = self.principal_cauchy_stress_pa(stretch, g_pa, k_pa);
        std::array::from_fn(|i| s[i] * stretch[(i + 1) % 3] * stretch[(i + 2) % 3])
    }
}

/// The strain sweeps the cubic ratio is fitted over.
#[derive(Debug, Clone, Serialize)]
pub struct FitSweeps {
    /// Axial stretches of the uniaxial-stress sweep (lateral faces free).
    pub uniaxial_stretches: Vec<f64>,
    /// Volume ratios J of the hydrostatic sweep.
    pub volume_ratios: Vec<f64>,
}

impl Default for FitSweeps {
    fn default() -> Self {
        FitSweeps {
            uniaxial_stretches: (1..=10).map(|k| 1.0 + 0.025 * k as f64).collect(),
            volume_ratios: (1..=10)
                .flat_map(|k| [1.0 - 0.02 * k as f64, 1.0 + 0.02 * k as f64])
                .collect(),
        }
    }
}

/// One point of a sweep: the law's and the element's response.
#[derive(Debug, Clone, Serialize)]
pub struct ResponsePoint {
    /// Axial stretch (uniaxial sweep) or volume ratio J (hydrostatic sweep).
    pub strain_measure: f64,
    /// The law's nominal axial stress (uniaxial) or Cauchy pressure, tension positive, in Pa.
    pub law_stress_pa: f64,
    /// The element's, same measure.
    pub element_stress_pa: f64,
    /// The law's lateral stretch (uniaxial sweep; 0 for the hydrostatic one).
    pub law_lateral_stretch: f64,
    /// The element's lateral stretch (uniaxial sweep; 0 for the hydrostatic one).
    pub element_lateral_stretch: f64,
}

impl ResponsePoint {
    /// (element − law)/law of the stress.
    pub fn stress_error(&self) -> f64 {
        self.element_stress_pa / self.law_stress_pa - 1.0
    }
}

/// A cube's response along both sweeps for one material.
#[derive(Debug, Clone, Serialize)]
pub struct CubeResponse {
    /// The law compared with.
    pub law: ContinuumLaw,
    /// The element's spring law.
    pub spring_law: SpringLaw,
    /// The element's volumetric law, if any.
    pub volumetric_law: Option<ContinuumLaw>,
    /// The element's continuum correction law, if any.
    pub continuum_correction: Option<ContinuumLaw>,
    /// Uniaxial-stress sweep.
    pub uniaxial: Vec<ResponsePoint>,
    /// Hydrostatic sweep.
    pub hydrostatic: Vec<ResponsePoint>,
}

impl CubeResponse {
    /// Root mean square of the relative stress errors over both sweeps.
    pub fn rms_stress_error(&self) -> f64 {
        let all: Vec<f64> = self
            .uniaxial
            .iter()
            .chain(&self.hydrostatic)
            .map(ResponsePoint::stress_error)
            .collect();
        (all.iter().map(|e| e * e).sum::<f64>() / all.len() as f64).sqrt()
    }

    /// Largest |relative stress error| over both sweeps.
    pub fn max_stress_error(&self) -> f64 {
        self.uniaxial
            .iter()
            .chain(&self.hydrostatic)
            .map(|p| p.stress_error().abs())
            .fold(0.0, f64::max)
    }
}

/// Runs both sweeps on a unit cube of `material` (its springs and volumetric law) against
/// `law` with the same small-strain moduli; stresses in pascals.
pub fn cube_response(
    law: ContinuumLaw,
    material: Material,
    sweeps: &FitSweeps,
) -> Result<CubeResponse> {
    let (g, k) = (material.shear_modulus_pa(), material.bulk_modulus_pa());
    let cube = BrickCoefficients::new(BrickShape::cube(1.0), material)?;
    let uniaxial = sweeps
        .uniaxial_stretches
        .iter()
        .map(|&l| {
            let element_lateral = free_lateral_stretch(|m| cube.box_face_forces_n([l, m, m])[1]);
            let law_lateral = free_lateral_stretch(|m| law.nominal_stress_pa([l, m, m], g, k)[1]);
            ResponsePoint {
                strain_measure: l,
                law_stress_pa: law.nominal_stress_pa([l, law_lateral, law_lateral], g, k)[0],
                element_stress_pa: cube.box_face_forces_n([l, element_lateral, element_lateral])[0],
                law_lateral_stretch: law_lateral,
                element_lateral_stretch: element_lateral,
            }
        })
        .collect();
    let hydrostatic = sweeps
        .volume_ratios
        .iter()
        .map(|&j| {
            let s = j.cbrt();
            ResponsePoint {
                strain_measure: j,
                law_stress_pa: law.principal_cauchy_stress_pa([s; 3], g, k)[0],
                element_stress_pa: cube.box_face_forces_n([s; 3])[0] / (s * s),
                law_lateral_stretch: 0.0,
                element_lateral_stretch: 0.0,
            }
        })
        .collect();
    Ok(CubeResponse {
        law,
        spring_law: material.spring_law,
        volumetric_law: material.volumetric_law,
        continuum_correction: material.continuum_correction,
        uniaxial,
        hydrostatic,
    })
}

/// The Cauchy shear stress σ_xy (Pa) that one unit cube of `material` carries under the simple
/// shear F = I + γ·e_x⊗e_y: its corner forces at x_a = F·X_a projected on the homogeneous
/// modes, P = −Σ_a f_a ⊗ X_a (V₀ = 1), and σ_xy = (P·Fᵀ)_xy/J = P_xy since J = 1.
///
/// The projection is what a lattice of such cubes carries under that shear: the rest of the
/// corner forces (the body diagonals' unequal tensions put a self-equilibrated s_x·s_y·s_z
/// pattern on the corners) cancels between neighbours.
pub fn simple_shear_stress_pa(material: Material, gamma: f64) -> Result<f64> {
    let cube = BrickCoefficients::new(BrickShape::cube(1.0), material)?;
    let offsets = cube.corner_offsets_m();
    let x = offsets.map(|o| nalgebra::Vector3::new(o.x + gamma * o.y, o.y, o.z));
    let f = cube.corner_forces(&x, None);
    Ok(-f.iter().zip(&offsets).map(|(f, o)| f.x * o.y).sum::<f64>())
}

/// The lateral stretch at which the lateral face force `lateral(m)` vanishes (bisection: the
/// force rises with m for any admissible law), within 1e-12.
fn free_lateral_stretch(lateral: impl Fn(f64) -> f64) -> f64 {
    let (mut lo, mut hi) = (0.3, 1.5);
    for _ in 0..60 {
        let mid = 0.5 * (lo + hi);
        if lateral(mid) > 0.0 {
            hi = mid;
        } else {
            lo = mid;
        }
    }
    0.5 * (lo + hi)
}

/// The cubic ratio minimising the RMS relative stress error of [`cube_response`] against `law`
/// over the default sweeps: a scan of [−1/3, 10] followed by golden-section refinement.
pub fn fit_cubic_ratio(law: ContinuumLaw, poisson_ratio: f64) -> Result<CubeResponse> {
    let sweeps = FitSweeps::default();
    let material = |c: f64| -> Result<Material> {
        Material::new(1.0, poisson_ratio, 1.0)?.with_spring_law(SpringLaw::Cubic(c))
    };
    let cost = |c: f64| cube_response(law, material(c)?, &sweeps).map(|r| r.rms_stress_error());
    let (lo, hi, steps) = (-1.0 / 3.0, 10.0, 62);
    let h = (hi - lo) / steps as f64;
    let mut best = (lo, f64::INFINITY);
    for i in 0..=steps {
        let c = lo + h * i as f64;
        let e = cost(c)?;
        if e < best.1 {
            best = (c, e);
        }
    }
    let (mut a, mut b) = ((best.0 - h).max(lo), (best.0 + h).min(hi));
    let phi = 0.5 * (5f64.sqrt() - 1.0);
    while b - a > 1e-6 {
        let (c1, c2) = (b - phi * (b - a), a + phi * (b - a));
        if cost(c1)? < cost(c2)? {
            b = c2;
        } else {
            a = c1;
        }
    }
    cube_response(law, material(0.5 * (a + b))?, &sweeps)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn linear_springs_match_the_law_at_small_strain() {
        let sweeps = FitSweeps {
            uniaxial_stretches: vec![1.0001],
            volume_ratios: vec![0.9999, 1.0001],
        };
        for nu in [0.1, 0.3, 0.45] {
            let m = Material::new(1.0, nu, 1.0).unwrap();
            let r = cube_response(ContinuumLaw::NeoHookean, m, &sweeps).unwrap();
            assert!(r.max_stress_error() < 1e-3, "ν {nu}: {r:?}");
            let p = &r.uniaxial[0];
            assert!((p.element_lateral_stretch - p.law_lateral_stretch).abs() < 1e-7);
        }
    }

    #[test]
    fn neo_hookean_cauchy_stress_is_the_closed_form() {
        // Incompressible-like uniaxial check: pure volumetric state has no deviator.
        let s = ContinuumLaw::NeoHookean.principal_cauchy_stress_pa([1.1; 3], 2.0, 5.0);
        let j: f64 = 1.1f64.powi(3);
        for v in s {
            assert!((v - 5.0 * (j - 1.0)).abs() < 1e-12);
        }
        // Isochoric stretch (λ, λ^-½, λ^-½): σ₁ − σ₂ = G(λ² − 1/λ).
        let l: f64 = 1.2;
        let s = ContinuumLaw::NeoHookean.principal_cauchy_stress_pa(
            [l, l.powf(-0.5), l.powf(-0.5)],
            2.0,
            5.0,
        );
        assert!((s[0] - s[1] - 2.0 * (l * l - 1.0 / l)).abs() < 1e-12);
    }

    #[test]
    fn refuses_cubic_ratios_that_soften_to_negative_stiffness() {
        for c in [-0.34, -1.0, f64::NAN, 1e3] {
            let err = SpringLaw::Cubic(c).validate(0.3).unwrap_err().to_string();
            assert!(
                err.contains("cubic ratio") && err.contains("negative"),
                "{err}"
            );
        }
        assert!(SpringLaw::Cubic(-0.33).validate(0.3).is_ok());
        assert!(SpringLaw::Cubic(2.0).validate(0.3).is_ok());
    }

    #[test]
    fn names_parse_and_print_back() {
        for (text, law) in [
            ("linear", SpringLaw::Linear),
            ("cubic", SpringLaw::CubicNeoHookean),
            ("cubic:2.5", SpringLaw::Cubic(2.5)),
            ("cubic:-0.2", SpringLaw::Cubic(-0.2)),
        ] {
            assert_eq!(text.parse::<SpringLaw>().unwrap(), law);
            let json = serde_json::to_string(&law).unwrap();
            assert_eq!(
                serde_json::from_str::<SpringLaw>(&json).unwrap(),
                law,
                "{json}"
            );
        }
        assert_eq!(
            serde_json::to_string(&SpringLaw::Cubic(2.5)).unwrap(),
            r#"{"cubic":2.5}"#
        );
        for bad in ["quadratic", "cubic:", "cubic:x", ""] {
            let err = bad.parse::<SpringLaw>().unwrap_err();
            assert!(err.contains("cubic"), "{bad}: {err}");
        }
        let err = serde_json::from_str::<SpringLaw>(r#"{"cubic": 1, "linear": 2}"#).unwrap_err();
        assert!(err.to_string().contains("`linear`"), "{err}");
    }

    #[test]
    fn the_neo_hookean_fit_is_admissible_memoised_and_no_worse_than_linear() {
        let nu = 0.3;
        let c = SpringLaw::CubicNeoHookean.cubic_ratio(nu);
        assert!(SpringLaw::CubicNeoHookean.validate(nu).is_ok());
        assert!((-1.0 / 3.0..=MAX_CUBIC_RATIO).contains(&c), "{c}");
        assert_eq!(fitted_cubic_ratio(ContinuumLaw::NeoHookean, nu).unwrap(), c);
        let sweeps = FitSweeps::default();
        let rms = |law: SpringLaw| {
            let m = Material::new(1.0, nu, 1.0)
                .unwrap()
                .with_spring_law(law)
                .unwrap();
            cube_response(ContinuumLaw::NeoHookean, m, &sweeps)
                .unwrap()
                .rms_stress_error()
        };
        assert!(rms(SpringLaw::Cubic(c)) <= rms(SpringLaw::Linear));
        // A material with an inadmissible ν has no fit to give: the material refuses it first.
        assert!(Material::new(1.0, 0.5, 1.0)
            .and_then(|m| m.with_spring_law(SpringLaw::CubicNeoHookean))
            .is_err());
    }
}
