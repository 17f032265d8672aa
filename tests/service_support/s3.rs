//! An S3 server of the tests' own: moto's (`moto_server`, from PyPI's `moto[server]`, which
//! `.ci/run` installs), started on a free loopback port, its buckets made here, stopped when
//! dropped. moto speaks the S3 protocol over HTTP (SigV4 signatures, multipart uploads,
//! presigned URLs); with [`S3Server::enforce_credentials`] it checks access keys against its
//! own IAM, so refused credentials can be tested.

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use super::postgres::free_port;

/// The access key the tests' servers use while moto does not check credentials.
pub const TEST_KEY_ID: &str = "lungmotion-test";
/// Its secret.
pub const TEST_SECRET: &str = "lungmotion-test-secret";
/// Longest wait for moto to answer after its start.
const START_TIMEOUT: Duration = Duration::from_secs(60);

/// A running moto S3 server.
pub struct S3Server {
    child: Child,
    /// Its port on 127.0.0.1.
    pub port: u16,
    log: PathBuf,
    http: reqwest::blocking::Client,
}

/// A fake SigV4 `Authorization` header naming `service`, so moto routes an unsigned request
/// (IAM here) while it does not check signatures.
fn routed_to(service: &str) -> String {
    format!(
        "AWS4-HMAC-SHA256 Credential={TEST_KEY_ID}/20260101/us-east-1/{service}/aws4_request, \
         SignedHeaders=host, Signature=0"
    )
}

impl S3Server {
    /// Starts `moto_server` on a free loopback port, its log in `dir` (created).
    pub fn start(dir: &Path) -> S3Server {
        std::fs::create_dir_all(dir).unwrap();
        let log = dir.join("moto.log");
        let port = free_port();
        let child = Command::new("moto_server")
            .args(["-H", "127.0.0.1", "-p", &port.to_string()])
            .stdin(Stdio::null())
            .stdout(Stdio::from(std::fs::File::create(&log).unwrap()))
            .stderr(Stdio::from(
                std::fs::OpenOptions::new().append(true).open(&log).unwrap(),
            ))
            .spawn()
            .expect("moto_server is missing: python3 -m pip install 'moto[server]' (.ci/run does)");
        let server = S3Server {
            child,
            port,
            log,
            http: reqwest::blocking::Client::builder()
                .timeout(Duration::from_secs(30))
                .redirect(reqwest::redirect::Policy::none())
                .build()
                .unwrap(),
        };
        let deadline = Instant::now() + START_TIMEOUT;
        loop {
            if server
                .http
                .get(format!("{}/moto-api/", server.endpoint()))
                .send()
                .is_ok()
            {
                break;
            }
            assert!(
                Instant::now() < deadline,
                "moto_server did not answer within {START_TIMEOUT:?}: {}",
                server.log()
            );
            std::thread::sleep(Duration::from_millis(100));
        }
        server
    }

    /// `http://127.0.0.1:PORT`.
    pub fn endpoint(&self) -> String {
        format!("http://127.0.0.1:{}", self.port)
    }

    /// What moto wrote.
    pub fn log(&self) -> String {
        std::fs::read_to_string(&self.log).unwrap_or_default()
    }

    /// Makes the bucket `name` (while credentials are not checked).
    pub fn create_bucket(&self, name: &str) {
        let resp = self
            .http
            .put(format!("{}/{name}", self.endpoint()))
            .send()
            .unwrap();
        assert!(
            resp.status().is_success(),
            "create bucket {name}: {:?}",
            resp.text()
        );
    }

    /// Removes the (empty) bucket `name` (while credentials are not checked).
    pub fn delete_bucket(&self, name: &str) {
        let resp = self
            .http
            .delete(format!("{}/{name}", self.endpoint()))
            .send()
            .unwrap();
        assert!(
            resp.status().is_success(),
            "delete bucket {name}: {:?}",
            resp.text()
        );
    }

    /// The keys under `prefix` in `bucket`, sorted (while credentials are not checked).
    pub fn keys(&self, bucket: &str, prefix: &str) -> Vec<String> {
        let mut keys = Vec::new();
        let mut token: Option<String> = None;
        loop {
            let mut query = vec![
                ("list-type", "2".to_string()),
                ("prefix", prefix.to_string()),
            ];
            if let Some(t) = &token {
                query.push(("continuation-token", t.clone()));
            }
            let text = self
                .http
                .get(format!("{}/{bucket}", self.endpoint()))
                .header("authorization", routed_to("s3"))
                .query(&query)
                .send()
                .unwrap()
                .text()
                .unwrap();
            keys.extend(tag_values(&text, "Key"));
            token = tag_values(&text, "NextContinuationToken")
                .into_iter()
                .next();
            if token.is_none() {
                break;
            }
        }
        keys.sort();
        keys
    }

