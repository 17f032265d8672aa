//! Tracked points: the user's points file in, one trajectory row per frame and point out.
//!
//! Convention: every coordinate is in DICOM patient space, **LPS millimetres** (+x towards
//! the patient's left, +y posterior, +z superior), the space of the CT's
//! `ImagePositionPatient`. Both files are plain comma-separated text, UTF-8, one header line,
//! no quoting (names may not contain commas or double quotes); blank lines and lines starting
//! with `#` are ignored when reading.
//!
//! * Points file (user input): header `name,x_mm,y_mm,z_mm`, then one row per point at its
//!   position in the CT (rest, i.e. at the scan's breathing state). Names are unique and
//!   non-empty; coordinates finite.
//! * Trajectories file (output): header `frame,time_s,point,rest_x_mm,rest_y_mm,rest_z_mm,
//!   moved_x_mm,moved_y_mm,moved_z_mm,dx_mm,dy_mm,dz_mm,inside_lung`, one row per (frame,
//!   point), frames in increasing order and points in the points file's order. `rest_*` is
//!   the point as given (its place in the CT), `moved_*` where it is at the frame (rest +
//!   displacement), `dx,dy,dz` the displacement, all in LPS mm written with 4 decimals
//!   (0.1 µm); `time_s` is seconds on
//!   the breathing trace's clock with 6 decimals; `inside_lung` is `true` when the point lies
//!   inside an element of the lung mesh and `false` when it was extrapolated from the
//!   nearest one. The file is written under a `.partial` name and renamed when complete, so a
//!   file with the final name is never a truncated run.

use std::collections::HashMap;
use std::fmt::Write as _;
use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};

use crate::{Error, IoContext, IoOp, Result};

/// Header line of the points file.
pub const POINTS_HEADER: &str = "name,x_mm,y_mm,z_mm";

/// Header line of the trajectories file.
pub const TRAJECTORY_HEADER: &str = "frame,time_s,point,rest_x_mm,rest_y_mm,rest_z_mm,\
    moved_x_mm,moved_y_mm,moved_z_mm,dx_mm,dy_mm,dz_mm,inside_lung";

/// Most points a points file may list (more is a sign of a wrong file, e.g. a point cloud).
pub const MAX_POINTS: usize = 10_000;

/// A named point the user wants followed, at its position in the CT.
#[derive(Debug, Clone, PartialEq)]
pub struct TrackedPoint {
    /// The user's name for it (tumour centre, carina, …), unique within a file.
    pub name: String,
    /// Position in the CT, LPS mm.
    pub rest_lps_mm: [f64; 3],
}

/// One row of a trajectories file.
#[derive(Debug, Clone, PartialEq)]
pub struct TrajectorySample {
    /// Output frame index.
    pub frame: usize,
    /// Time of the frame on the breathing trace, seconds.
    pub time_s: f64,
    /// Name of the tracked point.
    pub point: String,
    /// Position given in the points file (in the CT), LPS mm.
    pub rest_lps_mm: [f64; 3],
    /// Moved position, LPS mm.
    pub position_lps_mm: [f64; 3],
    /// Displacement from the CT position, LPS mm.
    pub displacement_mm: [f64; 3],
    /// Whether the point lies inside the lung mesh (else extrapolated from the nearest element).
    pub inside_lung: bool,
}

/// Reads a points file; errors name the file, the line and the problem.
pub fn read_points(path: &Path) -> Result<Vec<TrackedPoint>> {
    let text = std::fs::read_to_string(path).at(IoOp::Read, path)?;
    parse_points(&text).map_err(|reason| Error::Points {
        file: Some(path.to_path_buf()),
        point: None,
        reason,
    })
}

