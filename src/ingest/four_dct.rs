//! A 4D-CT as its phases: a folder of phase sub-folders (each a DICOM series), a zip of such
//! sub-folders, or a folder of one NIfTI or NRRD file per phase. Phases are named by their
//! sub-folder or file stem and ordered by name with numbers compared as numbers (`T5` before
//! `T10`), which is the breathing order of the usual names (`T00`…`T90`, `0%`…`90%`,
//! `phase-1`…`phase-10`).

use std::cmp::Ordering;
use std::path::{Path, PathBuf};

use serde::Serialize;

use super::scan::{classify_header, ScanFormat};
use crate::formats::archive::{looks_like_zip, read_zip_file, ArchiveLimits};
use crate::volume::VolumeGeometry;
use crate::{Error, IoContext, IoOp, Result};

/// How the phases of a 4D-CT were laid out.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "kebab-case")]
pub enum FourDctLayout {
    /// A folder of phase sub-folders, each a DICOM series.
    DicomFolders,
    /// A zip whose top-level folders are the phases' DICOM series.
    DicomZip,
    /// A folder of one NIfTI or NRRD file per phase.
    ImageFiles,
}

/// One phase of a 4D-CT: its name and where its CT is (a DICOM folder or an image file).
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct PhaseSource {
    /// The sub-folder's name or the file's stem (`T00` for `T00.nii.gz`).
    pub name: String,
    /// What [`crate::ingest::scan::load_ct`] reads for it.
    pub path: PathBuf,
}

/// The index of the phase of `phases` named `asked`, else whose 0-based index `asked` is; the
/// reason, listing the names, when it is neither.
pub fn find_phase(phases: &[PhaseSource], asked: &str) -> std::result::Result<usize, String> {
    phases
        .iter()
        .position(|p| p.name == asked)
        .or_else(|| asked.parse::<usize>().ok().filter(|&i| i < phases.len()))
        .ok_or_else(|| {
            format!(
                "{asked:?} is neither a phase name ({}) nor an index below {}",
                phases
                    .iter()
                    .map(|p| p.name.as_str())
                    .collect::<Vec<_>>()
                    .join(", "),
                phases.len()
            )
        })
}

/// The phases of a 4D-CT, in breathing order.
#[derive(Debug)]
pub struct FourDctPhases {
    /// How they were laid out.
    pub layout: FourDctLayout,
    /// The phases.
    pub phases: Vec<PhaseSource>,
    /// The folder a zip was unpacked into, removed when this is dropped.
    unpacked: Option<PathBuf>,
}

impl Drop for FourDctPhases {
    fn drop(&mut self) {
        if let Some(dir) = &self.unpacked {
            let _ = std::fs::remove_dir_all(dir);
        }
    }
}

/// Fewest phases a 4D-CT must have.
pub const MIN_PHASES: usize = 2;
/// Most phases accepted (scanners bin 8 to 25; beyond, the input is not a 4D-CT).
pub const MAX_PHASES: usize = 100;

/// Finds the phases of the 4D-CT at `input`. A zip is unpacked into a fresh folder under
/// `scratch` (removed when the result is dropped), within the limits of any zip the crate
/// reads. Refused, naming `input`: fewer than [`MIN_PHASES`] or more than [`MAX_PHASES`]
/// phases, a folder holding both phase folders and image files, two phases of one name.
pub fn list_four_dct_phases(input: &Path, scratch: &Path) -> Result<FourDctPhases> {
    let meta = std::fs::metadata(input).at(IoOp::Open, input)?;
    let (layout, phases, unpacked) = if meta.is_dir() {
        let (layout, phases) = phases_of_folder(input)?;
        (layout, phases, None)
    } else if looks_like_zip(input) {
        let dir = unpack_zip(input, scratch)?;
        // The unpacked folder is removed on every path out, by the guard or by the result.
        let guard = FourDctPhases {
            layout: FourDctLayout::DicomZip,
            phases: Vec::new(),
            unpacked: Some(dir.clone()),
        };
        let (mut layout, mut phases) = phases_of_folder(&dir)?;
        // A zip of one top folder holding the phase folders (what zipping a folder makes):
        // its phases are one level down.
        if layout == FourDctLayout::DicomFolders && phases.len() == 1 {
            let (l, p) = phases_of_folder(&phases[0].path)?;
            if l == FourDctLayout::DicomFolders && p.len() >= MIN_PHASES {
                (layout, phases) = (l, p);
            }
        }
        if layout != FourDctLayout::DicomFolders {
            return Err(Error::scan(
                input,
                "the zip's top level holds image files; a 4D-CT zip holds one folder per phase, \
                 each a DICOM series",
            ));
        }
        let mut result = guard;
        result.phases = phases;
        return check_count(input, result);
    } else {
        return Err(Error::scan(
            input,
            "a 4D-CT is a folder of phase folders (DICOM), a zip of them, or a folder of one \
             NIfTI or NRRD file per phase; this is a single file",
        ));
    };
    check_count(
        input,
        FourDctPhases {
            layout,
            phases,
            unpacked,
        },
    )
}

