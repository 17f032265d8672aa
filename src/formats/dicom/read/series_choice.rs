//! Which series of a folder is read: the one the user names (by SeriesInstanceUID, series
//! number or description), else the only CT volume; otherwise an error that lists them all.

use std::collections::BTreeMap;
use std::fmt;
use std::str::FromStr;

use dicom_core::Tag;
use dicom_dictionary_std::tags;
use serde::{Deserialize, Serialize};

use super::{text, DicomReadOptions, ParsedFile};
use crate::{Error, Result};

/// How the error of a folder with several series says to choose one.
pub const HOW_TO_CHOOSE: &str = "choose one by its UID, number or description: `--series \
     <choice>` on the command line, `series = \"<choice>\"` in the run configuration, or \
     `?series=<choice>` on POST /v1/scans (choice: `uid:<UID>`, `number:<N>`, \
     `description:<text>`, or the bare value)";

/// A series named by the user.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
#[serde(try_from = "String", into = "String")]
pub enum SeriesChoice {
    /// SeriesInstanceUID (0020,000E), exactly.
    Uid(String),
    /// SeriesNumber (0020,0011).
    Number(i64),
    /// SeriesDescription (0008,103E), ignoring case and surrounding spaces.
    Description(String),
}

impl FromStr for SeriesChoice {
    type Err = Error;

    /// `uid:<UID>`, `number:<N>`, `description:<text>`; a bare value is a number when it is
    /// all digits, a UID when digits and dots, a description otherwise.
    fn from_str(s: &str) -> Result<Self> {
        let bad = |m: String| Error::argument(format!("series choice {s:?}"), m);
        let value = s.trim();
        let prefixed = |prefix: &str| {
            value
                .get(..prefix.len())
                .filter(|p| p.eq_ignore_ascii_case(prefix))
                .map(|_| value[prefix.len()..].trim())
        };
        let choice = if let Some(uid) = prefixed("uid:") {
            SeriesChoice::Uid(uid.to_string())
        } else if let Some(n) = prefixed("number:") {
            let n = n
                .parse()
                .map_err(|_| bad(format!("series number {n:?} is not an integer")))?;
            SeriesChoice::Number(n)
        } else if let Some(d) = prefixed("description:") {
            SeriesChoice::Description(d.to_string())
        } else if !value.is_empty() && value.bytes().all(|b| b.is_ascii_digit()) {
            SeriesChoice::Number(value.parse().map_err(|_| bad("number too large".into()))?)
        } else if value.contains('.') && value.bytes().all(|b| b.is_ascii_digit() || b == b'.') {
            SeriesChoice::Uid(value.to_string())
        } else {
            SeriesChoice::Description(value.to_string())
        };
        match &choice {
            SeriesChoice::Uid(v) | SeriesChoice::Description(v) if v.is_empty() => {
                Err(bad("empty".into()))
            }
            _ => Ok(choice),
        }
    }
}

impl TryFrom<String> for SeriesChoice {
    type Error = Error;

    fn try_from(s: String) -> Result<Self> {
        s.parse()
    }
}

impl From<SeriesChoice> for String {
    fn from(choice: SeriesChoice) -> String {
        choice.to_string()
    }
}

impl fmt::Display for SeriesChoice {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            SeriesChoice::Uid(uid) => write!(f, "uid:{uid}"),
            SeriesChoice::Number(n) => write!(f, "number:{n}"),
            SeriesChoice::Description(d) => write!(f, "description:{d}"),
        }
    }
}

impl SeriesChoice {
    /// How an error names the wanted series.
    fn wanted(&self) -> String {
        match self {
            SeriesChoice::Uid(uid) => uid.clone(),
            SeriesChoice::Number(n) => format!("numbered {n}"),
            SeriesChoice::Description(d) => format!("described \"{d}\""),
        }
    }

    fn matches(&self, series: &SeriesFiles) -> bool {
        match self {
            SeriesChoice::Uid(uid) => &series.uid == uid,
            SeriesChoice::Number(n) => series.number() == Some(*n),
            SeriesChoice::Description(d) => series
                .description()
                .is_some_and(|s| s.trim().eq_ignore_ascii_case(d.trim())),
        }
    }
}

/// Files of one series, in no particular order.
pub(super) struct SeriesFiles {
    pub uid: String,
    pub files: Vec<ParsedFile>,
}

impl SeriesFiles {
    fn modality(&self) -> &str {
        &self.files[0].modality
    }

    fn number(&self) -> Option<i64> {
        let first = &self.files[0].object;
        first.get(tags::SERIES_NUMBER)?.to_int::<i64>().ok()
    }

    fn description(&self) -> Option<&str> {
        self.files[0].description.as_deref()
    }

    fn first_value(&self, tag: Tag) -> Option<usize> {
        self.files
            .iter()
            .find_map(|f| f.object.get(tag)?.to_int::<u32>().ok())
            .map(|v| v as usize)
    }

