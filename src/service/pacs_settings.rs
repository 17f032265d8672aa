//! The service's PACS: the DICOMweb server jobs take their CT from and push their DICOM
//! outputs to, set by the configuration file's `[pacs]` table and the `LUNGMOTION_PACS_*`
//! environment (see [`super::config`]), never by a request: a client names a study and
//! series on the server the operator configured, not a server of its own.
//!
//! ```toml
//! [pacs]
//! url = "dicomweb://pacs.example.org:8042/dicom-web"   # or http(s)://…, or dicomwebs://
//! username = "lungmotion"                  # HTTP Basic, with password_file
//! password_file = "/etc/lungmotion/pacs-password"
//! # token_file = "/etc/lungmotion/pacs-token"  # or a bearer token instead
//! push = false                             # push every job's DICOM outputs unless it says
//! connect_timeout_s = 10
//! timeout_s = 600                          # one request, a whole series pulled or a batch stored
//! ```

use std::path::{Path, PathBuf};
use std::time::Duration;

use serde::Deserialize;

use crate::error::{IoContext, IoOp};
use crate::pacs::{ClientOptions, DicomWebAddress, DicomWebAuth, DicomWebClient};
use crate::{Error, Result};

/// The PACS settings' environment variables (each overrides the file's key).
pub const PACS_ENV_VARS: [&str; 9] = [
    "LUNGMOTION_PACS_URL",
    "LUNGMOTION_PACS_USERNAME",
    "LUNGMOTION_PACS_PASSWORD",
    "LUNGMOTION_PACS_PASSWORD_FILE",
    "LUNGMOTION_PACS_TOKEN",
    "LUNGMOTION_PACS_TOKEN_FILE",
    "LUNGMOTION_PACS_PUSH",
    "LUNGMOTION_PACS_CONNECT_TIMEOUT_S",
    "LUNGMOTION_PACS_TIMEOUT_S",
];

/// The DICOMweb server of the service and how it is reached.
#[derive(Clone, PartialEq)]
pub struct PacsSettings {
    /// The server's DICOMweb root as an http(s) URL (Orthanc: `http://host:8042/dicom-web`).
    pub root_url: String,
    /// HTTP Basic user name (with `password`).
    pub username: Option<String>,
    /// HTTP Basic password.
    pub password: Option<String>,
    /// Bearer token (instead of a user name and password).
    pub token: Option<String>,
    /// Whether a job pushes its DICOM outputs when its request does not say.
    pub push_by_default: bool,
    /// Longest time to connect, s.
    pub connect_timeout_s: f64,
    /// Longest time for one request, from connecting to the answer's last byte, s.
    pub timeout_s: f64,
}

impl std::fmt::Debug for PacsSettings {
    // The password and token never reach a log.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("PacsSettings")
            .field("root_url", &self.root_url)
            .field("username", &self.username)
            .field("password", &self.password.as_ref().map(|_| "<set>"))
            .field("token", &self.token.as_ref().map(|_| "<set>"))
            .field("push_by_default", &self.push_by_default)
            .field("connect_timeout_s", &self.connect_timeout_s)
            .field("timeout_s", &self.timeout_s)
            .finish()
    }
}

/// The `[pacs]` table of the configuration file.
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub(super) struct PacsFile {
    url: Option<String>,
    username: Option<String>,
    password_file: Option<PathBuf>,
    token_file: Option<PathBuf>,
    push: Option<bool>,
    connect_timeout_s: Option<f64>,
    timeout_s: Option<f64>,
}

impl PacsSettings {
    /// Settings for the server at `url` (`dicomweb://`, `dicomwebs://`, `http://` or
    /// `https://`, the DICOMweb root without a study), no credentials, default bounds.
    pub fn new(url: &str) -> Result<Self> {
        Ok(PacsSettings {
            root_url: root_url_of(url)?,
            username: None,
            password: None,
            token: None,
            push_by_default: false,
            connect_timeout_s: 10.0,
            timeout_s: 600.0,
        })
    }

