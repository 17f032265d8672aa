//! The DICOMweb requests: QIDO-RS searches, WADO-RS series retrieval streamed to files, and
//! STOW-RS stores in bounded batches.

use std::collections::{BTreeMap, HashSet};
use std::path::{Path, PathBuf};
use std::time::Duration;

use dicom_dictionary_std::tags;
use dicom_object::OpenFileOptions;
use serde_json::Value;
use tokio::io::AsyncWriteExt;

use super::multipart::{boundary_of, stow_body};
use crate::{Error, IoContext, IoOp, Result};

/// Most bytes one series may bring by default (a 512 × 512 × 1 000 CT is about 0.5 GB).
const MAX_SERIES_BYTES: u64 = 4 << 30;
/// Most bytes one instance may bring.
const MAX_INSTANCE_BYTES: u64 = 1 << 30;
/// Most instances one series may bring.
const MAX_INSTANCES: usize = 10_000;
/// Bytes sent in one STOW-RS request (the last file may take it over).
const STOW_BATCH_BYTES: usize = 64 << 20;
/// Time allowed to connect, by default.
const CONNECT_TIMEOUT: Duration = Duration::from_secs(10);
/// Time allowed to one whole request (a large series on a slow network), by default.
const REQUEST_TIMEOUT: Duration = Duration::from_secs(600);

/// A DICOMweb server.
pub struct DicomWebClient {
    http: reqwest::Client,
    root_url: String,
    max_series_bytes: u64,
    auth: Option<DicomWebAuth>,
}

/// How requests authenticate to the server.
#[derive(Clone, PartialEq, Eq)]
pub enum DicomWebAuth {
    /// HTTP Basic (Orthanc's `RegisteredUsers`, most PACS gateways).
    Basic {
        /// The user name.
        username: String,
        /// The password.
        password: String,
    },
    /// `Authorization: Bearer <token>` (an OAuth2 access token, DICOMweb proxies).
    Bearer(String),
}

impl std::fmt::Debug for DicomWebAuth {
    // Credentials never reach a log.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            DicomWebAuth::Basic { username, .. } => {
                write!(f, "Basic {{ username: {username:?}, password: <set> }}")
            }
            DicomWebAuth::Bearer(_) => f.write_str("Bearer(<set>)"),
        }
    }
}

/// What a client may spend and how it identifies itself.
#[derive(Debug, Clone, PartialEq)]
pub struct ClientOptions {
    /// Credentials sent with every request, if the server asks for them.
    pub auth: Option<DicomWebAuth>,
    /// Time allowed to connect.
    pub connect_timeout: Duration,
    /// Time allowed to one whole request, from connecting to the last byte of the answer.
    pub request_timeout: Duration,
    /// Most bytes one pulled series may bring.
    pub max_series_bytes: u64,
}

impl Default for ClientOptions {
    fn default() -> Self {
        ClientOptions {
            auth: None,
            connect_timeout: CONNECT_TIMEOUT,
            request_timeout: REQUEST_TIMEOUT,
            max_series_bytes: MAX_SERIES_BYTES,
        }
    }
}

/// What a push did.
#[derive(Debug, Clone, Default, PartialEq, Eq, serde::Serialize)]
pub struct PushReport {
    /// Instances stored by this push.
    pub stored: usize,
    /// Instances the server already held (not sent again).
    pub already_stored: usize,
    /// Files under the paths that are not DICOM (not sent).
    pub not_dicom: usize,
}

/// A DICOM file to push: its path and the UIDs that identify it on the server.
struct Outgoing {
    path: PathBuf,
    study_uid: String,
    sop_instance_uid: String,
}

impl DicomWebClient {
    /// A client of the server at `root_url` (http or https) with the default options.
    pub fn new(root_url: &str) -> Result<Self> {
        Self::with_options(root_url, &ClientOptions::default())
    }

    /// A client of the server at `root_url` with `options`' credentials and bounds.
    pub fn with_options(root_url: &str, options: &ClientOptions) -> Result<Self> {
        let http = reqwest::Client::builder()
            .connect_timeout(options.connect_timeout)
            .timeout(options.request_timeout)
            .build()
            .map_err(|e| pacs_error(root_url, None, format!("cannot build the client: {e}")))?;
        Ok(DicomWebClient {
            http,
            root_url: root_url.trim_end_matches('/').to_string(),
            max_series_bytes: options.max_series_bytes,
            auth: options.auth.clone(),
        })
    }

