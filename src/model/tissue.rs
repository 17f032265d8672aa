//! Tissue that varies element by element: stiffness and density from the CT's density, and a
//! target several times stiffer than the parenchyma around it, carried as extra element
//! classes so the force kernels and the multigrid keep their per-class coefficients.
//!
//! # The mapping
//!
//! * **Tissue fraction from Hounsfield units.** A CT number is linear in the attenuation
//!   between air (−1000 HU) and water (0 HU), so a lung voxel of H HU holds a fraction
//!   φ = 1 + H/1000 of water-like tissue and blood, the rest air (the definition of the
//!   Hounsfield scale; inflated parenchyma at −850 HU is φ ≈ 0.15). φ is clamped to 0–1.2.
//! * **Stiffness from the tissue fraction** (default): lung parenchyma is an open-cell foam of
//!   alveolar walls, whose Young's modulus scales with the square of its relative density
//!   (Gibson & Ashby, *Cellular Solids*, 2nd ed. 1997, ch. 5: E*/E_s ≈ (ρ*/ρ_s)²). Each element
//!   takes E = E_material · (φ_e/φ_ref)^n, φ_ref the median element's φ, so the median element
//!   keeps the material's modulus (Gefen's 390 Pa by default); n = `stiffness_exponent`
//!   (2 by default) and the ratio is clamped to [1/`max_stiffness_ratio`,
//!   `max_stiffness_ratio`] so one vessel-filled element cannot become a rigid block.
//! * **Or a table** `hu_to_youngs_modulus_pa`: E in pascals against the element's mean HU,
//!   piecewise linear, constant beyond its ends; no clamp. The mean HU is that of φ, so of
//!   voxels clamped to −1000…+200 HU.
//! * **Density** follows φ: ρ = ρ_material · φ_e/φ_ref (same clamp).
//! * **A target** (the run's tumour mask) is `target_stiffness_ratio` times the material's
//!   modulus; an element partly in it takes the volume-weighted mean of the two
//!   (Voigt's bound, the stiffer estimate for a partly filled element).
//!
//! Ratios are rounded to steps of `stiffness_step` on a log scale (5 % by default) so elements
//! of equal stiffness share a class.

use std::collections::HashMap;

use serde::{Deserialize, Serialize};

use super::{BrickCoefficients, HexMesh};
use crate::{Error, Result};

/// How the lung's tissue varies from element to element (`[tissue]` of a run configuration).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct TissueSettings {
    /// Take each element's stiffness and density from the CT's Hounsfield units.
    pub from_ct: bool,
    /// n of E ∝ φⁿ (φ the tissue fraction); 2 for an open-cell foam.
    pub stiffness_exponent: f64,
    /// Largest ratio of an element's modulus (and density) to the material's, either way.
    pub max_stiffness_ratio: f64,
    /// Relative step the ratios are rounded to (one element class per step).
    pub stiffness_step: f64,
    /// Young's modulus of the run's target relative to the material's (1: as the lung).
    pub target_stiffness_ratio: f64,
    /// E in pascals against mean HU, `[[hu, pa], …]` with HU increasing, instead of the
    /// power law.
    pub hu_to_youngs_modulus_pa: Option<Vec<[f64; 2]>>,
}

impl Default for TissueSettings {
    /// Homogeneous tissue: no CT mapping, the target as stiff as the lung.
    fn default() -> Self {
        TissueSettings {
            from_ct: false,
            stiffness_exponent: 2.0,
            max_stiffness_ratio: 10.0,
            stiffness_step: 0.05,
            target_stiffness_ratio: 1.0,
            hu_to_youngs_modulus_pa: None,
        }
    }
}

/// Largest target stiffness ratio accepted (a tumour is 3–10× parenchyma; beyond 1000 the
/// element is a rigid block and the solver's conditioning suffers for nothing).
pub const MAX_TARGET_STIFFNESS_RATIO: f64 = 1000.0;

