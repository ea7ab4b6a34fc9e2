//! Command-line arguments, converted into a library [`WorkerConfig`].

use std::num::NonZeroUsize;
use std::path::PathBuf;

use clap::Parser;

use crate::{WorkerConfig, WorkerError};

/// Join a hypertexture render farm: dial the coordinator, render the pixel sets it
/// hands out, send the tiles back. Stateless: the scene arrives with the work.
#[derive(Debug, Parser)]
#[command(version, about, long_about = None)]
pub struct Cli {
    /// The coordinator's address, e.g. http://10.0.0.5:50051 (https:// with --ca).
    #[arg(long, value_name = "URL")]
    pub coordinator: String,
    /// Render threads (default: every core).
    #[arg(long, value_name = "N")]
    pub threads: Option<NonZeroUsize>,
    /// Shared secret the coordinator requires.
    #[arg(
        long,
        env = "HYPERTEXTURE_TOKEN",
        hide_env_values = true,
        value_name = "TOKEN"
    )]
    pub token: Option<String>,
    /// Name shown in the coordinator's logs (default: host name and process id).
    #[arg(long, value_name = "NAME")]
    pub name: Option<String>,
    /// CA certificate (PEM) to verify the coordinator's TLS certificate.
    #[arg(long, value_name = "FILE")]
    pub ca: Option<PathBuf>,
    /// Exit when the coordinator says the frame is finished (instead of waiting
    /// for the next render). Used for the coordinator's own local workers.
    #[arg(long)]
    pub exit_when_done: bool,
    /// A tag for jobs that require it (repeatable), e.g. --tag gpu --tag big-memory:
    /// jobs submitted with --require-tag go only to workers carrying all their tags.
    #[arg(long = "tag", value_name = "NAME", value_parser = tag)]
    pub tag: Vec<String>,
    /// Exit as soon as the process with this id is no longer this worker's
    /// parent (set by the coordinator for its own local workers).
    #[arg(long, value_name = "PID", hide = true)]
    pub parent_pid: Option<u32>,
    /// Only warnings and errors.
    #[arg(long, short)]
    pub quiet: bool,
}

impl Cli {
    /// The library configuration these arguments ask for.
    pub fn into_config(self) -> Result<WorkerConfig, WorkerError> {
        let ca = match &self.ca {
            Some(path) => Some(std::fs::read(path).map_err(|source| WorkerError::Ca {
                path: path.clone(),
                source,
            })?),
            None => None,
        };
        Ok(WorkerConfig {
            coordinator: self.coordinator,
            threads: self.threads.map_or_else(
                || std::thread::available_parallelism().map_or(1, NonZeroUsize::get),
                NonZeroUsize::get,
            ),
            token: self.token.filter(|t| !t.is_empty()),
            name: self.name.unwrap_or_else(default_name),
            ca,
            exit_when_done: self.exit_when_done,
            fault: None,
            shares_process: false,
            tags: self.tag,
        })
    }
}

/// Host name and process id.
fn default_name() -> String {
    let host = std::fs::read_to_string("/proc/sys/kernel/hostname")
        .map(|h| h.trim().to_string())
        .ok()
        .filter(|h| !h.is_empty())
        .or_else(|| std::env::var("HOSTNAME").ok())
        .unwrap_or_else(|| "worker".into());
    format!("{host}-{}", std::process::id())
}

/// A tag: 1 to 64 of `A-Z a-z 0-9 . _ -`.
fn tag(s: &str) -> Result<String, String> {
    if !s.is_empty()
        && s.len() <= 64
        && s.chars()
            .all(|c| c.is_ascii_alphanumeric() || matches!(c, '.' | '_' | '-'))
    {
        Ok(s.to_string())
    } else {
        Err(format!(
            "expected 1 to 64 of A-Z a-z 0-9 . _ -, found {s:?}"
        ))
    }
}
