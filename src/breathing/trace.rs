//! A breathing trace: lung volume over time, as a spirometer records it.
//!
//! Convention: the trace holds, at strictly increasing times in seconds, the lung volume
//! **change from the scanned state** in millilitres (positive = more air than in the CT).
//! The scanned state is the mechanical reference (zero transpulmonary pressure change).
//!
//! File formats:
//! * CSV (default, what scripts rely on): a header line `time_s,volume_ml`, then one row per
//!   sample. Other units through the header (`time_ms`, `volume_l`) or [`TraceOptions`];
//!   absolute volumes through [`VolumeReference::Absolute`] with the scanned lung volume.
//!   Blank lines and lines starting with `#` are ignored; a UTF-8 BOM and CRLF are accepted.
//! * JSON: `{"time_s": [...], "volume_ml": [...]}` (same meaning and options).

use std::path::Path;

use serde::{Deserialize, Serialize};

use super::airflow::integrate_flow;
use super::columns::{parse_csv, parse_json, Quantity, Signal};
use crate::{Error, IoContext, IoOp, Result};

/// Largest volume increase over the scanned state accepted, mL (total lung capacity is ≈ 6 L).
pub const MAX_VOLUME_GAIN_ML: f64 = 5000.0;
/// Largest volume decrease below the scanned state accepted, mL (residual volume is ≈ 1.2 L).
pub const MAX_VOLUME_LOSS_ML: f64 = 3000.0;
/// Largest flow accepted, mL/s (peak expiratory flow of a healthy adult is ≈ 10 L/s).
pub const MAX_FLOW_ML_PER_S: f64 = 15_000.0;
/// Most samples a trace may hold (a day at 100 Hz is 8.6 million).
pub const MAX_SAMPLES: usize = 10_000_000;
/// Least peak-to-peak volume a trace read from a file or request may have, mL: a shallow
/// breath moves a few hundred; under this the column is most likely litres read as mL.
pub const MIN_PEAK_TO_PEAK_ML: f64 = 20.0;

/// Lung volume change from the scanned state over time.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct BreathingTrace {
    /// Sample times in seconds, strictly increasing.
    pub time_s: Vec<f64>,
    /// Volume change from the scanned state at each time, mL.
    pub volume_change_ml: Vec<f64>,
}

/// How the volume column relates to the scanned lung.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum VolumeReference {
    /// The column is already the change from the scanned state.
    #[default]
    ChangeFromScan,
    /// The column is the absolute lung volume; the scanned lung holds `scanned_volume_ml`.
    Absolute {
        /// Lung volume at the instant of the CT, mL.
        scanned_volume_ml: f64,
    },
}

/// File format of a trace.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum TraceFormat {
    /// From the file's first non-blank character: `{` is JSON, anything else CSV.
    #[default]
    Detect,
    /// Comma-separated, header `time_s,volume_ml`.
    Csv,
    /// `{"time_s": [...], "volume_ml": [...]}`.
    Json,
}

/// How to read a trace file.
#[derive(Debug, Clone, Copy, PartialEq, Default, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct TraceOptions {
    /// File format.
    pub format: TraceFormat,
    /// Change from the scan (default) or absolute volumes.
    pub reference: VolumeReference,
    /// Multiplies the time column to get seconds; `None` reads the unit from the header.
    pub seconds_per_time_unit: Option<f64>,
    /// Multiplies the volume column to get mL; `None` reads the unit from the header.
    pub ml_per_volume_unit: Option<f64>,
    /// Keeps only the samples from the first time to the second, s (e.g. the tidal breaths
    /// of a recording that also holds vital-capacity manoeuvres); a flow is integrated and
    /// its drift removed over the whole recording first. `None`: the whole trace.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub window_s: Option<[f64; 2]>,
}

/// A trace read from a file, with what was done to it on the way (an integrated airflow, a
/// column left unused), for the console and `summary.json`.
#[derive(Debug, Clone, PartialEq)]
pub struct TraceReading {
    /// The volume change over time.
    pub trace: BreathingTrace,
    /// One sentence per thing done beyond reading a volume column.
    pub notes: Vec<String>,
}

