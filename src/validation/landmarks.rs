//! Landmark pairs of a 4D-CT, the same points at every phase, in the two forms clinics and
//! the public DIR-Lab data use:
//!
//! * **DIR-Lab text files**: a folder with one `.txt` file per phase, taken in name order
//!   (numbers compared as numbers) and paired with the phases in their order; each non-empty
//!   line is one point, `x y z` (whitespace- or comma-separated), the 1-based voxel indices of
//!   the point in that phase's image as read (i, j, k of the crate's grid; for a DICOM series
//!   k grows along the slice normal). Fractional indices are accepted. Line n of every file is
//!   the same point, so every file must have the same count.
//! * **CSV in LPS millimetres**: one file, a header naming the columns `phase`, `point`,
//!   `x_mm`, `y_mm`, `z_mm` (any order, case-insensitive; `id`/`landmark` for `point` and
//!   `x`/`y`/`z` are accepted), one row per point and phase; `phase` is a phase name or its
//!   0-based index in phase order, `point` any identifier; every phase must list the same
//!   points.
//!
//! Refusals name the file, the 1-based line and the value at fault (as
//! [`Error::Points`]): a line that is not three numbers, an index or position outside the
//! image, a count that differs between phases, an unknown phase, a point missing at a phase.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use nalgebra::Vector3;
use serde::Serialize;

use crate::ingest::four_dct::{find_phase, natural_cmp, PhaseSource};
use crate::volume::VolumeGeometry;
use crate::{Error, IoContext, IoOp, Result};

/// Largest landmark file read, bytes (DIR-Lab's 300 points are under 4 kB per phase).
const MAX_LANDMARK_FILE_BYTES: u64 = 16 << 20;

/// Where the landmarks come from.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
#[serde(rename_all = "kebab-case", tag = "format", content = "path")]
pub enum LandmarkInput {
    /// A folder of DIR-Lab text files, one per phase.
    DirLab(PathBuf),
    /// One CSV file in LPS millimetres.
    Csv(PathBuf),
}

impl LandmarkInput {
    /// A folder is DIR-Lab text files, a file is CSV.
    pub fn detect(path: &Path) -> Result<LandmarkInput> {
        let meta = std::fs::metadata(path).at(IoOp::Open, path)?;
        Ok(if meta.is_dir() {
            LandmarkInput::DirLab(path.to_path_buf())
        } else {
            LandmarkInput::Csv(path.to_path_buf())
        })
    }
}

/// The landmarks of every phase, LPS mm, paired by position in each list.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct PhaseLandmarks {
    /// The file each phase's points came from (the CSV for every phase).
    pub files: Vec<PathBuf>,
    /// The points' identifiers (line numbers for DIR-Lab files).
    pub names: Vec<String>,
    /// `points[phase][point]`, LPS mm.
    pub points: Vec<Vec<[f64; 3]>>,
}

/// Reads the landmarks of `phases`, all on `geometry`, from `input`.
pub fn read_landmarks(
    input: &LandmarkInput,
    phases: &[PhaseSource],
    geometry: &VolumeGeometry,
) -> Result<PhaseLandmarks> {
    match input {
        LandmarkInput::DirLab(dir) => read_dirlab_folder(dir, phases, geometry),
        LandmarkInput::Csv(file) => read_landmark_csv(file, phases, geometry),
    }
}

fn refuse(file: &Path, line: Option<usize>, reason: String) -> Error {
    Error::Points {
        file: Some(file.to_path_buf()),
        point: line,
        reason,
    }
}

fn read_text(path: &Path) -> Result<String> {
    let meta = std::fs::metadata(path).at(IoOp::Open, path)?;
    if meta.len() > MAX_LANDMARK_FILE_BYTES {
        return Err(refuse(
            path,
            None,
            format!(
                "{} bytes; a landmark file is at most {MAX_LANDMARK_FILE_BYTES}",
                meta.len()
            ),
        ));
    }
    let bytes = std::fs::read(path).at(IoOp::Read, path)?;
    String::from_utf8(bytes).map_err(|_| refuse(path, None, "not UTF-8 text".to_string()))
}

