//! The farm: a gRPC server that hands interleaved pixel sets to workers.
//!
//! Workers dial in, register, pull units and push tiles back; the
//! [`Scheduler`] decides everything else. This file is
//! the gRPC edge: authentication, conversion of refusals to `tonic::Status`, the
//! run loop (lease expiry, progress, previews, time-outs, finished frames) and
//! the local workers. A sequence of frames is one session: one server, the same
//! workers, each frame handed over as soon as it is complete. The service and
//! the studio see a running farm through the methods of [`Shared`] in `view`,
//! which take its lock once and hand back plain values: the scheduler and the
//! farm's state are private to `farm/`.

pub mod cert;
pub mod gate;
pub mod limits;
pub mod local;
pub mod panics;
pub mod progress;
pub mod scheduler;
mod view;

use std::collections::HashMap;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use hypertexture::render::interleave::farm_units;
use hypertexture_proto::pb::farm_server::{Farm as FarmRpc, FarmServer};
use hypertexture_proto::pb::{self, get_work_result::Outcome};
use hypertexture_proto::{MAX_MESSAGE_BYTES, PROTOCOL_VERSION, convert};
use tokio::sync::{broadcast, watch};
use tonic::{Request, Response, Status};

pub use crate::farm::scheduler::{Accepted, JobId};
use crate::farm::scheduler::{Next, Refusal, Scheduler};
use crate::image::canvas::FrameImage;
pub use view::{LIVE_PRIORITY, QueueView, WorkerSummary};

/// The largest HTTP/2 frame the coordinator accepts (the protocol's default is
/// 16 KiB, less than a tile of whole-set units at 512²).
const MAX_FRAME_BYTES: u32 = 1 << 20;
/// Concurrent HTTP/2 streams a connection may open (a worker uses three:
/// its tile stream, GetWork and a heartbeat).
const MAX_STREAMS: u32 = 32;
/// HTTP/2 pings and TCP keepalive probes this often; a peer that does not
/// answer a ping within as long is dropped.
const KEEPALIVE: Duration = Duration::from_secs(20);

/// How the farm runs.
#[derive(Clone, Debug)]
pub struct FarmConfig {
    /// Where to listen (port 0: any free port).
    pub listen: SocketAddr,
    /// Shared secret every worker must present.
    pub token: Option<String>,
    /// A worker silent this long loses its units.
    pub lease: Duration,
    /// Give up when no worker is present for this long.
    pub worker_timeout: Duration,
    /// Local worker processes to start.
    pub local_workers: usize,
    /// Threads per local worker.
    pub local_threads: usize,
    /// Rewrite the partial image (at the frame's output path) this often.
    pub preview_every: Option<Duration>,
    /// TLS certificate and key (PEM).
    pub tls: Option<(Vec<u8>, Vec<u8>)>,
    /// The pixel-set interleave B.
    pub interleave: u32,
    /// Show a progress bar.
    pub progress: bool,
    /// Unauthenticated connections: how many, for how long.
    pub gate: crate::farm::gate::GateLimits,
    /// The fraction of units rendered a second time and compared (verified
    /// rendering, 0 to 1; 0: none).
    pub verify: f64,
    /// Host names served besides loopback ones when there is no token
    /// (`--allow-host`; see [`crate::guard`]).
    pub allow_hosts: Vec<String>,
}

/// The fraction of units rendered twice unless `--verify` says otherwise.
pub const DEFAULT_VERIFY: f64 = 0.02;

/// How long the coordinator's own rendering of a unit (a check) may take.
const CHECK_TIMEOUT: Duration = Duration::from_secs(120);

/// Why the farm could not render.
#[derive(Debug, thiserror::Error)]
pub enum FarmError {
    /// The address could not be bound.
    #[error("cannot listen on {addr}: {source}")]
    Bind {
        /// The address.
        addr: SocketAddr,
        /// What the OS said.
        source: std::io::Error,
    },
    /// Listening beyond loopback without a token.
    #[error(
        "listening on {0} (not loopback) needs a shared token: pass --token or set HYPERTEXTURE_TOKEN"
    )]
    TokenRequired(SocketAddr),
    /// TLS set-up failed.
    #[error("TLS: {0}")]
    Tls(String),
    /// The caller stopped taking finished frames (their images cannot be written).
    #[error("{0}")]
    Stopped(String),
    /// No worker came, or all left, for the whole worker time-out.
    #[error("{0}")]
    NoWorkers(String),
    /// Workers could not render a unit, again and again, or none can build the scene.
    #[error("{0}")]
    GaveUp(crate::farm::scheduler::GiveUp),
    /// The gRPC server failed.
    #[error("the farm's server failed: {0}")]
    Server(String),
    /// The frame's units do not cover every pixel exactly once (a defect).
    #[error("the frame's units are wrong: {0}")]
    Units(String),
    /// The coordinator panicked (a defect): the render cannot be trusted.
    #[error("the coordinator failed: {0}")]
    Panicked(String),
    /// This build's known-answer probe did not run (a defect of the build).
    #[error("the known-answer probe: {0}")]
    Probe(#[from] hypertexture::render::probe::ProbeError),
    /// A local worker could not be started.
    #[error("cannot start local worker {path}: {source}")]
    Spawn {
        /// The binary.
        path: PathBuf,
        /// What the OS said.
        source: std::io::Error,
    },
}

/// A frame of a render, and where its image goes (previews are written there).
#[derive(Clone, Debug)]
pub struct FrameOut {
    /// The frame number.
    pub frame: u32,
    /// The output image.
    pub out: PathBuf,
}

/// What to render: one scene, one frame or a sequence.
#[derive(Clone, Debug)]
pub struct FrameJob {
    /// The scene, its overrides with the image size every worker builds
    /// ([`hypertexture::RenderRequest::with_size_of`], or a bake's lattice
    /// laid out as an image), the tiles' pixel format and a bake's lattice.
    pub request: hypertexture::RenderRequest,
    /// The frames, rendered in this order (at least one).
    pub frames: Vec<FrameOut>,
    /// What the images record (previews too).
    pub metadata: std::sync::Arc<crate::image::output::ImageMetadata>,
    /// The files the scene names (meshes), which workers fetch by hash.
    pub assets: Vec<Asset>,
}

impl FrameJob {
    /// Image width: the request's (0 when it carries none).
    pub fn width(&self) -> u32 {
        self.request.overrides.width.unwrap_or(0)
    }

    /// Image height: the request's (0 when it carries none).
    pub fn height(&self) -> u32 {
        self.request.overrides.height.unwrap_or(0)
    }
}

/// A file a scene names, as the farm serves it (`GetAsset`).
#[derive(Clone, Debug)]
pub struct Asset {
    /// The path as the scene writes it.
    pub path: String,
    /// FNV-1a of the bytes ([`hypertexture::mesh::content_hash`]).
    pub hash: u64,
    /// The file.
    pub bytes: Arc<Vec<u8>>,
}

impl Asset {
    /// Every file `scene` names, read beside the scene file `scene_name`:
    /// the bytes the scene was built from (their hashes must agree).
    pub fn of_scene(scene: &hypertexture::Scene, scene_name: &str) -> Result<Vec<Asset>, String> {
        Asset::read_all(scene.asset_hashes(), scene_name)
    }

    /// The files `hashes` names (as the scene writes them, with their
    /// content hashes), read beside the scene file `scene_name`; a file whose
    /// bytes no longer have its hash is an error.
    pub fn read_all(hashes: &[(String, u64)], scene_name: &str) -> Result<Vec<Asset>, String> {
        hashes
            .iter()
            .map(|(path, hash)| {
                let file = hypertexture::scene::asset_path(scene_name, path);
                let bytes = hypertexture::scene::read_asset(&file)
                    .map_err(|e| format!("{}: {e}", file.display()))?;
                if hypertexture::mesh::content_hash(&bytes) != *hash {
                    return Err(format!(
                        "{}: the file changed after the scene was loaded",
                        file.display()
                    ));
                }
                Ok(Asset {
                    path: path.clone(),
                    hash: *hash,
                    bytes: Arc::new(bytes),
                })
            })
            .collect()
    }
}

/// A frame the farm has finished.
#[derive(Clone, Debug)]
pub struct FrameDone {
    /// The frame, its image, its units' costs and render time.
    pub frame: crate::farm::scheduler::CompletedFrame,
    /// Where its image goes.
    pub out: PathBuf,
}