/// Parses the text of a points file; errors say `line N: problem`.
pub fn parse_points(text: &str) -> std::result::Result<Vec<TrackedPoint>, String> {
    let mut points: Vec<TrackedPoint> = Vec::new();
    let mut line_of_name: HashMap<String, usize> = HashMap::new();
    for_each_row(text, "points", POINTS_HEADER, |n, fields| {
        let name = parse_name(n, fields[0])?;
        if let Some(first) = line_of_name.get(name) {
            return Err(format!(
                "line {n}: point name {name:?} already used on line {first}"
            ));
        }
        let mut rest_lps_mm = [0.0; 3];
        for (a, v) in rest_lps_mm.iter_mut().enumerate() {
            *v = parse_finite(n, ["x_mm", "y_mm", "z_mm"][a], fields[1 + a])?;
        }
        if points.len() == MAX_POINTS {
            return Err(format!("line {n}: more than {MAX_POINTS} points"));
        }
        line_of_name.insert(name.to_string(), n);
        points.push(TrackedPoint {
            name: name.to_string(),
            rest_lps_mm,
        });
        Ok(())
    })?;
    if points.is_empty() {
        return Err("no points after the header".into());
    }
    Ok(points)
}

/// Streams trajectory rows, one frame at a time, to any writer.
#[derive(Debug)]
pub struct TrajectoryWriter<W: Write> {
    out: W,
    points: Vec<TrackedPoint>,
    last: Option<(usize, f64)>,
    /// Reused for every row so streaming does not allocate per frame.
    line: String,
    /// Where the rows go, as write failures name it.
    destination: PathBuf,
}

impl<W: Write> TrajectoryWriter<W> {
    /// Writes the header; `points` fixes the rows of every frame (names must be unique). Write
    /// failures name the destination `trajectories`; [`TrajectoryWriter::for_file`] names it.
    pub fn new(out: W, points: &[TrackedPoint]) -> Result<Self> {
        Self::for_file(out, points, Path::new("trajectories"))
    }

    /// [`TrajectoryWriter::new`] for rows going to the file at `path`, which write failures name.
    pub fn for_file(mut out: W, points: &[TrackedPoint], path: &Path) -> Result<Self> {
        let refused = |point: Option<usize>, reason: String| Error::Points {
            file: None,
            point,
            reason,
        };
        if points.is_empty() {
            return Err(refused(None, "no points to track".into()));
        }
        let mut names = std::collections::HashSet::with_capacity(points.len());
        for (i, p) in points.iter().enumerate() {
            if let Some(problem) = name_problem(&p.name) {
                return Err(refused(
                    Some(i + 1),
                    format!("name {:?}: {problem}", p.name),
                ));
            }
            if !names.insert(p.name.as_str()) {
                return Err(refused(
                    Some(i + 1),
                    format!("name {:?} is used twice", p.name),
                ));
            }
            if p.rest_lps_mm.iter().any(|v| !v.is_finite()) {
                return Err(refused(
                    Some(i + 1),
                    format!(
                        "named {:?} has a non-finite position {:?}",
                        p.name, p.rest_lps_mm
                    ),
                ));
            }
        }
        writeln!(out, "{TRAJECTORY_HEADER}").at(IoOp::Write, path)?;
        Ok(TrajectoryWriter {
            out,
            points: points.to_vec(),
            last: None,
            line: String::with_capacity(160),
            destination: path.to_path_buf(),
        })
    }

    /// Appends the rows of one frame: the displacement (LPS mm) and inside-lung flag of each
    /// point, in the order the points were given. Frames must come in increasing order, at
    /// non-decreasing finite times.
    pub fn write_frame(
        &mut self,
        frame: usize,
        time_s: f64,
        displacements_mm: &[[f64; 3]],
        inside_lung: &[bool],
    ) -> Result<()> {
        let n = self.points.len();
        let refused = |reason: String| Error::Argument {
            what: format!("trajectory frame {frame}"),
            reason,
        };
        if displacements_mm.len() != n || inside_lung.len() != n {
            return Err(refused(format!(
                "{} displacements and {} inside flags for {n} points",
                displacements_mm.len(),
                inside_lung.len()
            )));
        }
        if !time_s.is_finite() {
            return Err(refused(format!("time {time_s} s is not finite")));
        }
        if let Some((last_frame, last_time_s)) = self.last {
            if frame <= last_frame || time_s < last_time_s {
                return Err(refused(format!(
                    "frame {frame} at {time_s} s comes after frame {last_frame} at \
                     {last_time_s} s: frames must increase in number and time"
                )));
            }
        }
        if let Some((p, d)) = self
            .points
            .iter()
            .zip(displacements_mm)
            .find(|(_, d)| d.iter().any(|v| !v.is_finite()))
        {
            return Err(refused(format!(
                "point {:?} has a non-finite displacement {d:?}",
                p.name
            )));
        }
        for ((p, d), inside) in self.points.iter().zip(displacements_mm).zip(inside_lung) {
            let x = p.rest_lps_mm;
            self.line.clear();
            // Writing into a String cannot fail.
            let _ = writeln!(
                self.line,
                "{frame},{time_s:.6},{},{:.4},{:.4},{:.4},{:.4},{:.4},{:.4},{:.4},{:.4},{:.4},\
                 {inside}",
                p.name,
                x[0],
                x[1],
                x[2],
                x[0] + d[0],
                x[1] + d[1],
                x[2] + d[2],
                d[0],
                d[1],
                d[2],
            );
            self.out
                .write_all(self.line.as_bytes())
                .at(IoOp::Write, &self.destination)?;
        }
        self.last = Some((frame, time_s));
        Ok(())
    }

