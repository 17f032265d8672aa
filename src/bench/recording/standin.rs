//! The stand-in for issue 18's spirometer recording, which is not in `../shared/data`: a real
//! irregular breathing waveform (the MIMIC respiration channel) scaled to a 500 mL median
//! breath, with a vital-capacity manoeuvre written over it, sampled at 100 Hz.
//!
//! The recording the issue describes: 55 s at 100 Hz, tidal breaths, a manoeuvre up to
//! +1150 mL and a dip to −436 mL below the scanned state. The waveform file holds a chest
//! belt's signal in millivolts (`time_s,value`, `#` comments, 125 Hz), so its scale is not a
//! volume: every breath's rise (a trough to the next peak) is measured, and the signal is
//! scaled so that the median rise is [`MEDIAN_BREATH_ML`], with the median trough at 0 mL
//! (the CT taken at a typical end-exhale).
//!
//! The steps, in order:
//! 1. the first [`DURATION_S`] of the waveform;
//! 2. a centred moving average over [`SMOOTHING_SAMPLES`] samples (fewer at the ends), so
//!    the belt's noise makes no false extrema;
//! 3. troughs and peaks: samples that are the smallest (largest) within
//!    ±[`EXTREMUM_HALF_WINDOW`] samples;
//! 4. each peak's rise above the last trough before it; the scale is
//!    `MEDIAN_BREATH_ML / median(rises)` and the offset the median trough;
//! 5. linear resampling at [`RATE_HZ`];
//! 6. the manoeuvre: a raised-cosine from the curve's value at 20 s up to +1150 mL at 24 s,
//!    down to −436 mL at 29 s and back to the curve's value at 32 s.

use std::path::Path;

use crate::{Error, IoContext, IoOp, Result};

/// Length of the recording, s.
pub const DURATION_S: f64 = 55.0;
/// Sampling rate of the recording, Hz.
pub const RATE_HZ: f64 = 100.0;
/// Median breath the waveform is scaled to, mL.
pub const MEDIAN_BREATH_ML: f64 = 500.0;
/// Samples of the centred moving average.
pub const SMOOTHING_SAMPLES: usize = 25;
/// Half-width of the window a trough or peak is the extremum of, samples.
pub const EXTREMUM_HALF_WINDOW: usize = 100;
/// The manoeuvre: (start s, top s, bottom s, end s) and its top and bottom volumes, mL.
pub const MANOEUVRE_S: [f64; 4] = [20.0, 24.0, 29.0, 32.0];
/// Highest volume of the manoeuvre, mL above the scanned state.
pub const MANOEUVRE_TOP_ML: f64 = 1150.0;
/// Lowest volume of the manoeuvre, mL (below the scanned state).
pub const MANOEUVRE_BOTTOM_ML: f64 = -436.0;

/// A waveform's samples: time s and value (any unit).
#[derive(Debug, Clone, PartialEq)]
pub struct Waveform {
    /// Sample times, s, increasing.
    pub time_s: Vec<f64>,
    /// Sample values.
    pub value: Vec<f64>,
}

/// The stand-in recording and how its scale was found.
#[derive(Debug, Clone)]
pub struct StandInRecording {
    /// Sample times, s (0, 0.01, …, 55).
    pub time_s: Vec<f64>,
    /// Volume change from the scanned state, mL.
    pub volume_ml: Vec<f64>,
    /// Breaths (trough to peak) measured in the waveform.
    pub breaths: usize,
    /// mL per waveform unit.
    pub scale_ml_per_unit: f64,
}

