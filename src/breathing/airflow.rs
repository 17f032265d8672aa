//! Airflow traces: a spirometer's flow column integrated into the lung volume change, with the
//! integration drift removed.
//!
//! Integrating flow turns any offset of the flow sensor (a few mL/s) into a volume that
//! drifts without bound, so the drift is estimated and removed: the end-expiratory volumes
//! of a steady breather lie on a level line, so the slope of the line through them is the
//! drift. The slope is the Theil–Sen estimate (the median of the slopes between every pair of
//! end-expirations), which a few deeper exhalations or sighs do not pull. The first sample
//! stays at zero: it is taken as the scanned state, as in a volume column.

/// Fewest end-expirations from which a drift is estimated; with fewer (a single breath, a
/// ramp) there is no level to compare with and nothing is removed.
pub const MIN_END_EXPIRATIONS: usize = 3;

/// Smallest swing, mL, that counts as a breath when finding end-expirations (below it:
/// cardiogenic oscillations and sensor noise).
const MIN_BREATH_SWING_ML: f64 = 20.0;

/// Share of the larger swings (their 90th percentile) a breath must reach.
const BREATH_SWING_SHARE: f64 = 0.3;

/// Most end-expirations the slope is estimated from (evenly picked beyond), bounding the
/// pairwise slopes to about 20 000 whatever the recording's length.
const MAX_SLOPE_POINTS: usize = 200;

/// The volume a flow column integrates to, with what was done to get it.
#[derive(Debug, Clone, PartialEq)]
pub struct IntegratedFlow {
    /// Volume change from the first sample at each time, drift removed, mL.
    pub volume_ml: Vec<f64>,
    /// The drift removed, mL/s (0 when too few end-expirations were found).
    pub drift_ml_per_s: f64,
    /// End-expirations found.
    pub end_expirations: usize,
}

impl IntegratedFlow {
    /// What was done, in one sentence for the console and `summary.json`.
    pub fn note(&self, column: &str) -> String {
        let integrated = format!(
            "airflow column '{column}' integrated (trapezoid rule) into the volume change, the \
             first sample taken as the scanned state"
        );
        if self.end_expirations >= MIN_END_EXPIRATIONS {
            format!(
                "{integrated}; a drift of {:+.2} mL/s removed (Theil-Sen slope through {} \
                 end-expirations)",
                self.drift_ml_per_s, self.end_expirations
            )
        } else {
            format!(
                "{integrated}; no drift removed: {} end-expiration(s) found, at least \
                 {MIN_END_EXPIRATIONS} are needed to tell drift from breathing",
                self.end_expirations
            )
        }
    }
}

/// Integrates `flow_ml_per_s` (positive = air in) over `time_s` (strictly increasing, as
/// many as the flows) and removes the drift.
pub fn integrate_flow(time_s: &[f64], flow_ml_per_s: &[f64]) -> IntegratedFlow {
    let mut volume_ml = Vec::with_capacity(time_s.len());
    let mut v = 0.0;
    for i in 0..time_s.len().min(flow_ml_per_s.len()) {
        if i > 0 {
            v += 0.5 * (flow_ml_per_s[i - 1] + flow_ml_per_s[i]) * (time_s[i] - time_s[i - 1]);
        }
        volume_ml.push(v);
    }
    let minima = end_expirations(&volume_ml);
    let drift_ml_per_s = if minima.len() >= MIN_END_EXPIRATIONS {
        theil_sen_slope(&minima, time_s, &volume_ml)
    } else {
        0.0
    };
    if drift_ml_per_s != 0.0 {
        let t0 = time_s[0];
        for (v, &t) in volume_ml.iter_mut().zip(time_s) {
            *v -= drift_ml_per_s * (t - t0);
        }
    }
    IntegratedFlow {
        volume_ml,
        drift_ml_per_s,
        end_expirations: minima.len(),
    }
}

/// Indices of the end-expirations: the minima between breaths, each deeper by at least a
/// breath's swing than the peaks on both sides (a swing being 30 % of the larger breaths, at
/// least 20 mL), so noise on a minimum does not count as another breath.
fn end_expirations(volume_ml: &[f64]) -> Vec<usize> {
    let first_pass = turning_points(volume_ml, MIN_BREATH_SWING_ML);
    let mut swings: Vec<f64> = first_pass
        .windows(2)
        .map(|w| (volume_ml[w[1].0] - volume_ml[w[0].0]).abs())
        .collect();
    if swings.is_empty() {
        return Vec::new();
    }
    swings.sort_by(f64::total_cmp);
    let large = swings[(swings.len() * 9 / 10).min(swings.len() - 1)];
    let threshold = (BREATH_SWING_SHARE * large).max(MIN_BREATH_SWING_ML);
    let points = turning_points(volume_ml, threshold);
    // A minimum counts only with a peak on both sides: the first and last samples are not
    // end-expirations just because the recording starts or stops there.
    points
        .iter()
        .enumerate()
        .filter(|&(k, &(_, is_min))| is_min && k > 0 && k + 1 < points.len())
        .map(|(_, &(i, _))| i)
        .collect()
}