/// What the farm reports when every frame is done.
#[derive(Clone, Debug)]
pub struct SessionReport {
    /// Wall time from the first unit handed out to the last tile.
    pub render_time: Duration,
    /// One line per worker: name, units, pixels, CPU.
    pub workers: Vec<crate::farm::scheduler::WorkerState>,
    /// Bytes of tiles received.
    pub tile_bytes: u64,
    /// Sampled units rendered twice and compared (`--verify`).
    pub verified: u64,
}

/// What the farm reports when a single frame is done ([`render`]).
#[derive(Clone, Debug)]
pub struct FarmReport {
    /// The image.
    pub image: FrameImage,
    /// Wall time from the first unit handed out to the last tile.
    pub render_time: Duration,
    /// One line per worker: name, units, pixels, CPU.
    pub workers: Vec<crate::farm::scheduler::WorkerState>,
    /// CPU microseconds of each unit.
    pub unit_costs: Vec<u64>,
    /// CPU microseconds of the async thread of each unit's worker since its
    /// tile before.
    pub unit_calls: Vec<u64>,
    /// Bytes of tiles received.
    pub tile_bytes: u64,
}

/// A job as the farm sends it to workers.
#[derive(Clone, Debug)]
pub struct WireJob {
    /// With its scene text.
    pub with_text: pb::Job,
    /// Without it, for workers that have built the scene.
    pub without_text: pb::Job,
    /// The files the scene names, served by hash (`GetAsset`).
    pub assets: Vec<Asset>,
}

impl WireJob {
    /// The wire form of `job` (its frame is set per assignment).
    pub fn of(job: &FrameJob) -> WireJob {
        let request = hypertexture::RenderRequest {
            frames: hypertexture::FrameRange::one(job.frames.first().map_or(0, |f| f.frame)),
            ..job.request.clone()
        };
        let refs = job
            .assets
            .iter()
            .map(|a| pb::AssetRef {
                path: a.path.clone(),
                hash: a.hash,
                size: a.bytes.len() as u64,
            })
            .collect();
        let with_text = hypertexture_proto::request::to_wire(&request, refs);
        WireJob {
            assets: job.assets.clone(),
            without_text: pb::Job {
                scene_text: String::new(),
                ..with_text.clone()
            },
            with_text,
        }
    }
}

/// Where accepted tiles go besides the canvas: the service's store. Called
/// with the farm's state locked, before the tile is acknowledged, so a tile
/// a worker was told is in is stored.
pub trait TileSink: Send + Sync {
    /// Keeps the pixels of an accepted unit. A tile held for a second
    /// rendering ([`Accepted::held`]) comes again, not held, once confirmed.
    /// A worker's tile that cannot be kept (`Err`, the reason) is refused and
    /// its unit handed out again ([`Scheduler::accept_kept`]); a confirmed
    /// tile that cannot be kept stays in memory only, as it was while held.
    fn tile(&self, accepted: &Accepted, pixels: &[u8]) -> Result<(), String>;

    /// Frames of a job already complete that are rendered again, because a
    /// worker caught lying delivered some of their tiles.
    fn redo(&self, _job: JobId, _frames: &[u32]) {}
}

/// Hands the tiles the scheduler confirmed since the last call to `sink`.
fn store_confirmed(scheduler: &mut Scheduler, sink: Option<&Arc<dyn TileSink>>) {
    let confirmed = scheduler.take_confirmed();
    if let Some(sink) = sink {
        for (accepted, pixels) in &confirmed {
            // The sink reports its own failures.
            let _ = sink.tile(accepted, pixels);
        }
    }
}

/// The number of buckets of the unit latency histogram, and their upper
/// bounds in seconds.
pub const LATENCY_BUCKETS: [f64; 12] = [
    0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0, 30.0,
];

/// Counters the metrics report.
#[derive(Clone, Debug, Default)]
pub struct FarmStats {
    /// Accepted units per bucket of [`LATENCY_BUCKETS`] (the last: above them all).
    pub latency_buckets: [u64; LATENCY_BUCKETS.len() + 1],
    /// Sum of the accepted units' latencies, in seconds.
    pub latency_sum: f64,
    /// Accepted units.
    pub latency_count: u64,
    /// Units given back by workers and handed out again.
    pub retries: u64,
    /// Workers blocklisted for a job.
    pub blocklisted: u64,
    /// Registrations refused (protocol or arithmetic mismatch).
    pub refused_workers: u64,
    /// Calls refused for a missing or wrong token.
    pub unauthenticated: u64,
    /// Requests whose handler panicked (each answered 500 or INTERNAL).
    pub handler_panics: u64,
    /// Units the coordinator rendered itself to check a sample, a dispute
    /// or a failure claim.
    pub checks: u64,
    /// Workers caught lying (blocklisted for the job).
    pub liars: u64,
}

impl FarmStats {
    fn observe(&mut self, latency: Duration) {
        let secs = latency.as_secs_f64();
        let bucket = LATENCY_BUCKETS
            .iter()
            .position(|&b| secs <= b)
            .unwrap_or(LATENCY_BUCKETS.len());
        self.latency_buckets[bucket] += 1;
        self.latency_sum += secs;
        self.latency_count += 1;
    }
}

/// The farm's state: the scheduler, the jobs' wire forms and the counters,
/// behind one lock.
struct FarmState {
    /// Who renders what.
    scheduler: Scheduler,
    /// Every job in the scheduler, as sent to workers.
    wire: HashMap<JobId, WireJob>,
    /// Counters for the metrics.
    stats: FarmStats,
}

/// The shared state behind the gRPC service.
pub struct Shared {
    state: Mutex<FarmState>,
    token: Option<String>,
    heartbeat: Duration,
    /// This build's known-answer probe digest ([`hypertexture::render::probe`]): a
    /// worker must match it to join.
    arithmetic_digest: u64,
    /// Notified when a frame completes or a job is given up.
    finished: watch::Sender<bool>,
    /// Notified when jobs are added: idle workers' GetWork waits on it.
    jobs_added: watch::Sender<u64>,
    tile_bytes: std::sync::atomic::AtomicU64,
    first_assignment: Mutex<Option<Instant>>,
    sink: Option<Arc<dyn TileSink>>,
    /// The interleave and the farm size new jobs' units are made for.
    unit_layout: Mutex<(u32, usize)>,
    /// Assignments taken back from workers (worker id, assignment id), to
    /// each worker's Withdrawals stream.
    withdrawals: broadcast::Sender<Arc<Vec<(String, u64)>>>,
    /// Set when the server stops: Withdrawals streams end.
    closing: watch::Sender<bool>,
    /// The front door: token checks before any body, connection limits.
    gate: Arc<crate::farm::gate::Gate>,
    /// The files the jobs name, by content hash (`GetAsset`).
    assets: Mutex<HashMap<u64, Arc<Vec<u8>>>>,
    /// The fraction of units of each job rendered twice ([`Shared::add_verified_job`]).
    verify: f64,
    /// Notified when the scheduler has a unit for the coordinator to check.
    checks: tokio::sync::Notify,
}

impl Shared {
    /// The state of a farm starting with `scheduler`: no jobs' wire forms,
    /// no counters, nothing sent yet.
    fn new(
        config: &FarmConfig,
        scheduler: Scheduler,
        arithmetic_digest: u64,
        finished: watch::Sender<bool>,
        sink: Option<Arc<dyn TileSink>>,
    ) -> Shared {
        let token = config.token.clone();
        Shared {
            state: Mutex::new(FarmState {
                scheduler,
                wire: HashMap::new(),
                stats: FarmStats::default(),
            }),
            gate: crate::farm::gate::Gate::new(token.as_deref(), config.gate, &config.allow_hosts),
            token,
            heartbeat: (config.lease / 4).max(Duration::from_millis(50)),
            arithmetic_digest,
            finished,
            jobs_added: watch::channel(0).0,
            tile_bytes: std::sync::atomic::AtomicU64::new(0),
            first_assignment: Mutex::new(None),
            sink,
            unit_layout: Mutex::new((config.interleave, config.local_workers.max(1))),
            withdrawals: broadcast::channel(WITHDRAWALS_CAPACITY).0,
            closing: watch::channel(false).0,
            assets: Mutex::new(HashMap::new()),
            verify: config.verify,
            checks: tokio::sync::Notify::new(),
        }
    }