    /// The keys under `prefix` in `bucket` with their sizes, bytes (while credentials are not
    /// checked; one page of a listing, 1 000 keys, is enough for one scan or job).
    pub fn key_sizes(&self, bucket: &str, prefix: &str) -> Vec<(String, u64)> {
        let text = self
            .http
            .get(format!("{}/{bucket}", self.endpoint()))
            .header("authorization", routed_to("s3"))
            .query(&[("list-type", "2"), ("prefix", prefix)])
            .send()
            .unwrap()
            .text()
            .unwrap();
        tag_values(&text, "Key")
            .into_iter()
            .zip(tag_values(&text, "Size"))
            .map(|(k, n)| (k, n.parse().unwrap()))
            .collect()
    }

    /// The object `key` of `bucket` and its ETag, fetched without a signature (while
    /// credentials are not checked).
    pub fn object(&self, bucket: &str, key: &str) -> (Vec<u8>, String) {
        let resp = self
            .http
            .get(format!("{}/{bucket}/{key}", self.endpoint()))
            // moto refuses anonymous reads of private objects; it checks no signature.
            .header("authorization", routed_to("s3"))
            .send()
            .unwrap();
        assert!(
            resp.status().is_success(),
            "GET {bucket}/{key}: {}",
            resp.status()
        );
        let etag = resp
            .headers()
            .get("etag")
            .map(|v| v.to_str().unwrap().to_string())
            .unwrap_or_default();
        (resp.bytes().unwrap().to_vec(), etag)
    }

    /// Makes an IAM user allowed everything with an access key, then has moto check every
    /// request's credentials from now on; the key id and secret.
    pub fn enforce_credentials(&self) -> (String, String) {
        let iam = |form: &[(&str, &str)]| {
            let resp = self
                .http
                .post(self.endpoint())
                .header("authorization", routed_to("iam"))
                .form(form)
                .send()
                .unwrap();
            let status = resp.status();
            let text = resp.text().unwrap();
            assert!(status.is_success(), "IAM {form:?}: {text}");
            text
        };
        let version = ("Version", "2010-05-08");
        iam(&[("Action", "CreateUser"), ("UserName", "lm"), version]);
        let created = iam(&[("Action", "CreateAccessKey"), ("UserName", "lm"), version]);
        iam(&[
            ("Action", "PutUserPolicy"),
            ("UserName", "lm"),
            ("PolicyName", "everything"),
            (
                "PolicyDocument",
                r#"{"Version":"2012-10-17","Statement":[{"Effect":"Allow","Action":"*","Resource":"*"}]}"#,
            ),
            version,
        ]);
        let id = tag_values(&created, "AccessKeyId").remove(0);
        let secret = tag_values(&created, "SecretAccessKey").remove(0);
        let resp = self
            .http
            .post(format!("{}/moto-api/reset-auth", self.endpoint()))
            .header("content-type", "text/plain")
            .body("0")
            .send()
            .unwrap();
        assert!(resp.status().is_success(), "reset-auth: {:?}", resp.text());
        (id, secret)
    }

    /// The service's environment for the store `s3://<bucket>/<prefix>` on this server,
    /// with the tests' access key.
    pub fn service_env(&self, bucket: &str, prefix: &str) -> Vec<(String, String)> {
        vec![
            (
                "LUNGMOTION_OBJECT_STORE_URL".into(),
                format!("s3://{bucket}/{prefix}"),
            ),
            ("LUNGMOTION_S3_ENDPOINT".into(), self.endpoint()),
            ("AWS_ACCESS_KEY_ID".into(), TEST_KEY_ID.into()),
            ("AWS_SECRET_ACCESS_KEY".into(), TEST_SECRET.into()),
        ]
    }
}

impl Drop for S3Server {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// The texts of every `<tag>…</tag>` in `xml`, in order (S3's answers are flat enough).
pub fn tag_values(xml: &str, tag: &str) -> Vec<String> {
    let (open, close) = (format!("<{tag}>"), format!("</{tag}>"));
    let mut found = Vec::new();
    let mut rest = xml;
    while let Some(start) = rest.find(&open) {
        let after = &rest[start + open.len()..];
        let Some(end) = after.find(&close) else {
            break;
        };
        found.push(after[..end].replace("&quot;", "\"").replace("&amp;", "&"));
        rest = &after[end + close.len()..];
    }
    found
}
