//! The instants at which displacement fields are wanted: every sample, every k-th, a fixed
//! frame rate, or the phases of one breathing cycle as a 4D-CT bins them.
//!
//! Phase convention: as in clinical 4D-CT (Varian RPM), phase 0 % is end-inhale; N phases
//! split one cycle, from an end-inhale peak to the next, into N equal time steps. A trace
//! holding one breath only (end-exhale, end-inhale, end-exhale) is taken as one period of a
//! periodic breathing: the cycle lasts from one end-exhale to the other, phase 0 % is its
//! end-inhale, and the phases that would fall after the second end-exhale are taken one period
//! earlier, in the inspiration. A trace without a complete breath (a ramp) gets a frame at
//! every sample instead, and the plan says so.

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

/// The output instants of one trace, with each frame's breathing phase when phases were
/// asked for, and what was done instead of what was asked, if anything.
#[derive(Debug, Clone, PartialEq)]
pub struct InstantPlan {
    /// Output times, s, increasing, within the trace.
    pub times: Vec<f64>,
    /// Phase of each output time, percent of the cycle from end-inhale (phases only).
    pub phase_percent: Option<Vec<f64>>,
    /// How the request was met when not literally (one breath, no breath), for the summary
    /// and the console.
    pub note: Option<String>,
}

impl OutputInstants {
    /// The output times in seconds, increasing, within the trace.
    pub fn times(&self, trace: &BreathingTrace) -> Result<Vec<f64>> {
        Ok(self.plan(trace)?.times)
    }

    /// The output times with their phases and any note on how the request was met.
    pub fn plan(&self, trace: &BreathingTrace) -> Result<InstantPlan> {
        let bad = |key: &str, reason: String| {
            Err(Error::Config {
                settings: "output instants",
                file: None,
                key: Some(key.to_string()),
                reason,
            })
        };
        let mut phase_percent = None;
        let mut note = None;
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
                let breaths = find_breaths(trace).map_err(|reason| Error::Config {
                    settings: "output instants",
                    file: None,
                    key: None,
                    reason,
                })?;
                let (times, phases, how) = phases_of(trace, &breaths, count);
                phase_percent = phases;
                note = how;
                times
            }
        };
        if times.len() > MAX_FRAMES {
            return bad(
                "kind",
                format!("{} frames; at most {MAX_FRAMES} per run", times.len()),
            );
        }
        Ok(InstantPlan {
            times,
            phase_percent,
            note,
        })
    }
}

/// The breaths of a trace: each complete stretch above the curve's mid-level, with the
/// end-exhale troughs around it when the trace holds them.
struct Breaths {
    /// Sample index of each complete breath's end-inhale peak.
    peaks: Vec<usize>,
    /// The lowest sample between the trace's start or the previous breath and each peak's
    /// rise, and between each peak's fall and the next rise or the trace's end; `None`
    /// where the trace starts or ends above the mid-level.
    troughs: Vec<(Option<usize>, Option<usize>)>,
    /// The mid-level, mL.
    mid_ml: f64,
}

/// Finds the complete breaths of `trace`; refuses a trace that does not breathe (under 1 mL
/// of variation).
fn find_breaths(trace: &BreathingTrace) -> std::result::Result<Breaths, String> {
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
    let lowest = |a: usize, b: usize| (a..b).min_by(|&x, &y| v[x].total_cmp(&v[y]));
    let (mut peaks, mut troughs) = (Vec::new(), Vec::new());
    let mut below_since = (v[0] < mid).then_some(0);
    let mut start = None;
    for i in 1..v.len() {
        if v[i - 1] < mid && v[i] >= mid {
            start = Some((i, below_since.and_then(|b| lowest(b, i))));
        } else if v[i - 1] >= mid && v[i] < mid {
            below_since = Some(i);
            if let Some((s, before)) = start.take() {
                peaks.push((s..i).max_by(|&a, &b| v[a].total_cmp(&v[b])).unwrap());
                let next_rise = (i + 1..v.len())
                    .find(|&j| v[j - 1] < mid && v[j] >= mid)
                    .unwrap_or(v.len());
                troughs.push((before, lowest(i, next_rise)));
            }
        }
    }
    Ok(Breaths {
        peaks,
        troughs,
        mid_ml: mid,
    })
}