    /// The server's DICOMweb root.
    pub fn root_url(&self) -> &str {
        &self.root_url
    }

    /// A request to `url` carrying the credentials, if any.
    fn request(&self, method: reqwest::Method, url: &str) -> reqwest::RequestBuilder {
        let request = self.http.request(method, url);
        match &self.auth {
            Some(DicomWebAuth::Basic { username, password }) => {
                request.basic_auth(username, Some(password))
            }
            Some(DicomWebAuth::Bearer(token)) => request.bearer_auth(token),
            None => request,
        }
    }

    /// The one CT series of `study` (QIDO-RS); refuses a study the server does not hold, one
    /// without a CT series and one with several, listing what it holds.
    pub async fn find_ct_series(&self, study: &str) -> Result<String> {
        let url = format!("{}/studies/{study}/series", self.root_url);
        let series = self.search(&url).await?.unwrap_or_default();
        if series.is_empty() {
            return Err(pacs_error(
                &url,
                Some(404),
                format!("the server holds no study {study}"),
            ));
        }
        let described: Vec<(String, String, String)> = series
            .iter()
            .map(|s| {
                (
                    attribute(s, "0020000E").unwrap_or_default(),
                    attribute(s, "00080060").unwrap_or_default(),
                    attribute(s, "0008103E").unwrap_or_default(),
                )
            })
            .collect();
        let ct: Vec<&(String, String, String)> =
            described.iter().filter(|(_, m, _)| m == "CT").collect();
        let list = |items: &[&(String, String, String)]| {
            items
                .iter()
                .map(|(uid, m, d)| format!("{m} {uid} '{d}'"))
                .collect::<Vec<_>>()
                .join("; ")
        };
        match ct[..] {
            [one] => Ok(one.0.clone()),
            [] => Err(pacs_error(
                &url,
                Some(404),
                format!(
                    "study {study} holds no CT series (it holds: {})",
                    list(&described.iter().collect::<Vec<_>>())
                ),
            )),
            _ => Err(pacs_error(
                &url,
                Some(409),
                format!(
                    "study {study} holds {} CT series: name one with /series/UID ({})",
                    ct.len(),
                    list(&ct)
                ),
            )),
        }
    }

    /// Retrieves `series` of `study` (WADO-RS) into `dir`, streaming each instance to its own
    /// file within the size bounds; returns the files.
    pub async fn retrieve_series(
        &self,
        study: &str,
        series: &str,
        dir: &Path,
    ) -> Result<Vec<PathBuf>> {
        let url = format!("{}/studies/{study}/series/{series}", self.root_url);
        let response = self
            .send(
                &url,
                self.request(reqwest::Method::GET, &url)
                    .header("Accept", "multipart/related; type=\"application/dicom\""),
            )
            .await?;
        let content_type = response
            .headers()
            .get(reqwest::header::CONTENT_TYPE)
            .and_then(|v| v.to_str().ok())
            .unwrap_or("")
            .to_string();
        let boundary = boundary_of(&content_type, &url)?;
        let limits = multer::Constraints::new().size_limit(
            multer::SizeLimit::new()
                .whole_stream(self.max_series_bytes)
                .per_field(MAX_INSTANCE_BYTES.min(self.max_series_bytes)),
        );
        let mut parts =
            multer::Multipart::with_constraints(response.bytes_stream(), boundary, limits);
        tokio::fs::create_dir_all(dir)
            .await
            .at(IoOp::CreateDir, dir)?;
        let broken = |e: multer::Error| pacs_error(&url, Some(200), format!("broken answer: {e}"));
        let mut files = Vec::new();
        while let Some(mut part) = parts.next_field().await.map_err(broken)? {
            if files.len() == MAX_INSTANCES {
                return Err(pacs_error(
                    &url,
                    Some(200),
                    format!("the series has more than {MAX_INSTANCES} instances"),
                ));
            }
            let path = dir.join(format!("IMG{:05}.dcm", files.len() + 1));
            let mut file = tokio::fs::File::create(&path)
                .await
                .at(IoOp::Create, &path)?;
            while let Some(chunk) = part.chunk().await.map_err(broken)? {
                file.write_all(&chunk).await.at(IoOp::Write, &path)?;
            }
            file.flush().await.at(IoOp::Write, &path)?;
            files.push(path);
        }
        if files.is_empty() {
            return Err(pacs_error(
                &url,
                Some(200),
                "the series holds no instance".into(),
            ));
        }
        Ok(files)
    }