fn check_count(input: &Path, phases: FourDctPhases) -> Result<FourDctPhases> {
    let n = phases.phases.len();
    if !(MIN_PHASES..=MAX_PHASES).contains(&n) {
        return Err(Error::scan(
            input,
            format!(
                "{n} phases found ({}); a 4D-CT has {MIN_PHASES} to {MAX_PHASES}: phase \
                 sub-folders each holding a DICOM series, or one NIfTI/NRRD file per phase",
                phases
                    .phases
                    .iter()
                    .map(|p| p.name.as_str())
                    .collect::<Vec<_>>()
                    .join(", ")
            ),
        ));
    }
    for pair in phases.phases.windows(2) {
        if pair[0].name == pair[1].name {
            return Err(Error::scan(
                input,
                format!(
                    "two phases are named {:?} ({} and {})",
                    pair[0].name,
                    pair[0].path.display(),
                    pair[1].path.display()
                ),
            ));
        }
    }
    Ok(phases)
}

/// The phases of a folder: its sub-folders (DICOM series) or its NIfTI/NRRD files; hidden
/// entries and other files (landmarks, notes) are ignored.
fn phases_of_folder(dir: &Path) -> Result<(FourDctLayout, Vec<PhaseSource>)> {
    let mut folders = Vec::new();
    let mut images = Vec::new();
    for entry in std::fs::read_dir(dir).at(IoOp::List, dir)? {
        let entry = entry.at(IoOp::List, dir)?;
        let name = entry.file_name().to_string_lossy().into_owned();
        if name.starts_with('.') {
            continue;
        }
        let path = entry.path();
        let meta = std::fs::metadata(&path).at(IoOp::Metadata, &path)?;
        if meta.is_dir() {
            folders.push(PhaseSource { name, path });
        } else if is_volume_file(&path)? {
            images.push(PhaseSource {
                name: image_stem(&name),
                path,
            });
        }
    }
    let (layout, mut phases) = match (folders.is_empty(), images.is_empty()) {
        (false, true) => (FourDctLayout::DicomFolders, folders),
        (true, false) => (FourDctLayout::ImageFiles, images),
        (true, true) => (FourDctLayout::ImageFiles, Vec::new()),
        (false, false) => {
            return Err(Error::scan(
                dir,
                format!(
                    "holds both phase folders ({}) and image files ({}); keep one layout",
                    folders[0].name, images[0].name
                ),
            ))
        }
    };
    phases.sort_by(|a, b| natural_cmp(&a.name, &b.name));
    Ok((layout, phases))
}

/// Whether a file is a NIfTI or NRRD volume, by content.
fn is_volume_file(path: &Path) -> Result<bool> {
    use std::io::Read;
    let mut head = Vec::with_capacity(544);
    std::fs::File::open(path)
        .and_then(|f| f.take(544).read_to_end(&mut head))
        .at(IoOp::Read, path)?;
    Ok(matches!(
        classify_header(&head),
        Some(ScanFormat::Nifti | ScanFormat::Nrrd)
    ))
}

/// A file name without its volume extension (`.nii.gz`, `.nii`, `.nrrd`, `.nhdr`).
fn image_stem(name: &str) -> String {
    for ext in [".nii.gz", ".nii", ".nrrd", ".nhdr"] {
        if let Some(stem) = name.strip_suffix(ext) {
            return stem.to_string();
        }
    }
    name.to_string()
}