/// Reads a `time,value` waveform CSV (`#` lines are comments, a header line is skipped).
pub fn read_waveform(path: &Path) -> Result<Waveform> {
    let text = std::fs::read_to_string(path).at(IoOp::Read, path)?;
    let mut time_s = Vec::new();
    let mut value = Vec::new();
    for (row, line) in text.lines().enumerate() {
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let mut fields = line.split(',').map(str::trim);
        let (Some(t), Some(v)) = (fields.next(), fields.next()) else {
            return Err(waveform_error(
                path,
                row,
                "expected two columns: time, value",
            ));
        };
        match (t.parse::<f64>(), v.parse::<f64>()) {
            // A `nan` value is a gap in the recording (the MIMIC file ends with four): the
            // sample is left out, the time axis keeps its other samples.
            (Ok(t), Ok(v)) if t.is_finite() && v.is_nan() => {
                if time_s.last().is_some_and(|&last| t <= last) {
                    return Err(waveform_error(path, row, "time does not increase"));
                }
            }
            (Ok(t), Ok(v)) if t.is_finite() && v.is_finite() => {
                if time_s.last().is_some_and(|&last| t <= last) {
                    return Err(waveform_error(path, row, "time does not increase"));
                }
                time_s.push(t);
                value.push(v);
            }
            // The first non-comment line may be a header.
            _ if time_s.is_empty() => continue,
            _ => return Err(waveform_error(path, row, "not two finite numbers")),
        }
    }
    if time_s.len() < 2 {
        return Err(waveform_error(path, 0, "fewer than two samples"));
    }
    Ok(Waveform { time_s, value })
}

fn waveform_error(path: &Path, row: usize, problem: &str) -> Error {
    Error::Trace {
        path: Some(path.to_path_buf()),
        row: Some(row + 1),
        reason: format!("waveform line {}: {problem}", row + 1),
    }
}

/// Builds the stand-in recording from `waveform` (steps in the module documentation).
pub fn stand_in_recording(waveform: &Waveform) -> Result<StandInRecording> {
    let n = waveform.time_s.partition_point(|&t| t <= DURATION_S);
    let t = &waveform.time_s[..n];
    let smooth = moving_average(&waveform.value[..n], SMOOTHING_SAMPLES);
    let (troughs, peaks) = extrema(&smooth, EXTREMUM_HALF_WINDOW);
    let rises: Vec<f64> = peaks
        .iter()
        .filter_map(|&p| {
            let before = troughs.iter().rev().find(|&&tr| tr < p)?;
            Some(smooth[p] - smooth[*before])
        })
        .collect();
    if rises.is_empty() || troughs.is_empty() {
        return Err(Error::Argument {
            what: "breathing waveform".into(),
            reason: format!(
                "no breath found in its first {DURATION_S} s ({} troughs, {} peaks)",
                troughs.len(),
                peaks.len()
            ),
        });
    }
    let median_rise = median(&rises);
    if median_rise <= 0.0 {
        return Err(Error::Argument {
            what: "breathing waveform".into(),
            reason: format!("median breath rise {median_rise} is not positive"),
        });
    }
    let scale = MEDIAN_BREATH_ML / median_rise;
    let base = median(&troughs.iter().map(|&i| smooth[i]).collect::<Vec<_>>());
    let volume: Vec<f64> = smooth.iter().map(|v| (v - base) * scale).collect();
    let samples = (DURATION_S * RATE_HZ).round() as usize + 1;
    let time_s: Vec<f64> = (0..samples).map(|i| i as f64 / RATE_HZ).collect();
    let tidal: Vec<f64> = time_s.iter().map(|&x| interpolate(t, &volume, x)).collect();
    let [start, top, bottom, end] = MANOEUVRE_S;
    let at_start = interpolate(&time_s, &tidal, start);
    let at_end = interpolate(&time_s, &tidal, end);
    let volume_ml = time_s
        .iter()
        .zip(&tidal)
        .map(|(&x, &v)| {
            if (start..top).contains(&x) {
                raised_cosine(at_start, MANOEUVRE_TOP_ML, (x - start) / (top - start))
            } else if (top..bottom).contains(&x) {
                raised_cosine(
                    MANOEUVRE_TOP_ML,
                    MANOEUVRE_BOTTOM_ML,
                    (x - top) / (bottom - top),
                )
            } else if (bottom..end).contains(&x) {
                raised_cosine(MANOEUVRE_BOTTOM_ML, at_end, (x - bottom) / (end - bottom))
            } else {
                v
            }
        })
        .collect();
    Ok(StandInRecording {
        time_s,
        volume_ml,
        breaths: rises.len(),
        scale_ml_per_unit: scale,
    })
}