    /// Flushes and returns the underlying writer.
    pub fn finish(mut self) -> Result<W> {
        self.out.flush().at(IoOp::Write, &self.destination)?;
        Ok(self.out)
    }
}

/// A trajectories file being written: rows go to `<path>.partial`, renamed to `path` by
/// [`TrajectoryFile::finish`].
#[derive(Debug)]
pub struct TrajectoryFile {
    writer: TrajectoryWriter<BufWriter<File>>,
    partial: PathBuf,
    path: PathBuf,
}

impl TrajectoryFile {
    /// Starts the file (header written to the `.partial` sibling).
    pub fn create(path: &Path, points: &[TrackedPoint]) -> Result<Self> {
        let mut name = path.as_os_str().to_owned();
        name.push(".partial");
        let partial = PathBuf::from(name);
        let file = File::create(&partial).at(IoOp::Create, &partial)?;
        Ok(TrajectoryFile {
            writer: TrajectoryWriter::for_file(BufWriter::new(file), points, &partial)?,
            partial,
            path: path.to_path_buf(),
        })
    }

    /// Appends one frame (see [`TrajectoryWriter::write_frame`]).
    pub fn write_frame(
        &mut self,
        frame: usize,
        time_s: f64,
        displacements_mm: &[[f64; 3]],
        inside_lung: &[bool],
    ) -> Result<()> {
        self.writer
            .write_frame(frame, time_s, displacements_mm, inside_lung)
    }

    /// Flushes, syncs and gives the file its final name, which it returns.
    pub fn finish(self) -> Result<PathBuf> {
        let file = self
            .writer
            .finish()?
            .into_inner()
            .map_err(|e| Error::io(IoOp::Write, &self.partial, e.into_error()))?;
        file.sync_all().at(IoOp::Sync, &self.partial)?;
        std::fs::rename(&self.partial, &self.path).at(IoOp::Replace, &self.path)?;
        Ok(self.path)
    }
}

/// Reads a trajectories file; errors name the file, the line and the problem.
pub fn read_trajectories(path: &Path) -> Result<Vec<TrajectorySample>> {
    let text = std::fs::read_to_string(path).at(IoOp::Read, path)?;
    parse_trajectories(&text).map_err(|reason| Error::Format {
        path: path.to_path_buf(),
        reason,
    })
}

/// Parses the text of a trajectories file; errors say `line N: problem`.
pub fn parse_trajectories(text: &str) -> std::result::Result<Vec<TrajectorySample>, String> {
    let mut samples = Vec::new();
    for_each_row(text, "trajectories", TRAJECTORY_HEADER, |n, f| {
        let frame = f[0]
            .parse::<usize>()
            .map_err(|_| format!("line {n}: frame {:?} is not a non-negative integer", f[0]))?;
        let time_s = parse_finite(n, "time_s", f[1])?;
        let point = parse_name(n, f[2])?.to_string();
        let mut v = [0.0; 9];
        let columns = TRAJECTORY_HEADER.split(',').skip(3);
        for ((value, column), field) in v.iter_mut().zip(columns).zip(&f[3..12]) {
            *value = parse_finite(n, column, field)?;
        }
        let inside_lung = match f[12] {
            "true" | "1" => true,
            "false" | "0" => false,
            other => return Err(format!("line {n}: inside_lung {other:?} is not true/false")),
        };
        samples.push(TrajectorySample {
            frame,
            time_s,
            point,
            rest_lps_mm: [v[0], v[1], v[2]],
            position_lps_mm: [v[3], v[4], v[5]],
            displacement_mm: [v[6], v[7], v[8]],
            inside_lung,
        });
        Ok(())
    })?;
    Ok(samples)
}

