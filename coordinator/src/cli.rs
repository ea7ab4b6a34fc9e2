//! Command-line arguments, converted into the library's configurations
//! ([`Config`], [`ServeConfig`], [`StudioConfig`]) and requests ([`JobSpec`]).

use std::net::SocketAddr;
use std::num::NonZeroUsize;
use std::path::PathBuf;
use std::time::Duration;

use clap::Parser;
use hypertexture::{FrameRange, Overrides, Quality, RenderRequest};

use worker::cli::positive_seconds;

use crate::CoordinatorError;
use crate::pipeline::run::{Config, FarmOptions};
use crate::service::client::{ClientError, Endpoint};
use crate::service::jobs::JobSpec;
use crate::service::{ServeConfig, StudioConfig};

/// Render a hypertexture scene to PNG or OpenEXR, on a farm of workers (by
/// default local worker processes, one per core) or in-process.
#[derive(Debug, Parser)]
#[command(version, about, long_about = None, args_conflicts_with_subcommands = true, subcommand_negates_reqs = true)]
#[command(mut_arg("tls_cert", |a| a.help("TLS certificate (PEM) for the farm's server; needs --tls-key")))]
pub struct Cli {
    /// Other tasks than rendering.
    #[command(subcommand)]
    pub command: Option<Command>,
    /// Scene file (RON), e.g. scenes/fur.ron.
    #[arg(long, value_name = "FILE", required = true)]
    pub scene: Option<PathBuf>,
    /// Output image; the extension chooses the format (.png or .exr).
    /// Default: the scene's name with .png, in the current directory.
    #[arg(long, value_name = "FILE")]
    pub out: Option<PathBuf>,
    /// What the render overrides: size, samples, quality, knobs.
    #[command(flatten)]
    pub request: RequestArgs,
    /// Render in this process with a thread pool, without the farm (no gRPC).
    #[arg(long)]
    pub in_process: bool,
    /// Threads: of the pool with --in-process (default: every core; 1 is the serial
    /// baseline), or of each local worker on the farm (default 1). At most 4 ×
    /// the cores, and 1024.
    #[arg(long, value_name = "N", value_parser = worker::cli::threads)]
    pub threads: Option<NonZeroUsize>,
    /// The farm: where it listens, its local workers, token and time-outs.
    #[command(flatten)]
    pub farm: FarmArgs,
    /// Rewrite the partial image at --out every SECS seconds while rendering.
    #[arg(long, value_name = "SECS", value_parser = positive_seconds)]
    pub preview_every: Option<f64>,
    /// The farm server's TLS certificate and key.
    #[command(flatten)]
    pub tls: TlsArgs,
    /// How units are checked and split.
    #[command(flatten)]
    pub units: UnitArgs,
    /// Frame number (animated scenes drift their noise by frame · flow; expressions
    /// see `frame` and `t = frame / frame_rate`).
    #[arg(long, value_name = "F", default_value_t = 0)]
    pub frame: u32,
    /// Render frames A to B as a numbered sequence (A..B excludes B, A..=B includes
    /// it): --out fire.png writes fire_0001.png, fire_0002.png, …
    #[arg(long, value_name = "A..B", conflicts_with = "frame", value_parser = frame_range)]
    pub frames: Option<(u32, u32)>,
    /// No progress bar and no log lines; errors are still printed.
    #[arg(long, short)]
    pub quiet: bool,
}

/// What a render asks besides its scene (`coordinator --scene` and `submit`).
#[derive(Debug, clap::Args)]
pub struct RequestArgs {
    /// Image width in pixels (overrides the scene's).
    #[arg(long, value_name = "PIXELS", value_parser = clap::value_parser!(u32).range(1..=16384))]
    pub width: Option<u32>,
    /// Image height in pixels (overrides the scene's).
    #[arg(long, value_name = "PIXELS", value_parser = clap::value_parser!(u32).range(1..=16384))]
    pub height: Option<u32>,
    /// Samples per pixel: jittered positions, step phases and (with the scene's
    /// shutter) times within each pixel, averaged (overrides the scene's `sampling.spp`).
    #[arg(long, value_name = "N", value_parser = clap::value_parser!(u32).range(1..=1024))]
    pub spp: Option<u32>,
    /// Marching step: `interactive` (the scene's interactive_step, 4× its step by
    /// default) or `high` (the scene's step, the default).
    #[arg(long, value_name = "PRESET", value_parser = quality())]
    pub quality: Option<Quality>,
    /// The knobs set.
    #[command(flatten)]
    pub knobs: KnobArgs,
}

impl RequestArgs {
    /// The request these flags ask for, over `frames` (its scene text is
    /// read later).
    pub fn request(self, frames: FrameRange) -> RenderRequest {
        RenderRequest {
            overrides: Overrides {
                width: self.width,
                height: self.height,
                spp: self.spp,
                quality: self.quality,
                knobs: self.knobs.knob_list(),
            },
            frames,
            ..RenderRequest::new(String::new(), String::new())
        }
    }
}

/// How a one-shot render or bake runs its farm.
#[derive(Debug, clap::Args)]
#[command(mut_arg("listen", |a| a
    .default_value("127.0.0.1:0")
    .help("Where the farm listens for workers. Anything but loopback needs --token")))]
#[command(mut_arg("token", |a| a.help("Shared secret workers must present (required beyond loopback)")))]
pub struct FarmArgs {
    /// Where it listens and its local workers.
    #[command(flatten)]
    pub listen: ListenArgs,
    /// The workers' secret.
    #[command(flatten)]
    pub token: worker::cli::TokenArg,
    /// When a silent worker's units go to others.
    #[command(flatten)]
    pub lease: LeaseArg,
    /// Give up (exit non-zero) when no worker is connected for this many seconds.
    #[arg(long, value_name = "SECS", default_value_t = 60.0, value_parser = positive_seconds)]
    pub worker_timeout: f64,
}

