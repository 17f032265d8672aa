//! Admits one file into a read: its bytes taken within the read's memory budget, checked
//! by the pre-scan, and only then parsed by dicom-rs.

use std::fmt;

use dicom_object::{DefaultDicomObject, OpenFileOptions};

use super::budget::{mb, MemoryBudget, OverBudget};
use super::prescan::check_file;
use super::Source;

/// A file parsed by dicom-rs after its checks.
pub(super) struct Admitted {
    /// The file's path, or `zip:entry`.
    pub name: String,
    /// The parsed object.
    pub object: DefaultDicomObject,
    /// Memory reserved for the object in the budget (returned if the file is dropped).
    pub parsed_bytes: u64,
    /// Repairs made to the bytes before parsing, one sentence each.
    pub repairs: Vec<String>,
}

/// A file left out of the read, and why.
#[derive(Debug, Clone)]
pub(super) struct Skipped {
    /// The file's path, or `zip:entry`.
    pub name: String,
    /// What is wrong with it, in plain words.
    pub reason: String,
    /// The read as a whole ran out of its memory budget here (not this file's fault alone).
    pub over_read_budget: bool,
}

impl Skipped {
    /// The file `name` is skipped for `reason`.
    pub(super) fn new(name: &str, reason: impl Into<String>) -> Self {
        Skipped {
            name: name.to_string(),
            reason: reason.into(),
            over_read_budget: false,
        }
    }
}

impl fmt::Display for Skipped {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}: skipped, {}", self.name, self.reason)
    }
}

/// Reserves `kept` + `transient` bytes, or says why the file cannot have them.
fn reserve(budget: &MemoryBudget, name: &str, kept: u64, transient: u64) -> Result<(), Skipped> {
    budget.reserve(kept, transient).map_err(|over| match over {
        OverBudget::File {
            needed_bytes,
            budget_bytes,
        } => Skipped::new(
            name,
            format!(
                "it would take {} of memory to read, more than the {} this read may use",
                mb(needed_bytes),
                mb(budget_bytes)
            ),
        ),
        OverBudget::Read {
            needed_bytes,
            budget_bytes,
            kept_bytes,
        } => Skipped {
            over_read_budget: true,
            ..Skipped::new(
                name,
                format!(
                    "it needs {} of memory while the files read before it already hold {} of \
                     the {} this read may use",
                    mb(needed_bytes),
                    mb(kept_bytes),
                    mb(budget_bytes)
                ),
            )
        },
    })
}

/// Reads, checks and parses one source within `budget`.
pub(super) fn admit(source: Source, budget: &MemoryBudget) -> Result<Admitted, Skipped> {
    let (name, raw) = match source {
        Source::File(path) => {
            let name = path.display().to_string();
            let size = std::fs::metadata(&path)
                .map_err(|e| Skipped::new(&name, format!("cannot read: {e}")))?
                .len();
            reserve(budget, &name, 0, size)?;
            match std::fs::read(&path) {
                Ok(bytes) => (name, bytes),
                Err(e) => {
                    budget.release(size, 0);
                    return Err(Skipped::new(&name, format!("cannot read: {e}")));
                }
            }
        }
        Source::Entry { zip, entry } => {
            let name = format!("{zip}:{}", entry.name);
            reserve(budget, &name, 0, entry.data.len() as u64)?;
            (name, entry.data)
        }
    };
    let raw_bytes = raw.len() as u64;
    let checked = check_file(raw, budget.total_bytes());
    budget.release(raw_bytes, 0);
    let checked =
        checked.map_err(|why| Skipped::new(&name, format!("not a readable DICOM file: {why}")))?;
    let transient = checked.bytes.len() as u64;
    reserve(budget, &name, checked.parsed_bytes, transient)?;
    let parsed = OpenFileOptions::new().from_reader(&checked.bytes[..]);
    drop(checked.bytes);
    budget.release(transient, 0);
    match parsed {
        Ok(object) => Ok(Admitted {
            name,
            object,
            parsed_bytes: checked.parsed_bytes,
            repairs: checked.repairs,
        }),
        Err(e) => {
            budget.release(0, checked.parsed_bytes);
            Err(Skipped::new(
                &name,
                format!("not a readable DICOM file ({e})"),
            ))
        }
    }
}
