//! A PostgreSQL server of the tests' own: `initdb` in a scratch directory (password
//! authentication, so refused credentials can be tested), `pg_ctl start` on a free loopback
//! port, stopped and removed when dropped. The binaries are Debian's
//! (`/usr/lib/postgresql/<version>/bin`, installed by `.ci/run`); as root they run as the
//! `postgres` user (`runuser`), since PostgreSQL refuses to run as root.
//!
//! Also `lungmotion worker` child processes, which take jobs from such a server.

use std::io::{BufRead, BufReader};
use std::net::TcpListener;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

/// The role the tests' servers are made with.
pub const PG_USER: &str = "lm";
/// Its password.
pub const PG_PASSWORD: &str = "lm-test-password";
/// The database the services use.
pub const PG_DATABASE: &str = "lungmotion";
/// What a worker prints on stdout once it takes jobs.
const WORKER_READY_PREFIX: &str = "lungmotion worker: taking jobs as ";

/// The newest `/usr/lib/postgresql/<version>/bin` holding `initdb`, if any.
pub fn pg_bin_dir() -> Option<PathBuf> {
    let mut dirs: Vec<(u32, PathBuf)> = std::fs::read_dir("/usr/lib/postgresql")
        .ok()?
        .flatten()
        .filter_map(|e| {
            let version = e.file_name().to_string_lossy().parse::<u32>().ok()?;
            let bin = e.path().join("bin");
            bin.join("initdb").is_file().then_some((version, bin))
        })
        .collect();
    dirs.sort();
    dirs.pop().map(|(_, bin)| bin)
}

fn running_as_root() -> bool {
    Command::new("id")
        .arg("-u")
        .output()
        .map(|o| String::from_utf8_lossy(&o.stdout).trim() == "0")
        .unwrap_or(false)
}

