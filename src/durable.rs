//! Writing files so that a reader never sees half of one: every write goes to a hidden
//! temporary sibling and is renamed into place.
//!
//! Two strengths, because they cost differently: [`write_atomic`] (rename only) for run
//! outputs that are staged in a directory and published as a whole, where the publication is
//! the commit point; [`write_durable`] (fsync of the file, rename, fsync of its directory) for
//! records that must survive a power cut the moment the call returns, such as the service's
//! job records.

use std::io::Write;
use std::path::{Path, PathBuf};

use crate::{IoContext, IoOp, Result};

/// Writes `bytes` to `path` through a hidden temporary sibling and a rename: a reader sees the
/// old file or the new one, never a part (not flushed to disk: see [`write_durable`]).
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<()> {
    write_via_temporary(path, bytes, false)
}

/// Writes `bytes` to `path` durably: temporary sibling, fsync, rename, fsync of the directory,
/// so the new content survives a crash once this returns.
pub fn write_durable(path: &Path, bytes: &[u8]) -> Result<()> {
    write_via_temporary(path, bytes, true)?;
    if let Some(parent) = path.parent() {
        sync_dir(parent);
    }
    Ok(())
}

/// Flushes a directory's entries (new, renamed or removed files) to disk; best effort, since
/// some filesystems refuse to open or sync a directory.
pub fn sync_dir(dir: &Path) {
    if let Ok(d) = std::fs::File::open(dir) {
        let _ = d.sync_all();
    }
}

/// The hidden temporary sibling `path` is written through (`.name.tmp`), so listings and globs
/// of the directory skip it.
pub fn temporary_sibling(path: &Path) -> PathBuf {
    let name = path.file_name().map(|n| n.to_string_lossy().into_owned());
    path.with_file_name(format!(".{}.tmp", name.unwrap_or_default()))
}

fn write_via_temporary(path: &Path, bytes: &[u8], sync: bool) -> Result<()> {
    let tmp = temporary_sibling(path);
    // Errors name the file the caller asked for, not the temporary it goes through.
    let result = (|| {
        let mut file = std::fs::File::create(&tmp).at(IoOp::Write, path)?;
        file.write_all(bytes).at(IoOp::Write, path)?;
        if sync {
            file.sync_all().at(IoOp::Sync, path)?;
        }
        drop(file);
        std::fs::rename(&tmp, path).at(IoOp::Replace, path)
    })();
    if result.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    result
}

/// Bytes of the files under `dir`, symbolic links not followed; what cannot be read counts 0
/// (a directory removed meanwhile is simply gone).
pub fn directory_bytes(dir: &Path) -> u64 {
    let mut total = 0;
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        let Ok(entries) = std::fs::read_dir(&d) else {
            continue;
        };
        for entry in entries.flatten() {
            match entry.metadata() {
                Ok(m) if m.is_dir() => stack.push(entry.path()),
                Ok(m) => total += m.len(),
                Err(_) => {}
            }
        }
    }
    total
}

#[cfg(test)]
mod tests {
    use super::*;

    fn scratch(name: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!("lm-durable-{name}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        dir
    }

    #[test]
    fn both_strengths_replace_the_file_and_leave_no_temporary() {
        let dir = scratch("replace");
        let path = dir.join("record.json");
        write_atomic(&path, b"old").unwrap();
        write_durable(&path, b"new").unwrap();
        assert_eq!(std::fs::read(&path).unwrap(), b"new");
        let names: Vec<_> = std::fs::read_dir(&dir)
            .unwrap()
            .map(|e| e.unwrap().file_name())
            .collect();
        assert_eq!(names, vec![std::ffi::OsString::from("record.json")]);
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn a_failed_write_keeps_the_old_file_and_no_temporary() {
        let dir = scratch("fail");
        let path = dir.join("out.bin");
        write_atomic(&path, b"kept").unwrap();
        // A directory where the temporary file should go makes File::create fail.
        std::fs::create_dir(temporary_sibling(&path)).unwrap();
        assert!(write_durable(&path, b"lost").is_err());
        assert_eq!(std::fs::read(&path).unwrap(), b"kept");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