    /// The interleave B and the number of workers new jobs' units are sized for.
    pub fn unit_layout(&self) -> (u32, usize) {
        *self.unit_layout.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Sets [`Shared::unit_layout`].
    pub fn set_unit_layout(&self, interleave: u32, workers: usize) {
        *self.unit_layout.lock().unwrap_or_else(|p| p.into_inner()) = (interleave, workers);
    }

    /// The farm's state, locked.
    fn lock(&self) -> std::sync::MutexGuard<'_, FarmState> {
        let mut state = self.lock_state();
        state.stats.unauthenticated = self.gate.refused();
        state.stats.handler_panics = crate::farm::panics::caught();
        state
    }

    /// The gate's counters: calls refused, unauthenticated connections closed.
    pub fn gate(&self) -> (u64, u64) {
        (self.gate.refused(), self.gate.closed())
    }

    fn lock_state(&self) -> std::sync::MutexGuard<'_, FarmState> {
        // A panic while holding the lock would be a bug; the state is still usable.
        self.state.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Serves `assets` to workers (`GetAsset`) from now on.
    pub fn add_assets(&self, assets: &[Asset]) {
        let mut served = self.assets.lock().unwrap_or_else(|p| p.into_inner());
        for a in assets {
            served.insert(a.hash, Arc::clone(&a.bytes));
        }
    }

    /// Adds a job whose units are not rendered twice ([`Shared::add_live_frame`]):
    /// its wire form and its plan; idle workers hear of it at once.
    fn add_job(
        &self,
        plan: crate::farm::scheduler::JobPlan,
        resume: crate::farm::scheduler::Resume,
        wire: WireJob,
    ) -> Result<(), hypertexture_proto::convert::WireError> {
        self.add_job_verifying(plan, resume, wire, 0.0)
    }

    /// Adds a job, the farm's fraction of its units rendered twice and
    /// compared (verified rendering): its wire form and its plan; idle
    /// workers hear of it at once.
    pub fn add_verified_job(
        &self,
        plan: crate::farm::scheduler::JobPlan,
        resume: crate::farm::scheduler::Resume,
        wire: WireJob,
    ) -> Result<(), hypertexture_proto::convert::WireError> {
        self.add_job_verifying(plan, resume, wire, self.verify)
    }

    fn add_job_verifying(
        &self,
        plan: crate::farm::scheduler::JobPlan,
        resume: crate::farm::scheduler::Resume,
        wire: WireJob,
        verify: f64,
    ) -> Result<(), hypertexture_proto::convert::WireError> {
        let id = plan.id;
        self.add_assets(&wire.assets);
        {
            let mut s = self.lock();
            s.scheduler.add_job(plan, resume)?;
            s.scheduler.set_job_verify(id, verify);
            s.wire.insert(id, wire);
        }
        self.jobs_added.send_modify(|n| *n += 1);
        // A job resumed complete is handed to the supervisor at once.
        let _ = self.finished.send(true);
        Ok(())
    }

    /// Takes a job out of the farm (cancelled, failed, or done).
    pub fn remove_job(&self, job: JobId) -> bool {
        let mut s = self.lock();
        s.wire.remove(&job);
        let removed = s.scheduler.remove_job(job).is_some();
        let withdrawn = s.scheduler.take_withdrawn();
        drop(s);
        if !withdrawn.is_empty() {
            // No receiver (no worker listening) is not an error.
            let _ = self.withdrawals.send(Arc::new(withdrawn));
        }
        removed
    }
}

/// How long a worker told to wait sleeps before it asks again (the least it
/// accepts): GetWork itself waits for work, so this is short.
const RETRY_AFTER_MS: u32 = 10;

/// The gRPC service.
#[derive(Clone)]
struct Service(Arc<Shared>);

/// The replies of a SubmitTiles stream: each tile is handled as it is read,
/// when the server polls for the next reply (no task or queue in between). A
/// refused tile ends the stream with its status, as SubmitTile would answer.
pub struct Replies {
    /// The worker's tiles; `None` once the stream has ended.
    tiles: Option<tonic::Streaming<pb::SubmitTilesParams>>,
    service: Service,
}

impl tonic::codegen::tokio_stream::Stream for Replies {
    type Item = Result<pb::SubmitTilesResult, Status>;

    fn poll_next(
        self: std::pin::Pin<&mut Self>,
        cx: &mut std::task::Context<'_>,
    ) -> std::task::Poll<Option<Self::Item>> {
        use std::task::Poll;
        let this = self.get_mut();
        let Some(tiles) = this.tiles.as_mut() else {
            return Poll::Ready(None);
        };
        let reply = match std::pin::Pin::new(tiles).poll_next(cx) {
            Poll::Pending => return Poll::Pending,
            Poll::Ready(None) => None,
            Poll::Ready(Some(Err(status))) => Some(Err(status)),
            Poll::Ready(Some(Ok(params))) => Some(
                params
                    .tile
                    .ok_or_else(|| Status::invalid_argument("a SubmitTiles message without a tile"))
                    .and_then(|tile| this.service.submit(tile))
                    .map(|result| pb::SubmitTilesResult {
                        result: Some(result),
                    }),
            ),
        };
        if !matches!(reply, Some(Ok(_))) {
            this.tiles = None;
        }
        Poll::Ready(reply)
    }
}

impl Service {
    fn authorize<T>(&self, request: &Request<T>) -> Result<(), Status> {
        let Some(token) = &self.0.token else {
            return Ok(());
        };
        let presented = request
            .metadata()
            .get(hypertexture_proto::AUTHORIZATION)
            .map(|v| v.as_bytes());
        if crate::guard::bearer_is(presented, token.as_bytes()) {
            Ok(())
        } else {
            // The gate refuses such calls from their headers (and logs them);
            // this check stands behind it.
            Err(Status::unauthenticated("missing or wrong token"))
        }
    }

    fn state(&self) -> std::sync::MutexGuard<'_, FarmState> {
        self.0.lock()
    }

    /// A tile (SubmitTile, or one message of SubmitTiles): stored if it is
    /// the unit's and well formed, refused otherwise; the reply hands out the
    /// worker's next unit when it asks.
    fn submit(&self, p: pb::SubmitTileParams) -> Result<pb::SubmitTileResult, Status> {
        let (accepted, next) = {
            let mut guard = self.state();
            let state = &mut *guard;
            let now = Instant::now();
            state
                .scheduler
                .note_calls_cpu(p.assignment_id, p.calls_cpu_micros);
            let sink = self.0.sink.as_ref();
            let accepted = state
                .scheduler
                .accept_kept(
                    &p.worker_id,
                    p.assignment_id,
                    (p.unit.as_ref(), &p.pixels),
                    p.render_cpu_micros,
                    now,
                    &mut |a, pixels| sink.map_or(Ok(()), |sink| sink.tile(a, pixels)),
                )
                .map_err(|r| {
                    if !matches!(r, Refusal::Unstored { .. }) {
                        // An unkept tile is the sink's to report (once a minute).
                        tracing::warn!(
                            "refused a tile from {}: {r}",
                            convert::name_from_wire(&p.worker_id)
                        );
                    }
                    if state.scheduler.has_checks() {
                        // A refused tile is a claim that the unit cannot be rendered.
                        self.0.checks.notify_one();
                    }
                    refusal(r)
                })?;
            if let Some(a) = &accepted {
                state.stats.observe(a.latency);
            }
            store_confirmed(&mut state.scheduler, self.0.sink.as_ref());
            if state.scheduler.has_completed() {
                let _ = self.0.finished.send(true);
            }
            if state.scheduler.has_checks() {
                self.0.checks.notify_one();
            }
            let next = if p.want_next {
                Some(state.scheduler.next(&p.worker_id, now).map_err(refusal)?)
            } else {
                None
            };
            let next = next.map(|n| self.work(state, n, p.known_scene_hash));
            (accepted.is_some(), next)
        };
        self.0
            .tile_bytes
            .fetch_add(p.pixels.len() as u64, std::sync::atomic::Ordering::Relaxed);
        Ok(pb::SubmitTileResult { accepted, next })
    }

    /// The scheduler's answer on the wire (for GetWork, and the next unit in a
    /// SubmitTile reply). The scene text is left out when the worker has built
    /// that scene already.
    fn work(&self, state: &FarmState, next: Next, known_scene_hash: u64) -> pb::GetWorkResult {
        let outcome = match next {
            Next::Assign {
                assignment_id,
                job,
                unit,
                frame,
            } => match state.wire.get(&job) {
                Some(wire) => {
                    self.0
                        .first_assignment
                        .lock()
                        .unwrap_or_else(|p| p.into_inner())
                        .get_or_insert_with(Instant::now);
                    let job = if known_scene_hash == wire.with_text.scene_hash {
                        &wire.without_text
                    } else {
                        &wire.with_text
                    };
                    Outcome::Assignment(pb::Assignment {
                        assignment_id,
                        job: Some(pb::Job {
                            frame,
                            ..job.clone()
                        }),
                        unit: Some(convert::unit_to_wire(&unit)),
                    })
                }
                // Every job in the scheduler has its wire form: not reached.
                None => Outcome::RetryAfterMs(RETRY_AFTER_MS),
            },
            // The worker asks again at once, and GetWork waits for it.
            Next::Wait => Outcome::RetryAfterMs(RETRY_AFTER_MS),
            Next::Finished => Outcome::Finished(true),
        };
        pb::GetWorkResult {
            outcome: Some(outcome),
        }
    }
}