/// Reads a folder of DIR-Lab files, the k-th in name order for the k-th phase.
pub fn read_dirlab_folder(
    dir: &Path,
    phases: &[PhaseSource],
    geometry: &VolumeGeometry,
) -> Result<PhaseLandmarks> {
    let mut files = Vec::new();
    for entry in std::fs::read_dir(dir).at(IoOp::List, dir)? {
        let path = entry.at(IoOp::List, dir)?.path();
        let name = path.file_name().map(|n| n.to_string_lossy().into_owned());
        if path.is_file()
            && name
                .as_deref()
                .is_some_and(|n| !n.starts_with('.') && n.to_ascii_lowercase().ends_with(".txt"))
        {
            files.push(path);
        }
    }
    files.sort_by(|a, b| natural_cmp(&a.to_string_lossy(), &b.to_string_lossy()));
    if files.len() != phases.len() {
        return Err(refuse(
            dir,
            None,
            format!(
                "{} DIR-Lab .txt files for {} phases; give one file per phase (they pair with \
                 the phases in name order)",
                files.len(),
                phases.len()
            ),
        ));
    }
    let mut points: Vec<Vec<[f64; 3]>> = Vec::with_capacity(files.len());
    for (k, file) in files.iter().enumerate() {
        let list = parse_dirlab(file, &read_text(file)?, geometry)?;
        if k > 0 && list.len() != points[0].len() {
            let first: &Vec<[f64; 3]> = &points[0];
            return Err(refuse(
                file,
                Some(list.len().min(first.len()) + 1),
                format!(
                    "{} points for phase {:?}, but {} has {} for phase {:?}: DIR-Lab files pair \
                     points by line, every phase needs the same count",
                    list.len(),
                    phases[k].name,
                    files[0].display(),
                    first.len(),
                    phases[0].name
                ),
            ));
        }
        points.push(list);
    }
    let names = (1..=points[0].len()).map(|n| n.to_string()).collect();
    Ok(PhaseLandmarks {
        files,
        names,
        points,
    })
}

/// Parses one DIR-Lab file: `x y z` 1-based voxel indices per line, into LPS mm.
pub fn parse_dirlab(file: &Path, text: &str, geometry: &VolumeGeometry) -> Result<Vec<[f64; 3]>> {
    let mut points = Vec::new();
    for (n, line) in text.lines().enumerate() {
        let line_no = n + 1;
        let fields: Vec<&str> = line
            .split(|c: char| c.is_whitespace() || c == ',')
            .filter(|f| !f.is_empty())
            .collect();
        if fields.is_empty() {
            continue;
        }
        if fields.len() != 3 {
            return Err(refuse(
                file,
                Some(line_no),
                format!(
                    "line {line_no}: {:?} has {} values; a DIR-Lab line is `x y z`",
                    line.trim(),
                    fields.len()
                ),
            ));
        }
        let mut index = [0.0; 3];
        for (a, f) in fields.iter().enumerate() {
            let v: f64 = f.parse().map_err(|_| {
                refuse(
                    file,
                    Some(line_no),
                    format!("line {line_no}: {f:?} is not a number"),
                )
            })?;
            let n_axis = geometry.dims[a] as f64;
            // Voxel centres are 1…n; half a voxel beyond is still inside the image.
            if !v.is_finite() || v < 0.5 || v > n_axis + 0.5 {
                return Err(refuse(
                    file,
                    Some(line_no),
                    format!(
                        "line {line_no}: {} index {v} is outside the image (1–{} along that \
                         axis)",
                        ["x", "y", "z"][a],
                        geometry.dims[a]
                    ),
                ));
            }
            index[a] = v - 1.0;
        }
        let p = geometry.voxel_to_lps_mm(Vector3::from(index));
        points.push([p.x, p.y, p.z]);
    }
    if points.is_empty() {
        return Err(refuse(file, None, "no points".to_string()));
    }
    Ok(points)
}