impl TissueSettings {
    /// Whether the elements differ at all (otherwise the mesh is left as it is).
    pub fn is_heterogeneous(&self) -> bool {
        self.from_ct || self.target_stiffness_ratio != 1.0
    }

    /// The first key no run can use, with the reason; `None` when all are usable.
    pub fn problem(&self) -> Option<(&'static str, String)> {
        let n = self.stiffness_exponent;
        if !(n.is_finite() && (0.0..=4.0).contains(&n)) {
            return Some((
                "tissue.stiffness_exponent",
                format!("{n} is not within 0–4 (2 for an open-cell foam)"),
            ));
        }
        let m = self.max_stiffness_ratio;
        if !(m.is_finite() && (1.0..=1000.0).contains(&m)) {
            return Some((
                "tissue.max_stiffness_ratio",
                format!("{m} is not within 1–1000"),
            ));
        }
        let s = self.stiffness_step;
        if !(s.is_finite() && (0.001..=0.5).contains(&s)) {
            return Some((
                "tissue.stiffness_step",
                format!("{s} is not within 0.001–0.5"),
            ));
        }
        let t = self.target_stiffness_ratio;
        if !(t.is_finite() && t > 0.0 && t <= MAX_TARGET_STIFFNESS_RATIO) {
            return Some((
                "tissue.target_stiffness_ratio",
                format!(
                    "{t} is not a positive ratio up to {MAX_TARGET_STIFFNESS_RATIO}: a target's \
                     stiffness must stay positive"
                ),
            ));
        }
        if let Some(table) = &self.hu_to_youngs_modulus_pa {
            if let Some(reason) = table_problem(table) {
                return Some(("tissue.hu_to_youngs_modulus_pa", reason));
            }
            if !self.from_ct {
                return Some((
                    "tissue.hu_to_youngs_modulus_pa",
                    "a table of stiffness against HU needs `from_ct = true`".into(),
                ));
            }
        }
        None
    }

    /// Refuses a stiffer target for a run that has none to stiffen.
    pub fn check_target(&self, has_target: bool) -> Result<()> {
        if self.target_stiffness_ratio != 1.0 && !has_target {
            return Err(Error::Config {
                settings: "configuration",
                file: None,
                key: Some("tissue.target_stiffness_ratio".into()),
                reason: format!(
                    "{} asks for a stiffer target, but there is none to stiffen (`lungmotion run` \
                     takes one with --target, a request with `target`)",
                    self.target_stiffness_ratio
                ),
            });
        }
        Ok(())
    }

    /// [`TissueSettings::problem`] as an error naming the key.
    pub fn validate(&self) -> Result<()> {
        match self.problem() {
            None => Ok(()),
            Some((key, reason)) => Err(Error::Config {
                settings: "tissue settings",
                file: None,
                key: Some(key.to_string()),
                reason,
            }),
        }
    }
}

/// Why a stiffness table cannot be used, if it cannot.
fn table_problem(table: &[[f64; 2]]) -> Option<String> {
    if table.len() < 2 {
        return Some(format!(
            "{} row(s): a table needs at least two [hu, pa] rows",
            table.len()
        ));
    }
    for (row, &[hu, pa]) in table.iter().enumerate() {
        if !(hu.is_finite() && (-1024.0..=3071.0).contains(&hu)) {
            return Some(format!("row {row}: {hu} HU is outside a CT's −1024…3071"));
        }
        if !(pa.is_finite() && pa > 0.0) {
            return Some(format!(
                "row {row}: {pa} Pa at {hu} HU is not a positive stiffness"
            ));
        }
        if row > 0 && hu <= table[row - 1][0] {
            return Some(format!(
                "row {row}: {hu} HU does not follow {} HU; HU must increase",
                table[row - 1][0]
            ));
        }
    }
    None
}