/// Tags (a worker's, or a job's required ones), checked: at most 16, each 1 to 64 of `A-Z a-z 0-9 . _ -`.
pub fn tags_from_wire(tags: &[String]) -> Result<Vec<String>, String> {
    if tags.len() > 16 {
        return Err(format!(
            "{} tags: a worker may carry at most 16",
            tags.len()
        ));
    }
    let mut out: Vec<String> = Vec::new();
    for t in tags {
        let ok = !t.is_empty()
            && t.len() <= 64
            && t.chars()
                .all(|c| c.is_ascii_alphanumeric() || matches!(c, '.' | '_' | '-'));
        if !ok {
            return Err(format!(
                "tag \"{}\": a tag is 1 to 64 of A-Z a-z 0-9 . _ -",
                convert::untrusted(t, convert::MAX_NAME_CHARS)
            ));
        }
        if !out.contains(t) {
            out.push(t.clone());
        }
    }
    Ok(out)
}

fn refusal(r: Refusal) -> Status {
    match r {
        Refusal::UnknownWorker(_) => Status::not_found(r.to_string()),
        Refusal::NotHeld(_) | Refusal::Unstored { .. } => {
            Status::failed_precondition(r.to_string())
        }
        Refusal::NeverAssigned(_)
        | Refusal::WrongUnit(_)
        | Refusal::Malformed { .. }
        | Refusal::BadReport(_) => Status::invalid_argument(r.to_string()),
    }
}

#[tonic::async_trait]
impl FarmRpc for Service {
    async fn register(
        &self,
        request: Request<pb::RegisterParams>,
    ) -> Result<Response<pb::RegisterResult>, Status> {
        self.authorize(&request)?;
        let peer = request.remote_addr();
        let params = request.into_inner();
        if params.protocol_version != PROTOCOL_VERSION {
            self.state().stats.refused_workers += 1;
            return Err(Status::failed_precondition(format!(
                "protocol version mismatch: the worker speaks {}, the coordinator {}",
                params.protocol_version, PROTOCOL_VERSION
            )));
        }
        // Kept escaped: every log line and message that names the worker is safe.
        let name = convert::name_from_wire(&params.name);
        if params.arithmetic_digest != self.0.arithmetic_digest {
            self.state().stats.refused_workers += 1;
            tracing::warn!(
                "refused worker {name} from {}: its arithmetic differs from this build's \
                 (probe digest {:016x}, here {:016x})",
                peer.map_or_else(|| "?".into(), |a| a.to_string()),
                params.arithmetic_digest,
                self.0.arithmetic_digest
            );
            return Err(Status::failed_precondition(format!(
                "arithmetic mismatch: the worker's known-answer probe gives digest {:016x}, \
                 the coordinator's {:016x}; it is another build (or platform) whose pixels \
                 would not be byte-identical: run the same release on both",
                params.arithmetic_digest, self.0.arithmetic_digest
            )));
        }
        let tags = tags_from_wire(&params.tags).map_err(Status::invalid_argument)?;
        let worker_id = self.state().scheduler.register_tagged(
            &name,
            params.threads,
            tags.clone(),
            Instant::now(),
        );
        tracing::info!(
            "worker {name} joined from {} ({} threads{})",
            peer.map_or_else(|| "?".into(), |a| a.to_string()),
            params.threads,
            if tags.is_empty() {
                String::new()
            } else {
                format!(", tags {}", tags.join(","))
            }
        );
        Ok(Response::new(pb::RegisterResult {
            worker_id,
            heartbeat_ms: self.0.heartbeat.as_millis() as u32,
        }))
    }

    async fn get_work(
        &self,
        request: Request<pb::GetWorkParams>,
    ) -> Result<Response<pb::GetWorkResult>, Status> {
        self.authorize(&request)?;
        let p = request.get_ref();
        // A worker with nothing to do waits here (up to a second) rather than
        // in a sleep of its own: a job added meanwhile starts at once. While
        // units are queued that it may not take yet, it looks again every 50 ms.
        let mut added = self.0.jobs_added.subscribe();
        let mut finished = self.0.finished.subscribe();
        let deadline = Instant::now() + Duration::from_secs(1);
        loop {
            let queued = {
                let mut state = self.state();
                let next = state
                    .scheduler
                    .next(&p.worker_id, Instant::now())
                    .map_err(refusal)?;
                if next != Next::Wait {
                    return Ok(Response::new(self.work(&state, next, p.known_scene_hash)));
                }
                state.scheduler.queued_units()
            };
            let now = Instant::now();
            if now >= deadline {
                break;
            }
            let wait = if queued == 0 {
                deadline - now
            } else {
                (deadline - now).min(Duration::from_millis(50))
            };
            // A job added, or a frame finished (a check settled it, so the
            // worker may be told the render is done), ends the wait.
            let woken = tokio::time::timeout(wait, async {
                tokio::select! {
                    r = added.changed() => r.is_ok(),
                    r = finished.changed() => r.is_ok(),
                }
            })
            .await;
            if let Ok(false) = woken {
                // The farm is stopping: nothing will change.
                tokio::time::sleep(wait).await;
            }
        }
        Ok(Response::new(pb::GetWorkResult {
            outcome: Some(Outcome::RetryAfterMs(RETRY_AFTER_MS)),
        }))
    }

    async fn submit_tile(
        &self,
        request: Request<pb::SubmitTileParams>,
    ) -> Result<Response<pb::SubmitTileResult>, Status> {
        self.authorize(&request)?;
        self.submit(request.into_inner()).map(Response::new)
    }

    type SubmitTilesStream = Replies;
    type WithdrawalsStream = std::pin::Pin<
        Box<dyn futures_util::Stream<Item = Result<pb::Withdrawal, Status>> + Send + 'static>,
    >;

    async fn submit_tiles(
        &self,
        request: Request<tonic::Streaming<pb::SubmitTilesParams>>,
    ) -> Result<Response<Replies>, Status> {
        // The token is checked once, for the stream; every tile on it is then
        // checked as SubmitTile checks it.
        self.authorize(&request)?;
        Ok(Response::new(Replies {
            tiles: Some(request.into_inner()),
            service: self.clone(),
        }))
    }

    type GetAssetStream =
        tonic::codegen::tokio_stream::Iter<std::vec::IntoIter<Result<pb::GetAssetResult, Status>>>;

    async fn get_asset(
        &self,
        request: Request<pb::GetAssetParams>,
    ) -> Result<Response<Self::GetAssetStream>, Status> {
        self.authorize(&request)?;
        let hash = request.get_ref().hash;
        let bytes = self
            .0
            .assets
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .get(&hash)
            .cloned()
            .ok_or_else(|| {
                Status::not_found(format!("no job names a file with hash {hash:016x}"))
            })?;
        let chunks: Vec<_> = bytes
            .chunks(convert::ASSET_CHUNK_BYTES)
            .map(|c| Ok(pb::GetAssetResult { chunk: c.to_vec() }))
            .collect();
        Ok(Response::new(tonic::codegen::tokio_stream::iter(chunks)))
    }