    /// The credentials as the client sends them (checked by [`PacsSettings::validate`]).
    pub fn auth(&self) -> Option<DicomWebAuth> {
        match (&self.username, &self.password, &self.token) {
            (Some(username), password, None) => Some(DicomWebAuth::Basic {
                username: username.clone(),
                password: password.clone().unwrap_or_default(),
            }),
            (None, None, Some(token)) => Some(DicomWebAuth::Bearer(token.clone())),
            _ => None,
        }
    }

    /// A client of the server with these credentials and timeouts; a pulled series may
    /// bring at most `max_series_bytes` (the service's upload bound).
    pub fn client(&self, max_series_bytes: u64) -> Result<DicomWebClient> {
        DicomWebClient::with_options(
            &self.root_url,
            &ClientOptions {
                auth: self.auth(),
                connect_timeout: Duration::from_secs_f64(self.connect_timeout_s),
                request_timeout: Duration::from_secs_f64(self.timeout_s),
                max_series_bytes,
            },
        )
    }

    /// Refuses credentials that do not go together and timeouts that cannot work.
    pub fn validate(&self) -> Result<()> {
        let bad = |m: String| Err(Error::settings("service configuration", m));
        if self.token.is_some() && (self.username.is_some() || self.password.is_some()) {
            return bad(
                "[pacs]: a bearer token (token_file, LUNGMOTION_PACS_TOKEN) or a user name and \
                 password, not both"
                    .into(),
            );
        }
        if self.password.is_some() && self.username.is_none() {
            return bad(
                "[pacs]: a password without a user name (username, LUNGMOTION_PACS_USERNAME)"
                    .into(),
            );
        }
        for (key, value) in [
            ("username", &self.username),
            ("password", &self.password),
            ("token", &self.token),
        ] {
            if value.as_deref().is_some_and(|v| {
                v.is_empty()
                    || v.chars().any(|c| c.is_control())
                    || (key == "username" && v.contains(':'))
            }) {
                return bad(format!(
                    "[pacs] {key}: empty, or holding a control character{}",
                    if key == "username" { " or a colon" } else { "" }
                ));
            }
        }
        for (key, seconds) in [
            ("connect_timeout_s", self.connect_timeout_s),
            ("timeout_s", self.timeout_s),
        ] {
            if !(seconds.is_finite() && seconds > 0.0 && seconds <= 86_400.0) {
                return bad(format!(
                    "[pacs] {key} must be a number of seconds above 0 and at most 86400, not \
                     {seconds}"
                ));
            }
        }
        Ok(())
    }
}

/// The http(s) root of a configured server address; refuses one that names a study.
fn root_url_of(url: &str) -> Result<String> {
    let text = url.trim();
    let as_dicomweb = if let Some(rest) = text.strip_prefix("http://") {
        format!("dicomweb://{rest}")
    } else if let Some(rest) = text.strip_prefix("https://") {
        format!("dicomwebs://{rest}")
    } else {
        text.to_string()
    };
    let address = DicomWebAddress::parse(&as_dicomweb)
        .map_err(|e| Error::settings("service configuration", format!("[pacs] url: {e}")))?;
    if address.study_uid.is_some() {
        return Err(Error::settings(
            "service configuration",
            format!(
                "[pacs] url {text:?} names a study: give the server's DICOMweb root; jobs name \
                 the study"
            ),
        ));
    }
    Ok(address.root_url)
}

fn read_secret(path: &Path) -> Result<String> {
    let text = std::fs::read_to_string(path).at(IoOp::Read, path)?;
    Ok(text.trim().to_string())
}