/// `count` phase times of the first complete cycle of `breaths`, with their phases and a note
/// when the trace holds one breath (its period taken from end-exhale to end-exhale) or none
/// (every sample instead).
fn phases_of(
    trace: &BreathingTrace,
    breaths: &Breaths,
    count: usize,
) -> (Vec<f64>, Option<Vec<f64>>, Option<String>) {
    let t = &trace.time_s;
    let percent = |k: usize| 100.0 * k as f64 / count as f64;
    if let [p1, p2, ..] = breaths.peaks[..] {
        let (t1, t2) = (t[p1], t[p2]);
        let times = (0..count)
            .map(|k| t1 + (t2 - t1) * k as f64 / count as f64)
            .collect();
        return (times, Some((0..count).map(percent).collect()), None);
    }
    if let (Some(&peak), Some(&(Some(a), Some(b)))) =
        (breaths.peaks.first(), breaths.troughs.first())
    {
        let (ta, tp, tb) = (t[a], t[peak], t[b]);
        let period = tb - ta;
        let mut phased: Vec<(f64, f64)> = (0..count)
            .map(|k| {
                let at = tp + period * k as f64 / count as f64;
                (if at > tb { at - period } else { at }, percent(k))
            })
            .collect();
        phased.sort_by(|x, y| x.0.total_cmp(&y.0));
        let note = format!(
            "the trace holds one breath: its {count} phases span one period from end-exhale \
             (t = {ta:.2} s) to end-exhale (t = {tb:.2} s), {period:.2} s, phase 0 % at its \
             end-inhale (t = {tp:.2} s); the phases after the second end-exhale are taken one \
             period earlier, in the inspiration, so frames in time order start at phase {:.0} %",
            phased[0].1
        );
        let (times, phases) = phased.into_iter().unzip();
        return (times, Some(phases), Some(note));
    }
    let note = format!(
        "the trace holds no complete breath (rising above its mid-level, {:.0} mL, from an \
         end-exhale and falling back below it to another): {count} phases cannot be placed, so \
         every sample gets a frame ({} frames)",
        breaths.mid_ml,
        t.len()
    );
    (t.clone(), None, Some(note))
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
    fn one_breath_from_end_exhale_to_end_exhale_is_one_period() {
        // End-exhale at 0 s and 4 s, end-inhale at 2 s.
        let trace = LujanBreathing::default().trace(4.0, 10.0).unwrap();
        let plan = OutputInstants::Phases { count: 10 }.plan(&trace).unwrap();
        let phases = plan.phase_percent.as_ref().unwrap();
        assert_eq!(plan.times.len(), 10);
        assert!(
            plan.times.windows(2).all(|w| w[0] < w[1]),
            "{:?}",
            plan.times
        );
        // Phase 0 % at end-inhale (2 s); 50 % at the second end-exhale (4 s); 60 % one period
        // earlier than 4.4 s, in the inspiration (0.4 s).
        let at = |p: f64| plan.times[phases.iter().position(|&q| q == p).unwrap()];
        assert!((at(0.0) - 2.0).abs() < 1e-9, "{plan:?}");
        assert!((at(50.0) - 4.0).abs() < 1e-9, "{plan:?}");
        assert!((at(60.0) - 0.4).abs() < 1e-9, "{plan:?}");
        assert_eq!(phases[0], 60.0);
        assert!((trace.volume_at(at(0.0)) - 500.0).abs() < 1e-6);
        let note = plan.note.unwrap();
        assert!(
            note.contains("one breath") && note.contains("start at phase 60 %"),
            "{note}"
        );
    }

    #[test]
    fn a_ramp_gets_every_sample_and_says_so() {
        let ramp =
            BreathingTrace::new(vec![0.0, 1.0, 2.0, 3.0], vec![0.0, 100.0, 200.0, 300.0]).unwrap();
        let plan = OutputInstants::Phases { count: 10 }.plan(&ramp).unwrap();
        assert_eq!(plan.times, ramp.time_s);
        assert_eq!(plan.phase_percent, None);
        let note = plan.note.unwrap();
        assert!(
            note.contains("no complete breath") && note.contains("every sample"),
            "{note}"
        );
        // Literal requests carry no note.
        let full = LujanBreathing::default().trace(12.0, 10.0).unwrap();
        assert_eq!(
            OutputInstants::Phases { count: 10 }
                .plan(&full)
                .unwrap()
                .note,
            None
        );
        assert_eq!(OutputInstants::EverySample.plan(&ramp).unwrap().note, None);
    }

    #[test]
    fn impossible_requests_are_explained() {
        let trace = LujanBreathing::default().trace(3.0, 10.0).unwrap();
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
