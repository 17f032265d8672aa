//! The PACS as a DICOMweb server: the planning CT pulled by study (QIDO-RS to find its CT
//! series, WADO-RS to fetch it), and a run's DICOM objects pushed back (STOW-RS), skipping
//! what the server already holds so that a retried push stores nothing twice.
//!
//! Addresses: `dicomweb://HOST:PORT/ROOT` (plain HTTP) or `dicomwebs://…` (HTTPS) for the
//! server, followed by `/studies/<StudyInstanceUID>[/series/<SeriesInstanceUID>]` for a CT
//! to pull. `ROOT` is the server's DICOMweb root (Orthanc: `/dicom-web`).

mod client;
mod multipart;

use std::path::{Path, PathBuf};

pub use client::{ClientOptions, DicomWebAuth, DicomWebClient, PushReport};

use crate::{Error, Result};

/// A DICOMweb server's root and, for a pull, the study and series asked for.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct DicomWebAddress {
    /// The server's DICOMweb root as an HTTP(S) URL, without a trailing slash.
    pub root_url: String,
    /// StudyInstanceUID, when the address names a study.
    pub study_uid: Option<String>,
    /// SeriesInstanceUID, when the address names a series.
    pub series_uid: Option<String>,
}

impl DicomWebAddress {
    /// Parses `dicomweb://…` / `dicomwebs://…`; errors name the address and what is wrong.
    pub fn parse(text: &str) -> Result<Self> {
        let bad = |reason: &str| {
            Error::argument(
                "DICOMweb address",
                format!(
                    "'{text}': {reason} (expected dicomweb://HOST:PORT/ROOT\
                     [/studies/STUDY_UID[/series/SERIES_UID]], or dicomwebs:// for HTTPS)"
                ),
            )
        };
        let (scheme, rest) = if let Some(rest) = text.strip_prefix("dicomweb://") {
            ("http", rest)
        } else if let Some(rest) = text.strip_prefix("dicomwebs://") {
            ("https", rest)
        } else {
            return Err(bad("not a DICOMweb address"));
        };
        let rest = rest.trim_end_matches('/');
        let (host, path) = rest.split_once('/').unwrap_or((rest, ""));
        if host.is_empty() || host.contains(['@', '?', '#', ' ']) {
            return Err(bad("no usable host"));
        }
        let segments: Vec<&str> = path.split('/').filter(|s| !s.is_empty()).collect();
        let studies_at = segments.iter().position(|&s| s == "studies");
        let (root, uids) = match studies_at {
            Some(i) => (&segments[..i], &segments[i..]),
            None => (&segments[..], &segments[..0]),
        };
        let (study_uid, series_uid) = match uids {
            [] => (None, None),
            ["studies", study] => (Some(*study), None),
            ["studies", study, "series", series] => (Some(*study), Some(*series)),
            _ => {
                return Err(bad(
                    "after the root, only /studies/UID[/series/UID] may follow",
                ))
            }
        };
        for uid in study_uid.iter().chain(&series_uid) {
            if !is_uid(uid) {
                return Err(bad(&format!(
                    "'{uid}' is not a DICOM UID (digits and dots, at most 64 characters)"
                )));
            }
        }
        let root_path = root.join("/");
        Ok(DicomWebAddress {
            root_url: if root_path.is_empty() {
                format!("{scheme}://{host}")
            } else {
                format!("{scheme}://{host}/{root_path}")
            },
            study_uid: study_uid.map(str::to_string),
            series_uid: series_uid.map(str::to_string),
        })
    }

    /// Whether `text` is meant as a DICOMweb address (and not a file path).
    pub fn is_dicomweb(text: &str) -> bool {
        text.starts_with("dicomweb://") || text.starts_with("dicomwebs://")
    }
}

/// Whether `uid` is a syntactically valid DICOM UID (PS3.5 §9.1).
pub fn is_uid(uid: &str) -> bool {
    uid.len() <= 64
        && uid.split('.').all(|c| {
            !c.is_empty()
                && c.bytes().all(|b| b.is_ascii_digit())
                && (c == "0" || !c.starts_with('0'))
        })
}

/// Pulls `series` of `study` from `client`'s server into `dir` (created if absent), or the
/// study's one CT series when no series is named; the series UID and the files. Blocking.
pub fn pull_series(
    client: &DicomWebClient,
    study: &str,
    series: Option<&str>,
    dir: &Path,
) -> Result<(String, Vec<PathBuf>)> {
    block_on(client.root_url(), async {
        let series = match series {
            Some(series) => series.to_string(),
            None => client.find_ct_series(study).await?,
        };
        let files = client.retrieve_series(study, &series, dir).await?;
        Ok((series, files))
    })
}

/// Pushes every DICOM file under `paths` (files or directories, searched recursively)
/// through `client` (its credentials and bounds), skipping instances the server already
/// holds. Blocking.
pub fn push_with(client: &DicomWebClient, paths: &[PathBuf]) -> Result<PushReport> {
    block_on(client.root_url(), async { client.push(paths).await })
}

/// Runs `work` on a current-thread runtime made for it.
fn block_on<T>(url: &str, work: impl std::future::Future<Output = Result<T>>) -> Result<T> {
    tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .map_err(|e| Error::Pacs {
            url: url.to_string(),
            status: None,
            reason: format!("cannot start the HTTP client's runtime: {e}"),
        })?
        .block_on(work)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn addresses_name_root_study_and_series() {
        let a =
            DicomWebAddress::parse("dicomweb://127.0.0.1:8042/dicom-web/studies/1.2.3/series/4.5")
                .unwrap();
        assert_eq!(a.root_url, "http://127.0.0.1:8042/dicom-web");
        assert_eq!(a.study_uid.as_deref(), Some("1.2.3"));
        assert_eq!(a.series_uid.as_deref(), Some("4.5"));
        let b = DicomWebAddress::parse("dicomwebs://pacs.example.org/dicom-web/").unwrap();
        assert_eq!(b.root_url, "https://pacs.example.org/dicom-web");
        assert_eq!(b.study_uid, None);
        for (bad, why) in [
            ("http://x/dicom-web", "not a DICOMweb address"),
            ("dicomweb:///dicom-web", "no usable host"),
            ("dicomweb://h/dw/studies/1.02.3", "not a DICOM UID"),
            (
                "dicomweb://h/dw/studies/1.2/instances/3",
                "only /studies/UID",
            ),
        ] {
            let e = DicomWebAddress::parse(bad).unwrap_err().to_string();
            assert!(e.contains(why), "{bad}: {e}");
        }
    }
}
