//! A real DICOMweb server for the PACS tests: Debian's Orthanc with its DICOMweb plugin
//! (`.ci/run` installs both), started on loopback ports of its own with its storage in a
//! scratch directory, optionally behind HTTP Basic authentication.

#![allow(dead_code)]

use std::net::TcpListener;
use std::path::{Path, PathBuf};
use std::process::{Child, Command};
use std::time::{Duration, Instant};

/// An Orthanc server on loopback, stopped and its storage removed on drop.
pub struct Orthanc {
    child: Child,
    dir: PathBuf,
    /// Its HTTP port.
    pub port: u16,
    /// HTTP Basic credentials it requires, if any.
    credentials: Option<(String, String)>,
}

/// A port nothing listens on now.
pub fn free_port() -> u16 {
    TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

impl Orthanc {
    /// Starts a server whose storage lives in a directory named after `test`.
    pub fn start(test: &str) -> Orthanc {
        Self::start_with(test, None)
    }

    /// As [`Orthanc::start`], requiring HTTP Basic `credentials` (user, password) when given.
    pub fn start_with(test: &str, credentials: Option<(&str, &str)>) -> Orthanc {
        let dir = std::env::temp_dir().join(format!("lm-orthanc-{test}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(dir.join("db")).unwrap();
        let port = free_port();
        let mut config = serde_json::json!({
            "Name": "lungmotion-test",
            "StorageDirectory": dir.join("db"),
            "IndexDirectory": dir.join("db"),
            "HttpPort": port,
            "DicomPort": free_port(),
            "RemoteAccessAllowed": false,
            "AuthenticationEnabled": credentials.is_some(),
            "Plugins": ["/usr/share/orthanc/plugins/libOrthancDicomWeb.so"],
            "DicomWeb": {"Enable": true, "Root": "/dicom-web/"}
        });
        if let Some((user, password)) = credentials {
            config["RegisteredUsers"] = serde_json::json!({ user: password });
        }
        std::fs::write(dir.join("orthanc.json"), config.to_string()).unwrap();
        let log = std::fs::File::create(dir.join("orthanc.log")).unwrap();
        let child = Command::new("Orthanc")
            .arg(dir.join("orthanc.json"))
            .stdout(log.try_clone().unwrap())
            .stderr(log)
            .spawn()
            .expect("Orthanc is not installed (apt-get install orthanc orthanc-dicomweb)");
        let server = Orthanc {
            child,
            dir,
            port,
            credentials: credentials.map(|(u, p)| (u.to_string(), p.to_string())),
        };
        let started = Instant::now();
        while server
            .get(&format!("{}/studies", server.http_root()))
            .is_none_or(|r| !r.status().is_success())
        {
            assert!(
                started.elapsed() < Duration::from_secs(30),
                "Orthanc did not start; its log: {}",
                std::fs::read_to_string(server.dir.join("orthanc.log")).unwrap_or_default()
            );
            std::thread::sleep(Duration::from_millis(200));
        }
        server
    }

    /// `dicomweb://127.0.0.1:PORT/dicom-web`.
    pub fn root(&self) -> String {
        format!("dicomweb://127.0.0.1:{}/dicom-web", self.port)
    }

    /// `http://127.0.0.1:PORT/dicom-web`.
    pub fn http_root(&self) -> String {
        format!("http://127.0.0.1:{}/dicom-web", self.port)
    }

    /// A GET with the server's credentials; `None` when it cannot be reached.
    pub fn get(&self, url: &str) -> Option<reqwest::blocking::Response> {
        let mut request = reqwest::blocking::Client::new().get(url);
        if let Some((user, password)) = &self.credentials {
            request = request.basic_auth(user, Some(password));
        }
        request.send().ok()
    }

    /// Stores every file of `dir` through Orthanc's own REST API (not DICOMweb, so that the
    /// code under test is not what puts them there); how many it stored.
    pub fn store_files(&self, dir: &Path) -> usize {
        let client = reqwest::blocking::Client::new();
        let mut stored = 0;
        for entry in std::fs::read_dir(dir).unwrap() {
            let path = entry.unwrap().path();
            let mut request = client
                .post(format!("http://127.0.0.1:{}/instances", self.port))
                .body(std::fs::read(&path).unwrap());
            if let Some((user, password)) = &self.credentials {
                request = request.basic_auth(user, Some(password));
            }
            let response = request.send().unwrap();
            assert!(
                response.status().is_success(),
                "Orthanc refused {}: {}",
                path.display(),
                response.text().unwrap_or_default()
            );
            stored += 1;
        }
        stored
    }

    /// The study's series as Orthanc's DICOMweb lists them: (modality, series UID).
    pub fn series_of(&self, study: &str) -> Vec<(String, String)> {
        let url = format!("{}/studies/{study}/series", self.http_root());
        let found: serde_json::Value = self.get(&url).unwrap().json().unwrap();
        found
            .as_array()
            .unwrap()
            .iter()
            .map(|s| {
                (
                    s["00080060"]["Value"][0].as_str().unwrap().to_string(),
                    s["0020000E"]["Value"][0].as_str().unwrap().to_string(),
                )
            })
            .collect()
    }

    /// The series' instances' metadata (DICOM JSON) as the server returns it.
    pub fn metadata(&self, study: &str, series: &str) -> serde_json::Value {
        let url = format!(
            "{}/studies/{study}/series/{series}/metadata",
            self.http_root()
        );
        self.get(&url).unwrap().json().unwrap()
    }
}

impl Drop for Orthanc {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
        let _ = std::fs::remove_dir_all(&self.dir);
    }
}

/// The StudyInstanceUID of the DICOM series in `dir` (read from its first file): what a test
/// asks the PACS for after storing that series.
pub fn study_uid_of(dir: &Path) -> String {
    use dicom_dictionary_std::tags;
    let first = std::fs::read_dir(dir)
        .unwrap()
        .next()
        .unwrap()
        .unwrap()
        .path();
    dicom_object::open_file(first)
        .unwrap()
        .element(tags::STUDY_INSTANCE_UID)
        .unwrap()
        .to_str()
        .unwrap()
        .trim_end_matches('\0')
        .to_string()
}
