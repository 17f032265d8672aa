//! Scans' uploads and jobs' outputs in an object store (`[store] object_store_url`): an
//! S3-compatible bucket (`s3://bucket/prefix`) or a directory through the same interface
//! (`file:///path`), with Apache Arrow's `object_store` crate.
//!
//! Without `object_store_url` nothing here is used: the data directory is the store, as
//! before. With one, the keys under the prefix mirror the data directory's layout:
//! `scans/<id>/<upload>` and `scans/<id>/ingest.bin` (put once the upload is received and
//! ingested), a scan's uploaded targets as `scans/<id>/targets/<name>/target.json` (the
//! record, naming its file) and `scans/<id>/targets/<name>/<upload id>/<file>` (no copy in
//! the data directory, so every API process and worker sees them; they go with the scan),
//! a job's copy of its target as `jobs/<id>/target/<file>`, and
//! `jobs/<id>/out/<path>` (put when the run succeeds; the run itself writes into
//! the local data directory, which then keeps no outputs). A worker on another machine fetches
//! a scan it lacks into its own data directory before running. Outputs are served by streaming
//! the object, or by a `307` to a presigned URL (`presigned_get`).
//!
//! Files of at most `multipart_part_mib` go in one PUT; larger ones in a multipart upload of
//! parts of that size, several parts in flight; a job's files go several at a time.
//!
//! The client runs on a small runtime of its own, so the simulation workers (OS threads) and
//! the HTTP handlers reach it alike (as the PostgreSQL client does).

use std::future::Future;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Duration, Instant};

use super::client_runtime::ClientRuntime;
use bytes::Bytes;
use futures_util::stream::{BoxStream, StreamExt, TryStreamExt};
use object_store::aws::{AmazonS3, AmazonS3Builder};
use object_store::local::LocalFileSystem;
use object_store::path::Path as Key;
use object_store::signer::Signer;
use object_store::{
    Attribute, Attributes, GetOptions, GetRange, ObjectStore, PutMultipartOptions, PutOptions,
    PutPayload, WriteMultipart,
};
use tokio::io::AsyncReadExt;

use crate::{Error, Result};

/// Default part size of multipart uploads (and the size above which a file is sent in parts),
/// MiB.
pub const DEFAULT_MULTIPART_PART_MIB: u64 = 16;
/// Smallest part size S3 accepts (but for the last part), MiB.
const MIN_PART_MIB: u64 = 5;
/// Default bound of a worker's copies of scans fetched from the store, MiB: about 50
/// POPI-sized scans (81 MB zipped upload plus 128 MB stored ingest at 8 mm each), so the
/// scans of a day's jobs stay local while a worker's disk never fills with a cohort's.
pub const DEFAULT_FETCHED_SCANS_MIB: u64 = 10_240;
/// Default lifetime of a presigned GET URL, s.
pub const DEFAULT_PRESIGNED_TTL_S: f64 = 300.0;
/// Parts of one multipart upload in flight at once.
const PARTS_IN_FLIGHT: usize = 4;
/// Files of one job put or fetched at once.
const FILES_IN_FLIGHT: usize = 8;
/// Longest wait for the readiness probe's list.
const PROBE_TIMEOUT: Duration = Duration::from_secs(5);

/// Where the blobs go and how to reach them (`[store] object_store_*`, `LUNGMOTION_S3_*`,
/// `AWS_*`).
#[derive(Clone, PartialEq)]
pub struct BlobSettings {
    /// `s3://bucket[/prefix]` or `file:///absolute/dir`.
    pub url: String,
    /// The S3 server's address (`http://127.0.0.1:9000`); AWS's regional one when absent.
    pub endpoint: Option<String>,
    /// The bucket's region (default `us-east-1`, which S3-compatible servers ignore).
    pub region: Option<String>,
    /// Access key id (`AWS_ACCESS_KEY_ID`).
    pub access_key_id: Option<String>,
    /// Secret access key (`AWS_SECRET_ACCESS_KEY`, `_FILE`, or the file's
    /// `object_store_secret_access_key_file`).
    pub secret_access_key: Option<String>,
    /// Answer output GETs with `307` to a presigned URL instead of streaming them (S3 only).
    pub presigned_get: bool,
    /// How long a presigned URL is valid, s.
    pub presigned_ttl_s: f64,
    /// Part size of multipart uploads, and the size above which a file is sent in parts, MiB.
    pub multipart_part_mib: u64,
    /// Bound of the local copies of scans in the data directory (uploads received, scans
    /// fetched), MiB; beyond it the least recently used ones not in use are removed (0: only
    /// those in use).
    pub fetched_scans_mib: u64,
}