impl BreathingTrace {
    /// Builds a trace from samples, checking everything [`BreathingTrace::validate`] checks.
    pub fn new(time_s: Vec<f64>, volume_change_ml: Vec<f64>) -> Result<Self> {
        let trace = BreathingTrace {
            time_s,
            volume_change_ml,
        };
        trace.validate()?;
        Ok(trace)
    }

    /// Reads a CSV or JSON trace file; errors name the file, the row and the problem.
    ///
    /// # Examples
    ///
    /// ```
    /// use lungmotion::breathing::{BreathingTrace, TraceOptions};
    ///
    /// let path = std::env::temp_dir().join(format!("lm-doc-trace-{}.csv", std::process::id()));
    /// std::fs::write(&path, "time_s,volume_ml\n0,0\n2,500\n4,0\n")?;
    /// let trace = BreathingTrace::read(&path, &TraceOptions::default())?;
    /// assert_eq!(trace.volume_at(1.0), 250.0); // linear between samples
    /// std::fs::remove_file(&path)?;
    /// # Ok::<(), Box<dyn std::error::Error>>(())
    /// ```
    pub fn read(path: &Path, options: &TraceOptions) -> Result<Self> {
        Self::read_with_notes(path, options).map(|r| r.trace)
    }

    /// [`BreathingTrace::read`], also saying what was done to the file's columns (an airflow
    /// integrated and its drift removed, a flow column not used).
    pub fn read_with_notes(path: &Path, options: &TraceOptions) -> Result<TraceReading> {
        let text = std::fs::read_to_string(path).at(IoOp::Read, path)?;
        Self::parse_located(&text, options).map_err(|fault| fault.into_error(Some(path)))
    }

    /// Parses trace text; the error message says which row and what is wrong.
    pub fn parse(text: &str, options: &TraceOptions) -> std::result::Result<Self, String> {
        Self::parse_with_notes(text, options).map(|r| r.trace)
    }

    /// [`BreathingTrace::parse`], also saying what was done to the columns.
    pub fn parse_with_notes(
        text: &str,
        options: &TraceOptions,
    ) -> std::result::Result<TraceReading, String> {
        Self::parse_located(text, options).map_err(|fault| fault.reason)
    }

    /// [`BreathingTrace::parse`] keeping the sample at fault apart from the message.
    fn parse_located(
        text: &str,
        options: &TraceOptions,
    ) -> std::result::Result<TraceReading, Fault> {
        let text = text.trim_start_matches('\u{feff}');
        let format = match options.format {
            TraceFormat::Detect if text.trim_start().starts_with(['{', '[']) => TraceFormat::Json,
            TraceFormat::Detect => TraceFormat::Csv,
            f => f,
        };
        let columns = match format {
            TraceFormat::Json => parse_json(text)?,
            _ => parse_csv(text)?,
        };
        let seconds = options
            .seconds_per_time_unit
            .unwrap_or(columns.seconds_per_unit);
        let time_s: Vec<f64> = columns.times.iter().map(|t| t * seconds).collect();
        let mut notes = Vec::new();
        let trace = match columns.signal.quantity {
            Quantity::Volume => {
                if let Some(flow) = &columns.unused_flow {
                    notes.push(format!(
                        "the flow column '{flow}' was not used: the volume column '{}' was read",
                        columns.signal.name
                    ));
                }
                volume_trace(time_s, &columns.signal, options)?
            }
            Quantity::Flow => {
                let (trace, note) = flow_trace(time_s, &columns.signal, options)?;
                notes.push(note);
                trace
            }
        };
        let trace = match options.window_s {
            Some(window) => {
                let (kept, note) = trace.window(window).map_err(Fault::whole)?;
                notes.push(note);
                kept
            }
            None => trace,
        };
        Ok(TraceReading { trace, notes })
    }