impl StandInRecording {
    /// The recording as a spirometer's CSV (`time_s,volume_ml`, 0.01 s and 0.01 mL).
    pub fn to_csv(&self) -> String {
        let mut s = String::from("time_s,volume_ml\n");
        for (t, v) in self.time_s.iter().zip(&self.volume_ml) {
            s.push_str(&format!("{t:.2},{v:.2}\n"));
        }
        s
    }
}

/// Centred moving average over `width` samples, over the samples there are near either end
/// (counting those beyond the ends as 0, as numpy's `convolve(…, mode="same")` does, would
/// ramp the recording's first and last 0.1 s towards 0).
fn moving_average(v: &[f64], width: usize) -> Vec<f64> {
    let half = width / 2;
    let mut prefix = Vec::with_capacity(v.len() + 1);
    prefix.push(0.0);
    for x in v {
        prefix.push(prefix.last().copied().unwrap_or(0.0) + x);
    }
    (0..v.len())
        .map(|i| {
            let lo = i.saturating_sub(half);
            let hi = (i + width - half).min(v.len());
            (prefix[hi] - prefix[lo]) / (hi - lo) as f64
        })
        .collect()
}

/// Indices of the samples that are the smallest (troughs) and largest (peaks) within
/// ±`half` samples, away from the ends.
fn extrema(v: &[f64], half: usize) -> (Vec<usize>, Vec<usize>) {
    let mut troughs = Vec::new();
    let mut peaks = Vec::new();
    for i in half..v.len().saturating_sub(half) {
        let window = &v[i - half..=i + half];
        if window.iter().all(|&x| v[i] <= x) {
            troughs.push(i);
        }
        if window.iter().all(|&x| v[i] >= x) {
            peaks.push(i);
        }
    }
    (troughs, peaks)
}

/// Median of `values` (not empty).
fn median(values: &[f64]) -> f64 {
    crate::math::median_sorting(&mut values.to_vec()).unwrap_or(f64::NAN)
}

/// Linear interpolation of (`x`, `y`) at `at`, held constant beyond the ends.
fn interpolate(x: &[f64], y: &[f64], at: f64) -> f64 {
    let i = x.partition_point(|&xi| xi <= at);
    if i == 0 {
        return y[0];
    }
    if i == x.len() {
        return y[x.len() - 1];
    }
    let f = (at - x[i - 1]) / (x[i] - x[i - 1]);
    y[i - 1] + f * (y[i] - y[i - 1])
}

