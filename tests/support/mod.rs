//! The one support module of the tests that run the real binaries (each
//! test binary's `main.rs` declares it): it starts coordinators, services,
//! workers and browsers, each wait bounded by a deadline and each child
//! killed when its handle drops, and holds the helpers the tests share.
//!
//! Tests of one binary run in parallel, so everything a test makes is its
//! own: [`scratch`] directories are unique per call, ports come from the
//! kernel (`127.0.0.1:0`, or [`free_port`]), and a test that must run beside
//! no other holds [`alone`].
#![allow(dead_code)]

use std::path::{Path, PathBuf};
use std::process::{Command, Output, Stdio};
use std::sync::atomic::{AtomicU32, Ordering};
use std::time::{Duration, Instant};

pub mod browser;
pub mod http;
pub mod service;

/// How long a coordinator run by [`coordinator`] may take before it is
/// killed and the test fails.
pub const RUN_SECS: u64 = 600;

/// The repository root.
pub fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

/// A scene of the gallery.
pub fn scene(name: &str) -> PathBuf {
    root().join("scenes").join(format!("{name}.ron"))
}

/// A fresh, empty scratch directory for one test, unique to this call (the
/// tests of one binary share its process id).
pub fn scratch(test: &str) -> PathBuf {
    static CALLS: AtomicU32 = AtomicU32::new(0);
    let call = CALLS.fetch_add(1, Ordering::Relaxed);
    let dir =
        std::env::temp_dir().join(format!("hypertexture-{test}-{}-{call}", std::process::id()));
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

/// Held by a test that must run beside no other test of its binary (one
/// that counts its process's children's CPU, or stops a worker past its
/// lease); released when the guard drops.
pub fn alone() -> std::sync::MutexGuard<'static, ()> {
    static ALONE: std::sync::Mutex<()> = std::sync::Mutex::new(());
    // A test that failed holding it leaves nothing to repair.
    ALONE
        .lock()
        .unwrap_or_else(std::sync::PoisonError::into_inner)
}

/// Runs the coordinator binary with `args` (killed, and the test failed,
/// after [`RUN_SECS`]).
pub fn coordinator(args: &[&str]) -> Output {
    output_within(
        Command::new(env!("CARGO_BIN_EXE_coordinator"))
            .args(args)
            .env_remove("RUST_LOG"),
        RUN_SECS,
    )
}

/// Runs `cmd` to completion, its stdin empty (as [`Command::output`] runs
/// it), killing it after `secs` seconds. Its output is read by threads of
/// its own, so that a full pipe never stalls it.
pub fn output_within(cmd: &mut Command, secs: u64) -> Output {
    let child = cmd
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap_or_else(|e| panic!("{cmd:?} does not start: {e}"));
    collect_within(child, secs)
}

/// Waits (at most `secs`, then kills it and fails the test) for `child`;
/// returns its output (what it wrote to the pipes it was started with),
/// read by threads of its own so that a full pipe never stalls it.
pub fn collect_within(mut child: std::process::Child, secs: u64) -> Output {
    fn drain(r: Option<impl std::io::Read + Send + 'static>) -> std::thread::JoinHandle<Vec<u8>> {
        std::thread::spawn(move || {
            let mut bytes = Vec::new();
            if let Some(mut r) = r {
                let _ = r.read_to_end(&mut bytes);
            }
            bytes
        })
    }
    let stdout = drain(child.stdout.take());
    let stderr = drain(child.stderr.take());
    let status = wait_within(&mut child, secs);
    Output {
        status,
        stdout: stdout.join().expect("stdout is read"),
        stderr: stderr.join().expect("stderr is read"),
    }
}

/// Waits (at most `secs`) for `child` to exit; kills it and fails the test
/// after that.
pub fn wait_within(child: &mut std::process::Child, secs: u64) -> std::process::ExitStatus {
    let deadline = Instant::now() + Duration::from_secs(secs);
    loop {
        if let Some(status) = child.try_wait().expect("the child can be waited for") {
            return status;
        }
        if Instant::now() > deadline {
            let _ = child.kill();
            let _ = child.wait();
            panic!("process {} did not finish within {secs} s", child.id());
        }
        std::thread::sleep(Duration::from_millis(20));
    }
}

/// Renders the gallery scene `scene_name` in-process to `out` (PNG or EXR
/// by extension) with `extra` flags, which must succeed.
pub fn in_process(scene_name: &str, out: &Path, extra: &[&str]) {
    in_process_file(&scene(scene_name), out, extra);
}

/// Renders the scene file `scene` in-process to `out` with `extra` flags,
/// which must succeed.
pub fn in_process_file(scene: &Path, out: &Path, extra: &[&str]) {
    let args = [
        "--scene",
        scene.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
    ];
    let o = coordinator(&[&args[..], extra, &["--in-process", "--quiet"]].concat());
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
}

/// Renders the gallery scene `scene_name` at `size`² in-process to `out`.
pub fn in_process_at(scene_name: &str, size: u32, out: &Path) {
    let size = size.to_string();
    in_process(scene_name, out, &["--width", &size, "--height", &size]);
}

/// A coordinator rendering `scene_name` at `size`² to `out` that starts no
/// workers of its own (the test brings them), with `extra` flags; and its
/// URL once it listens.
pub fn remote_only(scene_name: &str, size: u32, out: &Path, extra: &[&str]) -> (Running, String) {
    let size = size.to_string();
    let scene = scene(scene_name);
    let args = [
        "--scene",
        scene.to_str().unwrap(),
        "--out",
        out.to_str().unwrap(),
        "--width",
        &size,
        "--height",
        &size,
        "--local-workers",
        "0",
    ];
    let mut coord = Running::coordinator(&[&args[..], extra].concat());
    let url = format!("http://127.0.0.1:{}", coord.port());
    (coord, url)
}

/// Two files hold the same bytes.
pub fn same_bytes(a: &Path, b: &Path) {
    let (x, y) = (std::fs::read(a).unwrap(), std::fs::read(b).unwrap());
    assert!(x == y, "{} and {} differ", a.display(), b.display());
}

/// Polls `f` every 50 ms for at most `secs`; panics with `what` if it never holds.
pub fn until(secs: u64, what: &str, mut f: impl FnMut() -> bool) {
    let deadline = Instant::now() + Duration::from_secs(secs);
    while !f() {
        assert!(Instant::now() < deadline, "{what}: not within {secs} s");
        std::thread::sleep(Duration::from_millis(50));
    }
}

/// A process's resident set size in KiB, from /proc (`None` once it is gone).
pub fn rss_kib(pid: u32) -> Option<u64> {
    std::fs::read_to_string(format!("/proc/{pid}/status"))
        .ok()?
        .lines()
        .find_map(|l| l.strip_prefix("VmRSS:"))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse().ok())
}

/// The middle value.
pub fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
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
        fault,
        ..worker_config(url, name)
    };
    let task = runtime.spawn(worker::run(config, stopped));
    (runtime, stop, task)
}

/// The configuration of a worker that runs in this process (`worker::run`):
/// one thread, no token, staying (not `exit_when_done`), a lease of 10 s.
pub fn worker_config(url: &str, name: &str) -> worker::WorkerConfig {
    worker::WorkerConfig {
        coordinator: url.to_string(),
        threads: 1,
        token: None,
        name: name.to_string(),
        ca: None,
        exit_when_done: false,
        lease: std::time::Duration::from_secs(10),
        fault: None,
        shares_process: true,
        tags: Vec::new(),
        asset_cache_bytes: worker::cache::DEFAULT_ASSET_CACHE_MB << 20,
        idle_exit: None,
    }
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
