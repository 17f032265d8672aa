//! How much one scan may make a reader inflate and allocate: the decompression-ratio cap and
//! the voxel budget that the NIfTI, NRRD and zip readers share, checked against what a header
//! declares before anything of that size is inflated or allocated.
//!
//! Why two bounds. The ratio cap bounds the work per byte received: a CT's voxels carry noise
//! and compress 2–10×, DICOM files somewhat more, so 250× only stops bombs (deflate reaches
//! ≈ 1 030× on zeros). The voxel budget bounds memory: a header may declare a grid that fits
//! the format's limits and the stream's ratio yet not the machine, and the reader would only
//! find out after gigabytes of allocation.

use crate::{Error, Result};

/// Largest ratio of inflated to compressed bytes accepted for CT data.
pub const MAX_INFLATION_RATIO: u64 = 250;
/// Inflated sizes up to this are accepted whatever their ratio, so small, very regular data
/// (an all-air slice, a phantom) are not mistaken for bombs.
pub const RATIO_EXEMPT_BYTES: u64 = 1 << 20;
/// Fixed ceiling on one decoded volume, bytes of float32 voxels: 2³⁰ voxels, eight times a
/// 512 × 512 × 500 thin-slice chest CT, more than any chest CT holds.
pub const MAX_VOLUME_BYTES: u64 = 4 << 30;
/// One volume's float32 voxels may take at most this fraction (1/n) of the available memory:
/// ingest holds the CT, the stored samples while decoding, then masks, labels and distance
/// maps: `lungmotion ingest` of the POPI CT (37 M voxels, 148 MB as float32) peaks at 844 MB,
/// 5.7×; 8 leaves room for the rest of the process (README, "Memory and decompression
/// budget").
pub const MEMORY_SHARE_DIVISOR: u64 = 8;

/// The bounds one scan is read within.
#[derive(Debug, Clone, PartialEq)]
pub struct ScanBudget {
    /// Largest ratio of inflated to compressed bytes (decompression-bomb guard).
    pub max_inflation_ratio: u64,
    /// Inflated sizes up to this many bytes pass whatever their ratio.
    pub ratio_exempt_bytes: u64,
    /// Most bytes the decoded volume may take as float32 voxels (all components).
    pub max_volume_bytes: u64,
    /// What set `max_volume_bytes`, in words for the refusal message.
    pub set_by: String,
}

impl Default for ScanBudget {
    /// The fixed bounds, without looking at the machine.
    fn default() -> Self {
        ScanBudget {
            max_inflation_ratio: MAX_INFLATION_RATIO,
            ratio_exempt_bytes: RATIO_EXEMPT_BYTES,
            max_volume_bytes: MAX_VOLUME_BYTES,
            set_by: format!(
                "the fixed ceiling of {} per scan",
                size_words(MAX_VOLUME_BYTES)
            ),
        }
    }
}

impl ScanBudget {
    /// The fixed bounds, lowered to 1/[`MEMORY_SHARE_DIVISOR`] of the memory available now
    /// (MemAvailable or the cgroup limit, whichever is smaller) when that is less.
    pub fn for_this_machine() -> Self {
        let fixed = ScanBudget::default();
        match crate::process::available_memory() {
            Some((available, source)) if available / MEMORY_SHARE_DIVISOR < MAX_VOLUME_BYTES => {
                ScanBudget {
                    max_volume_bytes: available / MEMORY_SHARE_DIVISOR,
                    set_by: format!(
                        "1/{MEMORY_SHARE_DIVISOR} of the {} of memory available ({source}), \
                         since ingest needs about {MEMORY_SHARE_DIVISOR}× the CT",
                        size_words(available)
                    ),
                    ..fixed
                }
            }
            _ => fixed,
        }
    }

    /// The same memory budget without the ratio cap, for label maps and displacement fields:
    /// a mostly-zero mask legitimately compresses beyond 250×.
    pub fn without_ratio_cap(&self) -> Self {
        ScanBudget {
            max_inflation_ratio: u64::MAX,
            ..self.clone()
        }
    }

