//! The columns of a trace file (CSV or JSON), found by name with their units: the time, and
//! the lung volume or the airflow.

use super::trace::{clip, Fault, MAX_SAMPLES};

/// What a trace's second column measures.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Quantity {
    /// Lung volume (change or absolute), in mL times the unit.
    Volume,
    /// Airflow into the lungs, in mL/s times the unit.
    Flow,
}

/// The column the trace is made from.
#[derive(Debug)]
pub(super) struct Signal {
    pub quantity: Quantity,
    /// Its name as in the file (lower case).
    pub name: String,
    /// mL (volume) or mL/s (flow) per unit of the column; `None` for a name without a unit.
    pub unit: Option<f64>,
    pub values: Vec<f64>,
}

/// The columns read from a trace file.
#[derive(Debug)]
pub(super) struct Columns {
    pub times: Vec<f64>,
    /// Seconds per unit of the time column, from its name.
    pub seconds_per_unit: f64,
    pub signal: Signal,
    /// A flow column present beside the volume column read, and so not used.
    pub unused_flow: Option<String>,
}

/// The names a trace file's columns may have.
pub(super) const COLUMN_NAMES: &str = "time_s or time_ms, and volume_ml or volume_l (volume \
     change from the scan) or flow_l_per_s or flow_ml_per_s (airflow, positive into the lungs)";

fn time_unit(name: &str) -> Option<f64> {
    match name {
        "time_s" | "t_s" | "time" => Some(1.0),
        "time_ms" | "t_ms" => Some(1e-3),
        _ => None,
    }
}

/// mL per unit of a volume column: `Some(None)` for a bare `volume`.
fn volume_unit(name: &str) -> Option<Option<f64>> {
    match name {
        "volume_ml" | "volume_change_ml" => Some(Some(1.0)),
        "volume_l" | "volume_change_l" => Some(Some(1e3)),
        "volume" => Some(None),
        _ => None,
    }
}

/// mL/s per unit of a flow column: `Some(None)` for a bare `flow`.
fn flow_unit(name: &str) -> Option<Option<f64>> {
    match name {
        "flow_ml_per_s" | "flow_ml_s" => Some(Some(1.0)),
        "flow_l_per_s" | "flow_l_s" => Some(Some(1e3)),
        "flow" => Some(None),
        _ => None,
    }
}

/// Which of `names` are the time, volume and flow columns.
fn find_columns(names: &[String]) -> (Option<usize>, Option<usize>, Option<usize>) {
    let find = |f: &dyn Fn(&str) -> bool| names.iter().position(|n| f(n));
    (
        find(&|n| time_unit(n).is_some()),
        find(&|n| volume_unit(n).is_some()),
        find(&|n| flow_unit(n).is_some()),
    )
}

/// The signal made of column `name` (a volume or a flow name) and its values.
fn signal(name: &str, values: Vec<f64>) -> Signal {
    let (quantity, unit) = match volume_unit(name) {
        Some(unit) => (Quantity::Volume, unit),
        None => (Quantity::Flow, flow_unit(name).flatten()),
    };
    Signal {
        quantity,
        name: name.to_string(),
        unit,
        values,
    }
}

pub(super) fn parse_csv(text: &str) -> Result<Columns, Fault> {
    let mut lines = text
        .lines()
        .enumerate()
        .map(|(i, l)| (i + 1, l.trim()))
        .filter(|(_, l)| !l.is_empty() && !l.starts_with('#'));
    let (hline, header) = lines
        .next()
        .ok_or_else(|| Fault::whole("the file is empty".into()))?;
    let names: Vec<String> = header
        .split(',')
        .map(|c| c.trim().trim_matches('"').to_ascii_lowercase())
        .collect();
    let (time_col, vol_col, flow_col) = find_columns(&names);
    let (Some(tc), Some(sc)) = (time_col, vol_col.or(flow_col)) else {
        return Err(Fault::whole(format!(
            "line {hline}: header '{}' must name a time column and a volume or flow column \
             ({COLUMN_NAMES}), e.g. 'time_s,volume_ml'",
            clip(header)
        )));
    };
    let (mut times, mut values) = (Vec::new(), Vec::new());
    for (line, row) in lines {
        let at = |reason: String| Fault::at(times.len() + 1, reason);
        let cells: Vec<&str> = row.split(',').map(str::trim).collect();
        if cells.len() != names.len() {
            return Err(at(format!(
                "line {line}: {} columns where the header has {}",
                cells.len(),
                names.len()
            )));
        }
        let number = |c: usize| {
            cells[c].parse::<f64>().map_err(|_| {
                at(format!(
                    "line {line}: '{}' in column {} is not a number",
                    clip(cells[c]),
                    names[c]
                ))
            })
        };
        let (t, v) = (number(tc)?, number(sc)?);
        times.push(t);
        values.push(v);
        if times.len() > MAX_SAMPLES {
            return Err(Fault::whole(format!("more than {MAX_SAMPLES} samples")));
        }
    }
    Ok(Columns {
        seconds_per_unit: time_unit(&names[tc]).unwrap_or(1.0),
        times,
        signal: signal(&names[sc], values),
        unused_flow: vol_col.and(flow_col).map(|c| names[c].clone()),
    })
}