    /// The samples from `window[0]` to `window[1]` s, with a sentence saying what was kept.
    fn window(self, window: [f64; 2]) -> std::result::Result<(Self, String), String> {
        let [from, to] = window;
        let (first, last) = (self.time_s[0], self.time_s[self.time_s.len() - 1]);
        if !(from.is_finite() && to.is_finite() && from < to) {
            return Err(format!(
                "trace window [{from}, {to}] s: the start must be a number before the end"
            ));
        }
        let keep: Vec<usize> = (0..self.time_s.len())
            .filter(|&i| (from..=to).contains(&self.time_s[i]))
            .collect();
        if keep.len() < 2 {
            return Err(format!(
                "trace window [{from}, {to}] s holds {} sample(s); the trace runs from {first} s \
                 to {last} s",
                keep.len()
            ));
        }
        let note = format!(
            "kept the samples from {from} s to {to} s ({} of {}; window_s)",
            keep.len(),
            self.time_s.len()
        );
        let kept = BreathingTrace {
            time_s: keep.iter().map(|&i| self.time_s[i]).collect(),
            volume_change_ml: keep.iter().map(|&i| self.volume_change_ml[i]).collect(),
        };
        Ok((kept, note))
    }

    /// Checks finiteness, strictly increasing times, plausible volumes and flows.
    pub fn validate(&self) -> Result<()> {
        self.check().map_err(|fault| fault.into_error(None))
    }

    fn check(&self) -> std::result::Result<(), Fault> {
        let n = self.time_s.len();
        if n != self.volume_change_ml.len() {
            return Err(Fault::whole(format!(
                "{n} times but {} volumes",
                self.volume_change_ml.len()
            )));
        }
        if n < 2 {
            return Err(Fault::whole(format!(
                "{n} samples; a breathing curve needs at least 2"
            )));
        }
        if n > MAX_SAMPLES {
            return Err(Fault::whole(format!(
                "{n} samples; at most {MAX_SAMPLES} are accepted"
            )));
        }
        for (i, (&t, &v)) in self.time_s.iter().zip(&self.volume_change_ml).enumerate() {
            let at = |reason: String| Fault {
                row: Some(i + 1),
                reason,
            };
            if !t.is_finite() {
                return Err(at(format!("sample {}: time is {t}", i + 1)));
            }
            if !v.is_finite() {
                return Err(at(format!("sample {} (t = {t} s): volume is {v}", i + 1)));
            }
            if !(-MAX_VOLUME_LOSS_ML..=MAX_VOLUME_GAIN_ML).contains(&v) {
                return Err(at(format!(
                    "sample {} (t = {t} s): volume change {v:.1} mL is implausible: lungs hold \
                     between {MAX_VOLUME_LOSS_ML} mL less and {MAX_VOLUME_GAIN_ML} mL more than \
                     at the scan",
                    i + 1
                )));
            }
            if i > 0 {
                let (t0, v0) = (self.time_s[i - 1], self.volume_change_ml[i - 1]);
                if t <= t0 {
                    return Err(at(format!(
                        "sample {}: time {t} s is not after the previous sample's {t0} s \
                         (times must strictly increase: sort the rows, remove duplicates)",
                        i + 1
                    )));
                }
                let flow = (v - v0) / (t - t0);
                if flow.abs() > MAX_FLOW_ML_PER_S {
                    return Err(at(format!(
                        "samples {} to {} (t = {t0} … {t} s): flow {:.0} mL/s is implausible \
                         (more than {MAX_FLOW_ML_PER_S} mL/s; wrong units?)",
                        i,
                        i + 1,
                        flow
                    )));
                }
            }
        }
        Ok(())
    }

    /// Duration from the first to the last sample, s.
    pub fn duration_s(&self) -> f64 {
        self.time_s[self.time_s.len() - 1] - self.time_s[0]
    }

    /// Volume change at time `t_s` by linear interpolation, clamped to the end samples.
    pub fn volume_at(&self, t_s: f64) -> f64 {
        let t = &self.time_s;
        let v = &self.volume_change_ml;
        if t_s <= t[0] {
            return v[0];
        }
        if t_s >= t[t.len() - 1] {
            return v[v.len() - 1];
        }
        let i = t.partition_point(|&x| x <= t_s) - 1;
        let w = (t_s - t[i]) / (t[i + 1] - t[i]);
        v[i] + w * (v[i + 1] - v[i])
    }