/// From `a` at `s` = 0 to `b` at `s` = 1 along half a cosine (no jump in slope at either end).
fn raised_cosine(a: f64, b: f64, s: f64) -> f64 {
    a + (b - a) * (0.5 - 0.5 * (std::f64::consts::PI * s).cos())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A belt signal of 4 s breaths, 125 Hz, amplitude 0.3 mV about −1 mV.
    fn belt(amplitude: f64) -> Waveform {
        let time_s: Vec<f64> = (0..(60 * 125)).map(|i| i as f64 / 125.0).collect();
        let value = time_s
            .iter()
            .map(|t| -1.0 - amplitude * (2.0 * std::f64::consts::PI * t / 4.0).cos())
            .collect();
        Waveform { time_s, value }
    }

    #[test]
    fn a_regular_belt_becomes_500_ml_breaths_from_the_troughs() {
        let r = stand_in_recording(&belt(0.3)).unwrap();
        assert_eq!(r.time_s.len(), 5501);
        assert_eq!(r.time_s[5500], 55.0);
        // 13 full breaths peak in the first 55 s away from the window's ends.
        assert!(r.breaths >= 11, "{}", r.breaths);
        // The smoothing flattens a 4 s sine by under 0.1 %: troughs at 0, peaks at 500 mL.
        let tidal_part: Vec<f64> = r.volume_ml[200..2000].to_vec();
        let lo = tidal_part.iter().copied().fold(f64::INFINITY, f64::min);
        let hi = tidal_part.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        assert!(lo.abs() < 0.5 && (hi - 500.0).abs() < 0.5, "{lo} {hi}");
        // Twice the amplitude, half the scale: the output does not depend on the belt's gain.
        let doubled = stand_in_recording(&belt(0.6)).unwrap();
        assert!((doubled.scale_ml_per_unit * 2.0 - r.scale_ml_per_unit).abs() < 1e-6);
    }

    #[test]
    fn the_manoeuvre_reaches_its_volumes_and_joins_the_curve_smoothly() {
        let r = stand_in_recording(&belt(0.3)).unwrap();
        let at = |t: f64| r.volume_ml[(t * RATE_HZ).round() as usize];
        assert!((at(24.0) - MANOEUVRE_TOP_ML).abs() < 1e-9);
        assert!((at(29.0) - MANOEUVRE_BOTTOM_ML).abs() < 1e-9);
        let top = r
            .volume_ml
            .iter()
            .copied()
            .fold(f64::NEG_INFINITY, f64::max);
        let bottom = r.volume_ml.iter().copied().fold(f64::INFINITY, f64::min);
        assert_eq!((top, bottom), (MANOEUVRE_TOP_ML, MANOEUVRE_BOTTOM_ML));
        // No step anywhere, the ends included: neighbours differ by no more than the
        // steepest slope, the manoeuvre's fall of 1586 mL in 5 s along half a cosine
        // (π/2 times its mean slope, 498 mL/s: 4.98 mL between samples at 100 Hz).
        let [_, top_s, bottom_s, _] = MANOEUVRE_S;
        let steepest = std::f64::consts::FRAC_PI_2 * (MANOEUVRE_TOP_ML - MANOEUVRE_BOTTOM_ML)
            / (bottom_s - top_s)
            / RATE_HZ;
        let step = r
            .volume_ml
            .windows(2)
            .map(|w| (w[1] - w[0]).abs())
            .fold(0.0, f64::max);
        assert!(step <= steepest * 1.001, "{step} > {steepest}");
    }

    #[test]
    fn a_waveform_without_breaths_is_refused_by_name() {
        let flat = Waveform {
            time_s: (0..7000).map(|i| i as f64 / 125.0).collect(),
            value: vec![1.0; 7000],
        };
        // Every sample of a flat line is both a trough and a peak: rises of 0.
        let e = stand_in_recording(&flat).unwrap_err().to_string();
        assert!(e.contains("median breath rise"), "{e}");
    }

    #[test]
    fn the_waveform_reader_skips_comments_and_a_header_and_names_bad_rows() {
        let dir = std::env::temp_dir().join(format!("lm-waveform-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let good = dir.join("good.csv");
        std::fs::write(
            &good,
            "# time_s,RESP [mV] fs=125\ntime,resp\n0,1\n0.008,2\n0.016,nan\n0.024,3\n",
        )
        .unwrap();
        let w = read_waveform(&good).unwrap();
        assert_eq!(w.time_s, vec![0.0, 0.008, 0.024]);
        assert_eq!(w.value, vec![1.0, 2.0, 3.0]);
        let bad = dir.join("bad.csv");
        std::fs::write(&bad, "0,1\n0.008,inf\n").unwrap();
        let e = read_waveform(&bad).unwrap_err().to_string();
        assert!(e.contains("line 2") && e.contains("bad.csv"), "{e}");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
