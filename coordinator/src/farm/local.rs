//! The coordinator's own workers: `worker` processes beside this executable (one
//! per core by default), or in-process workers when that binary is absent.

use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use tokio::process::{Child, Command};
use tokio::sync::watch;

/// What the local workers are: how many, with how many threads, trusting
/// which certificate, on what lease.
#[derive(Clone, Copy, Debug)]
pub struct LocalSpec<'a> {
    /// Workers to start (0: none).
    pub count: usize,
    /// Threads per worker.
    pub threads: usize,
    /// The server's certificate (PEM) when the farm speaks TLS.
    pub cert: Option<&'a [u8]>,
    /// A worker silent this long loses its units.
    pub lease: Duration,
}

/// Why the local workers could not start.
#[derive(Debug, thiserror::Error)]
pub enum LocalError {
    /// The CA file for the workers could not be written.
    #[error("{0}")]
    Ca(String),
    /// A worker process could not be started.
    #[error("cannot start local worker {path}: {source}")]
    Spawn {
        /// The binary.
        path: PathBuf,
        /// What the OS said.
        source: std::io::Error,
    },
}

/// The `worker` binary beside this executable, if there is one.
pub fn worker_binary() -> Option<PathBuf> {
    let exe = std::env::current_exe().ok()?;
    let path = exe.with_file_name(format!("worker{}", std::env::consts::EXE_SUFFIX));
    path.is_file().then_some(path)
}

/// A local worker process.
pub struct LocalProcess {
    /// Its name (`local-0`, …).
    name: String,
    /// The process.
    child: Child,
    /// How it exited, once it has.
    exited: Option<std::process::ExitStatus>,
    /// Its stderr: the first line, and whether the pipe has closed. Every
    /// line is also logged here.
    stderr: Arc<Mutex<(Option<String>, bool)>>,
    /// The CA file it was given, removed with the last process holding it.
    _ca: Option<Arc<CaFile>>,
}

/// The CA file local worker processes trust (the server's certificate), in
/// a directory of its own: a fresh random name in the temporary directory,
/// created exclusively and readable by this user only, so no other user can
/// plant or swap it. Dropping it removes the directory.
pub struct CaFile {
    dir: tempfile::TempDir,
}

impl CaFile {
    /// The directory's name starts with this.
    pub const PREFIX: &'static str = "hypertexture-ca-";

    /// Writes `cert` as `ca.pem` in a new private directory.
    pub fn write(cert: &[u8]) -> std::io::Result<CaFile> {
        use std::io::Write as _;
        use std::os::unix::fs::{OpenOptionsExt as _, PermissionsExt as _};
        let dir = tempfile::Builder::new()
            .prefix(Self::PREFIX)
            .permissions(std::fs::Permissions::from_mode(0o700))
            .tempdir()?;
        let ca = CaFile { dir };
        let mut file = std::fs::OpenOptions::new()
            .write(true)
            .create_new(true)
            .custom_flags(libc::O_NOFOLLOW)
            .mode(0o600)
            .open(ca.path())?;
        file.write_all(cert)?;
        Ok(ca)
    }

    /// The file.
    pub fn path(&self) -> std::path::PathBuf {
        self.dir.path().join("ca.pem")
    }
}

impl LocalProcess {
    /// Reads the child's stderr until it closes: logs every line (a worker
    /// runs with --quiet, so these are its warnings and errors) and keeps
    /// the first, which says why a failed worker failed.
    fn watch_stderr(name: &str, child: &mut Child) -> Arc<Mutex<(Option<String>, bool)>> {
        let state = Arc::new(Mutex::new((None, false)));
        let Some(stderr) = child.stderr.take() else {
            state.lock().unwrap_or_else(|p| p.into_inner()).1 = true;
            return state;
        };
        let (name, kept) = (name.to_string(), Arc::clone(&state));
        tokio::spawn(async move {
            use tokio::io::AsyncBufReadExt as _;
            let mut lines = tokio::io::BufReader::new(stderr).lines();
            while let Ok(Some(line)) = lines.next_line().await {
                let line = hypertexture_proto::convert::untrusted(
                    &line,
                    hypertexture_proto::convert::MAX_REASON_CHARS,
                );
                tracing::warn!("local worker {name}: {line}");
                kept.lock()
                    .unwrap_or_else(|p| p.into_inner())
                    .0
                    .get_or_insert(line);
            }
            kept.lock().unwrap_or_else(|p| p.into_inner()).1 = true;
        });
        state
    }