    /// Writes the trace as the default CSV (`time_s,volume_ml`, change from the scan).
    pub fn to_csv(&self) -> String {
        let mut s = String::from("time_s,volume_ml\n");
        for (t, v) in self.time_s.iter().zip(&self.volume_change_ml) {
            s.push_str(&format!("{t},{v}\n"));
        }
        s
    }
}

/// The trace of a volume column: in the unit named, referred to the scanned state.
fn volume_trace(
    time_s: Vec<f64>,
    column: &Signal,
    options: &TraceOptions,
) -> std::result::Result<BreathingTrace, Fault> {
    // A volume column without a unit is read only with the unit given by name: litres
    // read as millilitres make a run that "succeeds" with no motion at all.
    let ml = options.ml_per_volume_unit.or(column.unit).ok_or_else(|| {
        Fault::whole(format!(
            "the volume column '{}' has no unit: name it volume_ml (millilitres) or volume_l \
             (litres), or give ml_per_volume_unit",
            column.name
        ))
    })?;
    let offset = match options.reference {
        VolumeReference::ChangeFromScan => 0.0,
        VolumeReference::Absolute { scanned_volume_ml } => {
            if !(scanned_volume_ml.is_finite() && scanned_volume_ml > 0.0) {
                return Err(Fault::whole(format!(
                    "the scanned lung volume must be a positive number of mL, got {scanned_volume_ml}"
                )));
            }
            scanned_volume_ml
        }
    };
    let trace = BreathingTrace {
        time_s,
        volume_change_ml: column.values.iter().map(|v| v * ml - offset).collect(),
    };
    trace.check().map_err(|mut fault| {
        if options.reference == VolumeReference::ChangeFromScan
            && trace.volume_change_ml.iter().all(|&v| v > 1000.0)
        {
            fault.reason.push_str(
                " (every volume is above 1000 mL: if these are absolute lung volumes, \
                 give the scanned lung volume so they can be turned into changes)",
            );
        }
        fault
    })?;
    check_breathes(
        &trace,
        "if the column holds litres, name it volume_l or give ml_per_volume_unit = 1000",
    )?;
    Ok(trace)
}

/// The trace of a flow column: checked sample by sample, integrated, its drift removed, and
/// held to the same bounds as a volume column; with the note saying what was done.
fn flow_trace(
    time_s: Vec<f64>,
    column: &Signal,
    options: &TraceOptions,
) -> std::result::Result<(BreathingTrace, String), Fault> {
    let name = &column.name;
    let ml_per_s = column.unit.ok_or_else(|| {
        Fault::whole(format!(
            "the flow column '{name}' has no unit: name it flow_l_per_s (litres per second) or \
             flow_ml_per_s (millilitres per second)"
        ))
    })?;
    if let VolumeReference::Absolute { .. } = options.reference {
        return Err(Fault::whole(format!(
            "the flow column '{name}' gives volume changes only: an absolute volume reference \
             (scanned_volume_ml) does not apply to it"
        )));
    }
    // The times first (finite, increasing), so a fault there is not reported as a volume.
    BreathingTrace {
        volume_change_ml: vec![0.0; time_s.len()],
        time_s: time_s.clone(),
    }
    .check()?;
    if time_s.len() != column.values.len() {
        return Err(Fault::whole(format!(
            "{} times but {} flows",
            time_s.len(),
            column.values.len()
        )));
    }
    let mut flow = Vec::with_capacity(column.values.len());
    for (i, (&f, &t)) in column.values.iter().zip(&time_s).enumerate() {
        let f = f * ml_per_s;
        if !f.is_finite() {
            return Err(Fault::at(
                i + 1,
                format!("sample {} (t = {t} s): flow is {f}", i + 1),
            ));
        }
        if f.abs() > MAX_FLOW_ML_PER_S {
            return Err(Fault::at(
                i + 1,
                format!(
                    "sample {} (t = {t} s): flow {f:.0} mL/s in column '{name}' is implausible \
                     (more than {MAX_FLOW_ML_PER_S} mL/s): if the column holds mL/s, name it \
                     flow_ml_per_s",
                    i + 1
                ),
            ));
        }
        flow.push(f);
    }
    let integrated = integrate_flow(&time_s, &flow);
    let note = integrated.note(name);
    let trace = BreathingTrace {
        time_s,
        volume_change_ml: integrated.volume_ml,
    };
    let integrated_from = |mut fault: Fault| {
        fault.reason = format!(
            "the volume integrated from flow column '{name}': {}",
            fault.reason
        );
        fault
    };
    trace.check().map_err(integrated_from)?;
    check_breathes(
        &trace,
        "if the column holds litres per second, name it flow_l_per_s",
    )
    .map_err(integrated_from)?;
    Ok((trace, note))
}