/// A free loopback port (bound then released; the server binds it a moment later).
pub fn free_port() -> u16 {
    TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

/// A running PostgreSQL server.
pub struct PgServer {
    bin: PathBuf,
    dir: PathBuf,
    /// Its port on 127.0.0.1.
    pub port: u16,
    as_root: bool,
}

impl PgServer {
    /// `initdb` and `pg_ctl start` under `dir` (created; removed on drop), with database
    /// [`PG_DATABASE`] owned by [`PG_USER`].
    pub fn start(dir: &Path) -> PgServer {
        let bin = pg_bin_dir().expect(
            "PostgreSQL's binaries (/usr/lib/postgresql/*/bin) are missing: apt-get install \
             postgresql (.ci/run does)",
        );
        let _ = std::fs::remove_dir_all(dir);
        std::fs::create_dir_all(dir).unwrap();
        let as_root = running_as_root();
        let pwfile = dir.join("pwfile");
        std::fs::write(&pwfile, PG_PASSWORD).unwrap();
        if as_root {
            let ok = Command::new("chown")
                .args(["-R", "postgres:postgres"])
                .arg(dir)
                .status()
                .unwrap()
                .success();
            assert!(ok, "chown of {} to postgres failed", dir.display());
        }
        let server = PgServer {
            bin,
            dir: dir.to_path_buf(),
            port: free_port(),
            as_root,
        };
        let data = dir.join("data");
        server.tool(
            "initdb",
            &[
                "-D".as_ref(),
                data.as_os_str(),
                "-U".as_ref(),
                PG_USER.as_ref(),
                "--pwfile".as_ref(),
                pwfile.as_os_str(),
                "-A".as_ref(),
                "scram-sha-256".as_ref(),
                "--no-sync".as_ref(),
                "-E".as_ref(),
                "UTF8".as_ref(),
                "--locale=C".as_ref(),
            ],
        );
        server.resume();
        server.psql("postgres", &format!("CREATE DATABASE {PG_DATABASE}"));
        server
    }

    /// Starts the server (again, after [`PgServer::stop`]) on its port and data, waiting until
    /// it accepts connections.
    pub fn resume(&self) {
        let data = self.dir.join("data");
        let options = format!(
            "-p {} -k {} -c listen_addresses=127.0.0.1 -c fsync=off -c max_connections=200",
            self.port,
            self.dir.display()
        );
        let log = self.dir.join("postgres.log");
        self.tool(
            "pg_ctl",
            &[
                "-D".as_ref(),
                data.as_os_str(),
                "-o".as_ref(),
                options.as_ref(),
                "-l".as_ref(),
                log.as_os_str(),
                "-w".as_ref(),
                "-t".as_ref(),
                "60".as_ref(),
                "start".as_ref(),
            ],
        );
    }

    /// Stops the server at once (`pg_ctl stop -m immediate`), as a lost database machine
    /// would go: its clients' connections drop and new ones are refused.
    pub fn stop(&self) {
        let data = self.dir.join("data");
        self.tool(
            "pg_ctl",
            &[
                "-D".as_ref(),
                data.as_os_str(),
                "-m".as_ref(),
                "immediate".as_ref(),
                "-w".as_ref(),
                "stop".as_ref(),
            ],
        );
    }

    /// Runs one of the server's programs (as `postgres` when root); panics with its output
    /// when it fails.
    fn tool(&self, name: &str, args: &[&std::ffi::OsStr]) -> String {
        let program = self.bin.join(name);
        let mut cmd = if self.as_root {
            let mut c = Command::new("runuser");
            c.args(["-u", "postgres", "--"]).arg(&program);
            c
        } else {
            Command::new(&program)
        };
        let out = cmd
            .args(args)
            .current_dir(&self.dir)
            .stdin(Stdio::null())
            .output()
            .unwrap_or_else(|e| panic!("cannot run {}: {e}", program.display()));
        assert!(
            out.status.success(),
            "{name} failed ({}): {}{}",
            out.status,
            String::from_utf8_lossy(&out.stdout),
            String::from_utf8_lossy(&out.stderr)
        );
        String::from_utf8_lossy(&out.stdout).into_owned()
    }

    /// Runs `sql` in `database` with `psql` as the server's owner; its output (unaligned).
    pub fn psql(&self, database: &str, sql: &str) -> String {
        let psql = self.bin.join("psql");
        let out = Command::new(&psql)
            .args([
                "-X",
                "-q",
                "-A",
                "-t",
                "-v",
                "ON_ERROR_STOP=1",
                "-h",
                "127.0.0.1",
            ])
            .args(["-p", &self.port.to_string(), "-U", PG_USER, "-d", database])
            .args(["-c", sql])
            .env("PGPASSWORD", PG_PASSWORD)
            .stdin(Stdio::null())
            .output()
            .unwrap_or_else(|e| panic!("cannot run {}: {e}", psql.display()));
        assert!(
            out.status.success(),
            "psql {sql:?} failed: {}",
            String::from_utf8_lossy(&out.stderr)
        );
        String::from_utf8_lossy(&out.stdout).into_owned()
    }

    /// The services' connection string, with `password`.
    pub fn url_with_password(&self, password: &str) -> String {
        format!(
            "postgres://{PG_USER}:{password}@127.0.0.1:{}/{PG_DATABASE}",
            self.port
        )
    }

    /// The services' connection string.
    pub fn url(&self) -> String {
        self.url_with_password(PG_PASSWORD)
    }

    /// The server's own log.
    pub fn log(&self) -> String {
        std::fs::read_to_string(self.dir.join("postgres.log")).unwrap_or_default()
    }
}

impl Drop for PgServer {
    fn drop(&mut self) {
        let data = self.dir.join("data");
        let program = self.bin.join("pg_ctl");
        let mut cmd = if self.as_root {
            let mut c = Command::new("runuser");
            c.args(["-u", "postgres", "--"]).arg(&program);
            c
        } else {
            Command::new(&program)
        };
        let _ = cmd
            .arg("-D")
            .arg(&data)
            .args(["-m", "immediate", "-w", "stop"])
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .status();
        if !std::thread::panicking() {
            let _ = std::fs::remove_dir_all(&self.dir);
        }
    }
}

/// A `lungmotion worker` child process.
pub struct WorkerProcess {
    child: Child,
    /// Its worker id, as it printed it.
    pub id: String,
    log_path: PathBuf,
}

impl WorkerProcess {
    /// Starts `lungmotion worker --data-dir <data_dir> <extra_args>` with `env` (its
    /// `LUNGMOTION_POSTGRES_URL` among them), its stderr into `log_path`, and waits until it
    /// takes jobs.
    pub fn start(
        data_dir: &Path,
        log_path: &Path,
        extra_args: &[&str],
        env: &[(&str, &str)],
    ) -> WorkerProcess {
        let log = std::fs::OpenOptions::new()
            .create(true)
            .append(true)
            .open(log_path)
            .unwrap();
        let mut cmd = Command::new(env!("CARGO_BIN_EXE_lungmotion"));
        cmd.arg("worker")
            .arg("--data-dir")
            .arg(data_dir)
            .args(extra_args);
        for name in lungmotion::service::config::ENV_VARS {
            cmd.env_remove(name);
        }
        for (k, v) in env {
            cmd.env(k, v);
        }
        let mut child = cmd
            .stdin(Stdio::null())
            .stdout(Stdio::piped())
            .stderr(Stdio::from(log))
            .spawn()
            .expect("spawn lungmotion worker");
        let stdout = child.stdout.take().unwrap();
        let (tx, rx) = mpsc::channel();
        std::thread::spawn(move || {
            for line in BufReader::new(stdout).lines() {
                let Ok(line) = line else { break };
                let _ = tx.send(line);
            }
        });
        let deadline = Instant::now() + Duration::from_secs(60);
        let id = loop {
            let left = deadline.saturating_duration_since(Instant::now());
            match rx.recv_timeout(left.max(Duration::from_millis(1))) {
                Ok(line) => {
                    if let Some(rest) = line.strip_prefix(WORKER_READY_PREFIX) {
                        break rest
                            .split_whitespace()
                            .next()
                            .unwrap_or_default()
                            .to_string();
                    }
                }
                Err(_) => {
                    let status = child.try_wait().ok().flatten();
                    let _ = child.kill();
                    let _ = child.wait();
                    panic!(
                        "the worker did not start (exit: {status:?}); its log:\n{}",
                        std::fs::read_to_string(log_path).unwrap_or_default()
                    );
                }
            }
        };
        WorkerProcess {
            child,
            id,
            log_path: log_path.to_path_buf(),
        }
    }

    /// The process id.
    pub fn pid(&self) -> u32 {
        self.child.id()
    }

    /// SIGKILL, then reap.
    pub fn kill(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }

    /// What it wrote on stderr.
    pub fn log(&self) -> String {
        std::fs::read_to_string(&self.log_path).unwrap_or_default()
    }
}

impl Drop for WorkerProcess {
    fn drop(&mut self) {
        self.kill();
    }
}

/// Runs `lungmotion <args>` with `env` to its end (bounded); its exit code and stderr.
pub fn run_to_exit(args: &[&str], env: &[(&str, &str)]) -> (Option<i32>, String) {
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_lungmotion"));
    cmd.args(args);
    for name in lungmotion::service::config::ENV_VARS {
        cmd.env_remove(name);
    }
    for (k, v) in env {
        cmd.env(k, v);
    }
    let mut child = cmd
        .stdin(Stdio::null())
        .stdout(Stdio::null())
        .stderr(Stdio::piped())
        .spawn()
        .expect("spawn lungmotion");
    let mut stderr = child.stderr.take().unwrap();
    let reader = std::thread::spawn(move || {
        let mut text = String::new();
        let _ = std::io::Read::read_to_string(&mut stderr, &mut text);
        text
    });
    let deadline = Instant::now() + Duration::from_secs(120);
    let status = loop {
        if let Some(status) = child.try_wait().unwrap() {
            break status;
        }
        if Instant::now() > deadline {
            let _ = child.kill();
            let _ = child.wait();
            panic!("lungmotion {args:?} did not exit within 120 s");
        }
        std::thread::sleep(Duration::from_millis(50));
    };
    (status.code(), reader.join().unwrap_or_default())
}
