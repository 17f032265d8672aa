//! Standard breathing curves, so tests and the demo need no spirometer file.
//!
//! Lujan's model (Lujan et al., Med. Phys. 26, 1999) describes breathing motion as
//! `z(t) = z₀ − b·cos²ⁿ(πt/τ − φ)`: a short inhalation peak and a long end-exhale plateau,
//! longer as n grows. Written for volume and started at end-exhale:
//! `ΔV(t) = baseline + tidal · sin²ⁿ(π t / period)`.

use serde::{Deserialize, Serialize};

use super::trace::BreathingTrace;
use crate::{Error, Result};

/// Regular breathing after Lujan: the same cycle repeated.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct LujanBreathing {
    /// Duration of one breath, s (≈ 4 s at 15 breaths / min).
    pub period_s: f64,
    /// Volume inhaled per breath, mL (≈ 500 mL at rest).
    pub tidal_volume_ml: f64,
    /// Volume change from the scanned state at end-exhale, mL (0: the CT is at end-exhale).
    pub baseline_ml: f64,
    /// Lujan's n: 1 is a sine; 2–3 give the typical long end-exhale plateau.
    pub exponent: u32,
}

impl Default for LujanBreathing {
    fn default() -> Self {
        LujanBreathing {
            period_s: 4.0,
            tidal_volume_ml: 500.0,
            baseline_ml: 0.0,
            exponent: 2,
        }
    }
}

impl LujanBreathing {
    /// Checks the parameters are physical.
    pub fn validate(&self) -> Result<()> {
        if !(self.period_s.is_finite() && self.period_s >= 0.5 && self.period_s <= 60.0) {
            return Err(model_setting(
                "period_s",
                format!("{} s outside 0.5–60 s", self.period_s),
            ));
        }
        if !(self.tidal_volume_ml.is_finite() && self.tidal_volume_ml.abs() <= 4000.0) {
            return Err(model_setting(
                "tidal_volume_ml",
                format!("{} mL outside ±4000 mL", self.tidal_volume_ml),
            ));
        }
        if !self.baseline_ml.is_finite() {
            return Err(model_setting("baseline_ml", "not finite".into()));
        }
        if !(1..=10).contains(&self.exponent) {
            return Err(model_setting(
                "exponent",
                format!("{} outside 1–10", self.exponent),
            ));
        }
        Ok(())
    }

    /// Volume change from the scanned state at time `t_s`, mL.
    pub fn volume_at(&self, t_s: f64) -> f64 {
        let s = (std::f64::consts::PI * t_s / self.period_s).sin();
        self.baseline_ml + self.tidal_volume_ml * s.powi(2 * self.exponent as i32)
    }

    /// Samples `duration_s` at `rate_hz` (both ends included).
    pub fn trace(&self, duration_s: f64, rate_hz: f64) -> Result<BreathingTrace> {
        self.validate()?;
        let times = sample_times(duration_s, rate_hz)?;
        let volumes = times.iter().map(|&t| self.volume_at(t)).collect();
        BreathingTrace::new(times, volumes)
    }
}

/// Irregular breathing: Lujan cycles whose period and depth vary from breath to breath, on a
/// drifting baseline (as patients relax during a session).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct IrregularBreathing {
    /// The mean cycle.
    pub mean: LujanBreathing,
    /// Relative standard deviation of the period between breaths (e.g. 0.15).
    pub period_variation: f64,
    /// Relative standard deviation of the tidal volume between breaths (e.g. 0.2).
    pub amplitude_variation: f64,
    /// Baseline drift, mL per minute.
    pub drift_ml_per_min: f64,
    /// Seed of the breath-to-breath variation (same seed, same curve).
    pub seed: u64,
}

impl Default for IrregularBreathing {
    fn default() -> Self {
        IrregularBreathing {
            mean: LujanBreathing::default(),
            period_variation: 0.15,
            amplitude_variation: 0.2,
            drift_ml_per_min: 30.0,
            seed: 1,
        }
    }
}