    /// Stores every DICOM file under `paths` (STOW-RS), skipping the instances the server
    /// already holds, in batches of about [`STOW_BATCH_BYTES`].
    pub async fn push(&self, paths: &[PathBuf]) -> Result<PushReport> {
        let mut report = PushReport::default();
        let mut outgoing = Vec::new();
        for path in dicom_files(paths)? {
            match identify(&path) {
                Some(o) => outgoing.push(o),
                None => report.not_dicom += 1,
            }
        }
        let mut by_study: BTreeMap<String, Vec<Outgoing>> = BTreeMap::new();
        for o in outgoing {
            by_study.entry(o.study_uid.clone()).or_default().push(o);
        }
        for (study, files) in by_study {
            let held = self.stored_instances(&study).await?;
            let (already, new): (Vec<Outgoing>, Vec<Outgoing>) = files
                .into_iter()
                .partition(|o| held.contains(&o.sop_instance_uid));
            report.already_stored += already.len();
            let mut batch = Vec::new();
            let mut batch_bytes = 0;
            for o in &new {
                let bytes = tokio::fs::read(&o.path).await.at(IoOp::Read, &o.path)?;
                batch_bytes += bytes.len();
                batch.push(bytes);
                if batch_bytes >= STOW_BATCH_BYTES {
                    report.stored += self.store(&std::mem::take(&mut batch)).await?;
                    batch_bytes = 0;
                }
            }
            if !batch.is_empty() {
                report.stored += self.store(&batch).await?;
            }
        }
        Ok(report)
    }

    /// SOPInstanceUIDs the server holds in `study` (none when it does not know the study).
    async fn stored_instances(&self, study: &str) -> Result<HashSet<String>> {
        let url = format!("{}/studies/{study}/instances", self.root_url);
        Ok(self
            .search(&url)
            .await?
            .unwrap_or_default()
            .iter()
            .filter_map(|i| attribute(i, "00080018"))
            .collect())
    }

    /// One STOW-RS request; the number of instances the server says it stored.
    async fn store(&self, parts: &[Vec<u8>]) -> Result<usize> {
        let url = format!("{}/studies", self.root_url);
        let boundary = format!(
            "lungmotion-{:032x}",
            std::time::SystemTime::now()
                .duration_since(std::time::UNIX_EPOCH)
                .map_or(0, |d| d.as_nanos())
        );
        let (body, content_type) = stow_body(parts, &boundary);
        let response = self
            .send(
                &url,
                self.request(reqwest::Method::POST, &url)
                    .header("Content-Type", content_type)
                    .header("Accept", "application/dicom+json")
                    .body(body),
            )
            .await?;
        let answer: Value = response.json().await.map_err(|e| {
            pacs_error(
                &url,
                Some(200),
                format!("the store's answer is not JSON: {e}"),
            )
        })?;
        let failed = answer
            .get("00081198")
            .and_then(|f| f.get("Value"))
            .and_then(Value::as_array)
            .map_or(0, Vec::len);
        if failed > 0 {
            return Err(pacs_error(
                &url,
                Some(200),
                format!("the server refused {failed} of {} instances", parts.len()),
            ));
        }
        Ok(answer
            .get("00081199")
            .and_then(|f| f.get("Value"))
            .and_then(Value::as_array)
            .map_or(parts.len(), Vec::len))
    }

    /// A QIDO-RS search; `None` when the server does not know what was searched (404).
    async fn search(&self, url: &str) -> Result<Option<Vec<Value>>> {
        let request = self
            .request(reqwest::Method::GET, url)
            .header("Accept", "application/dicom+json");
        let response = request.send().await.map_err(|e| unreachable(url, &e))?;
        let status = response.status();
        if status == reqwest::StatusCode::NOT_FOUND || status == reqwest::StatusCode::NO_CONTENT {
            return Ok(None);
        }
        let response = refuse_failure(url, response).await?;
        let found: Value = response.json().await.map_err(|e| {
            pacs_error(
                url,
                Some(status.as_u16()),
                format!("the answer is not JSON: {e}"),
            )
        })?;
        match found {
            Value::Array(items) => Ok(Some(items)),
            other => Err(pacs_error(
                url,
                Some(status.as_u16()),
                format!("expected a JSON array of datasets, got {}", kind_of(&other)),
            )),
        }
    }

