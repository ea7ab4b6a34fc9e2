//! Helpers shared by the tests that run the real binaries.
#![allow(dead_code)]

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

pub mod service;

/// The repository root.
pub fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

/// A scene of the gallery.
pub fn scene(name: &str) -> PathBuf {
    root().join("scenes").join(format!("{name}.ron"))
}

/// A fresh, empty scratch directory for one test.
pub fn scratch(test: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("hypertexture-{test}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).expect("scratch directory");
    dir
}

/// A free port on loopback (bound, then released).
pub fn free_port() -> u16 {
    std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

/// Runs the coordinator binary with `args`.
pub fn coordinator(args: &[&str]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_coordinator"))
        .args(args)
        .env_remove("RUST_LOG")
        .output()
        .expect("the coordinator binary runs")
}

/// Decodes a PNG to 8-bit RGBA.
pub fn decode_png(path: &Path) -> image::RgbaImage {
    image::open(path)
        .unwrap_or_else(|e| panic!("{}: {e}", path.display()))
        .to_rgba8()
}

/// The worker binary beside the coordinator, never older than it: built
/// (once per test process, with the test's profile and target directory) when
/// it is missing or stale. The coordinator links the worker library, so any
/// change to the worker's code makes the coordinator binary newer than a
/// `worker` binary left from before it.
pub fn worker_bin() -> PathBuf {
    static BUILT: std::sync::Once = std::sync::Once::new();
    let coordinator = Path::new(env!("CARGO_BIN_EXE_coordinator"));
    let path = coordinator.with_file_name(format!("worker{}", std::env::consts::EXE_SUFFIX));
    let modified = |p: &Path| std::fs::metadata(p).and_then(|m| m.modified()).ok();
    BUILT.call_once(|| {
        if modified(&path).is_some_and(|w| modified(coordinator).is_some_and(|c| w >= c)) {
            return;
        }
        let profile_dir = coordinator.parent().expect("the profile directory");
        let profile = match profile_dir.file_name().and_then(|n| n.to_str()) {
            Some("debug") | None => "dev",
            Some(other) => other,
        };
        let target_dir = profile_dir.parent().expect("the target directory");
        let status = Command::new(env!("CARGO"))
            // The worker package alone: its dependencies' builds are kept
            // apart from the coordinator's, so neither rebuilds the other.
            .args(["build", "--quiet", "-p", "worker", "--bin", "worker"])
            .args(["--profile", profile])
            .arg("--target-dir")
            .arg(target_dir)
            .current_dir(root())
            .status()
            .expect("cargo runs");
        assert!(status.success(), "building the worker binary");
    });
    assert!(path.exists(), "{} was not built", path.display());
    path
}

/// A coordinator started in the background with its stderr captured line by line.
pub struct Running {
    pub child: std::process::Child,
    pub lines: std::sync::mpsc::Receiver<String>,
    pub log: Vec<String>,
}

impl Running {
    /// Starts the coordinator with `args` (its log at info level). The
    /// worker binary is built first, so that its build never counts against
    /// the coordinator's time-outs.
    pub fn coordinator(args: &[&str]) -> Running {
        worker_bin();
        Running::spawn(Command::new(env!("CARGO_BIN_EXE_coordinator")).args(args))
    }

    /// Starts a worker with `args`.
    pub fn worker(args: &[&str]) -> Running {
        Running::spawn(
            Command::new(worker_bin())
                .args(args)
                .env_remove("HYPERTEXTURE_TOKEN"),
        )
    }

    /// Starts `cmd` with its stderr captured line by line.
    pub fn spawn(cmd: &mut Command) -> Running {
        use std::io::BufRead;
        let mut child = cmd
            .env("RUST_LOG", "info")
            .env("NO_COLOR", "1")
            .stdin(std::process::Stdio::null())
            .stdout(std::process::Stdio::null())
            .stderr(std::process::Stdio::piped())
            .spawn()
            .expect("the binary starts");
        let stderr = child.stderr.take().expect("piped");
        let (tx, lines) = std::sync::mpsc::channel();
        std::thread::spawn(move || {
            for line in std::io::BufReader::new(stderr)
                .lines()
                .map_while(Result::ok)
            {
                if tx.send(line).is_err() {
                    break;
                }
            }
        });
        Running {
            child,
            lines,
            log: Vec::new(),
        }
    }

    /// Waits (at most `secs`) for a log line containing `needle`; returns it.
    pub fn wait_for(&mut self, needle: &str, secs: u64) -> String {
        let deadline = std::time::Instant::now() + std::time::Duration::from_secs(secs);
        loop {
            let left = deadline.saturating_duration_since(std::time::Instant::now());
            match self.lines.recv_timeout(left) {
                Ok(line) => {
                    let found = line.contains(needle);
                    self.log.push(line.clone());
                    if found {
                        return line;
                    }
                }
                Err(_) => panic!(
                    "no line with {needle:?} within {secs} s; log so far:\n{}",
                    self.log.join("\n")
                ),
            }
        }
    }

    /// The port from the coordinator's "farm listening on ADDR" line.
    pub fn port(&mut self) -> u16 {
        let line = self.wait_for("farm listening on", 30);
        let addr = line
            .split("farm listening on ")
            .nth(1)
            .and_then(|r| r.split(':').nth(1))
            .expect("address");
        addr.trim_end_matches(|c: char| !c.is_ascii_digit())
            .parse()
            .expect("port")
    }

    /// Waits (at most `secs`) for the process to exit; returns its status and full log.
    pub fn finish(mut self, secs: u64) -> (std::process::ExitStatus, Vec<String>) {
        let deadline = std::time::Instant::now() + std::time::Duration::from_secs(secs);
        loop {
            while let Ok(line) = self.lines.try_recv() {
                self.log.push(line);
            }
            if let Some(status) = self.child.try_wait().expect("wait") {
                std::thread::sleep(std::time::Duration::from_millis(50));
                while let Ok(line) = self.lines.try_recv() {
                    self.log.push(line);
                }
                return (status, std::mem::take(&mut self.log));
            }
            if std::time::Instant::now() > deadline {
                let _ = self.child.kill();
                panic!(
                    "still running after {secs} s; log:\n{}",
                    self.log.join("\n")
                );
            }
            std::thread::sleep(std::time::Duration::from_millis(20));
        }
    }

    /// Sends a signal (SIGKILL = 9, SIGTERM = 15).
    pub fn signal(&self, signal: i32) {
        let status = Command::new("kill")
            .arg(format!("-{signal}"))
            .arg(self.child.id().to_string())
            .status()
            .expect("kill runs");
        assert!(status.success());
    }
}

impl Drop for Running {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

/// Runs `worker::run` in this process (the library the binary calls), with a
/// fault injected, on a runtime of its own; returns the stop switch and the task.
pub fn in_process_worker(
    url: &str,
    name: &str,
    fault: Option<worker::Fault>,
) -> (
    tokio::runtime::Runtime,
    tokio::sync::watch::Sender<bool>,
    tokio::task::JoinHandle<Result<worker::WorkerReport, worker::WorkerError>>,
) {
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(1)
        .enable_all()
        .build()
        .unwrap();
    let (stop, stopped) = tokio::sync::watch::channel(false);
    let config = worker::WorkerConfig {
        coordinator: url.to_string(),
        threads: 1,
        token: None,
        name: name.to_string(),
        ca: None,
        exit_when_done: false,
        lease: std::time::Duration::from_secs(10),
        fault,
        shares_process: true,
        tags: Vec::new(),
        asset_cache_bytes: worker::cache::DEFAULT_ASSET_CACHE_MB << 20,
    };
    let task = runtime.spawn(worker::run(config, stopped));
    (runtime, stop, task)
}

/// Runs `future` to completion on a runtime of its own (one thread), as a
/// test's hand-made client does.
pub fn block_on<F: std::future::Future>(future: F) -> F::Output {
    tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .expect("a tokio runtime")
        .block_on(future)
}

/// Registers a hand-driven worker (a raw gRPC client, for tests that play a
/// worker's part themselves) with this build's protocol and probe digest;
/// returns its id.
pub async fn register_raw(
    client: &mut hypertexture_proto::pb::farm_client::FarmClient<tonic::transport::Channel>,
    name: &str,
) -> String {
    client
        .register(hypertexture_proto::pb::RegisterParams {
            protocol_version: hypertexture_proto::PROTOCOL_VERSION,
            name: name.into(),
            threads: 1,
            arithmetic_digest: hypertexture::render::probe::arithmetic_digest().unwrap(),
            tags: Vec::new(),
        })
        .await
        .unwrap()
        .into_inner()
        .worker_id
}