    /// Refuses a grid whose float32 voxels (`components` per voxel) exceed the budget.
    pub fn check_volume(&self, what: &str, dims: [usize; 3], components: usize) -> Result<()> {
        let voxels = dims.iter().map(|&n| n as u128).product::<u128>();
        let bytes = voxels * components as u128 * 4;
        if bytes <= self.max_volume_bytes as u128 {
            return Ok(());
        }
        let per_voxel = if components == 1 {
            String::new()
        } else {
            format!(" × {components} components")
        };
        Err(Error::scan(
            what,
            format!(
                "declares {}×{}×{} voxels{per_voxel} = {} of float32, over the budget of {} \
                 (set by {})",
                dims[0],
                dims[1],
                dims[2],
                size_words(u64::try_from(bytes).unwrap_or(u64::MAX)),
                size_words(self.max_volume_bytes),
                self.set_by
            ),
        ))
    }

    /// Most bytes `compressed_bytes` may inflate to.
    pub fn inflation_bound(&self, compressed_bytes: u64) -> u64 {
        compressed_bytes
            .saturating_mul(self.max_inflation_ratio)
            .max(self.ratio_exempt_bytes)
    }

    /// Refuses, before inflating, a `stream` of `compressed_bytes` whose header declares
    /// `declared_bytes` once inflated, when that breaks the ratio cap.
    pub fn check_inflation(
        &self,
        what: &str,
        stream: &str,
        compressed_bytes: u64,
        declared_bytes: u64,
    ) -> Result<()> {
        if declared_bytes <= self.inflation_bound(compressed_bytes) {
            return Ok(());
        }
        Err(Error::scan(
            what,
            format!(
                "the header declares {declared_bytes} bytes of data from {compressed_bytes} \
                 bytes of {stream} ({}× its size), over the cap of {}× (a decompression bomb?)",
                declared_bytes / compressed_bytes.max(1),
                self.max_inflation_ratio
            ),
        ))
    }
}

/// A byte count in GiB or MiB with one decimal, as people read memory sizes.
pub fn size_words(bytes: u64) -> String {
    if bytes >= 1 << 30 {
        format!("{:.1} GiB", bytes as f64 / (1u64 << 30) as f64)
    } else {
        format!("{:.1} MiB", bytes as f64 / (1u64 << 20) as f64)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn refusals_name_the_grid_the_size_the_budget_and_its_source() {
        let budget = ScanBudget::default();
        budget.check_volume("ct.nii", [512, 512, 1000], 1).unwrap();
        let e = budget
            .check_volume("ct.nii", [2048, 1024, 1024], 1)
            .unwrap_err()
            .to_string();
        for part in [
            "ct.nii",
            "2048×1024×1024",
            "8.0 GiB of float32",
            "4.0 GiB",
            "fixed",
        ] {
            assert!(e.contains(part), "{part}: {e}");
        }
        let e = budget
            .check_volume("field.nii", [1024, 1024, 400], 3)
            .unwrap_err()
            .to_string();
        assert!(e.contains("× 3 components"), "{e}");
        let e = budget
            .check_inflation("ct.nii.gz", "gzip", 2_000_000, 2_000_000_000)
            .unwrap_err()
            .to_string();
        assert!(e.contains("1000×") && e.contains("250×"), "{e}");
        budget.check_inflation("a", "gzip", 10, 1 << 20).unwrap();
        budget
            .without_ratio_cap()
            .check_inflation("a", "gzip", 10, 1 << 40)
            .unwrap();
    }

    #[test]
    fn the_machine_budget_never_exceeds_the_fixed_ceiling() {
        let b = ScanBudget::for_this_machine();
        assert!(b.max_volume_bytes <= MAX_VOLUME_BYTES && b.max_volume_bytes > 0);
        assert!(!b.set_by.is_empty());
    }
}
