//! The deployment files (`deploy/`) against the program itself: the service settings file of
//! the compose example and its copy in the Kubernetes ConfigMap are accepted by the service's
//! own parser (unknown keys are refused by name) and say the same; every `LUNGMOTION_*`
//! variable the files name is one the service or the CLI reads; and the environment each
//! process is given there (API, worker), with its secrets as files, resolves to settings the
//! service starts with, as `lungmotion serve` and `lungmotion worker` resolve them.
//! The linters of `deploy/lint.sh` check the files' syntax and schemas; this checks meaning.
#![cfg(feature = "service")]

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use lungmotion::service::config::ENV_VARS;
use lungmotion::service::{ServeOverrides, ServiceConfig};

fn deploy(path: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("deploy")
        .join(path)
}

fn read(path: &Path) -> String {
    std::fs::read_to_string(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

fn no_env(_: &str) -> Option<String> {
    None
}

/// The text of `key: |` in a ConfigMap's `data`, its indentation removed.
fn configmap_entry(yaml: &str, key: &str) -> String {
    let mut lines = yaml.lines().skip_while(|l| l.trim() != format!("{key}: |"));
    let header = lines
        .next()
        .unwrap_or_else(|| panic!("no `{key}: |` in the ConfigMap"));
    let outer = header.len() - header.trim_start().len();
    let body: Vec<&str> = lines
        .take_while(|l| l.trim().is_empty() || l.len() - l.trim_start().len() > outer)
        .collect();
    let indent = body
        .iter()
        .filter(|l| !l.trim().is_empty())
        .map(|l| l.len() - l.trim_start().len())
        .min()
        .expect("an empty ConfigMap entry");
    body.iter()
        .map(|l| l.get(indent..).unwrap_or(""))
        .collect::<Vec<_>>()
        .join("\n")
}

/// `LUNGMOTION_*` variables a Kubernetes container sets (`- name: X` then `value: Y`).
fn manifest_env(yaml: &str) -> BTreeMap<String, String> {
    let lines: Vec<&str> = yaml.lines().map(str::trim).collect();
    let mut env = BTreeMap::new();
    for pair in lines.windows(2) {
        if let (Some(name), Some(value)) = (
            pair[0].strip_prefix("- name: "),
            pair[1].strip_prefix("value: "),
        ) {
            if name.starts_with("LUNGMOTION_") || name.starts_with("AWS_") {
                env.insert(name.to_string(), value.trim_matches('"').to_string());
            }
        }
    }
    env
}

/// `LUNGMOTION_*: value` lines of the compose file's environment blocks, by service
/// (`x-lungmotion-env` is the anchor both lungmotion services merge).
fn compose_env(yaml: &str) -> BTreeMap<String, BTreeMap<String, String>> {
    let mut by_block: BTreeMap<String, BTreeMap<String, String>> = BTreeMap::new();
    let mut block = String::new();
    for line in yaml.lines() {
        let indent = line.len() - line.trim_start().len();
        let text = line.trim();
        if text.starts_with('#') || text.is_empty() {
            continue;
        }
        if (indent == 0 || indent == 2) && text.ends_with(':') {
            block = text.trim_end_matches(':').to_string();
        } else if indent == 0 {
            block = text.split(':').next().unwrap_or("").to_string();
        }
        if let Some((name, value)) = text.split_once(": ") {
            if name.starts_with("LUNGMOTION_") || name.starts_with("AWS_") {
                by_block
                    .entry(block.clone())
                    .or_default()
                    .insert(name.to_string(), value.trim_matches('"').to_string());
            }
        }
    }
    by_block
}

#[test]
fn the_service_file_is_accepted_and_the_configmap_holds_the_same_settings() {
    let file = deploy("service.toml");
    let config = ServiceConfig::load(Some(&file), &no_env).unwrap();
    assert_eq!(config.max_attempts, 2);
    assert_eq!(config.shutdown_grace_s, 30.0);
    assert_eq!(config.run.element_size_mm, 8.0);
    // The pods' terminationGracePeriodSeconds (45 and 60 s) are above the grace of 30 s.
    assert!(config.shutdown_grace_s < 45.0);

    let embedded = configmap_entry(&read(&deploy("kubernetes/config.yaml")), "service.toml");
    let compose: toml::Value = toml::from_str(&read(&file)).unwrap();
    let kubernetes: toml::Value = toml::from_str(&embedded).unwrap();
    assert_eq!(
        compose, kubernetes,
        "deploy/service.toml and the ConfigMap in deploy/kubernetes/config.yaml differ"
    );
}

#[test]
fn every_variable_the_deployment_files_name_is_one_lungmotion_reads() {
    // The service's variables, and the logging ones every subcommand reads (cli/logging.rs).
    let known: Vec<&str> = ENV_VARS
        .iter()
        .copied()
        .chain(["LUNGMOTION_LOG", "LUNGMOTION_LOG_FORMAT"])
        .collect();
    let mut files = vec![deploy("")];
    let mut seen = 0;
    while let Some(path) = files.pop() {
        if path.is_dir() {
            if path.file_name().is_some_and(|n| n == "secrets") {
                continue;
            }
            for entry in std::fs::read_dir(&path).unwrap() {
                files.push(entry.unwrap().path());
            }
            continue;
        }
        let text = read(&path);
        let mut rest = text.as_str();
        while let Some(at) = rest.find("LUNGMOTION_") {
            let name: String = rest[at..]
                .chars()
                .take_while(|c| c.is_ascii_uppercase() || c.is_ascii_digit() || *c == '_')
                .collect();
            rest = &rest[at + name.len()..];
            if name == "LUNGMOTION_" {
                // The prefix alone, as in "LUNGMOTION_*" in a comment.
                continue;
            }
            seen += 1;
            assert!(
                known.contains(&name.as_str()),
                "{}: {name} is read by no part of lungmotion",
                path.display()
            );
        }
    }
    assert!(seen > 10, "only {seen} variables found under deploy/");
}

/// A file holding `text`, standing in for a mounted secret.
fn secret(dir: &Path, name: &str, text: &str) -> String {
    let path = dir.join(name);
    std::fs::write(&path, text).unwrap();
    path.to_string_lossy().into_owned()
}

/// The settings a process started with `env` (its secret files replaced by `secrets`) and
/// `listen` would resolve, as `lungmotion serve` / `worker` do.
fn resolve(
    env: &BTreeMap<String, String>,
    secrets: &BTreeMap<&str, String>,
    listen: Option<&str>,
) -> lungmotion::Result<ServiceConfig> {
    let lookup = |name: &str| {
        env.get(name).map(|value| {
            secrets
                .iter()
                .find(|(key, _)| value.ends_with(*key))
                .map(|(_, path)| path.clone())
                .unwrap_or_else(|| value.clone())
        })
    };
    let overrides = ServeOverrides {
        listen: listen.map(str::to_string),
        ..ServeOverrides::default()
    };
    ServiceConfig::resolve(Some(&deploy("service.toml")), &lookup, &overrides)
}

#[test]
fn the_api_and_worker_environments_resolve_to_settings_the_service_starts_with() {
    let dir = std::env::temp_dir().join(format!("lm-deploy-files-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let mut secrets = BTreeMap::new();
    secrets.insert(
        "api-token",
        secret(&dir, "api-token", "0123456789abcdef0123456789abcdef\n"),
    );
    secrets.insert(
        "db-password",
        secret(&dir, "db-password", "hunter2-but-long\n"),
    );
    secrets.insert(
        "s3-secret-access-key",
        secret(&dir, "s3-secret-access-key", "s3-secret-of-the-site\n"),
    );

    let api = manifest_env(&read(&deploy("kubernetes/api.yaml")));
    let worker = manifest_env(&read(&deploy("kubernetes/worker.yaml")));
    let compose = compose_env(&read(&deploy("compose.yaml")));
    let shared = &compose["x-lungmotion-env"];
    let mut compose_api = shared.clone();
    compose_api.extend(compose["api"].clone());
    let mut compose_worker = shared.clone();
    compose_worker.extend(compose["worker"].clone());
    assert!(api.contains_key("LUNGMOTION_API_TOKEN_FILE"), "{api:?}");
    assert!(compose_api.contains_key("LUNGMOTION_API_TOKEN_FILE"));

    for (what, env, listen) in [
        ("kubernetes api", &api, Some("0.0.0.0:8080")),
        ("compose api", &compose_api, Some("0.0.0.0:8080")),
        ("kubernetes worker", &worker, None),
        ("compose worker", &compose_worker, None),
    ] {
        let config = resolve(env, &secrets, listen).unwrap_or_else(|e| panic!("{what}: {e}"));
        let postgres = config.postgres.as_ref().expect("PostgreSQL configured");
        assert_eq!(
            postgres.password.as_deref(),
            Some("hunter2-but-long"),
            "{what}"
        );
        assert_eq!(
            postgres.server(),
            "lungmotion@postgres:5432/lungmotion",
            "{what}"
        );
        assert_eq!(config.data_dir, Path::new("/var/lib/lungmotion"), "{what}");
        // Below the pods' memory limits (6 and 8 GiB).
        assert_eq!(config.ingest_memory_mib, 4096, "{what}");
        // Every process on the bucket, its secret key from the secret's file.
        let blobs = config.object_store.as_ref().expect("an object store");
        assert_eq!(blobs.url, "s3://lungmotion/site", "{what}");
        assert_eq!(blobs.access_key_id.as_deref(), Some("lungmotion"), "{what}");
        assert_eq!(
            blobs.secret_access_key.as_deref(),
            Some("s3-secret-of-the-site"),
            "{what}"
        );
        blobs.validate().unwrap_or_else(|e| panic!("{what}: {e}"));
        if listen.is_none() {
            // Not the default (10 240): read from the environment.
            assert_eq!(blobs.fetched_scans_mib, 8192, "{what}");
        }
        if listen.is_some() {
            let token = config.api_token.as_deref();
            assert_eq!(token, Some("0123456789abcdef0123456789abcdef"), "{what}");
        }
    }

    // The Secret's placeholders are empty: an API given them refuses to start, by name.
    secrets.insert("api-token", secret(&dir, "api-token", ""));
    let e = resolve(&api, &secrets, Some("0.0.0.0:8080")).unwrap_err();
    assert!(e.to_string().contains("API token"), "{e}");
    let _ = std::fs::remove_dir_all(&dir);
}