/// Tissue fraction φ = 1 + H/1000 of a voxel of `hu` Hounsfield units, clamped to 0–1.2.
pub fn tissue_fraction(hu: f64) -> f64 {
    (1.0 + hu / 1000.0).clamp(0.0, 1.2)
}

/// What the CT says of each element, sampled over its cube.
#[derive(Debug, Clone, Default)]
pub struct ElementDensity {
    /// Mean tissue fraction of the element's parenchyma samples (lung, not target); NaN when
    /// it has none.
    pub parenchyma_fraction: Vec<f64>,
    /// Mean tissue fraction of all its tissue samples (parenchyma and target); NaN when none.
    pub tissue_fraction: Vec<f64>,
    /// Share of its tissue samples inside the target (0 without a target).
    pub target_fraction: Vec<f64>,
}

/// Each element's modulus and density relative to the material's.
#[derive(Debug, Clone)]
pub struct ElementTissue {
    /// E_element / E_material.
    pub stiffness_ratio: Vec<f64>,
    /// ρ_element / ρ_material.
    pub density_ratio: Vec<f64>,
}

/// What the tissue mapping gave, for `summary.json`.
#[derive(Debug, Clone, Default, Serialize, Deserialize, PartialEq)]
pub struct TissueReport {
    /// The settings used.
    pub settings: TissueSettings,
    /// Median element tissue fraction φ_ref (the material's modulus sits there).
    pub reference_tissue_fraction: f64,
    /// The HU of φ_ref.
    pub reference_hu: f64,
    /// Elements of the mesh.
    pub elements: usize,
    /// Distinct (modulus, density) steps after rounding: the element classes the tissue adds
    /// to each of the mesh's own.
    pub classes: usize,
    /// Stiffness ratio: smallest, 5th percentile, median, 95th percentile, largest.
    pub stiffness_ratio_quantiles: [f64; 5],
    /// Elements whose ratio hit the clamp below / above.
    pub clamped_soft: usize,
    /// Elements whose ratio hit the clamp above.
    pub clamped_stiff: usize,
    /// Elements with part of the target.
    pub target_elements: usize,
    /// Target volume they hold, in element volumes (Σ target fractions).
    pub target_element_volumes: f64,
    /// Elements with no tissue sample (kept at the material's values).
    pub unsampled_elements: usize,
}

