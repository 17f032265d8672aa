//! The memory budget of one DICOM read: how many bytes the parsed files may hold at once,
//! shared by the parallel parsers so that reading many files cannot multiply memory past
//! what the machine has.

use std::sync::{Condvar, Mutex};

/// Share of the memory available at start that one read may use.
const AVAILABLE_SHARE: f64 = 0.5;
/// Budget when the available memory cannot be read (no /proc): a modest machine.
const FALLBACK_BUDGET_BYTES: u64 = 4 << 30;
/// Never below this, so that a small series reads on a loaded machine.
const MIN_BUDGET_BYTES: u64 = 256 << 20;

/// The default budget of one read: half the available memory, at least 256 MiB.
pub(super) fn default_budget_bytes() -> u64 {
    crate::process::available_memory()
        .map(|(b, _)| (b as f64 * AVAILABLE_SHARE) as u64)
        .unwrap_or(FALLBACK_BUDGET_BYTES)
        .max(MIN_BUDGET_BYTES)
}

/// Bytes reserved by the parsers of one read: `kept` by parsed files (held until the volume
/// is built), `in_flight` by files being parsed (their raw bytes, released after parsing).
#[derive(Default)]
struct Reserved {
    kept: u64,
    in_flight: u64,
}

/// A budget shared by the parallel parsers; a parser waits while others' transient bytes
/// are in flight and gives up only when its file cannot fit even then.
pub(super) struct MemoryBudget {
    total_bytes: u64,
    reserved: Mutex<Reserved>,
    released: Condvar,
}

/// Why a reservation failed.
pub(super) enum OverBudget {
    /// The file alone needs more than the whole budget.
    File {
        needed_bytes: u64,
        budget_bytes: u64,
    },
    /// Files already parsed hold too much for this one to fit.
    Read {
        needed_bytes: u64,
        budget_bytes: u64,
        kept_bytes: u64,
    },
}

impl MemoryBudget {
    /// A budget of `total_bytes`.
    pub(super) fn new(total_bytes: u64) -> Self {
        MemoryBudget {
            total_bytes,
            reserved: Mutex::new(Reserved::default()),
            released: Condvar::new(),
        }
    }

    /// The whole budget, bytes.
    pub(super) fn total_bytes(&self) -> u64 {
        self.total_bytes
    }

    /// Reserves `kept_bytes` for good and `transient_bytes` until [`Self::release`],
    /// waiting while other parsers' transient bytes may free enough room.
    pub(super) fn reserve(&self, kept_bytes: u64, transient_bytes: u64) -> Result<(), OverBudget> {
        let needed_bytes = kept_bytes.saturating_add(transient_bytes);
        if needed_bytes > self.total_bytes {
            return Err(OverBudget::File {
                needed_bytes,
                budget_bytes: self.total_bytes,
            });
        }
        let mut reserved = self.reserved.lock().unwrap_or_else(|p| p.into_inner());
        loop {
            let used = reserved.kept + reserved.in_flight;
            if used.saturating_add(needed_bytes) <= self.total_bytes {
                reserved.kept += kept_bytes;
                reserved.in_flight += transient_bytes;
                return Ok(());
            }
            if reserved.in_flight == 0 {
                return Err(OverBudget::Read {
                    needed_bytes,
                    budget_bytes: self.total_bytes,
                    kept_bytes: reserved.kept,
                });
            }
            reserved = self
                .released
                .wait(reserved)
                .unwrap_or_else(|p| p.into_inner());
        }
    }

    /// Returns `transient_bytes` reserved by [`Self::reserve`] and `unkept_bytes` of its
    /// kept part (a file refused after its reservation).
    pub(super) fn release(&self, transient_bytes: u64, unkept_bytes: u64) {
        let mut reserved = self.reserved.lock().unwrap_or_else(|p| p.into_inner());
        reserved.in_flight = reserved.in_flight.saturating_sub(transient_bytes);
        reserved.kept = reserved.kept.saturating_sub(unkept_bytes);
        self.released.notify_all();
    }
}

/// A size for messages: MB with one decimal, or kB or bytes when smaller.
pub(super) fn mb(bytes: u64) -> String {
    match bytes {
        0..1_000 => format!("{bytes} bytes"),
        1_000..1_000_000 => format!("{:.1} kB", bytes as f64 / 1e3),
        _ => format!("{:.1} MB", bytes as f64 / 1e6),
    }
}