/// Checks the header of a `kind` CSV text, then hands `row` the 1-based line number and
/// trimmed fields of every data row, each row having exactly the header's column count.
fn for_each_row<'t>(
    text: &'t str,
    kind: &str,
    header: &str,
    mut row: impl FnMut(usize, &[&'t str]) -> std::result::Result<(), String>,
) -> std::result::Result<(), String> {
    let mut lines = content_lines(text);
    let Some((n, found)) = lines.next() else {
        return Err(format!("empty {kind} file: expected the header `{header}`"));
    };
    check_header(n, found, header)?;
    let columns = header.split(',').count();
    // One buffer for every row: a long file does not allocate per line.
    let mut fields: Vec<&'t str> = Vec::with_capacity(columns);
    for (n, line) in lines {
        fields.clear();
        fields.extend(line.split(',').map(str::trim));
        if fields.len() != columns {
            return Err(format!(
                "line {n}: {} fields, expected {columns} ({header})",
                fields.len()
            ));
        }
        row(n, &fields)?;
    }
    Ok(())
}

/// Non-blank, non-comment lines with their 1-based line numbers (BOM and CR removed).
fn content_lines(text: &str) -> impl Iterator<Item = (usize, &str)> {
    text.strip_prefix('\u{feff}')
        .unwrap_or(text)
        .lines()
        .enumerate()
        .map(|(i, l)| (i + 1, l.trim()))
        .filter(|(_, l)| !l.is_empty() && !l.starts_with('#'))
}

fn check_header(n: usize, found: &str, expected: &str) -> std::result::Result<(), String> {
    let columns: Vec<String> = found
        .split(',')
        .map(|c| c.trim().to_ascii_lowercase())
        .collect();
    if columns.iter().map(String::as_str).eq(expected.split(',')) {
        Ok(())
    } else {
        Err(format!(
            "line {n}: header `{expected}` required (LPS millimetres), found `{found}`"
        ))
    }
}

fn parse_name(n: usize, name: &str) -> std::result::Result<&str, String> {
    match name_problem(name) {
        Some(problem) => Err(format!("line {n}: point name {name:?}: {problem}")),
        None => Ok(name),
    }
}

/// Why a point name cannot be written unquoted in a CSV cell, if it cannot.
fn name_problem(name: &str) -> Option<&'static str> {
    if name.trim().is_empty() {
        Some("empty")
    } else if name.trim() != name {
        Some("leading or trailing spaces")
    } else if name.chars().any(|c| c == '"' || c == ',' || c.is_control()) {
        Some("contains a quote, comma or control character")
    } else {
        None
    }
}