    /// Why it failed: its exit status and the first line it wrote.
    fn failure(&self) -> String {
        let status = self
            .exited
            .map_or_else(|| "?".to_string(), |s| s.to_string());
        match &self.stderr.lock().unwrap_or_else(|p| p.into_inner()).0 {
            Some(line) => format!("local worker {} exited with {status}: {line}", self.name),
            None => format!(
                "local worker {} exited with {status}, saying nothing",
                self.name
            ),
        }
    }

    /// Whether its failure is a refusal by this coordinator (another
    /// protocol or arithmetic): the mark of a binary from another build.
    fn refused(&self) -> bool {
        self.stderr
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .0
            .as_deref()
            .is_some_and(|l| {
                l.contains("protocol version mismatch") || l.contains("arithmetic mismatch")
            })
    }
}

/// Local workers started for one render.
pub enum LocalWorkers {
    /// Child processes, and how to start in-process workers instead should
    /// every one of them fail (a `worker` binary left from an older build
    /// speaks an older protocol: `cargo run -p coordinator` does not rebuild it).
    Processes(Vec<LocalProcess>, Option<InProcessPlan>),
    /// Tasks in this process (no `worker` binary found).
    InProcess {
        /// Tells the tasks to stop.
        stop: watch::Sender<bool>,
        /// The tasks.
        tasks: Vec<tokio::task::JoinHandle<Result<worker::WorkerReport, worker::WorkerError>>>,
    },
}

/// What in-process workers need to dial the coordinator.
pub struct InProcessPlan {
    count: usize,
    threads: usize,
    url: String,
    token: Option<String>,
    ca: Option<Vec<u8>>,
    lease: Duration,
    /// Whether every local worker process that failed so far was refused
    /// for another protocol or arithmetic.
    all_refused: bool,
}

impl InProcessPlan {
    fn start(&self) -> LocalWorkers {
        let (stop, stopped) = watch::channel(false);
        let tasks = (0..self.count)
            .map(|i| {
                let cfg = worker::WorkerConfig {
                    coordinator: self.url.clone(),
                    threads: self.threads,
                    token: self.token.clone(),
                    name: format!("in-process-{i}"),
                    ca: self.ca.clone(),
                    exit_when_done: true,
                    lease: self.lease,
                    fault: None,
                    shares_process: true,
                    tags: Vec::new(),
                    asset_cache_bytes: worker::cache::DEFAULT_ASSET_CACHE_MB << 20,
                    idle_exit: None,
                };
                tokio::spawn(worker::run(cfg, stopped.clone()))
            })
            .collect::<Vec<_>>();
        LocalWorkers::InProcess { stop, tasks }
    }
}

/// The command that starts local worker `name` dialling `url`: its threads,
/// its lease, the token in its environment, the CA to trust, and never
/// outliving this process.
fn worker_command(
    path: &Path,
    spec: &LocalSpec<'_>,
    url: &str,
    token: Option<&str>,
    ca: Option<&CaFile>,
    name: &str,
) -> Command {
    let mut cmd = Command::new(path);
    cmd.args(["--coordinator", url, "--threads", &spec.threads.to_string()])
        .args(["--name", name, "--exit-when-done", "--quiet"])
        .args(["--lease-timeout", &spec.lease.as_secs_f64().to_string()])
        // A local worker never outlives this process, whatever
        // ends it: the worker watches its parent, and on Linux
        // the kernel kills it when this process dies.
        .args(["--parent-pid", &std::process::id().to_string()])
        .env_remove("HYPERTEXTURE_TOKEN")
        .stdin(std::process::Stdio::null())
        .stderr(std::process::Stdio::piped())
        .kill_on_drop(true);
    if let Some(t) = token {
        cmd.env("HYPERTEXTURE_TOKEN", t);
    }
    if let Some(ca) = ca {
        cmd.arg("--ca").arg(ca.path());
    }
    #[cfg(target_os = "linux")]
    // SAFETY: the closure runs in the child between fork and
    // exec and calls only prctl, which is async-signal-safe.
    unsafe {
        cmd.pre_exec(|| {
            if libc::prctl(libc::PR_SET_PDEATHSIG, libc::SIGKILL) != 0 {
                return Err(std::io::Error::last_os_error());
            }
            Ok(())
        });
    }
    cmd
}