/// The elements' moduli and densities from what the CT says of them.
pub fn map_element_tissue(
    density: &ElementDensity,
    settings: &TissueSettings,
    youngs_modulus_pa: f64,
) -> Result<(ElementTissue, TissueReport)> {
    settings.validate()?;
    let n = density.parenchyma_fraction.len();
    if density.tissue_fraction.len() != n || density.target_fraction.len() != n {
        return Err(Error::InvalidModel(format!(
            "tissue samples disagree on the element count ({n}, {}, {})",
            density.tissue_fraction.len(),
            density.target_fraction.len()
        )));
    }
    let mut sampled: Vec<f64> = density
        .parenchyma_fraction
        .iter()
        .copied()
        .filter(|p| p.is_finite())
        .collect();
    let phi_ref = if sampled.is_empty() {
        1.0
    } else {
        let mid = sampled.len() / 2;
        *sampled.select_nth_unstable_by(mid, |a, b| a.total_cmp(b)).1
    }
    .max(1e-3);
    let max = settings.max_stiffness_ratio;
    let mut report = TissueReport {
        settings: settings.clone(),
        reference_tissue_fraction: phi_ref,
        reference_hu: (phi_ref - 1.0) * 1000.0,
        elements: n,
        ..TissueReport::default()
    };
    let mut stiffness_ratio = Vec::with_capacity(n);
    let mut density_ratio = Vec::with_capacity(n);
    for e in 0..n {
        let phi_p = density.parenchyma_fraction[e];
        let phi_all = density.tissue_fraction[e];
        let f = density.target_fraction[e];
        if !phi_all.is_finite() {
            report.unsampled_elements += 1;
            stiffness_ratio.push(1.0);
            density_ratio.push(1.0);
            continue;
        }
        let parenchyma = if !settings.from_ct || !phi_p.is_finite() {
            1.0
        } else if let Some(table) = &settings.hu_to_youngs_modulus_pa {
            interpolate(table, (phi_p - 1.0) * 1000.0) / youngs_modulus_pa
        } else {
            let r = (phi_p / phi_ref).powf(settings.stiffness_exponent);
            if r < 1.0 / max {
                report.clamped_soft += 1;
            } else if r > max {
                report.clamped_stiff += 1;
            }
            r.clamp(1.0 / max, max)
        };
        if f > 0.0 {
            report.target_elements += 1;
            report.target_element_volumes += f;
        }
        let ratio = (1.0 - f) * parenchyma + f * settings.target_stiffness_ratio;
        if !(ratio.is_finite() && ratio > 0.0) {
            return Err(Error::InvalidModel(format!(
                "element {e}: the tissue mapping gives a stiffness ratio of {ratio} (tissue \
                 fraction {phi_p}, target share {f}); it must be positive"
            )));
        }
        stiffness_ratio.push(ratio);
        density_ratio.push(if settings.from_ct {
            (phi_all / phi_ref).clamp(1.0 / max, max)
        } else {
            1.0
        });
    }
    let steps: std::collections::HashSet<(i32, i32)> = stiffness_ratio
        .iter()
        .zip(&density_ratio)
        .map(|(&e, &rho)| {
            (
                step_of(e, settings.stiffness_step),
                step_of(rho, settings.stiffness_step),
            )
        })
        .collect();
    report.classes = steps.len();
    let mut sorted = stiffness_ratio.clone();
    sorted.sort_by(f64::total_cmp);
    let q = |p: f64| sorted[((sorted.len() - 1) as f64 * p).round() as usize];
    if !sorted.is_empty() {
        report.stiffness_ratio_quantiles = [q(0.0), q(0.05), q(0.5), q(0.95), q(1.0)];
    }
    Ok((
        ElementTissue {
            stiffness_ratio,
            density_ratio,
        },
        report,
    ))
}

/// The step of `ratio` on a log scale of relative steps `step`: ratio ≈ (1 + step)^k.
fn step_of(ratio: f64, step: f64) -> i32 {
    (ratio.ln() / (1.0 + step).ln()).round() as i32
}

/// The table's value at `hu`: piecewise linear, constant beyond its ends.
fn interpolate(table: &[[f64; 2]], hu: f64) -> f64 {
    let last = table.len() - 1;
    if hu <= table[0][0] {
        return table[0][1];
    }
    if hu >= table[last][0] {
        return table[last][1];
    }
    let i = table.partition_point(|row| row[0] <= hu);
    let ([h0, e0], [h1, e1]) = (table[i - 1], table[i]);
    e0 + (e1 - e0) * (hu - h0) / (h1 - h0)
}