fn parse_finite(n: usize, column: &str, text: &str) -> std::result::Result<f64, String> {
    match text.parse::<f64>() {
        Ok(v) if v.is_finite() => Ok(v),
        Ok(_) => Err(format!("line {n}: {column} {text:?} is not finite")),
        Err(_) => Err(format!("line {n}: {column} {text:?} is not a number")),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_points_file_with_comments_blank_lines_and_crlf_is_read() {
        let text = "\u{feff}# tumour and carina\r\nname, x_mm, y_mm, z_mm\r\n\r\ntumour,-42.5,10,-120.25\r\ncarina,0,-5e1,-60\r\n";
        let points = parse_points(text).unwrap();
        assert_eq!(points.len(), 2);
        assert_eq!(points[0].name, "tumour");
        assert_eq!(points[0].rest_lps_mm, [-42.5, 10.0, -120.25]);
        assert_eq!(points[1].rest_lps_mm, [0.0, -50.0, -60.0]);
    }

    #[test]
    fn points_file_errors_name_the_line_and_the_problem() {
        let cases = [
            ("", "empty points file"),
            (
                "tumour,1,2,3\n",
                "line 1: header `name,x_mm,y_mm,z_mm` required",
            ),
            ("name,x,y,z\na,1,2,3\n", "line 1: header"),
            ("name,x_mm,y_mm,z_mm\n", "no points"),
            (
                "name,x_mm,y_mm,z_mm\na,1,2\n",
                "line 2: 3 fields, expected 4",
            ),
            (
                "name,x_mm,y_mm,z_mm\na,1,2,3\n\na,4,5,6\n",
                "line 4: point name \"a\" already used on line 2",
            ),
            (
                "name,x_mm,y_mm,z_mm\n,1,2,3\n",
                "line 2: point name \"\": empty",
            ),
            (
                "name,x_mm,y_mm,z_mm\na,1,nan,3\n",
                "line 2: y_mm \"nan\" is not finite",
            ),
            (
                "name,x_mm,y_mm,z_mm\na,1,2,3mm\n",
                "line 2: z_mm \"3mm\" is not a number",
            ),
            ("name,x_mm,y_mm,z_mm\n\"a\",1,2,3\n", "line 2: point name"),
        ];
        for (text, expected) in cases {
            let e = parse_points(text).unwrap_err();
            assert!(e.contains(expected), "{text:?}: {e}");
        }
    }

    #[test]
    fn trajectories_file_errors_name_the_line_and_the_problem() {
        let row = "0,0.000000,p,1,2,3,1.5,2,3,0.5,0,0,true";
        let cases = [
            (String::new(), "empty trajectories file".to_string()),
            (format!("{row}\n"), "line 1: header".to_string()),
            (
                format!("{TRAJECTORY_HEADER}\n# note\n0,0,p,1,2,3\n"),
                "line 3: 6 fields, expected 13".to_string(),
            ),
            (
                format!("{TRAJECTORY_HEADER}\n{row}\n0,0,p,1,2,3,1,2,3,0,0,0,maybe\n"),
                "line 3: inside_lung \"maybe\"".to_string(),
            ),
            (
                format!("{TRAJECTORY_HEADER}\n0,0,p,1,2,3,1,x,3,0,0,0,true\n"),
                "line 2: moved_y_mm \"x\"".to_string(),
            ),
        ];
        for (text, expected) in &cases {
            let e = parse_trajectories(text).unwrap_err();
            assert!(e.contains(expected.as_str()), "{text:?}: {e}");
        }
        let crlf = format!("\u{feff}{TRAJECTORY_HEADER}\r\n\r\n{row}\r\n");
        let samples = parse_trajectories(&crlf).unwrap();
        assert_eq!(samples.len(), 1);
        assert_eq!(samples[0].rest_lps_mm, [1.0, 2.0, 3.0]);
        assert_eq!(samples[0].position_lps_mm, [1.5, 2.0, 3.0]);
        assert_eq!(samples[0].displacement_mm, [0.5, 0.0, 0.0]);
    }

    #[test]
    fn the_writer_refuses_inconsistent_frames() {
        let points = [TrackedPoint {
            name: "p".into(),
            rest_lps_mm: [0.0; 3],
        }];
        let mut w = TrajectoryWriter::new(Vec::new(), &points).unwrap();
        w.write_frame(0, 0.0, &[[0.0; 3]], &[true]).unwrap();
        assert!(w.write_frame(0, 0.5, &[[0.0; 3]], &[true]).is_err());
        assert!(w.write_frame(1, -0.5, &[[0.0; 3]], &[true]).is_err());
        assert!(w.write_frame(1, 0.5, &[[0.0; 3]; 2], &[true; 2]).is_err());
        let e = w
            .write_frame(1, 0.5, &[[f64::NAN, 0.0, 0.0]], &[true])
            .unwrap_err();
        assert!(e.to_string().contains("point \"p\""), "{e}");
        w.write_frame(1, 0.5, &[[0.0, 0.0, -1.0]], &[false])
            .unwrap();
        let text = String::from_utf8(w.finish().unwrap()).unwrap();
        assert_eq!(text.lines().count(), 3, "{text}");
        let dup = [points[0].clone(), points[0].clone()];
        assert!(TrajectoryWriter::new(Vec::new(), &dup).is_err());
        let comma = [TrackedPoint {
            name: "a,b".into(),
            rest_lps_mm: [0.0; 3],
        }];
        let e = TrajectoryWriter::new(Vec::new(), &comma).unwrap_err();
        assert!(
            e.to_string()
                .contains("point 1 name \"a,b\": contains a quote"),
            "{e}"
        );
    }
}