impl std::fmt::Debug for BlobSettings {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("BlobSettings")
            .field("url", &self.url)
            .field("endpoint", &self.endpoint)
            .field("region", &self.region)
            .field("access_key_id", &self.access_key_id)
            .field(
                "secret_access_key",
                &self.secret_access_key.as_ref().map(|_| "(set)"),
            )
            .field("presigned_get", &self.presigned_get)
            .field("presigned_ttl_s", &self.presigned_ttl_s)
            .field("multipart_part_mib", &self.multipart_part_mib)
            .field("fetched_scans_mib", &self.fetched_scans_mib)
            .finish()
    }
}

impl BlobSettings {
    /// Settings for `url` with every other setting at its default.
    pub fn new(url: impl Into<String>) -> Self {
        BlobSettings {
            url: url.into(),
            endpoint: None,
            region: None,
            access_key_id: None,
            secret_access_key: None,
            presigned_get: false,
            presigned_ttl_s: DEFAULT_PRESIGNED_TTL_S,
            multipart_part_mib: DEFAULT_MULTIPART_PART_MIB,
            fetched_scans_mib: DEFAULT_FETCHED_SCANS_MIB,
        }
    }

    /// Refuses settings that cannot work, naming the key.
    pub fn validate(&self) -> Result<()> {
        let bad = |m: String| Err(Error::settings("service configuration", m));
        match self.location() {
            Ok(Location::S3 { .. }) => {}
            Ok(Location::Directory(_)) if self.presigned_get => {
                return bad(format!(
                    "presigned_get needs an S3 object store; {} is a directory",
                    self.url
                ))
            }
            Ok(Location::Directory(_)) => {}
            Err(m) => return bad(m),
        }
        if let Some(endpoint) = &self.endpoint {
            if !(endpoint.starts_with("http://") || endpoint.starts_with("https://")) {
                return bad(format!(
                    "object_store_endpoint must be an http:// or https:// address, not \
                     {endpoint:?}"
                ));
            }
        }
        if self.access_key_id.is_some() != self.secret_access_key.is_some() {
            return bad(
                "an object store access key id needs its secret access key and the reverse \
                 (AWS_ACCESS_KEY_ID and AWS_SECRET_ACCESS_KEY or _FILE)"
                    .into(),
            );
        }
        if !(MIN_PART_MIB..=5 * 1024).contains(&self.multipart_part_mib) {
            return bad(format!(
                "object_store_multipart_part_mib must be {MIN_PART_MIB}–5120 (S3's part \
                 sizes), not {}",
                self.multipart_part_mib
            ));
        }
        if !(self.presigned_ttl_s.is_finite() && (1.0..=604_800.0).contains(&self.presigned_ttl_s))
        {
            return bad(format!(
                "presigned_ttl_s must be 1–604800 seconds (S3's limit is 7 days), not {}",
                self.presigned_ttl_s
            ));
        }
        Ok(())
    }

    /// What the URL names.
    fn location(&self) -> std::result::Result<Location, String> {
        if let Some(rest) = self.url.strip_prefix("s3://") {
            let (bucket, prefix) = rest.split_once('/').unwrap_or((rest, ""));
            let valid_bucket = (3..=63).contains(&bucket.len())
                && bucket
                    .chars()
                    .all(|c| c.is_ascii_lowercase() || c.is_ascii_digit() || c == '-' || c == '.');
            if !valid_bucket {
                return Err(format!(
                    "object_store_url {:?}: {bucket:?} is not a bucket name (3–63 of a-z, 0-9, \
                     '-' and '.')",
                    self.url
                ));
            }
            Ok(Location::S3 {
                bucket: bucket.to_string(),
                prefix: prefix.trim_matches('/').to_string(),
            })
        } else if let Some(path) = self.url.strip_prefix("file://") {
            if !path.starts_with('/') {
                return Err(format!(
                    "object_store_url {:?}: a file:// URL needs an absolute path \
                     (file:///var/lib/lungmotion-blobs)",
                    self.url
                ));
            }
            Ok(Location::Directory(PathBuf::from(path)))
        } else {
            Err(format!(
                "object_store_url {:?} is neither s3://bucket/prefix nor file:///directory",
                self.url
            ))
        }
    }
}

enum Location {
    S3 { bucket: String, prefix: String },
    Directory(PathBuf),
}

/// The object store of a service: its client, the prefix its keys live under, and a runtime
/// of its own for the client.
#[derive(Clone)]
pub struct BlobStore {
    inner: Arc<Inner>,
}