/// Refuses a trace moving by less than a breath; `hint` says which unit error is likely.
fn check_breathes(trace: &BreathingTrace, hint: &str) -> std::result::Result<(), Fault> {
    let (lowest, highest) = trace
        .volume_change_ml
        .iter()
        .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), &v| {
            (lo.min(v), hi.max(v))
        });
    if highest - lowest < MIN_PEAK_TO_PEAK_ML {
        return Err(Fault::whole(format!(
            "the volume varies by only {:.3} mL from its lowest to its highest sample, far \
             less than a breath (at least {MIN_PEAK_TO_PEAK_ML} mL): {hint}",
            highest - lowest
        )));
    }
    Ok(())
}

/// Longest piece of the file quoted in a message, characters.
const MAX_QUOTED_CHARS: usize = 120;

/// `text`, cut to [`MAX_QUOTED_CHARS`] with an ellipsis: a message quotes the fault, it does
/// not echo a 20 MB line (found by the hostile-input corpus).
pub(super) fn clip(text: &str) -> std::borrow::Cow<'_, str> {
    match text.char_indices().nth(MAX_QUOTED_CHARS) {
        Some((cut, _)) => format!("{}… ({} bytes)", &text[..cut], text.len()).into(),
        None => text.into(),
    }
}

/// What is wrong with a trace, and at which sample where one is to blame.
#[derive(Debug)]
pub(super) struct Fault {
    /// 1-based sample (data row).
    row: Option<usize>,
    reason: String,
}

impl Fault {
    /// A problem of the trace as a whole (or of its header).
    pub(super) fn whole(reason: String) -> Self {
        Fault { row: None, reason }
    }

    /// A problem at 1-based sample `row`.
    pub(super) fn at(row: usize, reason: String) -> Self {
        Fault {
            row: Some(row),
            reason,
        }
    }