impl LocalWorkers {
    /// Starts `spec.count` workers dialling `url`.
    pub fn start(
        spec: LocalSpec<'_>,
        url: &str,
        token: Option<&str>,
    ) -> Result<LocalWorkers, LocalError> {
        if spec.count == 0 {
            return Ok(LocalWorkers::Processes(Vec::new(), None));
        }
        let plan = InProcessPlan {
            count: spec.count,
            threads: spec.threads,
            url: url.to_string(),
            token: token.map(str::to_string),
            ca: spec.cert.map(<[u8]>::to_vec),
            lease: spec.lease,
            all_refused: true,
        };
        match worker_binary() {
            Some(path) => {
                let ca = match spec.cert {
                    Some(cert) => Some(Arc::new(CaFile::write(cert).map_err(|e| {
                        LocalError::Ca(format!(
                            "cannot write the local workers' CA file in {}: {e}",
                            std::env::temp_dir().display()
                        ))
                    })?)),
                    None => None,
                };
                let mut children = Vec::new();
                for i in 0..spec.count {
                    let name = format!("local-{i}");
                    let mut cmd = worker_command(&path, &spec, url, token, ca.as_deref(), &name);
                    let mut child = cmd.spawn().map_err(|source| LocalError::Spawn {
                        path: path.clone(),
                        source,
                    })?;
                    let stderr = LocalProcess::watch_stderr(&name, &mut child);
                    children.push(LocalProcess {
                        name,
                        child,
                        exited: None,
                        stderr,
                        _ca: ca.clone(),
                    });
                }
                tracing::info!(
                    "started {} local worker processes ({})",
                    children.len(),
                    path.display()
                );
                Ok(LocalWorkers::Processes(children, Some(plan)))
            }
            None => {
                tracing::info!(
                    "no worker binary beside the coordinator: started {} in-process workers",
                    plan.count
                );
                Ok(plan.start())
            }
        }
    }

    /// A message if a local worker process has died (its units are reassigned).
    ///
    /// When every local worker process has failed, in-process workers take
    /// their place (they are this very build, so they always speak its protocol).
    pub fn check(&mut self) -> Option<String> {
        let LocalWorkers::Processes(children, plan) = self else {
            return None;
        };
        let mut message = None;
        // A failed process is reported once its stderr has closed, so that the
        // message has the line saying why.
        children.retain_mut(|p| {
            if p.exited.is_none() {
                p.exited = p.child.try_wait().ok().flatten();
            }
            let reported = p.stderr.lock().unwrap_or_else(|e| e.into_inner()).1;
            match p.exited {
                Some(status) if !status.success() && reported => {
                    message = Some(p.failure());
                    if let Some(plan) = plan.as_mut() {
                        plan.all_refused &= p.refused();
                    }
                    false
                }
                _ => true,
            }
        });
        if let Some(last) = &message
            && children.is_empty()
            && let Some(plan) = plan.take()
        {
            let path = worker_binary().map_or_else(String::new, |p| p.display().to_string());
            let cause = if plan.all_refused {
                "a worker binary from an older build speaks another protocol or arithmetic; \
                 `cargo build --release --workspace` rebuilds it"
                    .to_string()
            } else {
                last.clone()
            };
            message = Some(format!(
                "every local worker process ({path}) has failed: running {} in-process workers \
                 instead ({cause})",
                plan.count
            ));
            *self = plan.start();
        }
        message
    }

    /// Waits up to `grace` for the workers to leave, then stops the rest (at
    /// once, and quietly, with no grace). With `terminate`, asks them to leave
    /// first (SIGTERM), as a service does when it stops: its workers hear no
    /// `finished`. The workers share the one `grace`, so however many are
    /// stuck (SIGSTOPped, say), this returns within `grace` and a kill each.
    pub async fn stop(self, grace: Duration, terminate: bool) {
        let deadline = tokio::time::Instant::now() + grace;
        match self {
            LocalWorkers::Processes(children, _) => {
                // Ask first (SIGTERM: a worker delivers its last tile and says
                // goodbye), so that a worker still rendering leaves within
                // the grace.
                #[cfg(unix)]
                for p in children.iter().filter(|_| terminate) {
                    if let Some(pid) = p.child.id() {
                        // SAFETY: kill(2) on our own child's pid, which it keeps
                        // until we wait for it.
                        unsafe {
                            libc::kill(pid as libc::pid_t, libc::SIGTERM);
                        }
                    }
                }
                for LocalProcess {
                    name, mut child, ..
                } in children
                {
                    match tokio::time::timeout_at(deadline, child.wait()).await {
                        Ok(_) => {}
                        Err(_) => {
                            if !grace.is_zero() {
                                tracing::warn!("local worker {name} did not leave: stopping it");
                            }
                            let _ = child.kill().await;
                        }
                    }
                }
            }
            LocalWorkers::InProcess { stop, tasks } => {
                let _ = stop.send(true);
                for task in tasks {
                    if tokio::time::timeout_at(deadline, task).await.is_err() && !grace.is_zero() {
                        tracing::warn!("an in-process worker did not stop in time");
                    }
                }
            }
        }
    }
}