/// Reads a landmark CSV in LPS mm.
pub fn read_landmark_csv(
    file: &Path,
    phases: &[PhaseSource],
    geometry: &VolumeGeometry,
) -> Result<PhaseLandmarks> {
    let text = read_text(file)?;
    let mut lines = text
        .lines()
        .enumerate()
        .filter(|(_, l)| !l.trim().is_empty());
    let Some((_, header)) = lines.next() else {
        return Err(refuse(file, None, "empty file".to_string()));
    };
    let columns: Vec<String> = header
        .split(',')
        .map(|c| c.trim().to_ascii_lowercase())
        .collect();
    let find = |names: &[&str]| columns.iter().position(|c| names.contains(&c.as_str()));
    let wanted = [
        ("phase", find(&["phase"])),
        ("point", find(&["point", "id", "landmark"])),
        ("x_mm", find(&["x_mm", "x"])),
        ("y_mm", find(&["y_mm", "y"])),
        ("z_mm", find(&["z_mm", "z"])),
    ];
    let mut col = [0usize; 5];
    for (k, (name, found)) in wanted.iter().enumerate() {
        col[k] = found.ok_or_else(|| {
            refuse(
                file,
                Some(1),
                format!(
                    "line 1: no column {name:?} in the header {header:?}; the header names \
                     phase,point,x_mm,y_mm,z_mm"
                ),
            )
        })?;
    }
    // Points per phase by identifier, and the identifiers in order of first appearance.
    let mut per_phase: Vec<BTreeMap<String, ([f64; 3], usize)>> =
        vec![BTreeMap::new(); phases.len()];
    let mut order: Vec<String> = Vec::new();
    let lo = -0.5;
    for (n, line) in lines {
        let line_no = n + 1;
        let fields: Vec<&str> = line.split(',').map(str::trim).collect();
        if fields.len() != columns.len() {
            return Err(refuse(
                file,
                Some(line_no),
                format!(
                    "line {line_no}: {} fields for a header of {}",
                    fields.len(),
                    columns.len()
                ),
            ));
        }
        let phase_field = fields[col[0]];
        let phase = find_phase(phases, phase_field).map_err(|reason| {
            refuse(
                file,
                Some(line_no),
                format!("line {line_no}: phase {reason}"),
            )
        })?;
        let mut p = [0.0; 3];
        for a in 0..3 {
            let f = fields[col[2 + a]];
            p[a] = f
                .parse::<f64>()
                .ok()
                .filter(|v| v.is_finite())
                .ok_or_else(|| {
                    refuse(
                        file,
                        Some(line_no),
                        format!("line {line_no}: {f:?} is not a finite number of millimetres"),
                    )
                })?;
        }
        let v = geometry.lps_mm_to_voxel(Vector3::from(p));
        if (0..3).any(|a| v[a] < lo || v[a] > geometry.dims[a] as f64 - 0.5) {
            return Err(refuse(
                file,
                Some(line_no),
                format!(
                    "line {line_no}: point ({}, {}, {}) mm is outside the image of phase {:?} \
                     (voxel index {:.1}, {:.1}, {:.1} of {:?})",
                    p[0], p[1], p[2], phases[phase].name, v[0], v[1], v[2], geometry.dims
                ),
            ));
        }
        let id = fields[col[1]].to_string();
        if per_phase[phase].insert(id.clone(), (p, line_no)).is_some() {
            return Err(refuse(
                file,
                Some(line_no),
                format!(
                    "line {line_no}: point {id:?} is listed twice for phase {:?}",
                    phases[phase].name
                ),
            ));
        }
        if !order.contains(&id) {
            order.push(id);
        }
    }
    if order.is_empty() {
        return Err(refuse(file, None, "no points".to_string()));
    }
    let mut points = Vec::with_capacity(phases.len());
    for (k, map) in per_phase.iter().enumerate() {
        let mut list = Vec::with_capacity(order.len());
        for id in &order {
            let Some(&(p, _)) = map.get(id) else {
                return Err(refuse(
                    file,
                    None,
                    format!(
                        "point {id:?} has no row for phase {:?} ({} of {} points listed there); \
                         every phase must list the same points",
                        phases[k].name,
                        map.len(),
                        order.len()
                    ),
                ));
            };
            list.push(p);
        }
        points.push(list);
    }
    Ok(PhaseLandmarks {
        files: vec![file.to_path_buf(); phases.len()],
        names: order,
        points,
    })
}