    async fn heartbeat(
        &self,
        request: Request<pb::HeartbeatParams>,
    ) -> Result<Response<pb::HeartbeatResult>, Status> {
        self.authorize(&request)?;
        self.state()
            .scheduler
            .heartbeat(&request.get_ref().worker_id, Instant::now())
            .map_err(refusal)?;
        Ok(Response::new(pb::HeartbeatResult {}))
    }

    async fn goodbye(
        &self,
        request: Request<pb::GoodbyeParams>,
    ) -> Result<Response<pb::GoodbyeResult>, Status> {
        self.authorize(&request)?;
        let p = request.into_inner();
        self.state()
            .scheduler
            .goodbye(&p.worker_id, p.process_cpu_micros)
            .map_err(refusal)?;
        Ok(Response::new(pb::GoodbyeResult {}))
    }

    async fn report_failure(
        &self,
        request: Request<pb::ReportFailureParams>,
    ) -> Result<Response<pb::ReportFailureResult>, Status> {
        self.authorize(&request)?;
        let p = request.into_inner();
        let kind =
            convert::failure_kind_from_wire(p.kind).map_err(|e| refusal(Refusal::BadReport(e)))?;
        let reason = convert::reason_from_wire(&p.reason);
        let mut state = self.state();
        let counted = state
            .scheduler
            .report(&p.worker_id, p.assignment_id, kind, &reason, Instant::now())
            .map_err(refusal)?;
        if let Some(c) = &counted {
            state.stats.retries += 1;
            if kind == hypertexture_proto::FailureKind::Assignment {
                tracing::warn!(
                    "worker {} could not use its assignment of unit {} of job {} ({}): {reason}",
                    c.worker,
                    c.index,
                    c.job,
                    crate::farm::scheduler::describe(&c.unit),
                );
                if c.blocklisted {
                    state.stats.blocklisted += 1;
                    tracing::error!(
                        "worker {} failed {} assignments of job {} and is blocklisted for it",
                        c.worker,
                        crate::farm::scheduler::MAX_FAILURES,
                        c.job
                    );
                }
            } else {
                // Counted only if the coordinator cannot render the unit either.
                tracing::warn!(
                    "worker {} says it cannot {} unit {} of job {} ({}): {kind}: {reason}; checking",
                    c.worker,
                    if kind == hypertexture_proto::FailureKind::Scene {
                        "build the scene of"
                    } else {
                        "render"
                    },
                    c.index,
                    c.job,
                    crate::farm::scheduler::describe(&c.unit),
                );
                self.0.checks.notify_one();
            }
        }
        if state.scheduler.gave_up_jobs().next().is_some() {
            // Wake the supervisor: it ends the job.
            let _ = self.0.finished.send(true);
        }
        Ok(Response::new(pb::ReportFailureResult {
            counted: counted.is_some(),
        }))
    }

    async fn withdrawals(
        &self,
        request: Request<pb::WithdrawalsParams>,
    ) -> Result<Response<Self::WithdrawalsStream>, Status> {
        self.authorize(&request)?;
        let worker_id = request.into_inner().worker_id;
        // Only a registered worker listens (and it counts as a sign of life).
        self.state()
            .scheduler
            .heartbeat(&worker_id, Instant::now())
            .map_err(refusal)?;
        let listening = Withdrawals {
            worker_id,
            rx: self.0.withdrawals.subscribe(),
            closing: self.0.closing.subscribe(),
        };
        let stream = futures_util::stream::unfold(listening, |mut l| async move {
            loop {
                let taken = tokio::select! {
                    received = l.rx.recv() => received,
                    _ = l.closing.wait_for(|c| *c) => return None,
                };
                match taken {
                    Ok(taken) => {
                        let assignment_ids: Vec<u64> = taken
                            .iter()
                            .filter(|(w, _)| *w == l.worker_id)
                            .map(|&(_, id)| id)
                            .collect();
                        if !assignment_ids.is_empty() {
                            return Some((Ok(pb::Withdrawal { assignment_ids }), l));
                        }
                    }
                    // Missed some: those units render to the end, and their
                    // tiles are ignored, as without this stream.
                    Err(broadcast::error::RecvError::Lagged(_)) => {}
                    Err(broadcast::error::RecvError::Closed) => return None,
                }
            }
        });
        Ok(Response::new(Box::pin(stream)))
    }
}

/// A worker's Withdrawals stream.
struct Withdrawals {
    worker_id: String,
    rx: broadcast::Receiver<Arc<Vec<(String, u64)>>>,
    closing: watch::Receiver<bool>,
}

/// Withdrawal batches a listening worker may fall behind by.
const WITHDRAWALS_CAPACITY: usize = 256;

/// Renders one frame on the farm (the first of `job.frames`) and returns its image.
pub async fn render(mut job: FrameJob, config: FarmConfig) -> Result<FarmReport, FarmError> {
    job.frames.truncate(1);
    let mut done = None;
    let session = render_frames(
        job,
        config,
        &mut |frame| {
            done = Some(frame);
            Ok(())
        },
        std::future::pending(),
    )
    .await?;
    let frame = done
        .ok_or_else(|| FarmError::Stopped("the farm finished without a frame".into()))?
        .frame;
    Ok(FarmReport {
        image: frame.image,
        render_time: frame.render_time,
        workers: session.workers,
        unit_costs: frame.unit_costs,
        unit_calls: frame.unit_calls,
        tile_bytes: session.tile_bytes,
    })
}

/// This build's known-answer probe digest ([`hypertexture::render::probe`]), which a
/// worker must match to join: computed once per process (about 5 ms), on the
/// calling thread.
pub fn arithmetic_digest() -> Result<u64, hypertexture::render::probe::ProbeError> {
    static DIGEST: std::sync::OnceLock<u64> = std::sync::OnceLock::new();
    if let Some(&d) = DIGEST.get() {
        return Ok(d);
    }
    let started = Instant::now();
    let d = hypertexture::render::probe::arithmetic_digest()?;
    tracing::debug!(
        "known-answer probe: digest {d:016x} in {:?}",
        started.elapsed()
    );
    Ok(*DIGEST.get_or_init(|| d))
}

/// Binds `config.listen`; beyond loopback only with a token.
async fn bind(config: &FarmConfig) -> Result<(tokio::net::TcpListener, SocketAddr), FarmError> {
    let loopback = config.listen.ip().is_loopback();
    if !loopback && config.token.is_none() {
        return Err(FarmError::TokenRequired(config.listen));
    }
    // On loopback without a token anyone on this machine may join (as the user's
    // own `worker` processes do); beyond loopback a token is required (above).
    let listener = tokio::net::TcpListener::bind(config.listen)
        .await
        .map_err(|source| FarmError::Bind {
            addr: config.listen,
            source,
        })?;
    let addr = listener.local_addr().map_err(|source| FarmError::Bind {
        addr: config.listen,
        source,
    })?;
    Ok((listener, addr))
}

/// The server's task and the sender that stops it.
type Server = (
    tokio::sync::oneshot::Sender<()>,
    tokio::task::JoinHandle<Result<(), tonic::transport::Error>>,
);

/// Serves the workers' gRPC (and `routes` beside it) on `listener`, behind
/// the gate, over TLS when `config.tls` is set. Returns the URL scheme and
/// the server.
fn serve(
    shared: &Arc<Shared>,
    config: &FarmConfig,
    routes: Option<axum::Router>,
    listener: tokio::net::TcpListener,
) -> Result<(&'static str, Server), FarmError> {
    // A tile arrives in one HTTP/2 DATA frame rather than 16 KB pieces: one
    // write for the worker and one wake-up here instead of two or three.
    // Each connection gets a bounded share of streams; HTTP/2 and TCP
    // keepalive drop peers that went away without closing.
    let mut server = tonic::transport::Server::builder()
        .max_frame_size(MAX_FRAME_BYTES)
        .max_concurrent_streams(MAX_STREAMS)
        .http2_keepalive_interval(Some(KEEPALIVE))
        .http2_keepalive_timeout(Some(KEEPALIVE))
        .tcp_keepalive(Some(KEEPALIVE))
        .accept_http1(routes.is_some());
    let scheme = if let Some((cert, key)) = &config.tls {
        let identity = tonic::transport::Identity::from_pem(cert, key);
        server = server
            .tls_config(
                tonic::transport::ServerTlsConfig::new()
                    .identity(identity)
                    .timeout(config.gate.handshake),
            )
            .map_err(|e| FarmError::Tls(e.to_string()))?;
        "https"
    } else {
        "http"
    };
    let service = FarmServer::new(Service(Arc::clone(shared)))
        .max_decoding_message_size(MAX_MESSAGE_BYTES)
        .max_encoding_message_size(MAX_MESSAGE_BYTES);
    let router = match routes {
        Some(routes) => tonic::service::Routes::from(routes).add_service(service),
        None => tonic::service::Routes::new(service),
    };
    let (stop_server, server_stopped) = tokio::sync::oneshot::channel::<()>();
    let gate = Arc::clone(&shared.gate);
    let server_task = tokio::spawn(
        server
            // Outermost: a handler's panic fails its request alone.
            .layer(crate::farm::panics::CatchLayer)
            .layer(crate::farm::gate::GateLayer(Arc::clone(&gate)))
            .add_routes(router)
            .serve_with_incoming_shutdown(gate.incoming(listener), async {
                let _ = server_stopped.await;
            }),
    );
    Ok((scheme, (stop_server, server_task)))
}