impl FarmArgs {
    /// The farm's options: these flags, no previews and no TLS, interleave
    /// 8 and the default verified fraction.
    pub fn options(self) -> FarmOptions {
        FarmOptions {
            listen: self.listen.listen,
            token: self.token.secret(),
            lease: self.lease.lease(),
            worker_timeout: Duration::from_secs_f64(self.worker_timeout),
            local_workers: self.listen.local_workers.unwrap_or_else(|| {
                std::thread::available_parallelism().map_or(1, NonZeroUsize::get)
            }),
            preview_every: None,
            tls: None,
            interleave: 8,
            verify: crate::farm::DEFAULT_VERIFY,
        }
    }
}

/// Where a farm listens and the workers it starts (render, bake, `serve`,
/// `studio`; each words the help its own way with `mut_arg`).
#[derive(Debug, clap::Args)]
pub struct ListenArgs {
    /// Where to listen. Anything but loopback needs --token.
    #[arg(long, value_name = "ADDR:PORT", default_value = "127.0.0.1:47000")]
    pub listen: SocketAddr,
    /// Local worker processes to start (default: one per core; 0 = remote workers only).
    #[arg(long, value_name = "N")]
    pub local_workers: Option<usize>,
}

/// Whom a service serves (`serve` and `studio`): its secret and the names
/// it answers to without one.
#[derive(Debug, clap::Args)]
pub struct AccessArgs {
    /// The secret workers and clients present.
    #[command(flatten)]
    pub token: worker::cli::TokenArg,
    /// A name of this machine the service answers to without a token, besides
    /// 127.0.0.1, localhost and [::1] (repeatable). Without a token any other
    /// `Host` is refused, so that a page elsewhere cannot reach the service by
    /// DNS rebinding; with --token any name is served.
    #[arg(long = "allow-host", value_name = "NAME", value_parser = allowed_host)]
    pub allow_host: Vec<String>,
}

/// A server's TLS certificate and key (a render's farm and `serve`).
#[derive(Debug, clap::Args)]
pub struct TlsArgs {
    /// TLS certificate (PEM); needs --tls-key.
    #[arg(long, value_name = "FILE", requires = "tls_key")]
    pub tls_cert: Option<PathBuf>,
    /// TLS private key (PEM); needs --tls-cert.
    #[arg(long, value_name = "FILE", requires = "tls_cert")]
    pub tls_key: Option<PathBuf>,
}

impl TlsArgs {
    /// The certificate and key, when both are given.
    pub fn pair(self) -> Option<(PathBuf, PathBuf)> {
        self.tls_cert.zip(self.tls_key)
    }
}

/// How a farm checks and splits its units (a render and `serve`).
#[derive(Debug, clap::Args)]
pub struct UnitArgs {
    /// Fraction of units rendered a second time (by another worker, or by the
    /// coordinator) and compared byte for byte; a worker whose tile differs
    /// from the coordinator's own rendering is blocklisted and its units
    /// rendered again. 0 turns it off, 1 checks every unit.
    #[arg(long, value_name = "FRACTION", default_value_t = crate::farm::DEFAULT_VERIFY, value_parser = fraction)]
    pub verify: f64,
    /// Pixel-set interleave B (B×B sets): 1, 2, 4, 8, 16, 32 or 64.
    #[arg(long, value_name = "B", default_value_t = 8, value_parser = interleave)]
    pub interleave: u32,
}

/// `--set KNOB=VALUE` (repeatable): knob values of a render, a bake or an
/// `eval`, parsed by [`Overrides::parse_knob`] (`eval` words the help with
/// `mut_arg`).
#[derive(Debug, clap::Args)]
pub struct KnobArgs {
    /// Set a knob of the scene (repeatable): --set curliness=0.8.
    #[arg(long = "set", value_name = "KNOB=VALUE", value_parser = Overrides::parse_knob)]
    pub set: Vec<(String, f64)>,
}

impl KnobArgs {
    /// The knobs as a request holds them ([`Overrides::knob_list`]).
    pub fn knob_list(self) -> Vec<(String, f64)> {
        Overrides::knob_list(self.set)
    }
}

/// `--lease-timeout` of a farm (a render's, a bake's and `serve`'s).
#[derive(Debug, clap::Args)]
pub struct LeaseArg {
    /// Seconds of silence after which a worker's units go to others.
    #[arg(long, value_name = "SECS", default_value_t = 10.0, value_parser = positive_seconds)]
    pub lease_timeout: f64,
}

impl LeaseArg {
    /// How long a lease lasts.
    pub fn lease(&self) -> Duration {
        Duration::from_secs_f64(self.lease_timeout)
    }
}

/// Subcommands.
#[derive(Debug, clap::Subcommand)]
pub enum Command {
    /// Measure the farm's speedup on this machine and simulate larger farms.
    Bench(BenchArgs),
    /// Print a greyscale PNG as a 2D shape transfer function, `Grid(rows: [...])`,
    /// to paste into a scene's distortion (left to right: noise; top to bottom:
    /// density 0 to 1; white = 1).
    Grid(GridArgs),
    /// Print the value of an expression at a point: a probe for designing
    /// hypertextures, e.g. `coordinator eval "improved(3.14, 42, 7)"`.
    Eval(EvalArgs),
    /// Sample the scene's hypertexture on a voxel lattice and write it as an
    /// OpenVDB file: a `density` grid and a `color` grid, for Blender or
    /// Houdini.
    Bake(BakeArgs),
    /// Map the density channel of a rendered EXR to colour again, without
    /// re-rendering (the 1985 paper's two-pass compositing).
    Recolor(RecolorArgs),
    /// Run the farm as a long-running service: a job queue kept under --data,
    /// workers that stay between jobs, an HTTP/JSON API and metrics on the
    /// workers' port.
    Serve(ServeArgs),
    /// The live studio: the service with its local workers and SCENE (or the
    /// first scene of DIR) open in a page (at the printed URL) that refines
    /// the image as units arrive, with a slider per knob, the scene's text
    /// editable and a browser of the directory's scenes.
    Studio(StudioArgs),
    /// Queue a job on a running service; prints its id.
    Submit(SubmitArgs),
    /// Show a service's jobs and workers (or one job).
    Status(StatusArgs),
    /// Cancel a job on a running service.
    Cancel(JobArgs),
    /// Wait for a job to end; exit status 0 only if it is done.
    Wait(JobArgs),
    /// Check or back up a service's store (`--data`), also while it runs.
    #[command(subcommand)]
    Store(StoreCommand),
    /// Make TLS certificates for a farm on a LAN: a CA (ca.pem, ca.key) and
    /// a server certificate signed by it (server.pem, server.key) for
    /// `serve --tls-cert DIR/server.pem --tls-key DIR/server.key`; workers
    /// trust it with `--ca DIR/ca.pem`.
    Cert(CertArgs),
}

