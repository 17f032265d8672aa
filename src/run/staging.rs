//! Publishing a run's output directory all at once.
//!
//! Files are written into a hidden sibling directory; only a finished run replaces the
//! output directory, so a failure (bad input found late, a full disk, a numerical blow-up)
//! leaves whatever was there before untouched. A non-empty directory that is not a previous
//! lungmotion run (no `summary.json`) is never replaced.

use std::path::{Path, PathBuf};

use crate::{Error, IoContext, IoOp, Result};

/// The file that marks a directory as a lungmotion run.
pub const SUMMARY_FILE: &str = "summary.json";

/// A staging directory that becomes the output directory on [`OutputStaging::publish`].
pub struct OutputStaging {
    target: PathBuf,
    staging: PathBuf,
    published: bool,
}

impl OutputStaging {
    /// Prepares to write `target`; refuses a non-empty directory that is not a previous run.
    pub fn new(target: &Path) -> Result<Self> {
        let refused = |reason: String| Error::OutputDir {
            path: target.to_path_buf(),
            reason,
        };
        if target.exists() {
            if !target.is_dir() {
                return Err(refused("exists and is not a directory".into()));
            }
            let mut entries = std::fs::read_dir(target).at(IoOp::List, target)?;
            if entries.next().is_some() && !target.join(SUMMARY_FILE).is_file() {
                return Err(refused(format!(
                    "the directory is not empty and holds no {SUMMARY_FILE} from an earlier \
                     run; choose a new or empty directory (nothing was written)"
                )));
            }
        }
        let name = target
            .file_name()
            .ok_or_else(|| refused("has no directory name".into()))?
            .to_string_lossy()
            .into_owned();
        let parent = match target.parent() {
            Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
            _ => PathBuf::from("."),
        };
        std::fs::create_dir_all(&parent).at(IoOp::CreateDir, &parent)?;
        let staging = parent.join(format!(".{name}.partial-{}", std::process::id()));
        if staging.exists() {
            std::fs::remove_dir_all(&staging).at(IoOp::Remove, &staging)?;
        }
        std::fs::create_dir_all(&staging).at(IoOp::CreateDir, &staging)?;
        Ok(OutputStaging {
            target: target.to_path_buf(),
            staging,
            published: false,
        })
    }

    /// Where files are written until publication.
    pub fn dir(&self) -> &Path {
        &self.staging
    }

    /// The final output directory.
    pub fn target(&self) -> &Path {
        &self.target
    }

    /// Replaces the output directory with the staged files.
    pub fn publish(mut self) -> Result<()> {
        let old = self.staging.with_file_name(format!(
            ".{}.old-{}",
            self.target
                .file_name()
                .map(|n| n.to_string_lossy().into_owned())
                .unwrap_or_default(),
            std::process::id()
        ));
        let had_old = self.target.exists();
        if had_old {
            // Moving the old run aside.
            std::fs::rename(&self.target, &old).at(IoOp::Rename, &self.target)?;
        }
        if let Err(e) = std::fs::rename(&self.staging, &self.target) {
            if had_old {
                // Put the previous run back: losing it would be worse than failing.
                let _ = std::fs::rename(&old, &self.target);
            }
            return Err(Error::io(IoOp::Replace, &self.target, e));
        }
        self.published = true;
        if had_old {
            let _ = std::fs::remove_dir_all(&old);
        }
        Ok(())
    }
}

impl Drop for OutputStaging {
    fn drop(&mut self) {
        if !self.published {
            let _ = std::fs::remove_dir_all(&self.staging);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn scratch(name: &str) -> PathBuf {
        let d =
            std::env::temp_dir().join(format!("lungmotion-staging-{name}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&d);
        std::fs::create_dir_all(&d).unwrap();
        d
    }

    #[test]
    fn a_failed_run_keeps_the_previous_one_and_a_finished_run_replaces_it() {
        let root = scratch("replace");
        let out = root.join("run");
        let first = OutputStaging::new(&out).unwrap();
        std::fs::write(first.dir().join(SUMMARY_FILE), "1").unwrap();
        first.publish().unwrap();
        assert_eq!(
            std::fs::read_to_string(out.join(SUMMARY_FILE)).unwrap(),
            "1"
        );

        let failed = OutputStaging::new(&out).unwrap();
        std::fs::write(failed.dir().join(SUMMARY_FILE), "2").unwrap();
        let staged = failed.dir().to_path_buf();
        drop(failed);
        assert!(!staged.exists());
        assert_eq!(
            std::fs::read_to_string(out.join(SUMMARY_FILE)).unwrap(),
            "1"
        );

        let second = OutputStaging::new(&out).unwrap();
        std::fs::write(second.dir().join(SUMMARY_FILE), "3").unwrap();
        second.publish().unwrap();
        assert_eq!(
            std::fs::read_to_string(out.join(SUMMARY_FILE)).unwrap(),
            "3"
        );
        let leftovers: Vec<_> = std::fs::read_dir(&root).unwrap().collect();
        assert_eq!(leftovers.len(), 1, "{leftovers:?}");
        std::fs::remove_dir_all(&root).unwrap();
    }

    #[test]
    fn a_foreign_directory_is_never_replaced() {
        let root = scratch("foreign");
        std::fs::write(root.join("notes.txt"), "keep").unwrap();
        let err = OutputStaging::new(&root).err().unwrap().to_string();
        assert!(err.contains("not empty"), "{err}");
        assert_eq!(
            std::fs::read_to_string(root.join("notes.txt")).unwrap(),
            "keep"
        );
        std::fs::remove_dir_all(&root).unwrap();
    }
}