/// What one turn of the supervisor found.
#[derive(Debug, Default)]
pub struct Tick {
    /// Frames completed since the last turn.
    pub completed: Vec<crate::farm::scheduler::CompletedFrame>,
    /// Jobs given up (nothing more of them is handed out; the caller takes
    /// them out of the farm).
    pub gave_up: Vec<(JobId, crate::farm::scheduler::GiveUp)>,
    /// Workers with a live connection that can render the one-shot job.
    pub able: usize,
    /// The first panic in this process ([`crate::farm::panics`]): the render (or
    /// the service) must stop with it.
    pub panicked: Option<String>,
}

/// A running farm: the server (the workers' gRPC and any routes beside it,
/// on one port), its state and its local workers. [`Farm::start`] serves,
/// [`Farm::tick`] supervises (a caller's loop calls it), [`Farm::finish`]
/// stops the local workers and the server. The one-shot render
/// ([`render_frames`]) and the service (`crate::service`) are both these
/// three pieces.
pub struct Farm {
    shared: Arc<Shared>,
    finished_rx: watch::Receiver<bool>,
    addr: SocketAddr,
    scheme: &'static str,
    public: String,
    stop_server: tokio::sync::oneshot::Sender<()>,
    server_task: tokio::task::JoinHandle<Result<(), tonic::transport::Error>>,
    locals: crate::farm::local::LocalWorkers,
    /// The coordinator's own renderings of units ([`run_checks`]).
    checker: tokio::task::JoinHandle<()>,
}

impl Farm {
    /// Binds `config.listen`, runs this build's probe, serves the workers'
    /// gRPC (and `routes`, the HTTP API, on the same port) and starts the
    /// local workers. Tiles accepted also go to `sink`.
    pub async fn start(
        config: FarmConfig,
        scheduler: Scheduler,
        routes: Option<axum::Router>,
        sink: Option<Arc<dyn TileSink>>,
    ) -> Result<Farm, FarmError> {
        let (listener, addr) = bind(&config).await?;
        crate::farm::limits::raise_open_files();
        let arithmetic_digest = tokio::task::spawn_blocking(arithmetic_digest)
            .await
            .map_err(|e| FarmError::Server(format!("the known-answer probe failed: {e}")))??;
        let (finished_tx, finished_rx) = watch::channel(false);
        let shared = Arc::new(Shared::new(
            &config,
            scheduler,
            arithmetic_digest,
            finished_tx,
            sink,
        ));
        let checker = tokio::spawn(run_checks(Arc::clone(&shared)));
        let (scheme, (stop_server, server_task)) = serve(&shared, &config, routes, listener)?;
        let public = if addr.ip().is_unspecified() {
            "THIS-HOST".to_string()
        } else {
            addr.ip().to_string()
        };
        tracing::info!(
            "farm listening on {addr}: workers join with `worker --coordinator {scheme}://{public}:{}{}`",
            addr.port(),
            if config.token.is_some() {
                " --token …"
            } else {
                ""
            }
        );
        let local_url = format!(
            "{scheme}://{}:{}",
            if config.tls.is_some() {
                "localhost"
            } else {
                "127.0.0.1"
            },
            addr.port()
        );
        let locals = crate::farm::local::LocalWorkers::start(
            local_spec(&config),
            &local_url,
            config.token.as_deref(),
        )?;
        Ok(Farm {
            shared,
            finished_rx,
            addr,
            scheme,
            public,
            stop_server,
            server_task,
            locals,
            checker,
        })
    }

    /// The farm's shared state.
    pub fn shared(&self) -> &Arc<Shared> {
        &self.shared
    }

    /// The address it listens on.
    pub fn addr(&self) -> SocketAddr {
        self.addr
    }

    /// `http` or `https`.
    pub fn scheme(&self) -> &'static str {
        self.scheme
    }

    /// Waits until a frame completes or a job is given up, or `every` passes.
    pub async fn wait(&mut self, every: Duration) {
        let _ = tokio::time::timeout(every, self.finished_rx.changed()).await;
    }

    /// One turn of the supervisor: expires silent workers' leases, takes the
    /// frames completed and the jobs given up (which leave the scheduler),
    /// and restarts failed local workers.
    pub fn tick(&mut self, now: Instant) -> Tick {
        let tick = {
            let mut s = self.shared.lock();
            for name in s.scheduler.expire(now) {
                tracing::warn!("worker {name} stopped answering: its units go to others");
            }
            let completed = s.scheduler.take_completed();
            if !completed.is_empty() {
                // A frame taken may finish the render: workers waiting in
                // GetWork look again, and may hear so at once.
                let _ = self.shared.finished.send(true);
            }
            let gave_up: Vec<(JobId, crate::farm::scheduler::GiveUp)> = s
                .scheduler
                .gave_up_jobs()
                .map(|(id, g)| (id, g.clone()))
                .collect();
            Tick {
                completed,
                gave_up,
                able: s.scheduler.able(),
                panicked: crate::farm::panics::first().map(str::to_string),
            }
        };
        if let Some(e) = self.locals.check() {
            tracing::warn!("{e}");
        }
        tick
    }

    /// Milliseconds of wall time from the first unit handed out until now.
    fn render_time(&self, start: Instant) -> Duration {
        self.shared
            .first_assignment
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .map_or(Duration::ZERO, |t| t.elapsed())
            .min(start.elapsed())
    }

    /// Stops the local workers (waiting up to `grace` for them to leave, after
    /// asking them to with `terminate`) and the server, once every worker of a
    /// finished render has heard that it is (within the same `grace`); returns
    /// every worker that joined.
    pub async fn finish(
        self,
        grace: Duration,
        terminate: bool,
    ) -> Vec<crate::farm::scheduler::WorkerState> {
        let Farm {
            shared,
            stop_server,
            mut server_task,
            locals,
            checker,
            ..
        } = self;
        let deadline = Instant::now() + grace;
        locals.stop(grace, terminate).await;
        // A finished render's remote workers hear it in the reply to their
        // next call; the server stays up (within `grace`) until each one has,
        // so an `--exit-when-done` worker is not left asking a closed port.
        while Instant::now() < deadline
            && shared.lock().scheduler.yet_to_hear_finished(Instant::now()) > 0
        {
            tokio::time::sleep(Duration::from_millis(10)).await;
        }
        let _ = shared.closing.send(true);
        checker.abort();
        let _ = stop_server.send(());
        // Graceful shutdown waits for open connections: daemon workers keep theirs
        // (they wait for the next frame), so give them a moment, then stop serving.
        // At most 1 s, and no more than the grace (at least 250 ms): a
        // service past its drain time must exit at once.
        let server_grace = grace.clamp(Duration::from_millis(250), Duration::from_secs(1));
        match tokio::time::timeout(server_grace, &mut server_task).await {
            Ok(Ok(Err(e))) => tracing::warn!("server: {e}"),
            Ok(_) => {}
            Err(_) => server_task.abort(),
        }
        let s = shared.lock();
        let mut workers: Vec<_> = s.scheduler.workers().cloned().collect();
        drop(s);
        workers.sort_by(|a, b| a.joined.cmp(&b.joined).then(a.name.cmp(&b.name)));
        workers
    }
}