/// `coordinator store …`.
#[derive(Debug, clap::Subcommand)]
pub enum StoreCommand {
    /// SQLite's full integrity_check and every stored tile's checksum; exit
    /// status 1 if anything is wrong.
    Check {
        /// The service's data directory.
        #[arg(long, value_name = "DIR")]
        data: PathBuf,
    },
    /// A consistent copy of the store to FILE, taken with SQLite's online
    /// backup API (the service may keep running). Restore: stop the service,
    /// put FILE in place of DIR/farm.sqlite, delete DIR/farm.sqlite-wal and
    /// DIR/farm.sqlite-shm, start with --accept-older-store (deploy/README.md).
    Backup {
        /// The service's data directory.
        #[arg(long, value_name = "DIR")]
        data: PathBuf,
        /// Where the copy goes (replaced if it exists).
        #[arg(value_name = "FILE")]
        file: PathBuf,
    },
}

/// The default address of `serve` and of the clients' `--server`.
pub const DEFAULT_SERVER: &str = "http://127.0.0.1:47000";

/// How the service logs.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum LogFormat {
    /// One line of text per event.
    Plain,
    /// One JSON object per event.
    Json,
}

/// Arguments of `coordinator serve`.
#[derive(Debug, clap::Args)]
#[command(mut_arg("listen", |a| a.help(
    "Where to listen: the workers' gRPC and the HTTP API share this port. Anything but loopback needs --token")))]
#[command(mut_arg("token", |a| a.help(
    "Shared secret that workers and API clients must present (required beyond loopback)")))]
#[command(mut_arg("tls_cert", |a| a.help(
    "TLS certificate (PEM); needs --tls-key. Covers gRPC and HTTP alike")))]
pub struct ServeArgs {
    /// Where the queue, job states and completed tiles are kept (created if missing).
    #[arg(long, value_name = "DIR")]
    pub data: PathBuf,
    /// Where it listens and its local workers.
    #[command(flatten)]
    pub listen: ListenArgs,
    /// Threads of each local worker (at most 4 × the cores, and 1024).
    #[arg(long, value_name = "N", default_value = "1", value_parser = worker::cli::threads)]
    pub threads: NonZeroUsize,
    /// Who it serves.
    #[command(flatten)]
    pub access: AccessArgs,
    /// Its TLS certificate and key.
    #[command(flatten)]
    pub tls: TlsArgs,
    /// When a silent worker's units go to others.
    #[command(flatten)]
    pub lease: LeaseArg,
    /// On SIGTERM or Ctrl-C: seconds that units in flight get to arrive.
    #[arg(long, value_name = "SECS", default_value_t = 30.0, value_parser = positive_seconds)]
    pub drain_timeout: f64,
    /// How units are checked and split.
    #[command(flatten)]
    pub units: UnitArgs,
    /// Open a store that is older than its generation file (jobs committed
    /// since are missing: a lost or truncated WAL, an older copy put back)
    /// and go on with what it holds; new job ids still start past every id
    /// given out.
    #[arg(long)]
    pub accept_older_store: bool,
    /// A directory jobs may write their outputs in (repeatable); every
    /// output must resolve inside one, after `..` and symlinks. Default: the
    /// directory serve is started in (never `/`).
    #[arg(long, value_name = "DIR")]
    pub output_root: Vec<PathBuf>,
    /// Jobs not ended (queued or running) the queue holds; one more
    /// submission is refused with 429 and Retry-After.
    #[arg(long, value_name = "N", default_value_t = crate::service::limits::DEFAULT_MAX_QUEUED)]
    pub max_queued: usize,
    /// How long ended jobs are kept: an age (7d, 12h, 30m, 90s), a number of
    /// the newest jobs, or both (7d,1000); then they leave the list and the
    /// store (their files stay).
    #[arg(long, value_name = "AGE,N", default_value = crate::service::limits::DEFAULT_KEEP_ENDED)]
    pub keep_ended: crate::service::limits::KeepEnded,
    /// Log lines as text or JSON.
    #[arg(long, value_name = "FORMAT", default_value = "plain")]
    pub log_format: LogFormat,
    /// Only warnings and errors.
    #[arg(long, short)]
    pub quiet: bool,
}

/// Arguments of `coordinator studio`.
#[derive(Debug, clap::Args)]
#[command(mut_arg("listen", |a| a.help(
    "Where to listen (port 0: any free port). Anything but loopback needs --token")))]
#[command(mut_arg("local_workers", |a| a.help("Local worker processes to start (default: one per core)")))]
#[command(mut_arg("token", |a| a.help("Shared secret workers and the page must present")))]
pub struct StudioArgs {
    /// The scene file (RON) to open, or a directory: the page's scene browser
    /// lists every `*.ron` scene under it (a file's own directory for a file)
    /// with thumbnails, and opens the first in path order. Save writes the
    /// open scene back (the file before to SCENE.~N~).
    #[arg(value_name = "SCENE|DIR")]
    pub scene: PathBuf,
    /// Where it listens and its local workers.
    #[command(flatten)]
    pub listen: ListenArgs,
    /// The service's store (default: a new directory under the system's temporary directory).
    #[arg(long, value_name = "DIR")]
    pub data: Option<PathBuf>,
    /// Who it serves.
    #[command(flatten)]
    pub access: AccessArgs,
    /// Only warnings and errors.
    #[arg(long, short)]
    pub quiet: bool,
}