    /// UID, number, description, modality, files and image size, for listings.
    fn describe(&self) -> String {
        let number = self
            .number()
            .map_or_else(|| "no number".to_string(), |n| format!("number {n}"));
        let frames: usize = self
            .files
            .iter()
            .map(|f| {
                f.object
                    .get(tags::NUMBER_OF_FRAMES)
                    .and_then(|e| e.to_int::<u32>().ok())
                    .map_or(1, |n| n.max(1) as usize)
            })
            .sum();
        let size = match (
            self.first_value(tags::ROWS),
            self.first_value(tags::COLUMNS),
        ) {
            (Some(r), Some(c)) if frames > self.files.len() => {
                format!(", {frames} frames of {r}×{c}")
            }
            (Some(r), Some(c)) => format!(", {r}×{c} pixels"),
            _ => String::new(),
        };
        format!(
            "{} ({number}, \"{}\", {}, {} file{}{size})",
            self.uid,
            self.description().unwrap_or(""),
            self.modality(),
            self.files.len(),
            if self.files.len() == 1 { "" } else { "s" }
        )
    }

    fn is_ct_image(&self) -> bool {
        self.modality() == "CT"
            && self
                .files
                .iter()
                .any(|f| f.object.get(tags::ROWS).is_some())
    }

    /// A scout: ImageType (0008,0008) says LOCALIZER.
    fn is_localizer(&self) -> bool {
        text(&self.files[0].object, tags::IMAGE_TYPE)
            .is_some_and(|t| t.to_ascii_uppercase().contains("LOCALIZER"))
    }
}

fn listing(list: &[SeriesFiles]) -> String {
    list.iter()
        .map(SeriesFiles::describe)
        .collect::<Vec<_>>()
        .join("; ")
}

/// Groups the files by series and picks the one to read: the user's choice, else the only CT
/// series that is not a scout (the others named in a warning).
pub(super) fn select_series(
    what: &str,
    files: Vec<ParsedFile>,
    options: &DicomReadOptions,
    warnings: &mut Vec<String>,
) -> Result<SeriesFiles> {
    let mut groups: BTreeMap<String, Vec<ParsedFile>> = BTreeMap::new();
    for f in files {
        groups.entry(f.series_uid.clone()).or_default().push(f);
    }
    let mut all: Vec<SeriesFiles> = groups
        .into_iter()
        .map(|(uid, files)| SeriesFiles { uid, files })
        .collect();
    if let Some(choice) = &options.series {
        return chosen_series(what, all, choice);
    }
    let volumes = all
        .iter()
        .filter(|s| s.is_ct_image() && !s.is_localizer())
        .count();
    if volumes == 1 {
        let i = all
            .iter()
            .position(|s| s.is_ct_image() && !s.is_localizer())
            .unwrap_or_else(|| unreachable!("one CT series was counted"));
        let chosen = all.swap_remove(i);
        if !all.is_empty() {
            warnings.push(format!(
                "{what}: read the CT series {}; ignored the other series: {}",
                chosen.uid,
                listing(&all)
            ));
        }
        return Ok(chosen);
    }
    if volumes == 0 && !all.iter().any(SeriesFiles::is_ct_image) {
        return Err(Error::scan(
            what,
            format!(
                "no CT image series; found modality {}: {}",
                all.iter()
                    .map(|s| s.modality().to_string())
                    .collect::<Vec<_>>()
                    .join(", "),
                listing(&all)
            ),
        ));
    }
    let ct: Vec<SeriesFiles> = all.into_iter().filter(|s| s.is_ct_image()).collect();
    let scouts = match ct.iter().filter(|s| s.is_localizer()).count() {
        0 => String::new(),
        n => format!(" ({n} of them scouts)"),
    };
    Err(Error::scan(
        what,
        format!(
            "{} CT series found{scouts}, {HOW_TO_CHOOSE}: {}",
            ct.len(),
            listing(&ct)
        ),
    ))
}

/// The series the user named, which must be one CT image series.
fn chosen_series(
    what: &str,
    mut all: Vec<SeriesFiles>,
    choice: &SeriesChoice,
) -> Result<SeriesFiles> {
    let matching: Vec<usize> = (0..all.len())
        .filter(|&i| choice.matches(&all[i]))
        .collect();
    let ct_matching: Vec<usize> = matching
        .iter()
        .copied()
        .filter(|&i| all[i].is_ct_image())
        .collect();
    match (matching.len(), ct_matching.as_slice()) {
        (0, _) => Err(Error::scan(
            what,
            format!(
                "no series {}; found {}; {HOW_TO_CHOOSE}",
                choice.wanted(),
                listing(&all)
            ),
        )),
        (_, [i]) => Ok(all.swap_remove(*i)),
        (_, []) => Err(Error::scan(
            what,
            format!(
                "series {} is not a CT image series: {}",
                choice.wanted(),
                matching
                    .iter()
                    .map(|&i| all[i].describe())
                    .collect::<Vec<_>>()
                    .join("; ")
            ),
        )),
        (_, several) => Err(Error::scan(
            what,
            format!(
                "{} CT series are {}: {}; name one by its UID (`uid:<UID>`)",
                several.len(),
                choice.wanted(),
                several
                    .iter()
                    .map(|&i| all[i].describe())
                    .collect::<Vec<_>>()
                    .join("; ")
            ),
        )),
    }
}