/// Renders every frame of `job` on the farm, one after another, as one session:
/// serves workers (starting local ones once) and hands each frame to `on_frame`
/// as soon as its last tile is in; when every frame is done, stops the local
/// workers and the server. An error from `on_frame`, or `shutdown` resolving
/// (Ctrl-C, SIGTERM), stops the render.
pub async fn render_frames(
    job: FrameJob,
    config: FarmConfig,
    on_frame: &mut dyn FnMut(FrameDone) -> Result<(), FarmError>,
    shutdown: impl std::future::Future<Output = ()>,
) -> Result<SessionReport, FarmError> {
    let (mut farm, unit_count) = start_session(&job, &config).await?;
    let start = Instant::now();
    let bar = crate::farm::progress::FarmProgress::new(
        config.progress,
        (unit_count * job.frames.len()) as u64,
    );
    let outcome = run_session(&mut farm, &job, &config, &bar, on_frame, shutdown).await;
    let render_time = farm.render_time(start);
    let tile_bytes = farm
        .shared
        .tile_bytes
        .load(std::sync::atomic::Ordering::Relaxed);
    let verified = farm.shared.lock().scheduler.verified();
    // Local workers see `finished` on their next call and exit; give them a
    // moment. After a failure they are told nothing more: stop them now.
    let grace = if outcome.is_ok() {
        Duration::from_secs(10)
    } else {
        Duration::ZERO
    };
    let workers = farm.finish(grace, false).await;
    outcome?;
    Ok(SessionReport {
        render_time,
        workers,
        tile_bytes,
        verified,
    })
}

/// Starts the farm of a one-shot session: `job`'s units, sized for the
/// workers expected, in a scheduler of their own, and the job's wire form
/// and files served. Returns the farm and the units per frame.
async fn start_session(job: &FrameJob, config: &FarmConfig) -> Result<(Farm, usize), FarmError> {
    if job.frames.is_empty() {
        return Err(FarmError::Stopped("no frame to render".into()));
    }
    // Units sized for the workers expected: the local ones, or, when workers
    // may join from the LAN, as many as the paper's 64 processors (at least
    // one unit each for up to 64 workers, however small the frame).
    let expected = if config.listen.ip().is_loopback() {
        config.local_workers.max(1)
    } else {
        config.local_workers.max(64)
    };
    let (width, height) = (job.width(), job.height());
    let units = farm_units(width, height, config.interleave, expected);
    hypertexture::render::interleave::check_partition(&units, width, height)
        .map_err(FarmError::Units)?;
    let unit_count = units.len();
    let interleave = units
        .first()
        .map_or(config.interleave, |u| u.set.interleave);
    let mut scheduler =
        Scheduler::new(units, width, height, job.request.pixel_format, config.lease).with_frames(
            hypertexture::FrameRange::consecutive(job.frames.iter().map(|f| f.frame))
                .ok_or_else(|| FarmError::Stopped("a render's frames are consecutive".into()))?,
        );
    scheduler.set_verify(config.verify);
    let wire = WireJob::of(job);
    let farm = Farm::start(config.clone(), scheduler, None, None).await?;
    farm.shared.add_assets(&wire.assets);
    farm.shared
        .lock()
        .wire
        .insert(crate::farm::scheduler::ONE_SHOT_JOB, wire);
    tracing::info!(
        "{width} × {height}, {unit_count} units of {} pixel sets",
        interleave * interleave
    );
    Ok((farm, unit_count))
}

/// Serves a one-shot session until every frame is done: hands each frame
/// completed to `on_frame`, writes previews off this thread, and stops on a
/// panic, a unit given up, an error from `on_frame`, `shutdown`, or no
/// worker for `config.worker_timeout`.
async fn run_session(
    farm: &mut Farm,
    job: &FrameJob,
    config: &FarmConfig,
    bar: &crate::farm::progress::FarmProgress,
    on_frame: &mut dyn FnMut(FrameDone) -> Result<(), FarmError>,
    shutdown: impl std::future::Future<Output = ()>,
) -> Result<(), FarmError> {
    let out_of = |frame: u32| {
        job.frames
            .iter()
            .find(|f| f.frame == frame)
            .map(|f| f.out.clone())
            .unwrap_or_default()
    };
    let mut last_preview = Instant::now();
    // A preview being encoded and written, off the thread that serves the workers.
    let mut writing_preview: Option<tokio::task::JoinHandle<()>> = None;
    let mut no_worker_since = Some(Instant::now());
    tokio::pin!(shutdown);
    let outcome = loop {
        tokio::select! {
            () = farm.wait(Duration::from_millis(100)) => {}
            () = &mut shutdown => break Err(FarmError::Stopped("stopped by a signal".into())),
        }
        let now = Instant::now();
        let tick = farm.tick(now);
        let writing = writing_preview.as_ref().is_some_and(|t| !t.is_finished());
        let (done, preview) = {
            let s = farm.shared.lock();
            bar.update(&s.scheduler, now);
            let preview = match config.preview_every {
                Some(every)
                    if now - last_preview >= every && !s.scheduler.finished() && !writing =>
                {
                    Some((s.scheduler.preview(), s.scheduler.frame()))
                }
                _ => None,
            };
            (s.scheduler.finished(), preview)
        };
        if let Some(p) = tick.panicked {
            break Err(FarmError::Panicked(p));
        }
        if let Some((_, why)) = tick.gave_up.into_iter().next() {
            break Err(FarmError::GaveUp(why));
        }
        if !tick.completed.is_empty()
            && let Some(task) = writing_preview.take()
        {
            // The final image replaces the preview: let the preview finish first.
            let _ = task.await;
        }
        let handed = tick.completed.into_iter().try_for_each(|frame| {
            let out = out_of(frame.frame);
            on_frame(FrameDone { frame, out })
        });
        if let Err(e) = handed {
            break Err(e);
        }
        if let Some((image, frame)) = preview {
            last_preview = now;
            let meta = job.metadata.at_frame(frame);
            writing_preview = Some(write_preview(image, out_of(frame), meta));
        }
        if done {
            break Ok(());
        }
        if tick.able > 0 {
            no_worker_since = None;
        } else if now - *no_worker_since.get_or_insert(now) >= config.worker_timeout {
            break Err(no_workers(farm, config));
        }
    };
    bar.finish();
    if let Some(task) = writing_preview {
        // The final image replaces the preview: let the preview finish first.
        let _ = task.await;
    }
    outcome
}

/// Encodes and writes a preview of `frame` to `path` on a blocking thread.
fn write_preview(
    image: FrameImage,
    path: PathBuf,
    meta: crate::image::output::ImageMetadata,
) -> tokio::task::JoinHandle<()> {
    let frame = meta.frame();
    tokio::task::spawn_blocking(move || {
        match crate::image::output::write_frame_image(&image, &path, &meta) {
            Ok(()) => tracing::debug!("preview of frame {frame} → {}", path.display()),
            Err(e) => tracing::warn!("preview: {e}"),
        }
    })
}

/// The error of a session no worker has been connected to for
/// `config.worker_timeout`: the progress, the connected workers that cannot
/// help, and how to start one.
fn no_workers(farm: &Farm, config: &FarmConfig) -> FarmError {
    let s = farm.shared.lock();
    let (complete, total) = s.scheduler.progress();
    let unable = s.scheduler.alive() - s.scheduler.able();
    let unable = if unable > 0 {
        format!(
            " ({unable} connected worker{} cannot build the scene or {} blocklisted: {})",
            if unable == 1 { "" } else { "s" },
            if unable == 1 { "is" } else { "are" },
            s.scheduler
                .blocklisted(crate::farm::scheduler::ONE_SHOT_JOB)
                .join(", ")
        )
    } else {
        String::new()
    };
    FarmError::NoWorkers(format!(
        "no worker has been connected for {:.0} s{unable} ({complete} of {total} units done); start workers with `worker --coordinator {}://{}:{}` or raise --worker-timeout",
        config.worker_timeout.as_secs_f64(),
        farm.scheme,
        farm.public,
        farm.addr.port()
    ))
}