/// How a client reaches the service.
#[derive(Debug, clap::Args)]
#[command(mut_arg("token", |a| a.help("The service's token (needed beyond loopback)")))]
#[command(mut_arg("ca", |a| a.help("CA certificate (PEM) to verify an https:// service")))]
pub struct ServerArgs {
    /// The service's URL.
    #[arg(long, value_name = "URL", default_value = DEFAULT_SERVER)]
    pub server: String,
    /// The service's token.
    #[command(flatten)]
    pub token: worker::cli::TokenArg,
    /// The service's CA.
    #[command(flatten)]
    pub ca: worker::cli::CaArg,
}

/// Arguments of `coordinator submit`.
#[derive(Debug, clap::Args)]
pub struct SubmitArgs {
    /// The service.
    #[command(flatten)]
    pub server: ServerArgs,
    /// Scene file (RON); its text is sent with the job.
    #[arg(value_name = "SCENE")]
    pub scene: PathBuf,
    /// Output path pattern on the coordinator's machine: `#` runs are the
    /// padded frame number (out/fur.####.exr); a relative path is made absolute
    /// against this directory.
    #[arg(long, value_name = "PATTERN")]
    pub out: String,
    /// Frames A..B (B excluded) or A..=B (B included); default: frame 0.
    #[arg(long, value_name = "A..B", value_parser = frame_range)]
    pub frames: Option<(u32, u32)>,
    /// Higher runs first; ties run oldest first.
    #[arg(
        long,
        value_name = "N",
        default_value_t = 0,
        allow_negative_numbers = true
    )]
    pub priority: i32,
    /// What the job overrides: size, samples, quality, knobs.
    #[command(flatten)]
    pub request: RequestArgs,
    /// Only workers carrying this tag render the job (repeatable: all of them).
    #[arg(long = "require-tag", value_name = "NAME")]
    pub require_tag: Vec<String>,
}

/// Arguments of `coordinator status`.
#[derive(Debug, clap::Args)]
pub struct StatusArgs {
    /// The service.
    #[command(flatten)]
    pub server: ServerArgs,
    /// One job's id (default: every job, and the workers).
    #[arg(value_name = "JOB")]
    pub job: Option<u64>,
}

/// Arguments of `coordinator cancel` and `coordinator wait`.
#[derive(Debug, clap::Args)]
pub struct JobArgs {
    /// The service.
    #[command(flatten)]
    pub server: ServerArgs,
    /// The job's id.
    #[arg(value_name = "JOB")]
    pub job: u64,
}

/// Arguments of `coordinator cert`.
#[derive(Debug, clap::Args)]
pub struct CertArgs {
    /// Directory to write ca.pem, ca.key, server.pem and server.key to
    /// (created readable by its owner only; existing files are never replaced).
    #[arg(long, value_name = "DIR")]
    pub out: PathBuf,
    /// A host name or IP address workers and clients dial the coordinator by
    /// (repeatable); localhost, 127.0.0.1 and ::1 are always included.
    #[arg(long = "name", value_name = "HOST")]
    pub name: Vec<String>,
}

/// Arguments of `coordinator grid`.
#[derive(Debug, clap::Args)]
pub struct GridArgs {
    /// The greyscale PNG.
    #[arg(long, value_name = "FILE")]
    pub png: PathBuf,
    /// Most values a side (2 to 64); larger images are box-filtered down.
    #[arg(long, value_name = "N", default_value_t = 16, value_parser = clap::value_parser!(u32).range(2..=64))]
    pub side: u32,
}

/// Arguments of `coordinator eval`.
#[derive(Debug, clap::Args)]
#[command(mut_arg("set", |a| a.help("Set a knob of the scene (repeatable)")))]
pub struct EvalArgs {
    /// The expression, e.g. "turbulence(x * 4)".
    #[arg(value_name = "EXPR")]
    pub expression: String,
    /// A scene whose knobs, functions, objects (D, named), colour map and noise
    /// seed the expression may use.
    #[arg(long, value_name = "FILE")]
    pub scene: Option<PathBuf>,
    /// The point x.
    #[arg(long, value_name = "X,Y,Z", default_value = "0,0,0", value_parser = point)]
    pub at: [f64; 3],
    /// The frame (t = frame / frame_rate).
    #[arg(long, value_name = "F", default_value_t = 0)]
    pub frame: u32,
    /// The knobs set.
    #[command(flatten)]
    pub knobs: KnobArgs,
}

/// Arguments of `coordinator bake`.
#[derive(Debug, clap::Args)]
pub struct BakeArgs {
    /// Scene file (RON), e.g. scenes/fur.ron.
    #[arg(value_name = "SCENE")]
    pub scene: PathBuf,
    /// The OpenVDB file; a run of # is the frame number padded to its length
    /// (fur.####.vdb), needed with --frames.
    #[arg(long, value_name = "FILE")]
    pub out: String,
    /// Voxels along the longest edge of the box where the density can be non-zero.
    #[arg(long, value_name = "N", default_value_t = 128, value_parser = clap::value_parser!(u32).range(2..=i64::from(crate::pipeline::bake::MAX_RESOLUTION)))]
    pub resolution: u32,
    /// Frame number (animated scenes).
    #[arg(long, value_name = "F", default_value_t = 0)]
    pub frame: u32,
    /// Bake frames A to B (A..B excludes B, A..=B includes it), one file each.
    #[arg(long, value_name = "A..B", conflicts_with = "frame", value_parser = frame_range)]
    pub frames: Option<(u32, u32)>,
    /// Threads: of the pool with --in-process (default: every core), or of
    /// each local worker on the farm (default 1).
    #[arg(long, value_name = "N", value_parser = worker::cli::threads)]
    pub threads: Option<NonZeroUsize>,
    /// The knobs set.
    #[command(flatten)]
    pub knobs: KnobArgs,
    /// Bake in this process with a thread pool, without the farm (no gRPC).
    #[arg(long)]
    pub in_process: bool,
    /// The farm: where it listens, its local workers, token and time-outs.
    #[command(flatten)]
    pub farm: FarmArgs,
    /// No log lines; errors are still printed.
    #[arg(long, short)]
    pub quiet: bool,
}