/// `mesh` with each element's class scaled by `tissue`: ratios rounded to steps of
/// `step` on a log scale, one class per distinct (original class, modulus step, density
/// step). Node masses follow the densities.
pub fn with_element_tissue(mesh: &HexMesh, tissue: &ElementTissue, step: f64) -> Result<HexMesh> {
    let n = mesh.element_count();
    if tissue.stiffness_ratio.len() != n || tissue.density_ratio.len() != n {
        return Err(Error::InvalidModel(format!(
            "tissue for {} elements on a mesh of {n}",
            tissue.stiffness_ratio.len()
        )));
    }
    let bin = |r: f64| step_of(r, step);
    let mut index: HashMap<(u32, i32, i32), u32> = HashMap::new();
    let mut classes: Vec<BrickCoefficients> = Vec::new();
    let mut element_class = Vec::with_capacity(n);
    for e in 0..n {
        let base = mesh.element_class[e];
        let key = (
            base,
            bin(tissue.stiffness_ratio[e]),
            bin(tissue.density_ratio[e]),
        );
        let class = match index.get(&key) {
            Some(&c) => c,
            None => {
                let original = &mesh.classes[base as usize];
                let mut material = original.material;
                material.youngs_modulus_pa *= (1.0 + step).powi(key.1);
                material.density_kg_per_m3 *= (1.0 + step).powi(key.2);
                classes.push(BrickCoefficients::new(original.shape, material)?);
                let c = (classes.len() - 1) as u32;
                index.insert(key, c);
                c
            }
        };
        element_class.push(class);
    }
    HexMesh::new(
        mesh.rest_positions_m.clone(),
        mesh.elements.clone(),
        element_class,
        classes,
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::model::{BrickShape, Material};

    fn density(phi: &[f64], target: &[f64]) -> ElementDensity {
        ElementDensity {
            parenchyma_fraction: phi.to_vec(),
            tissue_fraction: phi.to_vec(),
            target_fraction: target.to_vec(),
        }
    }

    #[test]
    fn the_median_element_keeps_the_material_and_density_follows_the_square_law() {
        let settings = TissueSettings {
            from_ct: true,
            ..TissueSettings::default()
        };
        let d = density(&[0.1, 0.15, 0.3, 0.075, 0.15], &[0.0; 5]);
        let (t, report) = map_element_tissue(&d, &settings, 390.0).unwrap();
        assert_eq!(report.reference_tissue_fraction, 0.15);
        assert!((report.reference_hu + 850.0).abs() < 1e-9);
        let expect = [(0.1f64 / 0.15).powi(2), 1.0, 4.0, 0.25, 1.0];
        for (got, want) in t.stiffness_ratio.iter().zip(expect) {
            assert!((got - want).abs() < 1e-12, "{got} vs {want}");
        }
        assert!((t.density_ratio[2] - 2.0).abs() < 1e-12);
        assert_eq!(report.clamped_soft + report.clamped_stiff, 0);
    }

    #[test]
    fn ratios_are_clamped_and_counted() {
        let settings = TissueSettings {
            from_ct: true,
            max_stiffness_ratio: 3.0,
            ..TissueSettings::default()
        };
        let (t, report) = map_element_tissue(
            &density(&[0.02, 0.2, 0.2, 1.0], &[0.0; 4]),
            &settings,
            390.0,
        )
        .unwrap();
        assert_eq!(t.stiffness_ratio, vec![1.0 / 3.0, 1.0, 1.0, 3.0]);
        assert_eq!((report.clamped_soft, report.clamped_stiff), (1, 1));
    }

    #[test]
    fn a_target_share_mixes_the_two_moduli_by_volume() {
        let settings = TissueSettings {
            target_stiffness_ratio: 5.0,
            ..TissueSettings::default()
        };
        let (t, report) =
            map_element_tissue(&density(&[0.15; 3], &[0.0, 0.5, 1.0]), &settings, 390.0).unwrap();
        assert_eq!(t.stiffness_ratio, vec![1.0, 3.0, 5.0]);
        assert_eq!(t.density_ratio, vec![1.0; 3]);
        assert_eq!(report.target_elements, 2);
        assert!((report.target_element_volumes - 1.5).abs() < 1e-12);
    }

    #[test]
    fn a_table_gives_pascals_against_the_mean_hu() {
        let settings = TissueSettings {
            from_ct: true,
            hu_to_youngs_modulus_pa: Some(vec![[-900.0, 100.0], [-800.0, 500.0]]),
            ..TissueSettings::default()
        };
        // φ 0.05 (−950 HU), 0.15 (−850 HU), 0.5 (−500 HU)
        let (t, _) =
            map_element_tissue(&density(&[0.05, 0.15, 0.5], &[0.0; 3]), &settings, 400.0).unwrap();
        let want = [0.25, 0.75, 1.25];
        for (got, want) in t.stiffness_ratio.iter().zip(want) {
            assert!((got - want).abs() < 1e-12, "{got} vs {want}");
        }
    }

    #[test]
    fn unusable_settings_are_refused_with_the_key_and_the_value() {
        let cases: Vec<(TissueSettings, &str, &str)> = vec![
            (
                TissueSettings {
                    target_stiffness_ratio: -2.0,
                    ..TissueSettings::default()
                },
                "tissue.target_stiffness_ratio",
                "-2",
            ),
            (
                TissueSettings {
                    from_ct: true,
                    hu_to_youngs_modulus_pa: Some(vec![[-900.0, 100.0], [-800.0, 0.0]]),
                    ..TissueSettings::default()
                },
                "tissue.hu_to_youngs_modulus_pa",
                "0 Pa at -800 HU",
            ),
            (
                TissueSettings {
                    from_ct: true,
                    hu_to_youngs_modulus_pa: Some(vec![[-800.0, 100.0], [-900.0, 50.0]]),
                    ..TissueSettings::default()
                },
                "tissue.hu_to_youngs_modulus_pa",
                "must increase",
            ),
            (
                TissueSettings {
                    from_ct: true,
                    hu_to_youngs_modulus_pa: Some(vec![[-800.0, 100.0]]),
                    ..TissueSettings::default()
                },
                "tissue.hu_to_youngs_modulus_pa",
                "at least two",
            ),
            (
                TissueSettings {
                    stiffness_exponent: f64::NAN,
                    ..TissueSettings::default()
                },
                "tissue.stiffness_exponent",
                "NaN",
            ),
            (
                TissueSettings {
                    max_stiffness_ratio: 0.5,
                    ..TissueSettings::default()
                },
                "tissue.max_stiffness_ratio",
                "0.5",
            ),
            (
                TissueSettings {
                    hu_to_youngs_modulus_pa: Some(vec![[-900.0, 100.0], [-800.0, 500.0]]),
                    ..TissueSettings::default()
                },
                "tissue.hu_to_youngs_modulus_pa",
                "from_ct",
            ),
        ];
        for (settings, key, value) in cases {
            let (k, reason) = settings.problem().expect("refused");
            assert_eq!(k, key);
            assert!(reason.contains(value), "{reason}");
            assert!(settings.validate().unwrap_err().to_string().contains(key));
        }
    }

    #[test]
    fn scaled_classes_carry_the_rounded_moduli_and_the_masses_follow_the_density() {
        let grid =
            crate::model::VoxelGrid::filled_box([2, 1, 1], [0.01; 3], nalgebra::Vector3::zeros());
        let mesh = grid.to_mesh(Material::LUNG).unwrap().mesh;
        let tissue = ElementTissue {
            stiffness_ratio: vec![1.0, 4.0],
            density_ratio: vec![1.0, 2.0],
        };
        let scaled = with_element_tissue(&mesh, &tissue, 0.05).unwrap();
        assert_eq!(scaled.classes.len(), 2);
        let e1 = &scaled.classes[scaled.element_class[1] as usize];
        let rounded = 1.05f64.powi((4.0f64.ln() / 1.05f64.ln()).round() as i32);
        assert!((e1.material.youngs_modulus_pa / 390.0 - rounded).abs() < 1e-12);
        assert!((rounded / 4.0 - 1.0).abs() < 0.025);
        let shape = BrickShape::cube(0.01);
        let plain = BrickCoefficients::new(shape, Material::LUNG).unwrap();
        assert!((e1.corner_mass_kg / plain.corner_mass_kg - 2.0).abs() < 0.05);
        assert!(
            (scaled.total_mass_kg() / mesh.total_mass_kg() - 1.5).abs() < 0.03,
            "{}",
            scaled.total_mass_kg() / mesh.total_mass_kg()
        );
    }
}
