//! Publishing a run's output directory all at once.
//!
//! Files are written into a hidden sibling directory; only a finished run replaces the
//! output directory, so a failure (bad input found late, a full disk, a numerical blow-up, an
//! interruption) leaves whatever was there before untouched and the staging directory is
//! removed. A non-empty directory that is not a previous lungmotion run (no `summary.json`
//! written by lungmotion) is never replaced, and a previous run of another CT only when asked
//! ([`Overwrite::AnyRun`]).
//!
//! A staging directory holds a lock file, locked by its run for as long as the run lives, so
//! the next run into the same place can tell one left by a killed run (lock free) from one in
//! use and remove the former.

use std::fs::File;
use std::path::{Path, PathBuf};

use crate::volume::Volume;
use crate::{Error, IoContext, IoOp, Result};

/// The file that marks a directory as a lungmotion run.
pub const SUMMARY_FILE: &str = "summary.json";

/// The lock file inside a staging directory, held by the run writing it.
const OWNER_LOCK: &str = ".lungmotion-run.lock";

/// Which earlier run in the output directory a finished run may replace.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Overwrite {
    /// Only a run of the same CT (same fingerprint); a run of another CT is refused.
    #[default]
    SameCtOnly,
    /// Any earlier lungmotion run (never a directory that is not one).
    AnyRun,
}

/// What identifies the CT a run was made from, as `summary.json` records it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct CtIdentity {
    /// The CT path as given.
    pub path: String,
    /// [`ct_fingerprint`] of the loaded CT.
    pub fingerprint: String,
    /// SeriesInstanceUID, when the CT was DICOM.
    pub series_uid: Option<String>,
}

/// A fingerprint of a loaded CT, its grid and every voxel value: `fnv1a64:<16 hex digits>`
/// (FNV-1a over the geometry's and the voxels' little-endian bits). It tells two CTs apart
/// whatever their file names or formats; it is not a cryptographic hash.
pub fn ct_fingerprint(ct: &Volume<f32>) -> String {
    const PRIME: u64 = 0x0000_0100_0000_01b3;
    let g = &ct.geometry;
    let mut hash: u64 = 0xcbf2_9ce4_8422_2325;
    let mut mix = |word: u64| {
        hash ^= word;
        hash = hash.wrapping_mul(PRIME);
    };
    g.dims.iter().for_each(|&d| mix(d as u64));
    let placement = g.spacing_mm.iter().chain(&g.origin_lps_mm);
    placement
        .chain(g.direction_lps.iter().flatten())
        .for_each(|v| mix(v.to_bits()));
    ct.as_slice()
        .iter()
        .for_each(|v| mix(u64::from(v.to_bits())));
    format!("fnv1a64:{hash:016x}")
}

/// A staging directory that becomes the output directory on [`OutputStaging::publish`].
pub struct OutputStaging {
    target: PathBuf,
    staging: PathBuf,
    published: bool,
    /// Held (locked) while the run lives; the OS releases it if the process is killed.
    _owner: Option<File>,
}