/// Whether a field name is of one kind (time, volume, flow).
type IsKind = fn(&str) -> bool;

/// The JSON shape, for messages.
const JSON_SHAPE: &str = "{\"time_s\": [numbers], \"volume_ml\": [numbers]}";

pub(super) fn parse_json(text: &str) -> Result<Columns, Fault> {
    let value: serde_json::Value = serde_json::from_str(text)
        .map_err(|e| Fault::whole(format!("not valid JSON: {}", clip(&e.to_string()))))?;
    let serde_json::Value::Object(object) = value else {
        return Err(Fault::whole(format!(
            "expected {JSON_SHAPE}, found a JSON {}",
            json_kind(&value)
        )));
    };
    let names: Vec<String> = object.keys().cloned().collect();
    if let Some(unknown) = names
        .iter()
        .find(|n| time_unit(n).is_none() && volume_unit(n).is_none() && flow_unit(n).is_none())
    {
        return Err(Fault::whole(format!(
            "unknown field '{}': expected {COLUMN_NAMES}",
            clip(unknown)
        )));
    }
    let (time_key, vol_key, flow_key) = find_columns(&names);
    let kinds: [(&str, IsKind); 3] = [
        ("time", |n| time_unit(n).is_some()),
        ("volume", |n| volume_unit(n).is_some()),
        ("flow", |n| flow_unit(n).is_some()),
    ];
    for (kind, is_kind) in kinds {
        if let [a, b, ..] = names.iter().filter(|n| is_kind(n)).collect::<Vec<_>>()[..] {
            return Err(Fault::whole(format!(
                "two {kind} fields, '{a}' and '{b}': give one"
            )));
        }
    }
    let (Some(tk), Some(sk)) = (time_key, vol_key.or(flow_key)) else {
        return Err(Fault::whole(format!(
            "expected {JSON_SHAPE} (or a flow_l_per_s or flow_ml_per_s field): no {} field",
            if time_key.is_none() {
                "time_s"
            } else {
                "volume_ml"
            }
        )));
    };
    let numbers = |key: &str| -> Result<Vec<f64>, Fault> {
        let serde_json::Value::Array(items) = &object[key] else {
            return Err(Fault::whole(format!(
                "expected {JSON_SHAPE}: '{key}' is a JSON {}, not an array of numbers",
                json_kind(&object[key])
            )));
        };
        if items.len() > MAX_SAMPLES {
            return Err(Fault::whole(format!("more than {MAX_SAMPLES} samples")));
        }
        items
            .iter()
            .enumerate()
            .map(|(i, x)| match x {
                // Non-finite numbers cannot be written in JSON; `null` is what many tools
                // write for NaN, so it is named as such.
                serde_json::Value::Null => Err(Fault::at(
                    i + 1,
                    format!("{key}[{i}] is null (NaN or a missing value?)"),
                )),
                _ => x.as_f64().ok_or_else(|| {
                    Fault::at(
                        i + 1,
                        format!(
                            "expected {JSON_SHAPE}: {key}[{i}] is a JSON {}, not a number",
                            json_kind(x)
                        ),
                    )
                }),
            })
            .collect()
    };
    Ok(Columns {
        times: numbers(&names[tk])?,
        seconds_per_unit: time_unit(&names[tk]).unwrap_or(1.0),
        signal: signal(&names[sk], numbers(&names[sk])?),
        unused_flow: vol_key.and(flow_key).map(|k| names[k].clone()),
    })
}

/// What a JSON value is, in words.
fn json_kind(value: &serde_json::Value) -> &'static str {
    match value {
        serde_json::Value::Null => "null",
        serde_json::Value::Bool(_) => "boolean",
        serde_json::Value::Number(_) => "number",
        serde_json::Value::String(_) => "string",
        serde_json::Value::Array(_) => "array",
        serde_json::Value::Object(_) => "object",
    }
}