impl std::fmt::Debug for BlobStore {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("BlobStore")
            .field("store", &self.inner.shown)
            .field("presigned_get", &self.presigns())
            .finish()
    }
}

struct Inner {
    store: Arc<dyn ObjectStore>,
    /// The S3 client again, for presigning, when `presigned_get` is on.
    signer: Option<Arc<AmazonS3>>,
    presigned_ttl: Duration,
    prefix: String,
    part_bytes: usize,
    /// Bound of the scans fetched into the data directory, bytes.
    fetched_scans_bytes: u64,
    /// Whether the store takes content types with a PUT (S3 does, a directory does not).
    attributes: bool,
    /// `s3://bucket/prefix at <endpoint>`, for errors and logs.
    shown: String,
    bucket: Option<String>,
    runtime: ClientRuntime,
}

/// One object as listed: its key relative to the listed directory, and its size.
pub type Listed = (String, u64);

impl BlobStore {
    /// Opens the store the settings name and checks that it answers (the bucket exists and
    /// the credentials are accepted): errors name the bucket, the endpoint and what the server
    /// said.
    pub fn open(settings: &BlobSettings) -> Result<Self> {
        settings.validate()?;
        let location = settings
            .location()
            .map_err(|m| Error::settings("service configuration", m))?;
        let runtime = ClientRuntime::start("lungmotion-blobs").map_err(|e| Error::ObjectStore {
            store: settings.url.clone(),
            key: None,
            reason: format!("cannot start the client's threads: {e}"),
        })?;
        let (store, signer, prefix, shown, bucket, attributes): (
            Arc<dyn ObjectStore>,
            _,
            _,
            _,
            _,
            _,
        ) = match location {
            Location::S3 { bucket, prefix } => {
                let endpoint = settings.endpoint.clone();
                let shown = format!(
                    "{} at {}",
                    settings.url.trim_end_matches('/'),
                    endpoint.as_deref().unwrap_or("AWS S3")
                );
                // Transient failures (5xx, a dropped connection) are retried for a minute at
                // most, so a job's upload fails in bounded time when the server is gone.
                let retry = object_store::RetryConfig {
                    max_retries: 5,
                    retry_timeout: Duration::from_secs(60),
                    ..object_store::RetryConfig::default()
                };
                let mut builder = AmazonS3Builder::new()
                    .with_retry(retry)
                    .with_bucket_name(&bucket)
                    .with_region(settings.region.as_deref().unwrap_or("us-east-1"));
                if let Some(endpoint) = &endpoint {
                    builder = builder
                        .with_endpoint(endpoint)
                        .with_allow_http(endpoint.starts_with("http://"));
                }
                if let (Some(id), Some(secret)) =
                    (&settings.access_key_id, &settings.secret_access_key)
                {
                    builder = builder
                        .with_access_key_id(id)
                        .with_secret_access_key(secret);
                }
                let s3 = Arc::new(builder.build().map_err(|e| Error::ObjectStore {
                    store: shown.clone(),
                    key: None,
                    reason: format!("cannot make the S3 client: {e}"),
                })?);
                let signer = settings.presigned_get.then(|| s3.clone());
                (
                    s3 as Arc<dyn ObjectStore>,
                    signer,
                    prefix,
                    shown,
                    Some(bucket),
                    true,
                )
            }
            Location::Directory(dir) => {
                std::fs::create_dir_all(&dir)
                    .map_err(|e| Error::io(crate::IoOp::CreateDir, &dir, e))?;
                let local =
                    LocalFileSystem::new_with_prefix(&dir).map_err(|e| Error::ObjectStore {
                        store: settings.url.clone(),
                        key: None,
                        reason: e.to_string(),
                    })?;
                (
                    Arc::new(local) as Arc<dyn ObjectStore>,
                    None,
                    String::new(),
                    settings.url.clone(),
                    None,
                    false,
                )
            }
        };
        let blobs = BlobStore {
            inner: Arc::new(Inner {
                store,
                signer,
                presigned_ttl: Duration::from_secs_f64(settings.presigned_ttl_s),
                prefix,
                part_bytes: (settings.multipart_part_mib << 20) as usize,
                fetched_scans_bytes: settings.fetched_scans_mib.saturating_mul(1 << 20),
                attributes,
                shown,
                bucket,
                runtime,
            }),
        };
        blobs.probe().map_err(|reason| Error::ObjectStore {
            store: blobs.inner.shown.clone(),
            key: None,
            reason,
        })?;
        Ok(blobs)
    }

    /// The store as `s3://bucket/prefix at <endpoint>` (or its `file://` URL).
    pub fn shown(&self) -> &str {
        &self.inner.shown
    }