    fn into_error(self, path: Option<&Path>) -> Error {
        Error::Trace {
            path: path.map(Path::to_path_buf),
            row: self.row,
            reason: self.reason,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(text: &str) -> std::result::Result<BreathingTrace, String> {
        BreathingTrace::parse(text, &TraceOptions::default())
    }

    #[test]
    fn default_csv_reads_and_round_trips() {
        let t = parse(
            "\u{feff}# spirometer\r\ntime_s,volume_ml\r\n0,0\r\n0.5,120.5\r\n\r\n1.0,250\r\n",
        )
        .unwrap();
        assert_eq!(t.time_s, vec![0.0, 0.5, 1.0]);
        assert_eq!(t.volume_change_ml, vec![0.0, 120.5, 250.0]);
        assert_eq!(parse(&t.to_csv()).unwrap(), t);
        assert!((t.volume_at(0.25) - 60.25).abs() < 1e-12);
        assert_eq!(t.volume_at(-1.0), 0.0);
        assert_eq!(t.volume_at(9.0), 250.0);
    }

    #[test]
    fn a_window_keeps_the_tidal_breaths_and_refuses_an_empty_or_inverted_one() {
        let text = "time_s,volume_ml\n0,0\n1,500\n2,0\n3,2500\n4,0\n";
        let opts = |w| TraceOptions {
            window_s: Some(w),
            ..TraceOptions::default()
        };
        let r = BreathingTrace::parse_with_notes(text, &opts([0.0, 2.0])).unwrap();
        assert_eq!(r.trace.time_s, vec![0.0, 1.0, 2.0]);
        assert_eq!(r.trace.volume_change_ml, vec![0.0, 500.0, 0.0]);
        assert!(r.notes[0].contains("3 of 5"), "{:?}", r.notes);
        let e = BreathingTrace::parse(text, &opts([2.5, 2.9])).unwrap_err();
        assert!(
            e.contains("holds 0 sample") && e.contains("from 0 s to 4 s"),
            "{e}"
        );
        let e = BreathingTrace::parse(text, &opts([3.0, 1.0])).unwrap_err();
        assert!(e.contains("start must be a number before the end"), "{e}");
    }

    #[test]
    fn units_come_from_the_header_or_the_options() {
        let t = parse("time_ms,volume_l\n0,0\n500,0.25\n").unwrap();
        assert_eq!(t.time_s, vec![0.0, 0.5]);
        assert!((t.volume_change_ml[1] - 250.0).abs() < 1e-9);
        let opts = TraceOptions {
            reference: VolumeReference::Absolute {
                scanned_volume_ml: 3000.0,
            },
            ..TraceOptions::default()
        };
        let t = BreathingTrace::parse("time_s,volume_ml\n0,3000\n1,3400\n", &opts).unwrap();
        assert_eq!(t.volume_change_ml, vec![0.0, 400.0]);
    }

    #[test]
    fn a_volume_column_without_its_unit_is_refused_unless_the_unit_is_given() {
        // The issue's case: litres under a bare `volume` header were read as mL.
        let litres = "time,volume\n0,0\n2,0.5\n4,0\n";
        let e = parse(litres).unwrap_err();
        assert!(
            e.contains("'volume' has no unit") && e.contains("volume_l"),
            "{e}"
        );
        let opts = TraceOptions {
            ml_per_volume_unit: Some(1000.0),
            ..TraceOptions::default()
        };
        let t = BreathingTrace::parse(litres, &opts).unwrap();
        assert_eq!(t.volume_change_ml, vec![0.0, 500.0, 0.0]);
    }

    #[test]
    fn a_trace_moving_less_than_a_breath_is_refused_as_a_likely_unit_error() {
        let e = parse("time_s,volume_ml\n0,0\n2,0.5\n4,0\n").unwrap_err();
        assert!(
            e.contains("varies by only 0.500 mL") && e.contains("volume_l"),
            "{e}"
        );
        assert!(parse("time_s,volume_l\n0,0\n2,0.5\n4,0\n").is_ok());
    }

    #[test]
    fn json_reads_like_csv() {
        let t = parse(r#"{"time_s": [0, 1, 2], "volume_ml": [0, 300, 0]}"#).unwrap();
        assert_eq!(t.volume_change_ml, vec![0.0, 300.0, 0.0]);
        let e = parse(r#"{"time_s": [0, 1], "volume_ml": [0, null]}"#).unwrap_err();
        assert!(e.contains("volume_ml[1] is null"), "{e}");
        let e = parse(r#"{"time_s": [0, 1]}"#).unwrap_err();
        assert!(e.contains("volume_ml"), "{e}");
    }

    #[test]
    fn bad_traces_say_exactly_what_is_wrong() {
        let cases = [
            ("", "empty"),
            ("t,v\n0,0\n", "header"),
            ("time_s,volume_ml\n0,0\n", "at least 2"),
            ("time_s,volume_ml\n0,0\n1,abc\n", "line 3: 'abc'"),
            (
                "time_s,volume_ml\n0,0\n1,NaN\n",
                "sample 2 (t = 1 s): volume is NaN",
            ),
            ("time_s,volume_ml\n0,0\ninf,1\n", "time is inf"),
            (
                "time_s,volume_ml\n0,0\n1,5\n1,6\n",
                "sample 3: time 1 s is not after",
            ),
            ("time_s,volume_ml\n0,0\n2,5\n1,6\n", "strictly increase"),
            ("time_s,volume_ml\n0,0\n1,9000\n", "implausible"),
            ("time_s,volume_ml\n0,0\n0.01,400\n", "flow"),
            ("time_s,volume_ml\n0,0,1\n", "3 columns"),
            (
                "time_s,volume_ml\n0,5500\n1,6000\n",
                "absolute lung volumes",
            ),
        ];
        for (text, want) in cases {
            let e = parse(text).unwrap_err();
            assert!(e.contains(want), "{text:?}: {e}");
        }
        let e = BreathingTrace::new(vec![0.0, 1.0], vec![0.0]).unwrap_err();
        assert!(e.to_string().contains("2 times but 1 volumes"), "{e}");
    }

    #[test]
    fn long_lines_are_quoted_cut_short_not_echoed() {
        let header = "x".repeat(1 << 20);
        let e = parse(&header).unwrap_err();
        assert!(
            e.contains("header 'xxx") && e.contains("(1048576 bytes)"),
            "{e}"
        );
        assert!(e.len() < 400, "{} bytes", e.len());
        let e = parse(&format!(
            "time_s,volume_ml\n0,0\n1,{}x\n",
            "9".repeat(1 << 20)
        ))
        .unwrap_err();
        assert!(e.contains("line 3: '999") && e.len() < 400, "{e}");
        let e = parse(&format!("{{\"time_s\": \"{}\"}}", "y".repeat(1 << 20))).unwrap_err();
        assert!(e.contains("expected {\"time_s\"") && e.len() < 400, "{e}");
        // A JSON array is read as JSON, so the reason is about JSON, not a CSV header.
        let e = parse("[[0, 0], [1, 250]]").unwrap_err();
        assert!(e.contains("found a JSON array"), "{e}");
    }

    #[test]
    fn a_trace_file_error_names_the_file_and_the_sample_in_fields() {
        let path = std::env::temp_dir().join(format!("lm-trace-row-{}.csv", std::process::id()));
        std::fs::write(&path, "time_s,volume_ml\n0,0\n1,5\n1,6\n").unwrap();
        let e = BreathingTrace::read(&path, &TraceOptions::default()).unwrap_err();
        assert!(
            matches!(&e, Error::Trace { path: Some(p), row: Some(3), .. } if *p == path),
            "{e:?}"
        );
        assert!(
            e.to_string().contains("sample 3: time 1 s is not after"),
            "{e}"
        );
        std::fs::remove_file(&path).unwrap();
        let e = BreathingTrace::read(&path, &TraceOptions::default()).unwrap_err();
        assert!(matches!(e, Error::Io { op: IoOp::Read, .. }), "{e:?}");
    }

    /// `breaths` breaths of 500 mL over 4 s at 25 Hz as a CSV of airflow in L/s, the sensor
    /// reading `offset_l_per_s` too much; the last column repeats the true volume, in mL.
    fn flow_csv(breaths: usize, offset_l_per_s: f64) -> (String, Vec<f64>) {
        let w = std::f64::consts::PI / 4.0;
        let mut csv = String::from("time_s,flow_l_per_s\n");
        let mut volume = Vec::new();
        for i in 0..=breaths * 100 {
            let t = i as f64 / 25.0;
            let flow_l_per_s = 0.5 * w * (2.0 * w * t).sin() + offset_l_per_s;
            csv.push_str(&format!("{t},{flow_l_per_s}\n"));
            volume.push(500.0 * (w * t).sin().powi(2));
        }
        (csv, volume)
    }

    #[test]
    fn an_airflow_column_is_integrated_with_its_drift_removed_and_said_so() {
        let (csv, volume) = flow_csv(10, 0.03);
        let r = BreathingTrace::parse_with_notes(&csv, &TraceOptions::default()).unwrap();
        // Stated accuracy: within 1 % of the tidal volume (5 mL) at every sample, where the
        // uncorrected integral is 1.2 L off at the end.
        let error = r
            .trace
            .volume_change_ml
            .iter()
            .zip(&volume)
            .map(|(a, b)| (a - b).abs())
            .fold(0.0, f64::max);
        assert!(error < 5.0, "largest error {error} mL");
        assert_eq!(r.notes.len(), 1, "{:?}", r.notes);
        let note = &r.notes[0];
        assert!(
            note.contains("'flow_l_per_s' integrated") && note.contains("+30.00 mL/s removed"),
            "{note}"
        );
        // The same in JSON, in mL/s under the short name.
        let (times, flows): (Vec<f64>, Vec<f64>) = csv
            .lines()
            .skip(1)
            .map(|l| {
                let (t, f) = l.split_once(',').unwrap();
                (t.parse::<f64>().unwrap(), f.parse::<f64>().unwrap() * 1e3)
            })
            .unzip();
        let json = serde_json::json!({"time_s": times, "flow_ml_s": flows}).to_string();
        let j = BreathingTrace::parse_with_notes(&json, &TraceOptions::default()).unwrap();
        for (a, b) in j
            .trace
            .volume_change_ml
            .iter()
            .zip(&r.trace.volume_change_ml)
        {
            assert!((a - b).abs() < 1e-6);
        }
    }

    #[test]
    fn with_both_volume_and_flow_the_volume_is_read_and_the_flow_named_as_unused() {
        let text = "time_s,volume_ml,flow_l_per_s\n0,0,0.3\n1,250,0\n2,0,-0.3\n";
        let r = BreathingTrace::parse_with_notes(text, &TraceOptions::default()).unwrap();
        assert_eq!(r.trace.volume_change_ml, vec![0.0, 250.0, 0.0]);
        assert_eq!(
            r.notes,
            vec![
                "the flow column 'flow_l_per_s' was not used: the volume column 'volume_ml' \
                  was read"
                    .to_string()
            ]
        );
        let json = r#"{"time_s": [0, 1, 2], "flow_ml_per_s": [1, 2, 3], "volume_l": [0, 0.25, 0]}"#;
        let r = BreathingTrace::parse_with_notes(json, &TraceOptions::default()).unwrap();
        assert_eq!(r.trace.volume_change_ml, vec![0.0, 250.0, 0.0]);
        assert!(
            r.notes[0].contains("'flow_ml_per_s' was not used"),
            "{:?}",
            r.notes
        );
    }

    #[test]
    fn an_implausible_airflow_is_refused_with_the_likely_unit_error() {
        // mL/s labelled L/s: refused at the first implausible sample.
        let e = parse("time_s,flow_l_per_s\n0,0\n1,300\n2,0\n").unwrap_err();
        assert!(
            e.contains("sample 2 (t = 1 s): flow 300000 mL/s") && e.contains("flow_ml_per_s"),
            "{e}"
        );
        // L/s labelled mL/s: a tidal volume of under a millilitre.
        let (csv, _) = flow_csv(3, 0.0);
        let e = parse(&csv.replace("flow_l_per_s", "flow_ml_per_s")).unwrap_err();
        assert!(
            e.contains("integrated from flow column 'flow_ml_per_s'")
                && e.contains("varies by only")
                && e.contains("name it flow_l_per_s"),
            "{e}"
        );
        // Plausible flows that integrate to an implausible volume: 12 s of steady 0.5 L/s.
        let steady: String = (0..=12).map(|t| format!("{t},0.5\n")).collect();
        let e = parse(&format!("time_s,flow_l_per_s\n{steady}")).unwrap_err();
        assert!(
            e.contains("integrated from flow column") && e.contains("5500.0 mL is implausible"),
            "{e}"
        );
        let cases = [
            ("time_s,flow\n0,0\n1,1\n", "'flow' has no unit"),
            ("time_s,flow_l_per_s\n0,0\n1,NaN\n", "flow is NaN"),
            (
                "time_s,flow_l_per_s\n0,0\n2,0.1\n1,0\n",
                "strictly increase",
            ),
            (
                r#"{"time_s": [0, 1], "flow_l_s": [0, null]}"#,
                "flow_l_s[1] is null",
            ),
            (
                r#"{"time_s": [0, 1], "flow_l_s": [0, 1], "flow_ml_s": [0, 1]}"#,
                "two flow",
            ),
        ];
        for (text, want) in cases {
            let e = parse(text).unwrap_err();
            assert!(e.contains(want), "{text:?}: {e}");
        }
        let absolute = TraceOptions {
            reference: VolumeReference::Absolute {
                scanned_volume_ml: 3000.0,
            },
            ..TraceOptions::default()
        };
        let e = BreathingTrace::parse(&csv, &absolute).unwrap_err();
        assert!(e.contains("absolute volume reference"), "{e}");
    }
}
