//! What `coordinator serve` and `coordinator studio` are asked to do (the
//! command line converts its arguments into these), and the
//! [`ServiceConfig`] each becomes.

use std::net::SocketAddr;
use std::num::NonZeroUsize;
use std::path::PathBuf;
use std::time::Duration;

use crate::farm::{self, FarmConfig};
use crate::pipeline::destination;
use crate::service::{ServiceConfig, ServiceError, limits};

/// `coordinator serve`'s settings.
#[derive(Clone, Debug)]
pub struct ServeConfig {
    /// Where the queue, job states and completed tiles are kept.
    pub data: PathBuf,
    /// Where the workers' gRPC and the HTTP API listen.
    pub listen: SocketAddr,
    /// Local worker processes to start (default: one per core).
    pub local_workers: Option<usize>,
    /// Threads of each local worker.
    pub threads: NonZeroUsize,
    /// Shared secret workers and API clients present (empty: none).
    pub token: Option<String>,
    /// Names of this machine served without a token besides loopback's.
    pub allow_hosts: Vec<String>,
    /// TLS certificate and key files.
    pub tls: Option<(PathBuf, PathBuf)>,
    /// A worker silent this long loses its units.
    pub lease: Duration,
    /// On shutdown, how long units in flight get to arrive.
    pub drain_timeout: Duration,
    /// The fraction of units rendered twice and compared.
    pub verify: f64,
    /// The interleave B.
    pub interleave: u32,
    /// Open a store older than its generation file.
    pub accept_older_store: bool,
    /// Directories outputs may be written in (default: the working directory).
    pub output_roots: Vec<PathBuf>,
    /// Jobs not ended the queue holds.
    pub max_queued: usize,
    /// How long ended jobs are kept.
    pub keep_ended: limits::KeepEnded,
    /// Log lines as JSON rather than text.
    pub json_logs: bool,
    /// Only warnings and errors.
    pub quiet: bool,
}

/// `coordinator studio`'s settings.
#[derive(Clone, Debug)]
pub struct StudioConfig {
    /// The scene file to open, or a directory whose first scene opens.
    pub scene: PathBuf,
    /// Where to listen.
    pub listen: SocketAddr,
    /// Local worker processes to start (default: one per core).
    pub local_workers: Option<usize>,
    /// The store (default: a new directory under the temporary directory).
    pub data: Option<PathBuf>,
    /// Shared secret workers and the page present (empty: none).
    pub token: Option<String>,
    /// Names of this machine served without a token besides loopback's.
    pub allow_hosts: Vec<String>,
    /// Only warnings and errors.
    pub quiet: bool,
}

/// The local workers of `asked`, or one per core.
fn local_workers(asked: Option<usize>) -> usize {
    asked.unwrap_or_else(|| std::thread::available_parallelism().map_or(1, NonZeroUsize::get))
}

/// A failure to set up the output roots.
fn roots_error(message: String) -> ServiceError {
    ServiceError::Roots(message)
}

impl ServeConfig {
    /// The service's configuration: the TLS files read, the output roots
    /// resolved against the working directory.
    pub fn service_config(self) -> Result<ServiceConfig, ServiceError> {
        let tls = match &self.tls {
            Some((cert, key)) => Some(crate::farm::cert::read_server_tls(cert, key)?),
            None => None,
        };
        let cwd = std::env::current_dir()
            .map_err(|e| roots_error(format!("cannot read the working directory: {e}")))?;
        let output_roots =
            destination::OutputRoots::for_serve(&self.output_roots, &cwd).map_err(roots_error)?;
        Ok(ServiceConfig {
            data: self.data,
            farm: FarmConfig {
                listen: self.listen,
                token: self.token.filter(|t| !t.is_empty()),
                lease: self.lease,
                worker_timeout: Duration::MAX,
                local_workers: local_workers(self.local_workers),
                local_threads: self.threads.get(),
                preview_every: None,
                tls,
                interleave: self.interleave,
                progress: false,
                gate: Default::default(),
                verify: self.verify,
                allow_hosts: self.allow_hosts,
            },
            drain_timeout: self.drain_timeout,
            studio_scene: None,
            studio_root: None,
            accept_older_store: self.accept_older_store,
            output_roots,
            max_queued: self.max_queued,
            keep_ended: self.keep_ended,
        })
    }
}

impl StudioConfig {
    /// The service's configuration: renders are written beside the scene
    /// or in the working directory; the store is a fresh temporary
    /// directory unless given.
    pub fn service_config(self) -> Result<ServiceConfig, ServiceError> {
        let (scene, scene_dir, browse_first) = self.opened()?;
        let data = self.data.unwrap_or_else(|| {
            std::env::temp_dir().join(format!("hypertexture-studio-{}", std::process::id()))
        });
        let mut dirs = vec![scene_dir.clone()];
        if let Ok(cwd) = std::env::current_dir()
            && cwd.parent().is_some()
        {
            dirs.push(cwd);
        }
        let output_roots = destination::OutputRoots::new(&dirs).map_err(roots_error)?;
        Ok(ServiceConfig {
            data,
            farm: FarmConfig {
                listen: self.listen,
                token: self.token.filter(|t| !t.is_empty()),
                lease: Duration::from_secs(10),
                worker_timeout: Duration::MAX,
                local_workers: local_workers(self.local_workers),
                local_threads: 1,
                preview_every: None,
                tls: None,
                interleave: hypertexture::render::interleave::DEFAULT_INTERLEAVE,
                progress: false,
                gate: Default::default(),
                verify: farm::DEFAULT_VERIFY,
                allow_hosts: self.allow_hosts,
            },
            drain_timeout: Duration::from_secs(5),
            studio_scene: Some(scene),
            studio_root: Some((scene_dir, browse_first)),
            accept_older_store: false,
            output_roots,
            max_queued: limits::DEFAULT_MAX_QUEUED,
            keep_ended: limits::KeepEnded::default(),
        })
    }
}

impl StudioConfig {
    /// The scene to open, the directory the scene browser lists, and whether
    /// the page opens with the browser shown: a directory's first scene (in
    /// path order), shown; or a file and its own directory. A directory
    /// without scenes is an error naming it.
    fn opened(&self) -> Result<(PathBuf, PathBuf, bool), ServiceError> {
        if self.scene.is_dir() {
            let first = crate::service::studio::first_scene(&self.scene).ok_or_else(|| {
                ServiceError::Studio(format!(
                    "{}: no scenes (`*.ron` files) in this directory",
                    self.scene.display()
                ))
            })?;
            return Ok((self.scene.join(first), self.scene.clone(), true));
        }
        let dir = match self.scene.parent() {
            Some(d) if !d.as_os_str().is_empty() => d.to_path_buf(),
            _ => PathBuf::from("."),
        };
        Ok((self.scene.clone(), dir, false))
    }
}

/// `coordinator serve`: sets up logging and the runtime, and serves until
/// SIGTERM or Ctrl-C.
pub fn run(config: ServeConfig) -> Result<(), ServiceError> {
    crate::logging::init_with(config.quiet, config.json_logs);
    super::serve_until_signal(config.service_config()?)
}

/// `coordinator studio SCENE`: the service with its local workers, the
/// scene open at `/`; prints the page's URL and serves until SIGTERM or Ctrl-C.
pub fn run_studio(config: StudioConfig) -> Result<(), ServiceError> {
    crate::logging::init_with(config.quiet, false);
    super::serve_until_signal(config.service_config()?)
}