/// Applies the file's `[pacs]` table over `current`.
pub(super) fn apply_file(current: &mut Option<PacsSettings>, file: PacsFile) -> Result<()> {
    if let Some(url) = &file.url {
        match current {
            Some(settings) => settings.root_url = root_url_of(url)?,
            None => *current = Some(PacsSettings::new(url)?),
        }
    }
    let Some(settings) = current else {
        return Err(Error::settings(
            "service configuration",
            "[pacs] has no url: the server's DICOMweb root, e.g. \
             \"dicomweb://127.0.0.1:8042/dicom-web\"",
        ));
    };
    if file.username.is_some() {
        settings.username = file.username;
    }
    if let Some(path) = &file.password_file {
        settings.password = Some(read_secret(path)?);
    }
    if let Some(path) = &file.token_file {
        settings.token = Some(read_secret(path)?);
    }
    if let Some(push) = file.push {
        settings.push_by_default = push;
    }
    if let Some(s) = file.connect_timeout_s {
        settings.connect_timeout_s = s;
    }
    if let Some(s) = file.timeout_s {
        settings.timeout_s = s;
    }
    Ok(())
}

/// Applies the `LUNGMOTION_PACS_*` environment over `current`; a variable other than the URL
/// with no server configured is refused by name.
pub(super) fn apply_env(
    current: &mut Option<PacsSettings>,
    env: &dyn Fn(&str) -> Option<String>,
) -> Result<()> {
    if let Some(url) = env("LUNGMOTION_PACS_URL") {
        match current {
            Some(settings) => settings.root_url = root_url_of(&url)?,
            None => *current = Some(PacsSettings::new(&url)?),
        }
    }
    let given: Vec<&str> = PACS_ENV_VARS[1..]
        .iter()
        .copied()
        .filter(|name| env(name).is_some())
        .collect();
    let Some(settings) = current else {
        if let Some(name) = given.first() {
            return Err(Error::settings(
                "service configuration",
                format!("environment {name} is set but no PACS is: set LUNGMOTION_PACS_URL or [pacs] url"),
            ));
        }
        return Ok(());
    };
    let parsed = |name: &str, value: &str, what: &str| -> Result<f64> {
        value.trim().parse().map_err(|_| {
            Error::settings(
                "service configuration",
                format!("environment {name}={value:?} is not {what}"),
            )
        })
    };
    if let Some(v) = env("LUNGMOTION_PACS_USERNAME") {
        settings.username = Some(v.trim().to_string());
    }
    if let Some(v) = env("LUNGMOTION_PACS_PASSWORD_FILE") {
        settings.password = Some(read_secret(Path::new(&v))?);
    }
    if let Some(v) = env("LUNGMOTION_PACS_PASSWORD") {
        settings.password = Some(v.trim().to_string());
    }
    if let Some(v) = env("LUNGMOTION_PACS_TOKEN_FILE") {
        settings.token = Some(read_secret(Path::new(&v))?);
    }
    if let Some(v) = env("LUNGMOTION_PACS_TOKEN") {
        settings.token = Some(v.trim().to_string());
    }
    if let Some(v) = env("LUNGMOTION_PACS_PUSH") {
        settings.push_by_default = v.trim().parse().map_err(|_| {
            Error::settings(
                "service configuration",
                format!("environment LUNGMOTION_PACS_PUSH={v:?} is not true or false"),
            )
        })?;
    }
    if let Some(v) = env("LUNGMOTION_PACS_CONNECT_TIMEOUT_S") {
        settings.connect_timeout_s = parsed(
            "LUNGMOTION_PACS_CONNECT_TIMEOUT_S",
            &v,
            "a number of seconds",
        )?;
    }
    if let Some(v) = env("LUNGMOTION_PACS_TIMEOUT_S") {
        settings.timeout_s = parsed("LUNGMOTION_PACS_TIMEOUT_S", &v, "a number of seconds")?;
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn env_of<'a>(pairs: &'a [(&'a str, &'a str)]) -> impl Fn(&str) -> Option<String> + 'a {
        move |k| {
            pairs
                .iter()
                .find(|(n, _)| *n == k)
                .map(|(_, v)| v.to_string())
        }
    }

    #[test]
    fn the_server_comes_from_the_file_then_the_environment_with_its_credentials() {
        let dir = std::env::temp_dir().join(format!("lm-pacs-settings-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let password = dir.join("password");
        std::fs::write(&password, "s3cret-from-file\n").unwrap();
        let file: PacsFile = toml::from_str(&format!(
            "url = \"http://127.0.0.1:8042/dicom-web/\"\nusername = \"lm\"\n\
             password_file = {:?}\npush = true\ntimeout_s = 60\n",
            password.display().to_string()
        ))
        .unwrap();
        let mut pacs = None;
        apply_file(&mut pacs, file).unwrap();
        let settings = pacs.clone().unwrap();
        assert_eq!(settings.root_url, "http://127.0.0.1:8042/dicom-web");
        assert!(settings.push_by_default);
        assert_eq!(settings.timeout_s, 60.0);
        assert_eq!(
            settings.auth(),
            Some(DicomWebAuth::Basic {
                username: "lm".into(),
                password: "s3cret-from-file".into()
            })
        );
        settings.validate().unwrap();
        assert!(!format!("{settings:?}").contains("s3cret"), "{settings:?}");
        // The environment wins: another server, and no push unless asked.
        apply_env(
            &mut pacs,
            &env_of(&[
                (
                    "LUNGMOTION_PACS_URL",
                    "dicomwebs://pacs.example.org/dicom-web",
                ),
                ("LUNGMOTION_PACS_PUSH", "false"),
            ]),
        )
        .unwrap();
        let settings = pacs.unwrap();
        assert_eq!(settings.root_url, "https://pacs.example.org/dicom-web");
        assert!(!settings.push_by_default);
        // A token and a password together are refused, as is a password alone.
        let both = PacsSettings {
            token: Some("abc".into()),
            ..settings.clone()
        };
        let e = both.validate().unwrap_err().to_string();
        assert!(e.contains("not both"), "{e}");
        let alone = PacsSettings {
            username: None,
            ..settings
        };
        let e = alone.validate().unwrap_err().to_string();
        assert!(e.contains("without a user name"), "{e}");
        let _ = std::fs::remove_dir_all(&dir);
    }

    #[test]
    fn unusable_addresses_and_variables_without_a_server_are_refused_by_name() {
        for (url, named) in [
            ("ftp://pacs/dicom-web", "not a DICOMweb address"),
            (
                "http://127.0.0.1:8042/dicom-web/studies/1.2.3",
                "names a study",
            ),
        ] {
            let e = PacsSettings::new(url).unwrap_err().to_string();
            assert!(e.contains(named), "{url}: {e}");
        }
        let mut pacs = None;
        let e = apply_env(&mut pacs, &env_of(&[("LUNGMOTION_PACS_TOKEN", "t0k3n")]))
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("LUNGMOTION_PACS_TOKEN") && e.contains("LUNGMOTION_PACS_URL"),
            "{e}"
        );
        let e = apply_file(&mut pacs, toml::from_str("push = true").unwrap())
            .unwrap_err()
            .to_string();
        assert!(e.contains("[pacs] has no url"), "{e}");
        let mut pacs = Some(PacsSettings::new("dicomweb://h:1/dw").unwrap());
        let e = apply_env(&mut pacs, &env_of(&[("LUNGMOTION_PACS_TIMEOUT_S", "soon")]))
            .unwrap_err()
            .to_string();
        assert!(e.contains("LUNGMOTION_PACS_TIMEOUT_S"), "{e}");
        let zero = PacsSettings {
            connect_timeout_s: 0.0,
            ..pacs.unwrap()
        };
        let e = zero.validate().unwrap_err().to_string();
        assert!(e.contains("connect_timeout_s"), "{e}");
    }
}