/// The coordinator's own renderings of units, one at a time, on a render
/// thread of its own (verified rendering): failure claims and disputes
/// first, then the sampled units whose second rendering no other worker
/// has taken. Each result goes back to the scheduler ([`Scheduler::checked`]),
/// and a worker caught lying is logged by its (escaped) name. Runs until
/// the farm stops.
async fn run_checks(shared: Arc<Shared>) {
    // Named as a render thread: a panic in the renderer is the unit's
    // failure, as on a worker, not the coordinator's.
    let pool = match rayon::ThreadPoolBuilder::new()
        .num_threads(1)
        .thread_name(|_| "render-check".into())
        .build()
    {
        Ok(pool) => Arc::new(pool),
        Err(e) => {
            tracing::error!("cannot start the thread that checks units: {e}; none is checked");
            return;
        }
    };
    let renderer = Arc::new(Mutex::new(worker::UnitRenderer::default()));
    let mut closing = shared.closing.subscribe();
    loop {
        let next = {
            let mut s = shared.lock();
            let check = s.scheduler.take_check();
            check.map(|c| {
                let job = s.wire.get(&c.job).map(|w| pb::Job {
                    frame: c.frame,
                    ..w.with_text.clone()
                });
                (c, job)
            })
        };
        let Some((check, job)) = next else {
            tokio::select! {
                () = shared.checks.notified() => {}
                () = tokio::time::sleep(Duration::from_millis(250)) => {}
                _ = closing.wait_for(|c| *c) => return,
            }
            continue;
        };
        let Some(job) = job else { continue };
        let outcome = render_check(&shared, &pool, &renderer, &job, &check, &mut closing).await;
        let now = Instant::now();
        let mut guard = shared.lock();
        let state = &mut *guard;
        state.stats.checks += 1;
        let verdict = state.scheduler.checked(&check, outcome.clone(), now);
        report_verdict(state, &check, &outcome, &verdict);
        if let Some(sink) = &shared.sink {
            if let Some((accepted, pixels)) = &verdict.stored {
                // The sink reports its own failures; the tile stays in the canvas.
                let _ = sink.tile(accepted, pixels);
            }
            for liar in verdict
                .liars
                .iter()
                .filter(|l| !l.earlier_frames.is_empty())
            {
                sink.redo(liar.job, &liar.earlier_frames);
            }
        }
        store_confirmed(&mut state.scheduler, shared.sink.as_ref());
        if state.scheduler.has_completed() || state.scheduler.gave_up_jobs().next().is_some() {
            let _ = shared.finished.send(true);
        }
    }
}

/// Renders the unit of a check on the check thread, within [`CHECK_TIMEOUT`]
/// (a render still going then, or when the farm closes, stops before its
/// next group of pixels, [`hypertexture::render::render_pixels_until`]).
async fn render_check(
    shared: &Arc<Shared>,
    pool: &Arc<rayon::ThreadPool>,
    renderer: &Arc<Mutex<worker::UnitRenderer>>,
    job: &pb::Job,
    check: &crate::farm::scheduler::Check,
    closing: &mut watch::Receiver<bool>,
) -> crate::farm::scheduler::CheckOutcome {
    use crate::farm::scheduler::CheckOutcome;
    let stop = Arc::new(std::sync::atomic::AtomicBool::new(false));
    let (done, result) = tokio::sync::oneshot::channel();
    {
        let (shared, renderer, job, unit, stop) = (
            Arc::clone(shared),
            Arc::clone(renderer),
            job.clone(),
            check.unit,
            Arc::clone(&stop),
        );
        pool.spawn(move || {
            let files = |hash: u64| {
                shared
                    .assets
                    .lock()
                    .unwrap_or_else(|p| p.into_inner())
                    .get(&hash)
                    .cloned()
            };
            let rendered = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
                renderer
                    .lock()
                    .unwrap_or_else(|p| p.into_inner())
                    .render(&job, &unit, &files, &stop)
            }));
            let _ = done.send(rendered);
        });
    }
    let outcome = tokio::select! {
        r = tokio::time::timeout(CHECK_TIMEOUT, result) => r.ok(),
        _ = closing.wait_for(|c| *c) => None,
    };
    stop.store(true, std::sync::atomic::Ordering::Relaxed);
    match outcome {
        Some(Ok(Ok(Ok(Some(tile))))) => CheckOutcome::Rendered(tile),
        Some(Ok(Ok(Err((kind, reason))))) => CheckOutcome::Failed(kind, reason),
        Some(Ok(Err(payload))) => CheckOutcome::Failed(
            hypertexture_proto::FailureKind::Render,
            format!("the render panicked: {}", panic_text(&*payload)),
        ),
        Some(Ok(Ok(Ok(None)))) | Some(Err(_)) | None => CheckOutcome::TimedOut,
    }
}

/// The message a panic was raised with.
fn panic_text(payload: &(dyn std::any::Any + Send)) -> &str {
    payload
        .downcast_ref::<&str>()
        .copied()
        .or_else(|| payload.downcast_ref::<String>().map(String::as_str))
        .unwrap_or("(no message)")
}

/// Logs what a check decided and counts it.
fn report_verdict(
    state: &mut FarmState,
    check: &crate::farm::scheduler::Check,
    outcome: &crate::farm::scheduler::CheckOutcome,
    verdict: &crate::farm::scheduler::Verdict,
) {
    use crate::farm::scheduler::{CheckOutcome, CheckWhy};
    for liar in &verdict.liars {
        state.stats.liars += 1;
        state.stats.blocklisted += 1;
        let what = match &check.why {
            CheckWhy::Sample | CheckWhy::Dispute => format!(
                "its tile of unit {} of frame {} differs from the coordinator's own rendering",
                check.index, check.frame
            ),
            CheckWhy::Claim { kind, .. } => format!(
                "it said it cannot {} unit {} of frame {}, which the coordinator rendered",
                if *kind == hypertexture_proto::FailureKind::Scene {
                    "build the scene of"
                } else {
                    "render"
                },
                check.index,
                check.frame
            ),
        };
        let earlier = if liar.earlier_frames.is_empty() {
            String::new()
        } else {
            format!(
                "; the frames already complete that hold its tiles are rendered again, whole, and written again: {:?}",
                liar.earlier_frames
            )
        };
        tracing::error!(
            "worker {} lied about job {}: {what}; it is blocklisted for the job and its {} unit{} of this frame are rendered again{earlier}",
            liar.name,
            liar.job,
            liar.redone,
            if liar.redone == 1 { "" } else { "s" },
        );
    }
    match (&check.why, outcome) {
        (CheckWhy::Claim { name, .. }, CheckOutcome::Failed(kind, reason)) => tracing::warn!(
            "the coordinator cannot render unit {} of job {} either ({kind}: {reason}): worker {name}'s failure counts",
            check.index,
            check.job
        ),
        (CheckWhy::Claim { name, .. }, CheckOutcome::TimedOut) => tracing::warn!(
            "the coordinator's check of unit {} of job {} did not end within {} s: worker {name}'s failure counts",
            check.index,
            check.job,
            CHECK_TIMEOUT.as_secs()
        ),
        (_, CheckOutcome::Failed(kind, reason)) => tracing::warn!(
            "the coordinator cannot render unit {} of job {} to check it ({kind}: {reason}): it is rendered again",
            check.index,
            check.job
        ),
        _ => {}
    }
    if let Some(c) = &verdict.confirmed {
        if c.blocklisted {
            tracing::error!(
                "worker {} failed {} units of job {} and is blocklisted for it",
                c.worker,
                crate::farm::scheduler::MAX_FAILURES,
                c.job
            );
        }
        tracing::warn!(
            "worker {} could not render unit {} of job {} ({}), failure {} of at most {}",
            c.worker,
            c.index,
            c.job,
            crate::farm::scheduler::describe(&c.unit),
            c.failures,
            crate::farm::scheduler::MAX_FAILURES
        );
    }
}

/// The local workers a farm configuration asks for.
fn local_spec(config: &FarmConfig) -> local::LocalSpec<'_> {
    local::LocalSpec {
        count: config.local_workers,
        threads: config.local_threads,
        cert: config.tls.as_ref().map(|(cert, _)| cert.as_slice()),
        lease: config.lease,
    }
}

impl From<local::LocalError> for FarmError {
    fn from(error: local::LocalError) -> FarmError {
        match error {
            local::LocalError::Ca(message) => FarmError::Tls(message),
            local::LocalError::Spawn { path, source } => FarmError::Spawn { path, source },
        }
    }
}

/// Reads a PEM file for TLS (at most [`crate::files::MAX_PEM_BYTES`]).
pub fn read_pem(path: &Path) -> Result<Vec<u8>, FarmError> {
    crate::files::read_capped(path, crate::files::MAX_PEM_BYTES, "PEM file")
        .map_err(|e| FarmError::Tls(e.to_string()))
}

#[cfg(test)]
mod tests;