impl BakeArgs {
    /// The library configuration of the bake.
    pub fn into_config(self) -> crate::pipeline::bake::BakeConfig {
        crate::pipeline::bake::BakeConfig {
            scene: self.scene,
            out: self.out,
            resolution: self.resolution,
            frame: self.frame,
            frames: self.frames,
            threads: self.threads,
            knobs: self.knobs.set,
            farm: (!self.in_process).then(|| self.farm.options()),
        }
    }
}

/// Arguments of `coordinator recolor`.
#[derive(Debug, clap::Args)]
pub struct RecolorArgs {
    /// An EXR written by the coordinator (it has a `density` channel).
    #[arg(value_name = "IN.exr")]
    pub input: PathBuf,
    /// A colour map file, e.g. scenes/colormaps/fire.ron.
    #[arg(long, value_name = "FILE")]
    pub colormap: PathBuf,
    /// The output image (.png or .exr).
    #[arg(long, value_name = "FILE")]
    pub out: PathBuf,
}

/// Arguments of `coordinator bench`.
#[derive(Debug, clap::Args)]
pub struct BenchArgs {
    /// Scene to measure.
    #[arg(long, value_name = "FILE", default_value = "scenes/fur.ron")]
    pub scene: PathBuf,
    /// A deliberately unbalanced scene for the simulation (all density in one corner).
    #[arg(long, value_name = "FILE", default_value = "scenes/bench/corner.ron")]
    pub unbalanced: PathBuf,
    /// Image width (overrides the scene's).
    #[arg(long, value_name = "PIXELS", value_parser = clap::value_parser!(u32).range(1..=16384))]
    pub width: Option<u32>,
    /// Image height (overrides the scene's).
    #[arg(long, value_name = "PIXELS", value_parser = clap::value_parser!(u32).range(1..=16384))]
    pub height: Option<u32>,
    /// Local worker process counts to measure.
    #[arg(
        long,
        value_name = "N,N,…",
        value_delimiter = ',',
        default_value = "1,2,4"
    )]
    pub workers: Vec<usize>,
    /// Farm sizes to simulate.
    #[arg(
        long,
        value_name = "N,N,…",
        value_delimiter = ',',
        default_value = "8,16,64,256"
    )]
    pub simulate: Vec<usize>,
    /// Tiles as for an EXR output (every sample, 36 bytes a pixel) instead of a
    /// PNG's 8-bit colour (4 bytes a pixel).
    #[arg(long)]
    pub exr: bool,
    /// Rounds per farm size, each an in-process render on every core then the
    /// farm, taking turns; the row gives the medians.
    #[arg(long, value_name = "N", default_value_t = 3, value_parser = clap::value_parser!(u32).range(1..=100))]
    pub rounds: u32,
}

impl BenchArgs {
    /// The library configuration of the benchmark.
    pub fn into_config(self) -> crate::pipeline::bench::BenchConfig {
        crate::pipeline::bench::BenchConfig {
            scene: self.scene,
            unbalanced: self.unbalanced,
            width: self.width,
            height: self.height,
            workers: self.workers.into_iter().filter(|&n| n > 0).collect(),
            simulate: self.simulate.into_iter().filter(|&n| n > 0).collect(),
            rounds: self.rounds as usize,
            pixel_format: if self.exr {
                hypertexture::PixelFormat::Samples
            } else {
                hypertexture::PixelFormat::Srgb8
            },
        }
    }
}

impl Cli {
    /// The library configuration these arguments ask for (a render: no
    /// subcommand): the output checked and the scene read
    /// ([`Config::load`]).
    pub fn into_config(self) -> Result<Config, CoordinatorError> {
        let scene = self.scene.unwrap_or_default();
        let out = self.out.unwrap_or_else(|| {
            let stem = scene
                .file_stem()
                .map_or_else(|| "render".into(), |s| s.to_os_string());
            PathBuf::from(stem).with_extension("png")
        });
        let frames = match self.frames {
            Some((first, last)) => FrameRange { first, last },
            None => FrameRange::one(self.frame),
        };
        let request = self.request.request(frames);
        let config = Config::load(&scene, out, request, self.frames.is_some())?;
        let farm = (!self.in_process).then(|| FarmOptions {
            preview_every: self.preview_every.map(Duration::from_secs_f64),
            tls: self.tls.pair(),
            interleave: self.units.interleave,
            verify: self.units.verify,
            ..self.farm.options()
        });
        Ok(Config {
            threads: self.threads,
            progress: !self.quiet,
            farm,
            ..config
        })
    }
}

impl ServeArgs {
    /// The service's settings these arguments ask for.
    pub fn into_config(self) -> ServeConfig {
        ServeConfig {
            data: self.data,
            listen: self.listen.listen,
            local_workers: self.listen.local_workers,
            threads: self.threads,
            token: self.access.token.token,
            allow_hosts: self.access.allow_host,
            tls: self.tls.pair(),
            lease: self.lease.lease(),
            drain_timeout: Duration::from_secs_f64(self.drain_timeout),
            verify: self.units.verify,
            interleave: self.units.interleave,
            accept_older_store: self.accept_older_store,
            output_roots: self.output_root,
            max_queued: self.max_queued,
            keep_ended: self.keep_ended,
            json_logs: self.log_format == LogFormat::Json,
            quiet: self.quiet,
        }
    }
}

impl StudioArgs {
    /// The studio's settings these arguments ask for.
    pub fn into_config(self) -> StudioConfig {
        StudioConfig {
            scene: self.scene,
            listen: self.listen.listen,
            local_workers: self.listen.local_workers,
            data: self.data,
            token: self.access.token.token,
            allow_hosts: self.access.allow_host,
            quiet: self.quiet,
        }
    }
}