/// Compares names with runs of digits compared as numbers (`T5` < `T10`).
pub fn natural_cmp(a: &str, b: &str) -> Ordering {
    let (mut a, mut b) = (a, b);
    loop {
        match (a.chars().next(), b.chars().next()) {
            (None, None) => return Ordering::Equal,
            (None, Some(_)) => return Ordering::Less,
            (Some(_), None) => return Ordering::Greater,
            (Some(x), Some(y)) if x.is_ascii_digit() && y.is_ascii_digit() => {
                let na = a.find(|c: char| !c.is_ascii_digit()).unwrap_or(a.len());
                let nb = b.find(|c: char| !c.is_ascii_digit()).unwrap_or(b.len());
                let (da, db) = (
                    a[..na].trim_start_matches('0'),
                    b[..nb].trim_start_matches('0'),
                );
                let order = da.len().cmp(&db.len()).then_with(|| da.cmp(db));
                if order != Ordering::Equal {
                    return order;
                }
                a = &a[na..];
                b = &b[nb..];
            }
            (Some(x), Some(y)) => {
                if x != y {
                    return x.cmp(&y);
                }
                a = &a[x.len_utf8()..];
                b = &b[y.len_utf8()..];
            }
        }
    }
}

/// Unpacks a zip into a fresh folder under `scratch`; entry names that would leave it
/// (absolute, `..`) are refused.
fn unpack_zip(zip: &Path, scratch: &Path) -> Result<PathBuf> {
    let entries = read_zip_file(zip, &ArchiveLimits::default())?;
    let dir = scratch.join(format!(".lungmotion-4dct-{}", std::process::id()));
    if dir.exists() {
        std::fs::remove_dir_all(&dir).at(IoOp::Remove, &dir)?;
    }
    std::fs::create_dir_all(&dir).at(IoOp::CreateDir, &dir)?;
    let result = (|| {
        for entry in &entries {
            let parts: Vec<&str> = entry.name.split('/').filter(|p| !p.is_empty()).collect();
            if parts.is_empty() || parts.iter().any(|p| *p == ".." || p.contains('\\')) {
                return Err(Error::scan(
                    zip,
                    format!("entry {:?} would leave the archive's folder", entry.name),
                ));
            }
            let path = parts.iter().fold(dir.clone(), |p, part| p.join(part));
            if let Some(parent) = path.parent() {
                std::fs::create_dir_all(parent).at(IoOp::CreateDir, parent)?;
            }
            std::fs::write(&path, &entry.data).at(IoOp::Write, &path)?;
        }
        Ok(())
    })();
    if let Err(e) = result {
        let _ = std::fs::remove_dir_all(&dir);
        return Err(e);
    }
    Ok(dir)
}

/// Refuses a phase whose grid differs from the first phase's, naming both phases and what
/// differs: every phase of a 4D-CT must share one grid for masks and landmarks to compare.
pub fn check_same_grid(
    first: (&PhaseSource, &VolumeGeometry),
    other: (&PhaseSource, &VolumeGeometry),
) -> Result<()> {
    let (a, ga) = first;
    let (b, gb) = other;
    if ga.same_grid(gb, 1e-3) {
        return Ok(());
    }
    Err(Error::scan(
        &b.path,
        format!(
            "phase {:?} is on another grid than phase {:?}: dims {:?} against {:?}, spacing \
             {:?} against {:?} mm, origin {:?} against {:?} mm; every phase of a 4D-CT must \
             share one grid",
            b.name,
            a.name,
            gb.dims,
            ga.dims,
            gb.spacing_mm,
            ga.spacing_mm,
            gb.origin_lps_mm,
            ga.origin_lps_mm
        ),
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_sort_in_breathing_order() {
        let mut names = vec!["T10", "T5", "T00", "phase-10", "phase-2", "T50"];
        names.sort_by(|a, b| natural_cmp(a, b));
        assert_eq!(names, ["T00", "T5", "T10", "T50", "phase-2", "phase-10"]);
        assert_eq!(image_stem("T00.nii.gz"), "T00");
        assert_eq!(image_stem("ex.nrrd"), "ex");
    }
}