/// Alternating peaks and troughs (index, is a trough), each at least `swing_ml` away from the
/// one before (a zigzag filter); the last one found is kept even if the swing after it is
/// not complete.
fn turning_points(volume_ml: &[f64], swing_ml: f64) -> Vec<(usize, bool)> {
    let mut points = Vec::new();
    let Some(&first) = volume_ml.first() else {
        return points;
    };
    // Direction unknown until the signal has moved by a swing from the start.
    let (mut lo, mut hi) = ((0, first), (0, first));
    let mut rising: Option<bool> = None;
    for (i, &v) in volume_ml.iter().enumerate() {
        match rising {
            None => {
                if v < lo.1 {
                    lo = (i, v);
                }
                if v > hi.1 {
                    hi = (i, v);
                }
                if hi.1 - lo.1 >= swing_ml {
                    // Sample i has just widened the range: rising if it is the peak.
                    let now_rising = hi.0 == i;
                    points.push(if now_rising {
                        (lo.0, true)
                    } else {
                        (hi.0, false)
                    });
                    rising = Some(now_rising);
                }
            }
            Some(true) => {
                if v > hi.1 {
                    hi = (i, v);
                } else if hi.1 - v >= swing_ml {
                    points.push((hi.0, false));
                    rising = Some(false);
                    lo = (i, v);
                }
            }
            Some(false) => {
                if v < lo.1 {
                    lo = (i, v);
                } else if v - lo.1 >= swing_ml {
                    points.push((lo.0, true));
                    rising = Some(true);
                    hi = (i, v);
                }
            }
        }
    }
    match rising {
        Some(true) => points.push((hi.0, false)),
        Some(false) => points.push((lo.0, true)),
        None => {}
    }
    points
}