impl ServerArgs {
    /// The service these arguments name.
    pub fn endpoint(&self) -> Endpoint {
        Endpoint {
            url: self.server.clone(),
            token: self.token.token.clone(),
            ca: self.ca.ca.clone(),
        }
    }
}

impl SubmitArgs {
    /// The job these arguments describe, with the scene's text read from
    /// its file and a relative `--out` made absolute
    /// ([`crate::service::client::read_job`]).
    pub fn job(self) -> Result<JobSpec, ClientError> {
        let frames = self
            .frames
            .map_or(FrameRange::one(0), |(first, last)| FrameRange {
                first,
                last,
            });
        let job = JobSpec {
            request: self.request.request(frames),
            out: self.out,
            priority: self.priority,
            require_tags: self.require_tag,
        };
        crate::service::client::read_job(&self.scene, job)
    }
}

/// `--quality`: one of [`Quality::NAMES`] (listed in the help, each with
/// its [`Quality::step`], and in a refusal).
fn quality() -> impl clap::builder::TypedValueParser<Value = Quality> {
    use clap::builder::{PossibleValue, TypedValueParser as _};
    let values = Quality::ALL.map(|q| PossibleValue::new(q.name()).help(q.step()));
    clap::builder::PossibleValuesParser::new(values).try_map(|s| s.parse::<Quality>())
}

/// `A..B` (B excluded) or `A..=B` (B included), as the inclusive pair (A, last).
fn frame_range(s: &str) -> Result<(u32, u32), String> {
    let bad = || format!("expected frames A..B or A..=B, found {s:?}");
    let (a, b, inclusive) = if let Some((a, b)) = s.split_once("..=") {
        (a, b, true)
    } else if let Some((a, b)) = s.split_once("..") {
        (a, b, false)
    } else {
        return Err(bad());
    };
    let a: u32 = a.trim().parse().map_err(|_| bad())?;
    let b: u32 = b.trim().parse().map_err(|_| bad())?;
    let last = if inclusive { Some(b) } else { b.checked_sub(1) };
    match last {
        Some(last) if last >= a && last - a < 100_000 => Ok((a, last)),
        _ => Err(format!(
            "{s}: the range holds no frames (or more than 100000)"
        )),
    }
}

/// `x,y,z`.
fn point(s: &str) -> Result<[f64; 3], String> {
    let v: Vec<f64> = s
        .split(',')
        .map(|c| c.trim().parse::<f64>())
        .collect::<Result<_, _>>()
        .map_err(|_| format!("expected X,Y,Z, found {s:?}"))?;
    match v[..] {
        [x, y, z] if v.iter().all(|c| c.is_finite()) => Ok([x, y, z]),
        _ => Err(format!("expected three finite numbers X,Y,Z, found {s:?}")),
    }
}

/// A fraction from 0 to 1 (`--verify`).
fn fraction(s: &str) -> Result<f64, String> {
    match s.trim().parse::<f64>() {
        Ok(f) if (0.0..=1.0).contains(&f) => Ok(f),
        _ => Err(format!(
            "expected a fraction from 0 to 1 (0.02: one unit in 50), found {s:?}"
        )),
    }
}

/// A host name for `--allow-host`, in lower case.
fn allowed_host(s: &str) -> Result<String, String> {
    match crate::guard::host_name(s) {
        Some(name) if !s.contains(':') || s.starts_with('[') && s.ends_with(']') => Ok(name),
        _ => Err(format!(
            "expected a host name without a port (letters, digits, `-` and `.`, or an IPv6 \
             address in brackets), found {s:?}"
        )),
    }
}

