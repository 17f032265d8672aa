//! Safe reading of zip archives (a DICOM series as hospitals export it).
//!
//! Convention: entries are returned in memory, in archive order, with their names as written
//! in the archive (`/`-separated). Directory and symlink entries are skipped. Nothing is ever
//! written to disk, so an entry name cannot escape a target directory; names that would
//! (`..` components, absolute paths, drive letters, NUL bytes) are nevertheless refused, since
//! they mark a hostile or broken archive. Decompression is bounded by [`ArchiveLimits`],
//! counting the bytes the decoder actually produces: the sizes declared in the headers are
//! never trusted.
//!
//! In memory rather than extracting into a directory: a CT series is at most a few hundred
//! megabytes, each entry is parsed straight from its buffer, and there is no temporary
//! directory to clean up after a refusal.

use std::io::{Read, Seek, SeekFrom};
use std::path::Path;

use crate::formats::budget::{ScanBudget, MAX_INFLATION_RATIO, RATIO_EXEMPT_BYTES};
use crate::{Error, IoContext, IoOp, Result};

/// Bounds applied while reading an archive, each a guard against a hostile or broken file.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ArchiveLimits {
    /// Most entries (files and directories) an archive may declare.
    pub max_entries: usize,
    /// Most bytes all entries together may decompress to.
    pub max_total_uncompressed_bytes: u64,
    /// What that total limit is, as a refusal names it (a reader's memory budget, say).
    pub total_limit_name: &'static str,
    /// Most bytes one entry may decompress to.
    pub max_entry_uncompressed_bytes: u64,
    /// Largest ratio of decompressed to compressed bytes for one entry (decompression-bomb guard).
    pub max_entry_ratio: u64,
    /// Entries may always decompress to this many bytes whatever their ratio, so that small,
    /// very regular files (an all-air slice) are not mistaken for bombs.
    pub ratio_exempt_bytes: u64,
}

impl Default for ArchiveLimits {
    fn default() -> Self {
        ArchiveLimits {
            max_entries: 100_000,
            max_total_uncompressed_bytes: 4 << 30,
            total_limit_name: "the limit of all entries together",
            max_entry_uncompressed_bytes: 2 << 30,
            max_entry_ratio: MAX_INFLATION_RATIO,
            ratio_exempt_bytes: RATIO_EXEMPT_BYTES,
        }
    }
}

/// One regular file of an archive, decompressed.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ArchiveEntry {
    /// Name inside the archive (`/`-separated, relative).
    pub name: String,
    /// Decompressed content.
    pub data: Vec<u8>,
}

/// Whether a file starts with a zip signature (local header or empty-archive end record).
pub fn looks_like_zip(path: &Path) -> bool {
    let mut magic = [0u8; 4];
    std::fs::File::open(path)
        .and_then(|mut f| f.read_exact(&mut magic))
        .map(|_| &magic == b"PK\x03\x04" || &magic == b"PK\x05\x06")
        .unwrap_or(false)
}

/// Reads every regular file of the zip archive at `path` into memory, within `limits`.
pub fn read_zip_file(path: &Path, limits: &ArchiveLimits) -> Result<Vec<ArchiveEntry>> {
    let file = std::fs::File::open(path).at(IoOp::Open, path)?;
    read_zip_entries(
        std::io::BufReader::new(file),
        &path.display().to_string(),
        limits,
    )
}