impl OutputStaging {
    /// Prepares to write `target`: refuses a directory that is not a previous run, removes
    /// staging directories left there by killed runs, and creates this run's.
    pub fn new(target: &Path) -> Result<Self> {
        check_target(target)?;
        let name = target
            .file_name()
            .ok_or_else(|| refused(target, "has no directory name".into()))?
            .to_string_lossy()
            .into_owned();
        let parent = match target.parent() {
            Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
            _ => PathBuf::from("."),
        };
        std::fs::create_dir_all(&parent).at(IoOp::CreateDir, &parent)?;
        remove_stale_staging(&parent, &name);
        let staging = parent.join(format!(".{name}.partial-{}", std::process::id()));
        if staging.exists() {
            std::fs::remove_dir_all(&staging).at(IoOp::Remove, &staging)?;
        }
        std::fs::create_dir_all(&staging).at(IoOp::CreateDir, &staging)?;
        let owner = lock_owner(&staging)?;
        Ok(OutputStaging {
            target: target.to_path_buf(),
            staging,
            published: false,
            _owner: owner,
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

    /// Refuses to go on when the output directory holds a run of another CT than `ct`,
    /// unless `overwrite` allows it; called as soon as the CT is loaded.
    pub fn check_replaces(&self, ct: &CtIdentity, overwrite: Overwrite) -> Result<()> {
        let Some(earlier) = earlier_run(&self.target)? else {
            return Ok(());
        };
        if overwrite == Overwrite::AnyRun || same_ct(&earlier, ct) {
            return Ok(());
        }
        let earlier_ct = earlier["ct"].as_str().unwrap_or("an unnamed CT");
        let what = match earlier["ct_fingerprint"].as_str() {
            Some(f) => format!("a run of another CT ({earlier_ct}, fingerprint {f})"),
            None => format!(
                "a run of {earlier_ct}, from a version that did not record the CT's \
                 fingerprint, so it cannot be told to be the same CT"
            ),
        };
        Err(refused(
            &self.target,
            format!(
                "holds {what}, not of {} ({}): choose another --out, or give --overwrite to \
                 replace that run (nothing was written)",
                ct.path, ct.fingerprint
            ),
        ))
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
        // The lock stays held through its open file; only its name leaves the output.
        let _ = std::fs::remove_file(self.staging.join(OWNER_LOCK));
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

fn refused(target: &Path, reason: String) -> Error {
    Error::OutputDir {
        path: target.to_path_buf(),
        reason,
    }
}

/// Refuses a target that is a file, or a non-empty directory that is not a lungmotion run.
fn check_target(target: &Path) -> Result<()> {
    if !target.exists() {
        return Ok(());
    }
    if !target.is_dir() {
        return Err(refused(target, "exists and is not a directory".into()));
    }
    let mut entries = std::fs::read_dir(target).at(IoOp::List, target)?;
    if entries.next().is_some() && !target.join(SUMMARY_FILE).is_file() {
        return Err(refused(
            target,
            format!(
                "the directory is not empty and holds no {SUMMARY_FILE} from an earlier run; \
                 choose a new or empty directory (nothing was written; --overwrite never \
                 replaces a directory that is not a lungmotion run)"
            ),
        ));
    }
    earlier_run(target).map(|_| ())
}

/// The `summary.json` of the run in `target`, if it holds one; refused if that file is not
/// a lungmotion summary.
fn earlier_run(target: &Path) -> Result<Option<serde_json::Value>> {
    let path = target.join(SUMMARY_FILE);
    if !path.is_file() {
        return Ok(None);
    }
    let text = std::fs::read_to_string(&path).at(IoOp::Read, &path)?;
    match serde_json::from_str::<serde_json::Value>(&text) {
        Ok(v) if v["software"] == "lungmotion" => Ok(Some(v)),
        _ => Err(refused(
            target,
            format!(
                "holds a {SUMMARY_FILE} that lungmotion did not write, so the directory is \
                 not a lungmotion run; choose a new or empty directory (nothing was written; \
                 --overwrite never replaces a directory that is not a lungmotion run)"
            ),
        )),
    }
}

/// Whether the earlier run's summary names the same CT: by fingerprint when it has one, else
/// (a summary from before fingerprints) by DICOM series UID, else by the CT path as given.
fn same_ct(earlier: &serde_json::Value, ct: &CtIdentity) -> bool {
    if let Some(f) = earlier["ct_fingerprint"].as_str() {
        return f == ct.fingerprint;
    }
    let uid = earlier["ingest"]["source"]["series"]["series_instance_uid"].as_str();
    if let (Some(a), Some(b)) = (uid, ct.series_uid.as_deref()) {
        return a == b;
    }
    earlier["ct"].as_str() == Some(ct.path.as_str())
}

/// Creates this run's lock file inside `staging`, locked before it takes its name, so a lock
/// file that can be seen is always held while its run lives. `None` where the file system
/// offers no locks (the staging directory is then cleaned only by its own run).
fn lock_owner(staging: &Path) -> Result<Option<File>> {
    let fresh = staging.join(format!("{OWNER_LOCK}.new"));
    let file = File::create(&fresh).at(IoOp::Create, &fresh)?;
    if file.try_lock().is_err() {
        let _ = std::fs::remove_file(&fresh);
        return Ok(None);
    }
    let lock = staging.join(OWNER_LOCK);
    std::fs::rename(&fresh, &lock).at(IoOp::Rename, &fresh)?;
    Ok(Some(file))
}

/// Removes the staging directories (and the previous runs moved aside) that killed runs left
/// beside `<parent>/<name>`; best effort, as a leftover only costs disk space.
fn remove_stale_staging(parent: &Path, name: &str) {
    let Ok(entries) = std::fs::read_dir(parent) else {
        return;
    };
    let prefixes = [format!(".{name}.partial-"), format!(".{name}.old-")];
    for entry in entries.flatten() {
        let file_name = entry.file_name().to_string_lossy().into_owned();
        let Some(pid) = prefixes.iter().find_map(|p| {
            file_name
                .strip_prefix(p.as_str())
                .and_then(|pid| pid.parse::<u32>().ok())
        }) else {
            continue;
        };
        let dir = entry.path();
        if pid == std::process::id() || !dir.is_dir() || owner_alive(&dir, pid) {
            continue;
        }
        match std::fs::remove_dir_all(&dir) {
            Ok(()) => tracing::info!(
                "removed {}, left by an interrupted run (process {pid})",
                dir.display()
            ),
            Err(e) => tracing::warn!(
                "cannot remove {}, left by an interrupted run: {e}",
                dir.display()
            ),
        }
    }
}

/// Whether the run that made `dir` still lives: its lock is held, or, where it has no lock
/// (a previous run moved aside, an older version), its process exists.
fn owner_alive(dir: &Path, pid: u32) -> bool {
    match File::open(dir.join(OWNER_LOCK)) {
        Ok(lock) => match lock.try_lock() {
            Ok(()) => false,
            Err(std::fs::TryLockError::WouldBlock) => true,
            Err(std::fs::TryLockError::Error(_)) => process_exists(pid),
        },
        Err(_) => process_exists(pid),
    }
}

/// Whether process `pid` exists; `true` where that cannot be told, so nothing in use is
/// removed.
fn process_exists(pid: u32) -> bool {
    if cfg!(target_os = "linux") {
        Path::new("/proc").join(pid.to_string()).exists()
    } else {
        true
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

    /// A lungmotion summary told apart by `n`.
    fn summary(n: u32) -> String {
        format!("{{\"software\": \"lungmotion\", \"n\": {n}}}")
    }

    #[test]
    fn a_failed_run_keeps_the_previous_one_and_a_finished_run_replaces_it() {
        let root = scratch("replace");
        let out = root.join("run");
        let first = OutputStaging::new(&out).unwrap();
        std::fs::write(first.dir().join(SUMMARY_FILE), summary(1)).unwrap();
        first.publish().unwrap();
        assert_eq!(
            std::fs::read_to_string(out.join(SUMMARY_FILE)).unwrap(),
            summary(1)
        );

        let failed = OutputStaging::new(&out).unwrap();
        std::fs::write(failed.dir().join(SUMMARY_FILE), summary(2)).unwrap();
        let staged = failed.dir().to_path_buf();
        drop(failed);
        assert!(!staged.exists());
        assert_eq!(
            std::fs::read_to_string(out.join(SUMMARY_FILE)).unwrap(),
            summary(1)
        );

        let second = OutputStaging::new(&out).unwrap();
        std::fs::write(second.dir().join(SUMMARY_FILE), summary(3)).unwrap();
        second.publish().unwrap();
        assert_eq!(
            std::fs::read_to_string(out.join(SUMMARY_FILE)).unwrap(),
            summary(3)
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

    #[test]
    fn a_run_of_another_ct_is_replaced_only_when_asked_and_a_lock_marks_a_live_run() {
        let root = scratch("identity");
        let out = root.join("run");
        std::fs::create_dir_all(&out).unwrap();
        std::fs::write(
            out.join(SUMMARY_FILE),
            r#"{"software": "lungmotion", "ct": "a.nii.gz", "ct_fingerprint": "fnv1a64:1"}"#,
        )
        .unwrap();
        let ct = |fingerprint: &str| CtIdentity {
            path: "b.nii.gz".into(),
            fingerprint: fingerprint.into(),
            series_uid: None,
        };
        let staging = OutputStaging::new(&out).unwrap();
        // Whatever the CT's name, the fingerprint decides.
        staging
            .check_replaces(&ct("fnv1a64:1"), Overwrite::SameCtOnly)
            .unwrap();
        let e = staging
            .check_replaces(&ct("fnv1a64:2"), Overwrite::SameCtOnly)
            .unwrap_err();
        assert!(
            matches!(&e, Error::OutputDir { path, .. } if *path == out)
                && e.to_string()
                    .contains("a run of another CT (a.nii.gz, fingerprint fnv1a64:1)"),
            "{e}"
        );
        staging
            .check_replaces(&ct("fnv1a64:2"), Overwrite::AnyRun)
            .unwrap();
        // This run's own staging directory is locked, so it counts as alive.
        assert!(owner_alive(staging.dir(), u32::MAX));
        drop(staging);
        let v = serde_json::json!({"software": "lungmotion", "ct": "b.nii.gz"});
        assert!(same_ct(&v, &ct("fnv1a64:9")), "an old summary: by path");
        std::fs::remove_dir_all(&root).unwrap();
    }

    #[test]
    fn equal_voxels_on_equal_grids_have_one_fingerprint() {
        let geometry = crate::volume::VolumeGeometry::axis_aligned([2, 2, 1], [1.0; 3], [0.0; 3]);
        let a = Volume::from_data(geometry, vec![-1000.0f32, 0.0, 40.0, -500.0]).unwrap();
        let mut moved = a.clone();
        moved.geometry.origin_lps_mm[2] = 1.0;
        let mut changed = a.clone();
        changed.as_slice_mut()[3] = -499.0;
        assert_eq!(ct_fingerprint(&a), ct_fingerprint(&a.clone()));
        assert_ne!(ct_fingerprint(&a), ct_fingerprint(&moved));
        assert_ne!(ct_fingerprint(&a), ct_fingerprint(&changed));
    }
}