    /// Sends `request`, refusing an unreachable server and any non-success status.
    async fn send(&self, url: &str, request: reqwest::RequestBuilder) -> Result<reqwest::Response> {
        let response = request.send().await.map_err(|e| unreachable(url, &e))?;
        refuse_failure(url, response).await
    }
}

/// The response itself when it succeeded, else an error with its status and the start of
/// its body (what the server said).
async fn refuse_failure(url: &str, response: reqwest::Response) -> Result<reqwest::Response> {
    let status = response.status();
    if status.is_success() {
        return Ok(response);
    }
    let body = response.text().await.unwrap_or_default();
    let said: String = body.chars().take(300).collect();
    Err(pacs_error(
        url,
        Some(status.as_u16()),
        format!(
            "{}{}",
            status.canonical_reason().unwrap_or("failure"),
            if said.trim().is_empty() {
                String::new()
            } else {
                format!(": {}", said.trim())
            }
        ),
    ))
}

/// The error for a server that could not be reached.
fn unreachable(url: &str, e: &reqwest::Error) -> Error {
    let why = if e.is_timeout() {
        "no answer in time".to_string()
    } else if e.is_connect() {
        "cannot connect (is the server running, and is the address right?)".to_string()
    } else {
        "the request failed".to_string()
    };
    let mut cause = std::error::Error::source(e);
    let mut detail = String::new();
    while let Some(c) = cause {
        detail = c.to_string();
        cause = c.source();
    }
    pacs_error(
        url,
        None,
        if detail.is_empty() {
            why
        } else {
            format!("{why}: {detail}")
        },
    )
}

fn pacs_error(url: &str, status: Option<u16>, reason: String) -> Error {
    Error::Pacs {
        url: url.to_string(),
        status,
        reason,
    }
}

/// The first value of a DICOM JSON attribute (`"0020000E": {"vr": "UI", "Value": [...]}`).
fn attribute(dataset: &Value, tag: &str) -> Option<String> {
    match dataset.get(tag)?.get("Value")?.get(0)? {
        Value::String(s) => Some(s.clone()),
        other => Some(other.to_string()),
    }
}

fn kind_of(v: &Value) -> &'static str {
    match v {
        Value::Object(_) => "an object",
        Value::Array(_) => "an array",
        Value::String(_) => "a string",
        Value::Number(_) => "a number",
        Value::Bool(_) => "a boolean",
        Value::Null => "null",
    }
}

/// The files under `paths` (directories walked recursively), in a stable order.
fn dicom_files(paths: &[PathBuf]) -> Result<Vec<PathBuf>> {
    let mut out = Vec::new();
    let mut pending: Vec<PathBuf> = paths.to_vec();
    while let Some(path) = pending.pop() {
        let meta = std::fs::metadata(&path).at(IoOp::Metadata, &path)?;
        if meta.is_dir() {
            for entry in std::fs::read_dir(&path).at(IoOp::List, &path)? {
                pending.push(entry.at(IoOp::List, &path)?.path());
            }
        } else {
            out.push(path);
        }
    }
    out.sort();
    Ok(out)
}

/// The study and instance UIDs of a DICOM file (Part 10), or `None` for any other file.
fn identify(path: &Path) -> Option<Outgoing> {
    let object = OpenFileOptions::new()
        .read_until(tags::PIXEL_DATA)
        .open_file(path)
        .ok()?;
    let text = |tag| {
        object
            .element(tag)
            .ok()?
            .to_str()
            .ok()
            .map(|s| s.trim_end_matches(['\0', ' ']).to_string())
    };
    Some(Outgoing {
        path: path.to_path_buf(),
        study_uid: text(tags::STUDY_INSTANCE_UID)?,
        sop_instance_uid: text(tags::SOP_INSTANCE_UID)?,
    })
}
