//! Benchmarks behind `lungmotion bench`, one suite per module: [`core`] (the mechanics:
//! force kernel, memory, quasi-static block, CalculiX side by side), [`ingest`] (lung
//! segmentation), [`motion`] (the tidal cycle), [`recording`] (the whole spirometer recording on the POPI CT), [`scale`] (run time against error over element sizes) and [`service`] (the HTTP service).
//!
//! This module holds what every suite shares: [`Outcome`] for a measurement that may be
//! missing, [`TimeStats`] for repeated timings, and the description of the machine.
//!
//! Every timing is the median of repeated runs with min and max beside it, because the machine
//! is shared and noisy. Nothing here asserts a speed: the reports state the targets and whether
//! they were met.

pub mod core;
pub mod ingest;
pub mod motion;
pub mod recording;
pub mod scale;
pub mod service;

use std::time::{SystemTime, UNIX_EPOCH};

use serde::Serialize;

use crate::Result;

pub use self::core::{
    run_bench, BenchOptions, BenchReport, CalculixComparison, ForceThroughput, MemoryUsage,
    ParallelSpeedup, QuasiStaticBench, ScalingFit, SolverComparison, TargetCheck,
    BENCH_DAMPING_RATIO, BENCH_ELEMENT_EDGE_M, BENCH_PERTURBATION,
};

/// A measured value, or why it is missing.
#[derive(Debug, Clone, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Outcome<T> {
    /// Measured.
    Measured(T),
    /// The measurement ran and failed (the error message).
    Failed(String),
    /// Not run (the reason).
    Skipped(String),
}

impl<T> Outcome<T> {
    fn from_result(r: Result<T>) -> Self {
        match r {
            Ok(v) => Outcome::Measured(v),
            Err(e) => Outcome::Failed(e.to_string()),
        }
    }

    /// The measured value, if any.
    pub fn measured(&self) -> Option<&T> {
        match self {
            Outcome::Measured(v) => Some(v),
            _ => None,
        }
    }
}

/// Median, extremes and count of repeated timings, seconds.
#[derive(Debug, Clone, Copy, Serialize)]
pub struct TimeStats {
    /// Median in seconds.
    pub median_s: f64,
    /// Fastest run in seconds.
    pub min_s: f64,
    /// Slowest run in seconds.
    pub max_s: f64,
    /// Number of runs.
    pub runs: usize,
}

impl TimeStats {
    /// Statistics of `samples` (at least one).
    pub fn new(samples: &[f64]) -> Self {
        let mut s = samples.to_vec();
        let median = crate::math::median_sorting(&mut s).expect("at least one sample");
        let n = s.len();
        TimeStats {
            median_s: median,
            min_s: s[0],
            max_s: s[n - 1],
            runs: n,
        }
    }
}

/// Where and when the benchmark ran.
#[derive(Debug, Clone, Serialize)]
pub struct MachineInfo {
    /// Logical cores available to the process.
    pub cores: usize,
    /// CPU model from /proc/cpuinfo.
    pub cpu_model: String,
    /// Widest vector instructions the force kernel uses.
    pub simd: String,
    /// UTC date and time of the run (ISO 8601).
    pub date_utc: String,
    /// Threads of the parallel measurements.
    pub threads: usize,
    /// Crate version.
    pub lungmotion_version: String,
}

pub(crate) fn cpu_model() -> String {
    std::fs::read_to_string("/proc/cpuinfo")
        .ok()
        .and_then(|s| {
            s.lines()
                .find(|l| l.starts_with("model name"))
                .and_then(|l| l.split(':').nth(1))
                .map(|m| m.trim().to_string())
        })
        .unwrap_or_else(|| "unknown".into())
}

fn simd_level() -> &'static str {
    #[cfg(target_arch = "x86_64")]
    {
        if std::arch::is_x86_feature_detected!("avx2") {
            return "avx2 (4 × f64)";
        }
        "sse2 (2 × f64)"
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        "portable"
    }
}

/// Current UTC time as ISO 8601, from the system clock (no date crate needed).
fn utc_now() -> String {
    let secs = SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| d.as_secs()) as i64;
    let (days, rem) = (secs.div_euclid(86_400), secs.rem_euclid(86_400));
    // Howard Hinnant's civil-from-days.
    let z = days + 719_468;
    let era = z.div_euclid(146_097);
    let doe = z - era * 146_097;
    let yoe = (doe - doe / 1460 + doe / 36_524 - doe / 146_096) / 365;
    let doy = doe - (365 * yoe + yoe / 4 - yoe / 100);
    let mp = (5 * doy + 2) / 153;
    let day = doy - (153 * mp + 2) / 5 + 1;
    let month = if mp < 10 { mp + 3 } else { mp - 9 };
    let year = yoe + era * 400 + (month <= 2) as i64;
    format!(
        "{year:04}-{month:02}-{day:02}T{:02}:{:02}:{:02}Z",
        rem / 3600,
        rem % 3600 / 60,
        rem % 60
    )
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn median_of_even_and_odd_counts() {
        let s = TimeStats::new(&[3.0, 1.0, 2.0]);
        assert_eq!((s.median_s, s.min_s, s.max_s, s.runs), (2.0, 1.0, 3.0, 3));
        assert_eq!(TimeStats::new(&[4.0, 1.0, 2.0, 3.0]).median_s, 2.5);
    }

    #[test]
    fn date_is_iso_8601() {
        let d = utc_now();
        assert_eq!(d.len(), 20, "{d}");
        assert!(d.starts_with("20") && d.ends_with('Z'), "{d}");
    }
}
