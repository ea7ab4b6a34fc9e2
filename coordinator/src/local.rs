//! The coordinator's own workers: `worker` processes beside this executable (one
//! per core by default), or in-process workers when that binary is absent.

use std::time::Duration;

use tokio::process::{Child, Command};
use tokio::sync::watch;

use crate::farm::{FarmConfig, FarmError, worker_binary};

/// Local workers started for one render.
pub enum LocalWorkers {
    /// Child processes.
    Processes(Vec<(String, Child)>),
    /// Tasks in this process (no `worker` binary found).
    InProcess {
        /// Tells the tasks to stop.
        stop: watch::Sender<bool>,
        /// The tasks.
        tasks: Vec<tokio::task::JoinHandle<Result<worker::WorkerReport, worker::WorkerError>>>,
    },
}

impl LocalWorkers {
    /// Starts `config.local_workers` workers dialling `url`.
    pub fn start(
        config: &FarmConfig,
        url: &str,
        token: Option<&str>,
    ) -> Result<LocalWorkers, FarmError> {
        if config.local_workers == 0 {
            return Ok(LocalWorkers::Processes(Vec::new()));
        }
        let ca_path =
            std::env::temp_dir().join(format!("hypertexture-ca-{}.pem", std::process::id()));
        if let Some((cert, _)) = &config.tls {
            std::fs::write(&ca_path, cert)
                .map_err(|e| FarmError::Tls(format!("{}: {e}", ca_path.display())))?;
        }
        match worker_binary() {
            Some(path) => {
                let mut children = Vec::new();
                for i in 0..config.local_workers {
                    let name = format!("local-{i}");
                    let mut cmd = Command::new(&path);
                    cmd.args([
                        "--coordinator",
                        url,
                        "--threads",
                        &config.local_threads.to_string(),
                    ])
                    .args(["--name", &name, "--exit-when-done", "--quiet"])
                    .env_remove("HYPERTEXTURE_TOKEN")
                    .stdin(std::process::Stdio::null())
                    .kill_on_drop(true);
                    if let Some(t) = token {
                        cmd.env("HYPERTEXTURE_TOKEN", t);
                    }
                    if config.tls.is_some() {
                        cmd.arg("--ca").arg(&ca_path);
                    }
                    let child = cmd.spawn().map_err(|source| FarmError::Spawn {
                        path: path.clone(),
                        source,
                    })?;
                    children.push((name, child));
                }
                tracing::info!(
                    "started {} local worker processes ({})",
                    children.len(),
                    path.display()
                );
                Ok(LocalWorkers::Processes(children))
            }
            None => {
                let (stop, stopped) = watch::channel(false);
                let ca = config.tls.as_ref().map(|(cert, _)| cert.clone());
                let tasks = (0..config.local_workers)
                    .map(|i| {
                        let cfg = worker::WorkerConfig {
                            coordinator: url.to_string(),
                            threads: config.local_threads,
                            token: token.map(str::to_string),
                            name: format!("in-process-{i}"),
                            ca: ca.clone(),
                            exit_when_done: true,
                            fault: None,
                        };
                        tokio::spawn(worker::run(cfg, stopped.clone()))
                    })
                    .collect::<Vec<_>>();
                tracing::info!(
                    "no worker binary beside the coordinator: started {} in-process workers",
                    tasks.len()
                );
                Ok(LocalWorkers::InProcess { stop, tasks })
            }
        }
    }

    /// A message if a local worker process has died (its units are reassigned).
    pub fn check(&mut self) -> Option<String> {
        if let LocalWorkers::Processes(children) = self {
            let mut message = None;
            children.retain_mut(|(name, child)| match child.try_wait() {
                Ok(Some(status)) if !status.success() => {
                    message = Some(format!("local worker {name} exited with {status}"));
                    false
                }
                _ => true,
            });
            return message;
        }
        None
    }

    /// Waits up to `grace` for the workers to leave, then stops the rest (at
    /// once, and quietly, with no grace).
    pub async fn stop(self, grace: Duration) {
        match self {
            LocalWorkers::Processes(children) => {
                for (name, mut child) in children {
                    match tokio::time::timeout(grace, child.wait()).await {
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
                    if tokio::time::timeout(grace, task).await.is_err() && !grace.is_zero() {
                        tracing::warn!("an in-process worker did not stop in time");
                    }
                }
            }
        }
    }
}