/// Reads every regular file of a zip archive into memory, within `limits`; `zip_name` names
/// the archive in errors.
pub fn read_zip_entries<R: Read + Seek>(
    mut reader: R,
    zip_name: &str,
    limits: &ArchiveLimits,
) -> Result<Vec<ArchiveEntry>> {
    let bad = |m: String| Error::scan(zip_name, m);
    // An entry's declared compressed size cannot exceed the archive: bounding it so keeps a
    // lying header from widening its own ratio cap.
    let archive_bytes = reader
        .seek(SeekFrom::End(0))
        .and_then(|len| reader.seek(SeekFrom::Start(0)).map(|_| len))
        .map_err(|e| bad(format!("cannot measure the archive ({e})")))?;
    let inflation = ScanBudget {
        max_inflation_ratio: limits.max_entry_ratio,
        ratio_exempt_bytes: limits.ratio_exempt_bytes,
        ..ScanBudget::default()
    };
    let mut archive = zip::ZipArchive::new(reader)
        .map_err(|e| bad(format!("not a readable zip archive ({e})")))?;
    if archive.len() > limits.max_entries {
        return Err(bad(format!(
            "{} entries, more than the limit of {}",
            archive.len(),
            limits.max_entries
        )));
    }
    let mut entries = Vec::new();
    let mut total_bytes: u64 = 0;
    for index in 0..archive.len() {
        let mut file = archive
            .by_index(index)
            .map_err(|e| bad(format!("entry #{index} is unreadable ({e})")))?;
        let name = String::from_utf8_lossy(file.name_raw()).into_owned();
        check_entry_name(&name).map_err(|why| bad(format!("entry '{name}' refused: {why}")))?;
        if file.is_dir() || name.ends_with('/') || file.is_symlink() {
            continue;
        }
        let compressed_bytes = file.compressed_size().min(archive_bytes);
        let ratio_bound = inflation.inflation_bound(compressed_bytes);
        let remaining_total = limits
            .max_total_uncompressed_bytes
            .saturating_sub(total_bytes);
        let bound = ratio_bound
            .min(limits.max_entry_uncompressed_bytes)
            .min(remaining_total);
        // The declared size only sizes the first allocation; the bound is enforced on output.
        let capacity = file.size().min(bound).min(64 << 20) as usize;
        let mut data = Vec::with_capacity(capacity);
        (&mut file)
            .take(bound.saturating_add(1))
            .read_to_end(&mut data)
            .map_err(|e| bad(format!("entry '{name}' cannot be decompressed ({e})")))?;
        let produced = data.len() as u64;
        if produced > bound {
            let reason = if bound == ratio_bound {
                format!(
                    "decompresses to more than {}× its {} compressed bytes (decompression bomb?)",
                    limits.max_entry_ratio, compressed_bytes
                )
            } else if bound == remaining_total {
                format!(
                    "the archive decompresses to more than {} bytes, {}",
                    limits.max_total_uncompressed_bytes, limits.total_limit_name
                )
            } else {
                format!(
                    "decompresses to more than the per-entry limit of {} bytes",
                    limits.max_entry_uncompressed_bytes
                )
            };
            return Err(bad(format!("entry '{name}' refused: {reason}")));
        }
        total_bytes += produced;
        entries.push(ArchiveEntry { name, data });
    }
    Ok(entries)
}

/// Refuses names that would leave an extraction directory on any platform.
fn check_entry_name(name: &str) -> std::result::Result<(), &'static str> {
    if name.is_empty() {
        return Err("empty name");
    }
    if name.contains('\0') {
        return Err("NUL byte in the name");
    }
    if name.starts_with('/') || name.starts_with('\\') {
        return Err("absolute path");
    }
    let bytes = name.as_bytes();
    if bytes.len() >= 2 && bytes[0].is_ascii_alphabetic() && bytes[1] == b':' {
        return Err("drive letter");
    }
    if name.split(['/', '\\']).any(|component| component == "..") {
        return Err("'..' component leaves the archive");
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::check_entry_name;

    #[test]
    fn entry_names_that_escape_are_refused() {
        for ok in ["a.dcm", "series/IMG0001.dcm", "a..b/c", "dir/"] {
            assert!(check_entry_name(ok).is_ok(), "{ok}");
        }
        for (bad, why) in [
            ("../x", ".."),
            ("a/../../x", ".."),
            ("a\\..\\x", ".."),
            ("/etc/passwd", "absolute"),
            ("\\x", "absolute"),
            ("C:/x", "drive"),
            ("c:x", "drive"),
            ("", "empty"),
        ] {
            let e = check_entry_name(bad).unwrap_err();
            assert!(e.contains(why), "{bad}: {e}");
        }
    }
}