    /// Bound of the copies of scans fetched into the data directory, bytes.
    pub fn fetched_scans_bytes(&self) -> u64 {
        self.inner.fetched_scans_bytes
    }

    /// Whether outputs are answered with a presigned URL.
    pub fn presigns(&self) -> bool {
        self.inner.signer.is_some()
    }

    fn handle(&self) -> &tokio::runtime::Handle {
        self.inner.runtime.handle()
    }

    /// Runs `future` on the client's runtime and waits for it, from any thread.
    fn run<T: Send + 'static>(&self, future: impl Future<Output = T> + Send + 'static) -> T {
        self.inner.runtime.run(future)
    }

    /// Runs `future` on the client's runtime from async code.
    async fn run_async<T: Send + 'static>(
        &self,
        future: impl Future<Output = T> + Send + 'static,
    ) -> T {
        self.handle()
            .spawn(future)
            .await
            .expect("the object store client's runtime dropped a task")
    }

    /// The full key of `relative` (a path under the prefix, `/`-separated).
    fn key(&self, relative: &str) -> Key {
        if self.inner.prefix.is_empty() {
            Key::from(relative)
        } else {
            Key::from(format!("{}/{relative}", self.inner.prefix))
        }
    }

    /// The key `relative` as errors show it (under the prefix).
    fn error(&self, relative: &str, e: impl std::fmt::Display) -> Error {
        Error::ObjectStore {
            store: self.inner.shown.clone(),
            key: Some(relative.to_string()),
            reason: e.to_string(),
        }
    }

    /// Whether the store answers now (for `/readyz` and at start): lists the prefix. `Err`
    /// says why not, in words naming a missing bucket or refused credentials.
    pub fn probe(&self) -> std::result::Result<(), String> {
        let store = self.inner.store.clone();
        let prefix = (!self.inner.prefix.is_empty()).then(|| Key::from(self.inner.prefix.as_str()));
        let outcome = self.run(async move {
            tokio::time::timeout(PROBE_TIMEOUT, store.list_with_delimiter(prefix.as_ref())).await
        });
        match outcome {
            Ok(Ok(_)) => Ok(()),
            Ok(Err(e)) => Err(self.explain(&e)),
            Err(_) => Err(format!(
                "no answer within {} s listing the prefix",
                PROBE_TIMEOUT.as_secs()
            )),
        }
    }

    /// An object store error in words, naming the bucket when it is missing and saying when
    /// the credentials were refused (from S3's error code, which the client's message holds;
    /// its `<Code>` and `<Message>` are given rather than the whole XML body).
    fn explain(&self, e: &object_store::Error) -> String {
        let text = e.to_string();
        let bucket = self.inner.bucket.as_deref().unwrap_or("(directory)");
        let code = xml_text(&text, "Code");
        let said = match (&code, xml_text(&text, "Message")) {
            (Some(code), Some(message)) => format!("S3 {code}: {message}"),
            _ => text.clone(),
        };
        let refused = matches!(
            code.as_deref(),
            Some("InvalidAccessKeyId" | "SignatureDoesNotMatch" | "AccessDenied")
        ) || matches!(
            e,
            object_store::Error::PermissionDenied { .. }
                | object_store::Error::Unauthenticated { .. }
        );
        if code.as_deref() == Some("NoSuchBucket") {
            format!("the bucket \"{bucket}\" does not exist ({said})")
        } else if refused {
            format!("the server refused the credentials for bucket \"{bucket}\" ({said})")
        } else {
            said
        }
    }

    /// Puts the file `file` at `relative`: one PUT up to the part size, else a multipart
    /// upload (parts of that size, several in flight), aborted when a part fails.
    pub fn put_file(&self, relative: &str, file: &Path) -> Result<u64> {
        let this = self.clone();
        let (relative, file) = (relative.to_string(), file.to_path_buf());
        self.run(async move { this.put_file_async(&relative, &file).await })
    }

    async fn put_file_async(&self, relative: &str, file: &Path) -> Result<u64> {
        let key = self.key(relative);
        let io = |e: std::io::Error| Error::io(crate::IoOp::Read, file, e);
        let mut reader = tokio::fs::File::open(file).await.map_err(io)?;
        let len = reader.metadata().await.map_err(io)?.len();
        let attributes = if self.inner.attributes {
            let mut a = Attributes::new();
            a.insert(
                Attribute::ContentType,
                super::routes::content_type_of(relative).into(),
            );
            a
        } else {
            Attributes::new()
        };
        let store = &self.inner.store;
        if len <= self.inner.part_bytes as u64 {
            let mut bytes = Vec::with_capacity(len as usize);
            reader.read_to_end(&mut bytes).await.map_err(io)?;
            let opts = PutOptions {
                attributes,
                ..PutOptions::default()
            };
            store
                .put_opts(&key, PutPayload::from(bytes), opts)
                .await
                .map_err(|e| self.error(relative, self.explain(&e)))?;
            return Ok(len);
        }
        let opts = PutMultipartOptions {
            attributes,
            ..PutMultipartOptions::default()
        };
        let upload = store
            .put_multipart_opts(&key, opts)
            .await
            .map_err(|e| self.error(relative, self.explain(&e)))?;
        let mut writer = WriteMultipart::new_with_chunk_size(upload, self.inner.part_bytes);
        let mut buf = vec![0u8; 1 << 20];
        let written: std::result::Result<(), Error> = async {
            loop {
                let n = reader.read(&mut buf).await.map_err(io)?;
                if n == 0 {
                    return Ok(());
                }
                writer
                    .wait_for_capacity(PARTS_IN_FLIGHT)
                    .await
                    .map_err(|e| self.error(relative, self.explain(&e)))?;
                writer.write(&buf[..n]);
            }
        }
        .await;
        match written {
            Ok(()) => {
                writer
                    .finish()
                    .await
                    .map_err(|e| self.error(relative, self.explain(&e)))?;
                Ok(len)
            }
            Err(e) => {
                let _ = writer.abort().await;
                Err(e)
            }
        }
    }

    /// Puts `bytes` (a small record: a target's `target.json`) at `relative` in one PUT,
    /// which replaces the object whole: a reader gets the old bytes or the new, never part.
    pub fn put_bytes(&self, relative: &str, bytes: Vec<u8>) -> Result<()> {
        let this = self.clone();
        let relative = relative.to_string();
        self.run(async move {
            let mut attributes = Attributes::new();
            if this.inner.attributes {
                attributes.insert(
                    Attribute::ContentType,
                    super::routes::content_type_of(&relative).into(),
                );
            }
            let opts = PutOptions {
                attributes,
                ..PutOptions::default()
            };
            this.inner
                .store
                .put_opts(&this.key(&relative), PutPayload::from(bytes), opts)
                .await
                .map(|_| ())
                .map_err(|e| this.error(&relative, this.explain(&e)))
        })
    }

    /// Puts every file under the local directory `dir` at `relative/<its path>`, several at
    /// once; how many files and bytes. Hidden names are left out (the run writes none).
    pub fn put_tree(&self, relative: &str, dir: &Path) -> Result<(usize, u64)> {
        let files = local_files(dir).map_err(|e| Error::io(crate::IoOp::List, dir, e))?;
        let this = self.clone();
        let relative = relative.trim_end_matches('/').to_string();
        let dir = dir.to_path_buf();
        self.run(async move {
            let count = files.len();
            let bytes: Vec<u64> = futures_util::stream::iter(files)
                .map(|name| {
                    let (this, key, path) =
                        (this.clone(), format!("{relative}/{name}"), dir.join(&name));
                    async move { this.put_file_async(&key, &path).await }
                })
                .buffer_unordered(FILES_IN_FLIGHT)
                .try_collect()
                .await?;
            Ok((count, bytes.iter().sum()))
        })
    }

    /// Fetches the object `relative` into the file `dest` (written beside it, then renamed);
    /// `false` when there is no such object.
    pub fn fetch_file(&self, relative: &str, dest: &Path) -> Result<bool> {
        let this = self.clone();
        let (relative, dest) = (relative.to_string(), dest.to_path_buf());
        self.run(async move { this.fetch_file_async(&relative, &dest).await })
    }

    async fn fetch_file_async(&self, relative: &str, dest: &Path) -> Result<bool> {
        let got = match self.inner.store.get(&self.key(relative)).await {
            Ok(got) => got,
            Err(object_store::Error::NotFound { .. }) => return Ok(false),
            Err(e) => return Err(self.error(relative, self.explain(&e))),
        };
        // Beside the destination under its whole name plus a suffix: files of one tree that
        // differ only in their extension must not share a partial file.
        let mut partial = dest.as_os_str().to_owned();
        partial.push(".fetching");
        let partial = PathBuf::from(partial);
        let io = |e: std::io::Error| Error::io(crate::IoOp::Write, &partial, e);
        let mut file = tokio::fs::File::create(&partial).await.map_err(io)?;
        let mut stream = got.into_stream();
        let written: Result<()> = async {
            while let Some(chunk) = stream.next().await {
                let chunk = chunk.map_err(|e| self.error(relative, self.explain(&e)))?;
                tokio::io::AsyncWriteExt::write_all(&mut file, &chunk)
                    .await
                    .map_err(io)?;
            }
            file.sync_all().await.map_err(io)
        }
        .await;
        if let Err(e) = written {
            let _ = tokio::fs::remove_file(&partial).await;
            return Err(e);
        }
        tokio::fs::rename(&partial, dest)
            .await
            .map_err(|e| Error::io(crate::IoOp::Rename, &partial, e))?;
        Ok(true)
    }

    /// Fetches every object under `relative/` into the directory `dest` (created) under its
    /// path below `relative/`, several at once; how many files and bytes. Nothing listed is
    /// `(0, 0)`. `dest` should be a staging directory: a failure leaves it half filled.
    pub fn fetch_tree(&self, relative: &str, dest: &Path) -> Result<(usize, u64)> {
        let listed = self.list(relative)?;
        let this = self.clone();
        let relative = relative.trim_end_matches('/').to_string();
        let dest = dest.to_path_buf();
        self.run(async move {
            let count = listed.len();
            let bytes: Vec<u64> = futures_util::stream::iter(listed)
                .map(|(name, size)| {
                    let (this, key) = (this.clone(), format!("{relative}/{name}"));
                    // Listed names are `/`-separated keys below the prefix; none climbs out.
                    let path = name
                        .split('/')
                        .filter(|part| !part.is_empty() && *part != "." && *part != "..")
                        .fold(dest.clone(), |p, part| p.join(part));
                    async move {
                        if let Some(parent) = path.parent() {
                            tokio::fs::create_dir_all(parent)
                                .await
                                .map_err(|e| Error::io(crate::IoOp::CreateDir, parent, e))?;
                        }
                        if this.fetch_file_async(&key, &path).await? {
                            Ok(size)
                        } else {
                            Err(this.error(&key, "listed, then gone before it was fetched"))
                        }
                    }
                })
                .buffer_unordered(FILES_IN_FLIGHT)
                .try_collect()
                .await?;
            Ok((count, bytes.iter().sum()))
        })
    }

    /// The whole object `relative` in memory (small files: `summary.json`), `None` when there
    /// is no such object.
    pub fn read(&self, relative: &str) -> Result<Option<Bytes>> {
        let this = self.clone();
        let relative = relative.to_string();
        self.run(async move {
            match this.inner.store.get(&this.key(&relative)).await {
                Ok(got) => got
                    .bytes()
                    .await
                    .map(Some)
                    .map_err(|e| this.error(&relative, this.explain(&e))),
                Err(object_store::Error::NotFound { .. }) => Ok(None),
                Err(e) => Err(this.error(&relative, this.explain(&e))),
            }
        })
    }

    /// The size of the object `relative`, `None` when there is none.
    pub fn size(&self, relative: &str) -> Result<Option<u64>> {
        let this = self.clone();
        let relative = relative.to_string();
        self.run(async move { this.size_async(&relative).await })
    }

    async fn size_async(&self, relative: &str) -> Result<Option<u64>> {
        match self.inner.store.head(&self.key(relative)).await {
            Ok(meta) => Ok(Some(meta.size)),
            Err(object_store::Error::NotFound { .. }) => Ok(None),
            Err(e) => Err(self.error(relative, self.explain(&e))),
        }
    }

    /// The object `relative` as a stream of its bytes with its size, `None` when there is
    /// none; the stream is driven by the client's runtime.
    pub async fn get_stream(
        &self,
        relative: &str,
    ) -> Result<Option<(u64, BoxStream<'static, std::io::Result<Bytes>>)>> {
        let this = self.clone();
        let relative = relative.to_string();
        self.run_async(async move {
            let got = match this.inner.store.get(&this.key(&relative)).await {
                Ok(got) => got,
                Err(object_store::Error::NotFound { .. }) => return Ok(None),
                Err(e) => return Err(this.error(&relative, this.explain(&e))),
            };
            let size = got.meta.size;
            let stream = got
                .into_stream()
                .map(|chunk| chunk.map_err(std::io::Error::other))
                .boxed();
            Ok(Some((size, stream)))
        })
        .await
    }

    /// The size of the object `relative` from async code (a HEAD), `None` when there is none.
    pub async fn head(&self, relative: &str) -> Result<Option<u64>> {
        let this = self.clone();
        let relative = relative.to_string();
        self.run_async(async move { this.size_async(&relative).await })
            .await
    }

    /// The bytes `range` (end exclusive, inside the object) of the object `relative` as a
    /// stream, fetched with a ranged GET so that only those bytes travel; `None` when there is
    /// no such object. The stream is driven by the client's runtime.
    pub async fn get_range_stream(
        &self,
        relative: &str,
        range: std::ops::Range<u64>,
    ) -> Result<Option<BoxStream<'static, std::io::Result<Bytes>>>> {
        let this = self.clone();
        let relative = relative.to_string();
        self.run_async(async move {
            let options = GetOptions {
                range: Some(GetRange::Bounded(range)),
                ..GetOptions::default()
            };
            match this
                .inner
                .store
                .get_opts(&this.key(&relative), options)
                .await
            {
                Ok(got) => Ok(Some(
                    got.into_stream()
                        .map(|chunk| chunk.map_err(std::io::Error::other))
                        .boxed(),
                )),
                Err(object_store::Error::NotFound { .. }) => Ok(None),
                Err(e) => Err(this.error(&relative, this.explain(&e))),
            }
        })
        .await
    }

    /// A presigned GET URL of `relative` when presigning is on and the object exists;
    /// `Ok(None)` when there is no such object.
    pub async fn presigned_get(&self, relative: &str) -> Result<Option<String>> {
        let Some(signer) = self.inner.signer.clone() else {
            return Err(self.error(relative, "presigning is off"));
        };
        let this = self.clone();
        let relative = relative.to_string();
        self.run_async(async move {
            if this.size_async(&relative).await?.is_none() {
                return Ok(None);
            }
            let url = signer
                .signed_url(
                    reqwest::Method::GET,
                    &this.key(&relative),
                    this.inner.presigned_ttl,
                )
                .await
                .map_err(|e| this.error(&relative, this.explain(&e)))?;
            Ok(Some(url.to_string()))
        })
        .await
    }

    /// Every object under `relative/`: its path relative to it, size and time written.
    fn objects_under(&self, relative: &str) -> Result<Vec<(String, u64, std::time::SystemTime)>> {
        let this = self.clone();
        let relative = relative.trim_end_matches('/').to_string();
        self.run(async move {
            let dir = this.key(&relative);
            let metas: Vec<_> = this
                .inner
                .store
                .list(Some(&dir))
                .try_collect()
                .await
                .map_err(|e| this.error(&relative, this.explain(&e)))?;
            Ok(metas
                .into_iter()
                .filter_map(|m| {
                    let name = m.location.as_ref().strip_prefix(dir.as_ref())?;
                    let written = std::time::SystemTime::from(m.last_modified);
                    Some((name.trim_start_matches('/').to_string(), m.size, written))
                })
                .collect())
        })
    }

    /// Every object under `relative/`, as paths relative to it with their sizes, sorted.
    pub fn list(&self, relative: &str) -> Result<Vec<Listed>> {
        let mut found: Vec<Listed> = self
            .objects_under(relative)?
            .into_iter()
            .map(|(name, size, _)| (name, size))
            .collect();
        found.sort();
        Ok(found)
    }

    /// The owners of the objects under `relative/` (the first part of each key below it: a
    /// scan's or a job's id) with when the newest of each was written, sorted.
    pub fn owners(&self, relative: &str) -> Result<Vec<(String, std::time::SystemTime)>> {
        let mut owners = std::collections::BTreeMap::new();
        for (name, _, written) in self.objects_under(relative)? {
            let Some(owner) = name.split('/').next() else {
                continue;
            };
            let newest = owners.entry(owner.to_string()).or_insert(written);
            *newest = (*newest).max(written);
        }
        Ok(owners.into_iter().collect())
    }

    /// Removes every object under `relative/`; how many.
    pub fn delete_prefix(&self, relative: &str) -> Result<usize> {
        let this = self.clone();
        let relative = relative.trim_end_matches('/').to_string();
        self.run(async move {
            let dir = this.key(&relative);
            let store = this.inner.store.clone();
            let keys = store.list(Some(&dir)).map_ok(|m| m.location).boxed();
            let deleted: Vec<Key> = store
                .delete_stream(keys)
                .try_collect()
                .await
                .map_err(|e| this.error(&relative, this.explain(&e)))?;
            Ok(deleted.len())
        })
    }

    /// Puts a finished job's local output directory `out` at `jobs/<id>/out/`, logging the
    /// count, bytes and time; on failure, removes what was put.
    pub fn put_outputs(&self, job: &str, out: &Path) -> Result<(usize, u64, Duration)> {
        let started = Instant::now();
        let relative = format!("jobs/{job}/out");
        match self.put_tree(&relative, out) {
            Ok((files, bytes)) => Ok((files, bytes, started.elapsed())),
            Err(e) => {
                let _ = self.delete_prefix(&relative);
                Err(e)
            }
        }
    }
}

