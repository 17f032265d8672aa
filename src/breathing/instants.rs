//! The instants at which displacement fields are wanted: every sample, every k-th, a fixed
//! frame rate, or the phases of one breathing cycle as a 4D-CT bins them.
//!
//! Phase convention: as in clinical 4D-CT (Varian RPM), phase 0 % is end-inhale; N phases
//! split one cycle, from an end-inhale peak to the next, into N equal time steps.

use serde::{Deserialize, Serialize};

use super::trace::BreathingTrace;
use crate::{Error, Result};

/// Most output frames one run may ask for.
pub const MAX_FRAMES: usize = 100_000;

/// Which instants of a trace get a displacement field.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case", tag = "kind")]
pub enum OutputInstants {
    /// Every sample of the trace.
    EverySample,
    /// Every k-th sample, starting with the first.
    EveryKth {
        /// Stride in samples (≥ 1).
        k: usize,
    },
    /// A fixed frame rate from the first sample to the last.
    FrameRate {
        /// Frames per second.
        hz: f64,
    },
    /// `count` equally spaced phases of the first complete cycle, phase 0 at end-inhale.
    Phases {
        /// Number of phases (10 like a 4D-CT).
        count: usize,
    },
}

impl Default for OutputInstants {
    fn default() -> Self {
        OutputInstants::Phases { count: 10 }
    }
}

impl OutputInstants {
    /// The output times in seconds, increasing, within the trace.
    pub fn times(&self, trace: &BreathingTrace) -> Result<Vec<f64>> {
        let bad = |key: &str, reason: String| {
            Err(Error::Config {
                settings: "output instants",
                file: None,
                key: Some(key.to_string()),
                reason,
            })
        };
        let times: Vec<f64> = match *self {
            OutputInstants::EverySample => trace.time_s.clone(),
            OutputInstants::EveryKth { k } => {
                if k == 0 {
                    return bad("k", "the stride must be at least 1".into());
                }
                trace.time_s.iter().step_by(k).copied().collect()
            }
            OutputInstants::FrameRate { hz } => {
                if !(hz.is_finite() && hz > 0.0) {
                    return bad("hz", format!("frame rate {hz} Hz must be positive"));
                }
                let n = (trace.duration_s() * hz).floor();
                if n >= MAX_FRAMES as f64 {
                    return bad(
                        "hz",
                        format!("{n} frames at {hz} Hz; at most {MAX_FRAMES} per run"),
                    );
                }
                let t0 = trace.time_s[0];
                (0..=n as usize).map(|i| t0 + i as f64 / hz).collect()
            }
            OutputInstants::Phases { count } => {
                if count == 0 {
                    return bad("count", "the number of phases must be at least 1".into());
                }
                let (p1, p2) = first_cycle(trace).map_err(|reason| Error::Config {
                    settings: "output instants",
                    file: None,
                    key: None,
                    reason,
                })?;
                (0..count)
                    .map(|k| p1 + (p2 - p1) * k as f64 / count as f64)
                    .collect()
            }
        };
        if times.len() > MAX_FRAMES {
            return bad(
                "kind",
                format!("{} frames; at most {MAX_FRAMES} per run", times.len()),
            );
        }
        Ok(times)
    }
}

/// Times of the first two complete end-inhale peaks. A breath is a stretch above the curve's
/// mid-level; its peak is its maximum. Breaths cut by the trace's ends are not complete.
pub fn first_cycle(trace: &BreathingTrace) -> std::result::Result<(f64, f64), String> {
    let v = &trace.volume_change_ml;
    let (lo, hi) = v
        .iter()
        .fold((f64::MAX, f64::MIN), |(a, b), &x| (a.min(x), b.max(x)));
    if hi - lo < 1.0 {
        return Err(format!(
            "the trace varies by {:.2} mL only: no breathing cycle to split into phases",
            hi - lo
        ));
    }
    let mid = 0.5 * (lo + hi);
    let mut peaks = Vec::new();
    let mut start = None;
    for i in 1..v.len() {
        if v[i - 1] < mid && v[i] >= mid {
            start = Some(i);
        } else if v[i - 1] >= mid && v[i] < mid {
            if let Some(s) = start.take() {
                let peak = (s..i).max_by(|&a, &b| v[a].total_cmp(&v[b])).unwrap();
                peaks.push(trace.time_s[peak]);
                if peaks.len() == 2 {
                    return Ok((peaks[0], peaks[1]));
                }
            }
        }
    }
    Err(format!(
        "the trace holds {} complete breath(s); phases need one full cycle between two \
         end-inhale peaks, each with the curve rising above and falling below its mid-level \
         ({mid:.0} mL)",
        peaks.len()
    ))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::breathing::LujanBreathing;

    #[test]
    fn ten_phases_split_one_cycle_from_end_inhale() {
        let trace = LujanBreathing::default().trace(12.0, 50.0).unwrap();
        let times = OutputInstants::Phases { count: 10 }.times(&trace).unwrap();
        assert_eq!(times.len(), 10);
        assert!((times[0] - 2.0).abs() < 1e-9, "{times:?}");
        assert!((times[5] - 4.0).abs() < 1e-9, "{times:?}");
        assert!((trace.volume_at(times[0]) - 500.0).abs() < 1e-6);
        assert!(trace.volume_at(times[5]).abs() < 1e-6);
    }

    #[test]
    fn strides_and_frame_rates() {
        let trace = LujanBreathing::default().trace(4.0, 10.0).unwrap();
        assert_eq!(OutputInstants::EverySample.times(&trace).unwrap().len(), 41);
        let t = OutputInstants::EveryKth { k: 10 }.times(&trace).unwrap();
        assert_eq!(t.len(), 5);
        assert!((t[4] - 4.0).abs() < 1e-12);
        let t = OutputInstants::FrameRate { hz: 2.0 }.times(&trace).unwrap();
        assert_eq!(t, vec![0.0, 0.5, 1.0, 1.5, 2.0, 2.5, 3.0, 3.5, 4.0]);
    }

    #[test]
    fn impossible_requests_are_explained() {
        let trace = LujanBreathing::default().trace(3.0, 10.0).unwrap();
        let e = OutputInstants::Phases { count: 10 }
            .times(&trace)
            .unwrap_err();
        assert!(e.to_string().contains("1 complete breath"), "{e}");
        let flat = BreathingTrace::new(vec![0.0, 1.0], vec![5.0, 5.0]).unwrap();
        let e = OutputInstants::Phases { count: 10 }
            .times(&flat)
            .unwrap_err();
        assert!(e.to_string().contains("no breathing cycle"), "{e}");
        assert!(OutputInstants::EveryKth { k: 0 }.times(&trace).is_err());
        assert!(OutputInstants::FrameRate { hz: -1.0 }
            .times(&trace)
            .is_err());
        let e = OutputInstants::FrameRate { hz: 1e6 }
            .times(&trace)
            .unwrap_err();
        assert!(e.to_string().contains("at most"), "{e}");
    }
}