impl IrregularBreathing {
    /// Samples `duration_s` at `rate_hz`; each breath draws its own period and depth.
    pub fn trace(&self, duration_s: f64, rate_hz: f64) -> Result<BreathingTrace> {
        self.mean.validate()?;
        for (key, v) in [
            ("period_variation", self.period_variation),
            ("amplitude_variation", self.amplitude_variation),
        ] {
            if !(v.is_finite() && (0.0..=0.5).contains(&v)) {
                return Err(model_setting(key, format!("{v} outside 0–0.5")));
            }
        }
        if !self.drift_ml_per_min.is_finite() {
            return Err(model_setting("drift_ml_per_min", "not finite".into()));
        }
        let times = sample_times(duration_s, rate_hz)?;
        let mut rng = SplitMix64(self.seed);
        // Breath boundaries and depths, drawn until the trace is covered.
        let mut breaths = Vec::new();
        let mut start = 0.0;
        while start <= duration_s {
            let period = self.mean.period_s * (1.0 + self.period_variation * rng.standardised());
            let depth =
                self.mean.tidal_volume_ml * (1.0 + self.amplitude_variation * rng.standardised());
            breaths.push((start, period.max(0.5), depth));
            start += period.max(0.5);
        }
        let mut b = 0;
        let volumes = times
            .iter()
            .map(|&t| {
                while b + 1 < breaths.len() && t >= breaths[b + 1].0 {
                    b += 1;
                }
                let (t0, period, depth) = breaths[b];
                let s = (std::f64::consts::PI * (t - t0) / period).sin();
                self.mean.baseline_ml
                    + self.drift_ml_per_min * t / 60.0
                    + depth * s.powi(2 * self.mean.exponent as i32)
            })
            .collect();
        BreathingTrace::new(times, volumes)
    }
}

/// A refused setting of a breathing model.
fn model_setting(key: &str, reason: String) -> Error {
    Error::Config {
        settings: "breathing model",
        file: None,
        key: Some(key.to_string()),
        reason,
    }
}

fn sample_times(duration_s: f64, rate_hz: f64) -> Result<Vec<f64>> {
    if !(duration_s.is_finite() && duration_s > 0.0 && duration_s <= 86_400.0) {
        return Err(model_setting(
            "duration_s",
            format!("{duration_s} s outside (0, 1 day]"),
        ));
    }
    if !(rate_hz.is_finite() && rate_hz > 0.0 && rate_hz <= 1000.0) {
        return Err(model_setting(
            "rate_hz",
            format!("{rate_hz} Hz outside (0, 1000]"),
        ));
    }
    let n = (duration_s * rate_hz).round() as usize;
    Ok((0..=n).map(|i| i as f64 / rate_hz).collect())
}

/// A small, well-known generator: reproducible curves without a dependency.
struct SplitMix64(u64);

impl SplitMix64 {
    fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }

    /// Uniform on [−√3, √3]: zero mean, unit variance, bounded (no absurd breaths).
    fn standardised(&mut self) -> f64 {
        let u = (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64;
        (2.0 * u - 1.0) * 3f64.sqrt()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lujan_starts_at_end_exhale_and_peaks_at_half_period() {
        let m = LujanBreathing::default();
        assert_eq!(m.volume_at(0.0), 0.0);
        assert!((m.volume_at(2.0) - 500.0).abs() < 1e-9);
        assert!(m.volume_at(4.0).abs() < 1e-9);
        // n = 2: a quarter into the cycle the lungs hold (√½)⁴ = ¼ of the tidal volume,
        // less than a sine's half: the long end-exhale plateau.
        assert!((m.volume_at(1.0) - 125.0).abs() < 1e-9);
        let t = m.trace(8.0, 25.0).unwrap();
        assert_eq!(t.time_s.len(), 201);
        let max = t.volume_change_ml.iter().cloned().fold(f64::MIN, f64::max);
        assert!((max - 500.0).abs() < 1e-9);
    }

    #[test]
    fn irregular_breathing_varies_drifts_and_repeats_with_its_seed() {
        let m = IrregularBreathing::default();
        let a = m.trace(60.0, 10.0).unwrap();
        assert_eq!(a, m.trace(60.0, 10.0).unwrap());
        let other = IrregularBreathing { seed: 2, ..m };
        assert_ne!(a, other.trace(60.0, 10.0).unwrap());
        // Peaks of the individual breaths differ.
        let peaks: Vec<f64> = a
            .volume_change_ml
            .windows(3)
            .filter(|w| w[1] > w[0] && w[1] >= w[2] && w[1] > 100.0)
            .map(|w| w[1])
            .collect();
        assert!(peaks.len() >= 10, "{peaks:?}");
        let spread = peaks.iter().cloned().fold(f64::MIN, f64::max)
            - peaks.iter().cloned().fold(f64::MAX, f64::min);
        assert!(spread > 50.0, "{peaks:?}");
        // 30 mL/min drift over a minute raises the end-exhale floor by about 30 mL.
        let floor_late = a.volume_change_ml[450..]
            .iter()
            .cloned()
            .fold(f64::MAX, f64::min);
        assert!(floor_late > 15.0, "{floor_late}");
    }

    #[test]
    fn unphysical_parameters_are_refused() {
        let bad = LujanBreathing {
            period_s: 0.0,
            ..LujanBreathing::default()
        };
        assert!(bad
            .trace(10.0, 10.0)
            .unwrap_err()
            .to_string()
            .contains("period"));
        let m = LujanBreathing::default();
        assert!(m
            .trace(f64::NAN, 10.0)
            .unwrap_err()
            .to_string()
            .contains("duration"));
        assert!(m.trace(10.0, 0.0).unwrap_err().to_string().contains("rate"));
    }
}