/// Median slope, mL/s, between every pair of the chosen samples (at most
/// [`MAX_SLOPE_POINTS`] of them, evenly picked).
fn theil_sen_slope(chosen: &[usize], time_s: &[f64], volume_ml: &[f64]) -> f64 {
    let step = chosen.len().div_ceil(MAX_SLOPE_POINTS).max(1);
    let picked: Vec<usize> = chosen.iter().step_by(step).copied().collect();
    let mut slopes = Vec::with_capacity(picked.len() * picked.len() / 2);
    for (k, &a) in picked.iter().enumerate() {
        for &b in &picked[k + 1..] {
            slopes.push((volume_ml[b] - volume_ml[a]) / (time_s[b] - time_s[a]));
        }
    }
    crate::math::median_sorting(&mut slopes).unwrap_or(0.0)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `breaths` sine-squared breaths of `tidal_ml` over `period_s` each at `hz`: times, the
    /// true volume (0 at every end-expiration) and its exact flow.
    fn sine_breathing(
        breaths: usize,
        period_s: f64,
        tidal_ml: f64,
        hz: f64,
    ) -> (Vec<f64>, Vec<f64>, Vec<f64>) {
        let n = (breaths as f64 * period_s * hz).round() as usize;
        let w = std::f64::consts::PI / period_s;
        let t: Vec<f64> = (0..=n).map(|i| i as f64 / hz).collect();
        let v = t.iter().map(|t| tidal_ml * (w * t).sin().powi(2)).collect();
        let f = t
            .iter()
            .map(|t| tidal_ml * w * (2.0 * w * t).sin())
            .collect();
        (t, v, f)
    }

    fn largest_error(a: &[f64], b: &[f64]) -> f64 {
        a.iter()
            .zip(b)
            .map(|(x, y)| (x - y).abs())
            .fold(0.0, f64::max)
    }

    #[test]
    fn a_sine_flow_with_a_sensor_offset_integrates_back_to_its_volume() {
        // 12 breaths of 500 mL over 4 s at 50 Hz; the sensor reads 25 mL/s too much, which
        // integrates to +1.2 L over the 48 s.
        let (t, v, f) = sine_breathing(12, 4.0, 500.0, 50.0);
        let offset: Vec<f64> = f.iter().map(|f| f + 25.0).collect();
        let r = integrate_flow(&t, &offset);
        assert_eq!(r.end_expirations, 11);
        assert!((r.drift_ml_per_s - 25.0).abs() < 0.05, "{r:?}");
        // Stated accuracy: within 1 % of the tidal volume at every sample.
        let error = largest_error(&r.volume_ml, &v);
        assert!(error < 5.0, "largest error {error} mL");
        // Without an offset nothing is removed (the trapezoid error alone: < 0.5 mL).
        let r = integrate_flow(&t, &f);
        assert!(r.drift_ml_per_s.abs() < 0.01, "{r:?}");
        assert!(largest_error(&r.volume_ml, &v) < 0.5);
    }

    #[test]
    fn a_few_deep_exhalations_and_noise_do_not_pull_the_drift() {
        let (t, mut v, _) = sine_breathing(15, 4.0, 500.0, 25.0);
        // Breaths 5 and 10 end 400 mL deeper than the others (a sigh, a forced exhalation);
        // a 15 mL ripple at 1.3 Hz stands for the heart beat.
        for (i, t) in t.iter().enumerate() {
            let breath = (t / 4.0) as usize;
            if breath == 5 || breath == 10 {
                v[i] -= 400.0 * (std::f64::consts::PI * t / 4.0).sin().powi(2);
            }
            v[i] += 15.0 * (2.0 * std::f64::consts::PI * 1.3 * t).sin();
        }
        // Flow by differences, then 40 mL/s of offset.
        let mut flow = vec![0.0; t.len()];
        for i in 1..t.len() - 1 {
            flow[i] = (v[i + 1] - v[i - 1]) / (t[i + 1] - t[i - 1]) - 40.0;
        }
        let r = integrate_flow(&t, &flow);
        assert!((r.drift_ml_per_s + 40.0).abs() < 1.0, "{r:?}");
        assert!(r.end_expirations >= 12, "{r:?}");
    }

    #[test]
    fn a_single_inspiration_keeps_its_ramp() {
        let t: Vec<f64> = (0..=100).map(|i| i as f64 * 0.1).collect();
        let flow = vec![100.0; t.len()];
        let r = integrate_flow(&t, &flow);
        assert_eq!(r.drift_ml_per_s, 0.0);
        assert!((r.volume_ml[100] - 1000.0).abs() < 1e-9);
        assert!(r.note("flow_ml_per_s").contains("no drift removed"));
    }

    #[test]
    #[cfg_attr(not(shared_data), ignore = "needs ../shared/data (respiration-mimic)")]
    fn a_real_irregular_recording_gives_back_its_sensor_offset() {
        // The MIMIC impedance waveform (600 s at 125 Hz, irregular breaths with their own
        // baseline wander), scaled to 500 mL breaths and turned into flow by differences.
        let path = crate::datasets::shared_data_dir()
            .expect("shared data")
            .join("respiration-mimic/03700181_RESP.csv");
        let text = std::fs::read_to_string(path).unwrap();
        let (t, raw): (Vec<f64>, Vec<f64>) = text
            .lines()
            .filter(|l| !l.starts_with('#'))
            .map(|l| {
                let (a, b) = l.split_once(',').unwrap();
                (a.parse::<f64>().unwrap(), b.parse::<f64>().unwrap())
            })
            .unzip();
        let mut sorted = raw.clone();
        sorted.sort_by(f64::total_cmp);
        let n = sorted.len();
        let ml_per_mv = 500.0 / (sorted[n * 95 / 100] - sorted[n * 5 / 100]);
        let mut flow = vec![0.0; n];
        for i in 1..n - 1 {
            flow[i] = (raw[i + 1] - raw[i - 1]) * ml_per_mv / (t[i + 1] - t[i - 1]);
        }
        let plain = integrate_flow(&t, &flow);
        let offset: Vec<f64> = flow.iter().map(|f| f + 25.0).collect();
        let shifted = integrate_flow(&t, &offset);
        // About 20 breaths a minute for 10 minutes.
        assert!(
            (180..=220).contains(&plain.end_expirations),
            "{}",
            plain.end_expirations
        );
        assert!((shifted.drift_ml_per_s - plain.drift_ml_per_s - 25.0).abs() < 0.05);
        let error = largest_error(&shifted.volume_ml, &plain.volume_ml);
        assert!(error < 2.0, "{error} mL");
    }
}