/// The text of the first `<tag>…</tag>` in `text` (an S3 error body inside a message).
fn xml_text(text: &str, tag: &str) -> Option<String> {
    let open = format!("<{tag}>");
    let start = text.find(&open)? + open.len();
    let end = text[start..].find(&format!("</{tag}>"))? + start;
    Some(text[start..end].to_string())
}

/// The files under `dir` as `/`-separated paths relative to it, hidden names left out.
fn local_files(dir: &Path) -> std::io::Result<Vec<String>> {
    let mut found = Vec::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for entry in std::fs::read_dir(&d)? {
            let entry = entry?;
            if entry.file_name().to_string_lossy().starts_with('.') {
                continue;
            }
            let kind = entry.file_type()?;
            if kind.is_dir() {
                stack.push(entry.path());
            } else if kind.is_file() {
                let path = entry.path();
                let relative = path.strip_prefix(dir).unwrap_or(&path);
                let parts: Vec<String> = relative
                    .components()
                    .map(|c| c.as_os_str().to_string_lossy().into_owned())
                    .collect();
                found.push(parts.join("/"));
            }
        }
    }
    found.sort();
    Ok(found)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn settings_are_checked_by_name() {
        assert!(BlobSettings::new("s3://lungmotion-data/site-a")
            .validate()
            .is_ok());
        assert!(BlobSettings::new("file:///var/lib/blobs")
            .validate()
            .is_ok());
        for (url, says) in [
            ("s3://A_B/x", "not a bucket name"),
            ("file://relative", "absolute path"),
            ("gs://bucket", "neither s3://"),
        ] {
            let e = BlobSettings::new(url).validate().unwrap_err().to_string();
            assert!(e.contains(says), "{url}: {e}");
        }
        let mut s = BlobSettings::new("file:///tmp/x");
        s.presigned_get = true;
        assert!(s
            .validate()
            .unwrap_err()
            .to_string()
            .contains("presigned_get"));
        let mut s = BlobSettings::new("s3://bucket");
        s.multipart_part_mib = 1;
        assert!(s
            .validate()
            .unwrap_err()
            .to_string()
            .contains("multipart_part_mib"));
        s.multipart_part_mib = 5;
        s.access_key_id = Some("id".into());
        assert!(s
            .validate()
            .unwrap_err()
            .to_string()
            .contains("secret access key"));
        s.secret_access_key = Some("hidden-secret".into());
        assert!(!format!("{s:?}").contains("hidden-secret"));
    }

    #[test]
    fn a_directory_store_puts_lists_fetches_and_deletes_trees() {
        let root = std::env::temp_dir().join(format!("lm-blobs-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&root);
        let out = root.join("out");
        std::fs::create_dir_all(out.join("frames/0")).unwrap();
        std::fs::write(out.join("summary.json"), b"{}").unwrap();
        let big: Vec<u8> = (0..(6u32 << 20)).map(|i| (i % 251) as u8).collect();
        std::fs::write(out.join("frames/0/displacement.nii.gz"), &big).unwrap();
        std::fs::write(out.join(".hidden"), b"x").unwrap();
        let mut settings = BlobSettings::new(format!("file://{}", root.join("blobs").display()));
        settings.multipart_part_mib = 5;
        let blobs = BlobStore::open(&settings).unwrap();
        let (files, bytes, _) = blobs.put_outputs("j1", &out).unwrap();
        assert_eq!((files, bytes), (2, big.len() as u64 + 2));
        let listed = blobs.list("jobs/j1/out").unwrap();
        assert_eq!(
            listed,
            vec![
                ("frames/0/displacement.nii.gz".to_string(), big.len() as u64),
                ("summary.json".to_string(), 2)
            ]
        );
        let back = root.join("back");
        assert!(blobs
            .fetch_file("jobs/j1/out/frames/0/displacement.nii.gz", &back)
            .unwrap());
        assert_eq!(std::fs::read(&back).unwrap(), big);
        assert!(!blobs.fetch_file("jobs/j1/out/nothing", &back).unwrap());
        assert_eq!(
            blobs.read("jobs/j1/out/summary.json").unwrap().unwrap(),
            &b"{}"[..]
        );
        assert_eq!(blobs.size("jobs/j1/out/none").unwrap(), None);
        assert_eq!(blobs.delete_prefix("jobs/j1").unwrap(), 2);
        assert!(blobs.list("jobs/j1").unwrap().is_empty());
        let _ = std::fs::remove_dir_all(&root);
    }
}