fn interleave(s: &str) -> Result<u32, String> {
    match s.parse::<u32>() {
        Ok(b) if b.is_power_of_two() && b <= 64 => Ok(b),
        _ => Err(format!("expected 1, 2, 4, 8, 16, 32 or 64, found {s:?}")),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use hypertexture::Quality;

    fn parse(args: &[&str]) -> Result<Cli, String> {
        Cli::try_parse_from(std::iter::once("coordinator").chain(args.iter().copied()))
            .map_err(|e| e.to_string())
    }

    #[test]
    fn render_flags_become_the_request() {
        let cli = parse(&[
            "--scene",
            "s.ron",
            "--width",
            "64",
            "--height",
            "32",
            "--spp",
            "4",
            "--quality",
            "interactive",
            "--set",
            "b=1",
            "--set",
            "a=0.5",
            "--set",
            "b=2",
            "--frames",
            "3..=5",
        ])
        .unwrap();
        assert_eq!(cli.frames, Some((3, 5)));
        let request = cli.request.request(FrameRange { first: 3, last: 5 });
        assert_eq!(
            request.overrides,
            Overrides {
                width: Some(64),
                height: Some(32),
                spp: Some(4),
                quality: Some(Quality::Interactive),
                // One value a knob, the last given, in name order: as the
                // HTTP API's map gives them.
                knobs: vec![("a".into(), 0.5), ("b".into(), 2.0)],
            }
        );
        assert_eq!(request.frames, FrameRange { first: 3, last: 5 });
    }

    #[test]
    fn a_render_reads_its_scene_and_takes_its_format_from_out() {
        let dir = std::env::temp_dir().join(format!("coordinator-cli-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let scene = dir.join("s.ron");
        std::fs::write(&scene, "Scene()").unwrap();
        let out = dir.join("o.exr");
        let cli = parse(&[
            "--scene",
            scene.to_str().unwrap(),
            "--out",
            out.to_str().unwrap(),
            "--frame",
            "7",
            "--in-process",
            "-q",
        ])
        .unwrap();
        let config = cli.into_config().unwrap();
        assert_eq!(config.request.scene_text, "Scene()");
        assert_eq!(config.request.scene_name, scene.display().to_string());
        assert_eq!(config.request.frames, FrameRange::one(7));
        assert_eq!(
            config.request.pixel_format,
            hypertexture::PixelFormat::Samples
        );
        assert!(!config.sequence && config.farm.is_none() && !config.progress);
        let bad = parse(&["--scene", scene.to_str().unwrap(), "--out", "o.jpg"]).unwrap();
        let e = bad.into_config().unwrap_err().to_string();
        assert!(e.contains("o.jpg"), "{e}");
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn farm_flags_are_the_same_on_render_and_bake() {
        let render = parse(&[
            "--scene",
            "s.ron",
            "--listen",
            "0.0.0.0:7000",
            "--token",
            "t",
            "--lease-timeout",
            "2.5",
            "--worker-timeout",
            "9",
            "--local-workers",
            "3",
            "--interleave",
            "16",
        ])
        .unwrap();
        let Some(Command::Bake(bake)) = parse(&[
            "bake",
            "s.ron",
            "--out",
            "b.vdb",
            "--listen",
            "0.0.0.0:7000",
            "--token",
            "t",
            "--lease-timeout",
            "2.5",
            "--worker-timeout",
            "9",
            "--local-workers",
            "3",
        ])
        .unwrap()
        .command
        else {
            panic!("not a bake")
        };
        let (a, b) = (render.farm.options(), bake.farm.options());
        assert_eq!(
            (
                a.listen,
                a.token.clone(),
                a.lease,
                a.worker_timeout,
                a.local_workers
            ),
            (
                b.listen,
                b.token.clone(),
                b.lease,
                b.worker_timeout,
                b.local_workers
            )
        );
        assert_eq!(a.lease, Duration::from_millis(2500));
        assert_eq!(render.units.interleave, 16);
    }

    #[test]
    fn submit_flags_become_the_job() {
        let Some(Command::Submit(submit)) = parse(&[
            "submit",
            "s.ron",
            "--out",
            "o_##.png",
            "--frames",
            "2..5",
            "--priority",
            "-1",
            "--spp",
            "8",
            "--set",
            "k=2",
            "--require-tag",
            "gpu",
        ])
        .unwrap()
        .command
        else {
            panic!("not a submit")
        };
        assert_eq!(submit.frames, Some((2, 4)));
        assert_eq!(
            (submit.priority, submit.require_tag.clone()),
            (-1, vec!["gpu".into()])
        );
        let request = submit.request.request(FrameRange { first: 2, last: 4 });
        assert_eq!(request.overrides.spp, Some(8));
        assert_eq!(request.overrides.knobs, vec![("k".into(), 2.0)]);
    }

    #[test]
    fn serve_flags_become_the_service_settings() {
        let Some(Command::Serve(serve)) = parse(&[
            "serve",
            "--data",
            "d",
            "--drain-timeout",
            "3",
            "--log-format",
            "json",
            "--allow-host",
            "Farm.lan",
            "--output-root",
            "/tmp",
        ])
        .unwrap()
        .command
        else {
            panic!("not a serve")
        };
        let config = serve.into_config();
        assert_eq!(config.data, PathBuf::from("d"));
        assert_eq!(config.drain_timeout, Duration::from_secs(3));
        assert!(config.json_logs && !config.quiet);
        assert_eq!(config.allow_hosts, vec!["farm.lan".to_string()]);
        assert_eq!(config.output_roots, vec![PathBuf::from("/tmp")]);
        assert_eq!(config.lease, Duration::from_secs(10));
    }

    #[test]
    fn refusals_name_the_flag() {
        for (args, flag) in [
            (&["--scene", "s.ron", "--spp", "0"][..], "--spp"),
            (&["--scene", "s.ron", "--width", "20000"], "--width"),
            (&["--scene", "s.ron", "--set", "curliness"], "--set"),
            (&["--scene", "s.ron", "--set", "k=inf"], "knob k"),
            (&["--scene", "s.ron", "--frames", "5..2"], "--frames"),
            (
                &["--scene", "s.ron", "--frame", "1", "--frames", "1..3"],
                "--frame",
            ),
            (&["--scene", "s.ron", "--quality", "best"], "--quality"),
            (
                &["--scene", "s.ron", "--lease-timeout", "0"],
                "--lease-timeout",
            ),
            (&["--scene", "s.ron", "--verify", "2"], "--verify"),
            (&["--scene", "s.ron", "--interleave", "3"], "--interleave"),
            (&["--scene", "s.ron", "--tls-cert", "c.pem"], "--tls-key"),
            (&["submit", "s.ron"], "--out"),
            (
                &["serve", "--data", "d", "--allow-host", "a:1"],
                "--allow-host",
            ),
        ] {
            let e = parse(args)
                .err()
                .unwrap_or_else(|| panic!("{args:?} was accepted"));
            assert!(e.contains(flag), "{args:?}: {e}");
        }
    }

    #[test]
    fn serve_and_studio_read_listen_and_access_flags_alike() {
        let shared = [
            "--listen",
            "0.0.0.0:7000",
            "--local-workers",
            "2",
            "--token",
            "t",
            "--allow-host",
            "Farm.LAN",
        ];
        let serve = [&["serve", "--data", "d"][..], &shared].concat();
        let Some(Command::Serve(serve)) = parse(&serve).unwrap().command else {
            panic!("not a serve")
        };
        let studio = [&["studio", "s.ron"][..], &shared].concat();
        let Some(Command::Studio(studio)) = parse(&studio).unwrap().command else {
            panic!("not a studio")
        };
        let (a, b) = (serve.into_config(), studio.into_config());
        assert_eq!(
            (a.listen, a.local_workers, &a.token, &a.allow_hosts),
            (b.listen, b.local_workers, &b.token, &b.allow_hosts)
        );
        assert_eq!(a.listen, "0.0.0.0:7000".parse().unwrap());
        assert_eq!(a.local_workers, Some(2));
        assert_eq!(a.token.as_deref(), Some("t"));
        assert_eq!(a.allow_hosts, ["farm.lan"]);
        // Each command keeps its own default address.
        let Some(Command::Studio(studio)) = parse(&["studio", "s.ron"]).unwrap().command else {
            panic!("not a studio")
        };
        assert_eq!(studio.listen.listen, "127.0.0.1:47000".parse().unwrap());
        let render = parse(&["--scene", "s.ron"]).unwrap();
        assert_eq!(render.farm.listen.listen, "127.0.0.1:0".parse().unwrap());
        assert!(render.tls.pair().is_none());
        let render = parse(&["--scene", "s.ron", "--tls-cert", "c", "--tls-key", "k"]).unwrap();
        assert_eq!(render.tls.pair(), Some(("c".into(), "k".into())));
    }

    #[test]
    fn knobs_and_leases_read_alike_on_every_command() {
        let knobs = ["--set", "b=1", "--set", "a=0.5", "--set", "b=2"];
        let render =
            parse(&[&["--scene", "s.ron", "--lease-timeout", "3"][..], &knobs].concat()).unwrap();
        assert_eq!(render.farm.lease.lease(), Duration::from_secs(3));
        let bake = [
            &["bake", "s.ron", "--out", "f.vdb", "--lease-timeout", "3"][..],
            &knobs,
        ];
        let Some(Command::Bake(bake)) = parse(&bake.concat()).unwrap().command else {
            panic!("not a bake")
        };
        assert_eq!(bake.farm.lease.lease(), Duration::from_secs(3));
        let eval = [&["eval", "a + b", "--scene", "s.ron"][..], &knobs].concat();
        let Some(Command::Eval(eval)) = parse(&eval).unwrap().command else {
            panic!("not an eval")
        };
        let given = [("b", 1.0), ("a", 0.5), ("b", 2.0)].map(|(k, v)| (k.to_string(), v));
        assert_eq!(eval.knobs.set, given);
        assert_eq!(bake.into_config().knobs, given);
        assert_eq!(
            render.request.request(FrameRange::one(0)).overrides.knobs,
            [("a".to_string(), 0.5), ("b".to_string(), 2.0)]
        );
        let Some(Command::Serve(serve)) = parse(&["serve", "--data", "d", "--lease-timeout", "3"])
            .unwrap()
            .command
        else {
            panic!("not a serve")
        };
        assert_eq!(serve.into_config().lease, Duration::from_secs(3));
        // Each command words `--set` its own way.
        assert!(help(&["eval"]).contains("Set a knob of the scene (repeatable)\n"));
        for args in [&[][..], &["bake"], &["submit"]] {
            assert!(help(args).contains("--set curliness=0.8"), "{args:?}");
        }
    }

    /// The help of `args`' command (the subcommand's when given).
    fn help(args: &[&str]) -> String {
        use clap::CommandFactory;
        let mut command = Cli::command();
        let command = match args {
            [] => &mut command,
            [sub, ..] => command.find_subcommand_mut(sub).unwrap(),
        };
        command.render_help().to_string()
    }

    #[test]
    fn shared_flags_keep_each_commands_help() {
        // Each help ends as clap ends a doc comment's: no full stop, then
        // the default or the variable.
        for (args, words) in [
            (
                &[][..],
                &[
                    "Where the farm listens for workers. Anything but loopback needs --token \
                     [default: 127.0.0.1:0]\n",
                    "Shared secret workers must present (required beyond loopback) \
                     [env: HYPERTEXTURE_TOKEN]\n",
                    "TLS certificate (PEM) for the farm's server; needs --tls-key\n",
                    "[possible values: interactive, high]\n",
                    "Seconds of silence after which a worker's units go to others [default: 10]\n",
                ][..],
            ),
            (
                &["serve"],
                &[
                    "Where to listen: the workers' gRPC and the HTTP API share this port. \
                     Anything but loopback needs --token [default: 127.0.0.1:47000]\n",
                    "0 = remote workers only)\n",
                    "Shared secret that workers and API clients must present \
                     (required beyond loopback) [env: HYPERTEXTURE_TOKEN]\n",
                    "TLS certificate (PEM); needs --tls-key. Covers gRPC and HTTP alike\n",
                    "--allow-host <NAME>",
                    "Seconds of silence after which a worker's units go to others [default: 10]\n",
                ],
            ),
            (
                &["studio"],
                &[
                    "Where to listen (port 0: any free port). Anything but loopback needs \
                     --token [default: 127.0.0.1:47000]\n",
                    "Local worker processes to start (default: one per core)\n",
                    "Shared secret workers and the page must present [env: HYPERTEXTURE_TOKEN]\n",
                    "--allow-host <NAME>",
                ],
            ),
            (
                &["bake"],
                &[
                    "Where the farm listens for workers. Anything but loopback needs --token \
                     [default: 127.0.0.1:0]\n",
                    "Set a knob of the scene (repeatable): --set curliness=0.8\n",
                ],
            ),
            (
                &["submit"],
                &[
                    "The service's token (needed beyond loopback) [env: HYPERTEXTURE_TOKEN]\n",
                    "CA certificate (PEM) to verify an https:// service\n",
                    "[possible values: interactive, high]\n",
                ],
            ),
        ] {
            let text = help(args);
            for w in words {
                assert!(text.contains(w), "{args:?} lacks {w:?}:\n{text}");
            }
            assert!(text.contains("--token <TOKEN>"), "{args:?}");
        }
        use clap::CommandFactory;
        let long = Cli::command().render_long_help().to_string();
        for w in [
            "- interactive: The scene's interactive step\n",
            "- high:        The scene's step\n",
        ] {
            assert!(long.contains(w), "{w:?}:\n{long}");
        }
    }

    #[test]
    fn a_quality_is_one_of_the_librarys_names() {
        let cli = parse(&["--scene", "s.ron", "--quality", "high"]).unwrap();
        assert_eq!(cli.request.quality, Some(Quality::High));
        let e = parse(&["--scene", "s.ron", "--quality", "best"]).unwrap_err();
        assert!(e.contains("interactive") && e.contains("high"), "{e}");
    }
}
