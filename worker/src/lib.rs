//! The worker: a stateless renderer that dials the coordinator and pulls work.
//!
//! Each assignment carries the scene's content hash, and its text (a few KB)
//! unless the worker said it has built that scene; the worker builds the scene
//! once per hash, renders the unit's pixels with all its threads and submits the
//! tile. A unit it cannot render (the scene does not build here, the assignment
//! is unusable, the render panics) goes back to the coordinator with the reason
//! (ReportFailure), never held in silence. Tiles go up on one SubmitTiles stream,
//! a message per unit; the reply to a tile brings the next unit, and one unit
//! is always assigned ahead and queued on the render pool, so the render
//! threads never wait for the network or for this thread: while unit n
//! renders, tile n − 1 travels and its reply brings unit n + 1. A background
//! task heartbeats so the coordinator knows it is alive. When the coordinator
//! goes away the worker reconnects with exponential backoff; when asked to stop
//! (SIGTERM) it finishes the current unit, says goodbye and returns.

pub mod body;
pub mod cache;
pub mod cli;
pub mod logging;

use std::collections::{HashMap, VecDeque};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;

use hypertexture::Scene;
use hypertexture::render::interleave::WorkUnit;
use hypertexture_proto::pb::GetWorkResult;
use hypertexture_proto::pb::farm_client::FarmClient;
use hypertexture_proto::pb::{self, get_work_result::Outcome};
use hypertexture_proto::{FailureKind, MAX_MESSAGE_BYTES, PROTOCOL_VERSION, convert};
use tokio::sync::{oneshot, watch};
use tonic::transport::{Certificate, Channel, ClientTlsConfig, Endpoint};
use tonic::{Code, Status};

/// Everything a worker needs to know.
#[derive(Clone, Debug)]
pub struct WorkerConfig {
    /// The coordinator's URL.
    pub coordinator: String,
    /// Render threads.
    pub threads: usize,
    /// The farm's shared secret, if it has one.
    pub token: Option<String>,
    /// Name shown in the coordinator's logs.
    pub name: String,
    /// PEM CA certificate for TLS.
    pub ca: Option<Vec<u8>>,
    /// Return when the frame is finished instead of waiting for the next one;
    /// and fail ([`WorkerError::CoordinatorGone`]) once a coordinator this
    /// worker had reached (made a connection to, registered or not) has been
    /// unreachable for `lease`.
    pub exit_when_done: bool,
    /// How long a coordinator may be unreachable before an `exit_when_done`
    /// worker gives up on it (the coordinator's lease time-out).
    pub lease: Duration,
    /// Fail on purpose (tests of the failure path only; `None` in every binary).
    pub fault: Option<Fault>,
    /// The worker runs inside another program (the coordinator's in-process
    /// fallback), so the process's CPU is not its own: its goodbye reports
    /// none.
    pub shares_process: bool,
    /// Tags: the coordinator hands this worker only jobs whose required tags
    /// it carries.
    pub tags: Vec<String>,
    /// The most bytes of meshes kept between assignments ([`cache::AssetCache`]).
    pub asset_cache_bytes: u64,
}

/// A failure a test asks a worker to have, to exercise what follows it.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Fault {
    /// Every scene fails to build.
    Scene,
    /// Every render panics.
    Panic,
    /// The known-answer probe's digest is one bit off, as another build's would be.
    Arithmetic,
    /// Every tile is garbage of the right size: each float 1e38 in a tile of
    /// samples, each pixel opaque magenta in an 8-bit tile (a lying worker).
    Garbage,
    /// Tiles are true in frames before this one and garbage from it on (a
    /// worker that turns liar in the middle of a sequence).
    GarbageFrom(u32),
    /// Every unit is given back as one this worker cannot render, without
    /// trying (a lying worker).
    RenderClaim,
}

/// `tile` with every byte replaced by garbage of the same size ([`Fault::Garbage`]).
fn garbage(tile: &[u8], format: hypertexture::PixelFormat) -> Vec<u8> {
    let pattern: [u8; 4] = match format {
        hypertexture::PixelFormat::Srgb8 => [255, 0, 255, 255],
        hypertexture::PixelFormat::Samples => 1e38f32.to_le_bytes(),
    };
    pattern.iter().copied().cycle().take(tile.len()).collect()
}

/// Why a worker gave up. Network trouble is not here: it is retried forever.
#[derive(Debug, thiserror::Error)]
pub enum WorkerError {
    /// The coordinator URL cannot be used.
    #[error("invalid coordinator address {url}: {message}")]
    Address {
        /// The URL given.
        url: String,
        /// What is wrong with it.
        message: String,
    },
    /// The CA certificate file cannot be read.
    #[error("{path}: cannot read the CA certificate: {source}")]
    Ca {
        /// The file.
        path: std::path::PathBuf,
        /// What the OS said.
        source: std::io::Error,
    },
    /// The coordinator refused this worker for good (wrong token, other protocol
    /// version, other arithmetic).
    #[error("the coordinator refused this worker: {0}")]
    Refused(String),
    /// This build's known-answer probe did not run (a defect of the build).
    #[error("the known-answer probe: {0}")]
    Probe(String),
    /// The render threads could not be started.
    #[error("cannot start {threads} render threads: {message}")]
    Threads {
        /// How many.
        threads: usize,
        /// Why not.
        message: String,
    },
    /// An `exit_when_done` worker's coordinator has been unreachable for the
    /// whole lease: the render it served is over, one way or another.
    #[error("{url} has been unreachable for {secs:.0} s: leaving")]
    CoordinatorGone {
        /// The coordinator.
        url: String,
        /// How long it has been unreachable.
        secs: f64,
    },
}

/// What a worker did before it returned.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct WorkerReport {
    /// Units rendered and accepted.
    pub units: u64,
    /// Units dropped unfinished because the coordinator took them back (their
    /// job was cancelled, or a studio frame superseded).
    pub withdrawn: u64,
}

/// Resolves when the process is asked to stop (SIGTERM or Ctrl-C).
pub async fn shutdown_signal() {
    #[cfg(unix)]
    {
        use tokio::signal::unix::{SignalKind, signal};
        match signal(SignalKind::terminate()) {
            Ok(mut term) => {
                tokio::select! {
                    _ = term.recv() => {}
                    _ = tokio::signal::ctrl_c() => {}
                }
            }
            Err(_) => {
                let _ = tokio::signal::ctrl_c().await;
            }
        }
    }
    #[cfg(not(unix))]
    {
        let _ = tokio::signal::ctrl_c().await;
    }
}

/// Exits the process (status 1) once `parent` is no longer its parent: the
/// coordinator that started this worker has died, however it died. (The
/// coordinator also asks the kernel to kill it then, `PR_SET_PDEATHSIG`; this
/// covers the rest, such as another platform.)
pub async fn exit_when_orphaned(parent: u32) {
    let mut tick = tokio::time::interval(Duration::from_millis(250));
    loop {
        tick.tick().await;
        if std::os::unix::process::parent_id() != parent {
            eprintln!("error: the coordinator that started this worker (pid {parent}) has gone");
            std::process::exit(1);
        }
    }
}

/// The render threads, and the clock that tells their CPU time from the
/// async thread's.
struct RenderPool {
    threads: rayon::ThreadPool,
    /// The CPU clock of the async thread (the one that runs [`run`]).
    async_clock: CpuClock,
}

/// The CPU-time clock of one thread, readable from any thread (Linux's
/// `pthread_getcpuclockid`); reads 0 where the OS offers none.
#[derive(Clone, Copy, Debug)]
struct CpuClock(Option<ClockId>);

#[cfg(target_os = "linux")]
type ClockId = libc::clockid_t;
#[cfg(not(target_os = "linux"))]
type ClockId = ();

impl CpuClock {
    /// The clock of the calling thread.
    fn of_this_thread() -> CpuClock {
        #[cfg(target_os = "linux")]
        {
            let mut id: libc::clockid_t = 0;
            // SAFETY: pthread_self is the calling thread, alive; the call only
            // writes the clock id into `id`.
            let ok = unsafe { libc::pthread_getcpuclockid(libc::pthread_self(), &mut id) } == 0;
            CpuClock(ok.then_some(id))
        }
        #[cfg(not(target_os = "linux"))]
        {
            CpuClock(None)
        }
    }

    /// The thread's CPU time so far, in microseconds.
    fn micros(self) -> u64 {
        #[cfg(target_os = "linux")]
        {
            let Some(id) = self.0 else { return 0 };
            let mut t = libc::timespec {
                tv_sec: 0,
                tv_nsec: 0,
            };
            // SAFETY: clock_gettime only writes into `t`; a clock of a thread
            // that has exited gives an error, read as 0.
            if unsafe { libc::clock_gettime(id, &mut t) } != 0 {
                return 0;
            }
            t.tv_sec as u64 * 1_000_000 + t.tv_nsec as u64 / 1000
        }
        #[cfg(not(target_os = "linux"))]
        {
            0
        }
    }
}

/// The async thread's CPU time between one tile and the next.
struct CallsCpu {
    clock: CpuClock,
    last: u64,
}

impl CallsCpu {
    fn new(clock: CpuClock) -> CallsCpu {
        CallsCpu {
            clock,
            last: clock.micros(),
        }
    }

    /// Microseconds since the last call (or since `new`).
    fn since_last(&mut self) -> u64 {
        let now = self.clock.micros();
        let d = now.saturating_sub(self.last);
        self.last = now;
        d
    }
}

/// The process's CPU time (user + system) in microseconds, from the OS.
pub fn process_cpu_micros() -> u64 {
    #[cfg(unix)]
    {
        // SAFETY: getrusage only writes into the zeroed struct we pass.
        let mut usage: libc::rusage = unsafe { std::mem::zeroed() };
        if unsafe { libc::getrusage(libc::RUSAGE_SELF, &mut usage) } != 0 {
            return 0;
        }
        let micros = |t: libc::timeval| t.tv_sec as u64 * 1_000_000 + t.tv_usec as u64;
        micros(usage.ru_utime) + micros(usage.ru_stime)
    }
    #[cfg(not(unix))]
    {
        0
    }
}

type Client = FarmClient<
    tonic::service::interceptor::InterceptedService<body::EndStreamEarly<Channel>, Auth>,
>;

/// Adds `authorization: Bearer <token>` to every call.
#[derive(Clone)]
pub struct Auth(Option<tonic::metadata::MetadataValue<tonic::metadata::Ascii>>);

impl tonic::service::Interceptor for Auth {
    fn call(&mut self, mut request: tonic::Request<()>) -> Result<tonic::Request<()>, Status> {
        if let Some(value) = &self.0 {
            request
                .metadata_mut()
                .insert(hypertexture_proto::AUTHORIZATION, value.clone());
        }
        Ok(request)
    }
}

/// Exponential backoff between reconnection attempts: 100 ms doubling to 5 s.
struct Backoff(Duration);

impl Backoff {
    const FIRST: Duration = Duration::from_millis(100);
    const MAX: Duration = Duration::from_secs(5);

    fn next(&mut self) -> Duration {
        let now = self.0;
        self.0 = (self.0 * 2).min(Self::MAX);
        now
    }

    fn reset(&mut self) {
        self.0 = Self::FIRST;
    }
}

/// Sleeps for `d` unless asked to stop first; returns whether to stop.
async fn sleep_or_stop(d: Duration, stop: &mut watch::Receiver<bool>) -> bool {
    if *stop.borrow() {
        return true;
    }
    tokio::select! {
        _ = tokio::time::sleep(d) => *stop.borrow(),
        r = stop.changed() => r.is_err() || *stop.borrow(),
    }
}

/// This build's known-answer probe digest ([`hypertexture::render::probe`]), computed on
/// the render pool: the coordinator admits a worker only when it matches its own.
async fn probe(pool: &RenderPool) -> Result<u64, WorkerError> {
    let (done, digest) = oneshot::channel();
    pool.threads.spawn(move || {
        let started = std::time::Instant::now();
        let digest = std::panic::catch_unwind(hypertexture::render::probe::arithmetic_digest);
        if let Ok(Ok(d)) = &digest {
            tracing::debug!(
                "known-answer probe: digest {d:016x} in {:?}",
                started.elapsed()
            );
        }
        let _ = done.send(digest);
    });
    match digest.await {
        Ok(Ok(Ok(digest))) => Ok(digest),
        Ok(Ok(Err(e))) => Err(WorkerError::Probe(e.to_string())),
        Ok(Err(payload)) => Err(WorkerError::Probe(format!(
            "it panicked: {}",
            panic_message(&*payload)
        ))),
        Err(_) => Err(WorkerError::Probe("the render pool dropped it".into())),
    }
}

/// Why the connected loop ended.
enum Leave {
    /// Asked to stop, or the frame is done: return.
    Done,
    /// Lost the coordinator (or it forgot us): connect and register again.
    Reconnect,
}

/// The worker: connect, register, pull and render units until told to stop.
pub async fn run(
    config: WorkerConfig,
    mut stop: watch::Receiver<bool>,
) -> Result<WorkerReport, WorkerError> {
    let endpoint = endpoint(&config)?;
    let auth = Auth(match &config.token {
        Some(t) => Some(
            format!("Bearer {t}")
                .parse()
                .map_err(|_| WorkerError::Address {
                    url: config.coordinator.clone(),
                    message: "the token must be printable ASCII".into(),
                })?,
        ),
        None => None,
    });
    let pool = RenderPool {
        threads: rayon::ThreadPoolBuilder::new()
            .num_threads(config.threads)
            .thread_name(|i| format!("render-{i}"))
            .build()
            .map_err(|e| WorkerError::Threads {
                threads: config.threads,
                message: e.to_string(),
            })?,
        async_clock: CpuClock::of_this_thread(),
    };
    let arithmetic_digest = match config.fault {
        Some(Fault::Arithmetic) => probe(&pool).await? ^ 1,
        _ => probe(&pool).await?,
    };
    let mut report = WorkerReport::default();
    let mut scenes = SceneCache::new(config.asset_cache_bytes);
    let mut backoff = Backoff(Backoff::FIRST);
    // Since when the coordinator this worker had reached (a connection was
    // made to it) has been unreachable.
    let mut lost_since: Option<std::time::Instant> = None;
    let mut reached = false;
    let gone = |lost_since: Option<std::time::Instant>| match lost_since {
        Some(t) if config.exit_when_done && t.elapsed() >= config.lease => {
            Some(WorkerError::CoordinatorGone {
                url: config.coordinator.clone(),
                secs: t.elapsed().as_secs_f64(),
            })
        }
        _ => None,
    };
    // An `exit_when_done` worker waits no longer than the rest of its lease.
    let retry = |wait: Duration, lost_since: Option<std::time::Instant>| match lost_since {
        Some(t) if config.exit_when_done => wait
            .min(config.lease.saturating_sub(t.elapsed()))
            .max(Duration::from_millis(10)),
        _ => wait,
    };
    loop {
        if *stop.borrow() {
            return Ok(report);
        }
        if let Some(e) = gone(lost_since) {
            return Err(e);
        }
        let channel = match endpoint.connect().await {
            Ok(c) => c,
            Err(e) => {
                if reached {
                    lost_since.get_or_insert_with(std::time::Instant::now);
                }
                let wait = retry(backoff.next(), lost_since);
                tracing::warn!(
                    "cannot reach {}: {}; retrying in {wait:?}",
                    config.coordinator,
                    error_chain(&e)
                );
                if sleep_or_stop(wait, &mut stop).await {
                    return Ok(report);
                }
                continue;
            }
        };
        reached = true;
        let mut client = FarmClient::with_interceptor(body::EndStreamEarly(channel), auth.clone())
            .max_decoding_message_size(MAX_MESSAGE_BYTES)
            .max_encoding_message_size(MAX_MESSAGE_BYTES);
        let registered = client
            .register(pb::RegisterParams {
                protocol_version: PROTOCOL_VERSION,
                name: config.name.clone(),
                threads: config.threads as u32,
                arithmetic_digest,
                tags: config.tags.clone(),
            })
            .await;
        let registered = match registered {
            Ok(r) => r.into_inner(),
            Err(status) if is_refusal(&status) => {
                return Err(WorkerError::Refused(said(&status)));
            }
            Err(status) => {
                // It took the connection, so it was reached: a coordinator
                // gone before it answered counts against the lease.
                let since = *lost_since.get_or_insert_with(std::time::Instant::now);
                let wait = retry(backoff.next(), Some(since));
                tracing::warn!(
                    "cannot register with {}: {}; retrying in {wait:?}",
                    config.coordinator,
                    said(&status)
                );
                if sleep_or_stop(wait, &mut stop).await {
                    return Ok(report);
                }
                continue;
            }
        };
        backoff.reset();
        lost_since = None;
        tracing::info!(
            "registered with {} as {} ({} threads)",
            config.coordinator,
            shown(&registered.worker_id),
            config.threads
        );
        let heartbeat = tokio::spawn(heartbeat(
            client.clone(),
            registered.worker_id.clone(),
            Duration::from_millis(u64::from(registered.heartbeat_ms.max(50))),
        ));
        let withdrawn = Arc::new(Withdrawn::default());
        let listening = tokio::spawn(listen_for_withdrawals(
            client.clone(),
            registered.worker_id.clone(),
            Arc::clone(&withdrawn),
        ));
        let left = serve(
            &config,
            &mut client,
            &registered.worker_id,
            (&pool, &withdrawn),
            &mut scenes,
            &mut report,
            &mut stop,
        )
        .await;
        heartbeat.abort();
        listening.abort();
        match left {
            Ok(Leave::Done) => {
                let _ = client
                    .goodbye(pb::GoodbyeParams {
                        worker_id: registered.worker_id.clone(),
                        process_cpu_micros: if config.shares_process {
                            0
                        } else {
                            process_cpu_micros()
                        },
                    })
                    .await;
                tracing::info!("leaving after {} units", report.units);
                return Ok(report);
            }
            Ok(Leave::Reconnect) => {
                let since = *lost_since.get_or_insert_with(std::time::Instant::now);
                let wait = retry(backoff.next(), Some(since));
                if sleep_or_stop(wait, &mut stop).await {
                    return Ok(report);
                }
            }
            Err(e) => return Err(e),
        }
    }
}

/// What the work loop got when it asked for work.
enum Asked {
    Assignment(pb::Assignment),
    Wait(Duration),
    Finished,
}

/// Asks for the next unit, saying which scene this worker has built.
async fn ask(client: &mut Client, worker_id: &str, known_scene_hash: u64) -> Result<Asked, Status> {
    let work = client
        .get_work(pb::GetWorkParams {
            worker_id: worker_id.to_string(),
            known_scene_hash,
        })
        .await?
        .into_inner();
    Ok(Asked::from(work))
}

impl From<GetWorkResult> for Asked {
    fn from(work: GetWorkResult) -> Asked {
        match work.outcome {
            Some(Outcome::Assignment(a)) => Asked::Assignment(a),
            Some(Outcome::RetryAfterMs(ms)) => {
                Asked::Wait(Duration::from_millis(u64::from(ms).clamp(10, 5000)))
            }
            Some(Outcome::Finished(_)) => Asked::Finished,
            None => Asked::Wait(Duration::from_millis(500)),
        }
    }
}

/// A tile on its way to the coordinator: the reply may carry the next unit, and
/// the stream it went on comes back with it while the stream is still open.
type Sending = tokio::task::JoinHandle<(Option<TileStream>, Result<pb::SubmitTileResult, Status>)>;

/// A worker's tiles on one SubmitTiles stream: a message per tile each way,
/// without a call (headers, trailers, a new HTTP/2 stream) per unit.
struct TileStream {
    tiles: tokio::sync::mpsc::Sender<pb::SubmitTilesParams>,
    replies: tonic::Streaming<pb::SubmitTilesResult>,
}

impl TileStream {
    /// Opens a stream (one round trip: the coordinator answers at once).
    async fn open(client: &mut Client) -> Result<TileStream, Status> {
        // One tile is on a stream at a time: its reply is awaited before the next.
        let (tiles, queue) = tokio::sync::mpsc::channel(1);
        let replies = client
            .submit_tiles(tokio_stream::wrappers::ReceiverStream::new(queue))
            .await?
            .into_inner();
        Ok(TileStream { tiles, replies })
    }

    /// Sends a tile and waits for its reply. An error ends the stream: a
    /// refusal (as SubmitTile would refuse it) or a lost connection.
    async fn submit(&mut self, tile: pb::SubmitTileParams) -> Result<pb::SubmitTileResult, Status> {
        let closed = || Status::unavailable("the coordinator ended the tile stream");
        self.tiles
            .send(pb::SubmitTilesParams { tile: Some(tile) })
            .await
            .map_err(|_| closed())?;
        match self.replies.message().await? {
            Some(pb::SubmitTilesResult {
                result: Some(result),
            }) => Ok(result),
            Some(_) => Err(Status::internal("a SubmitTiles reply without its result")),
            None => Err(closed()),
        }
    }
}

/// Sends `tile` on `stream`, or on a new stream when there is none open.
fn send_tile(client: &Client, stream: Option<TileStream>, tile: pb::SubmitTileParams) -> Sending {
    let mut client = client.clone();
    tokio::spawn(async move {
        let mut stream = match stream {
            Some(stream) => stream,
            None => match TileStream::open(&mut client).await {
                Ok(stream) => stream,
                Err(status) => return (None, Err(status)),
            },
        };
        match stream.submit(tile).await {
            Ok(result) => (Some(stream), Ok(result)),
            Err(status) => (None, Err(status)),
        }
    })
}

/// Pulls and renders units over one connection. One unit is always assigned
/// ahead of the one rendering: it comes in the reply to the previous tile (or,
/// when there is none, from GetWork while the unit renders) and is queued on
/// the pool at once, so the render threads never wait for a round trip, nor
/// for this thread to hear that a unit is done.
async fn serve(
    config: &WorkerConfig,
    client: &mut Client,
    worker_id: &str,
    (pool, withdrawn): (&RenderPool, &Arc<Withdrawn>),
    scenes: &mut SceneCache,
    report: &mut WorkerReport,
    stop: &mut watch::Receiver<bool>,
) -> Result<Leave, WorkerError> {
    // The async thread's CPU since the previous tile (statistics).
    let mut calls_cpu = CallsCpu::new(pool.async_clock);
    // Assigned and not started yet.
    let mut ahead: Option<pb::Assignment> = None;
    // Assigned and already queued on the pool behind the unit rendering, so
    // the render threads go straight from one unit to the next.
    let mut queued: Option<(pb::Assignment, Rendering)> = None;
    // The previous tile, on its way while the next unit renders.
    let mut sending: Option<Sending> = None;
    // The open SubmitTiles stream, while no tile is on it: opened now, so the
    // first tile does not wait for it (if this fails, the first tile retries).
    let mut stream: Option<TileStream> = TileStream::open(client).await.ok();
    loop {
        if *stop.borrow() {
            // Deliver the last tile; a unit assigned ahead (queued or not) goes
            // back with the goodbye.
            return delivered(config, sending.take(), report, &mut stream)
                .await
                .map(|_| Leave::Done);
        }
        let (assignment, rendering) = match queued.take() {
            Some(started) => started,
            None => {
                let assignment = match ahead.take() {
                    Some(a) => a,
                    None => {
                        // Nothing ahead: the reply to the tile in flight may bring the next
                        // unit, or say that the frame is done; otherwise ask.
                        let asked =
                            match delivered(config, sending.take(), report, &mut stream).await? {
                                Delivered::Next(asked) => Ok(asked),
                                Delivered::Lost(status) => Err(status),
                                Delivered::Nothing => ask(client, worker_id, scenes.known()).await,
                            };
                        match asked {
                            Ok(Asked::Assignment(a)) => a,
                            Ok(Asked::Wait(d)) => {
                                if sleep_or_stop(d, stop).await {
                                    return Ok(Leave::Done);
                                }
                                continue;
                            }
                            Ok(Asked::Finished) => {
                                if config.exit_when_done
                                    || sleep_or_stop(Duration::from_secs(1), stop).await
                                {
                                    return Ok(Leave::Done);
                                }
                                continue;
                            }
                            Err(status) => return lost(config, status),
                        }
                    }
                };
                let started = match fetch_assets(client, worker_id, scenes, &assignment).await {
                    Ok(fetched) => start_render(
                        &assignment,
                        (pool, withdrawn),
                        (scenes, &fetched),
                        config.fault,
                    ),
                    Err(e) => Err(e),
                };
                match started {
                    Ok(rendering) => (assignment, rendering),
                    Err((kind, reason)) => {
                        // Give the unit back at once, with the reason: holding it would
                        // hang the frame (the heartbeat keeps the lease alive).
                        if let Err(status) =
                            report_failure(client, worker_id, &assignment, kind, &reason).await
                        {
                            let _ = delivered(config, sending.take(), report, &mut stream).await;
                            return lost(config, status);
                        }
                        continue;
                    }
                }
            }
        };
        // While it renders: the previous tile's reply brings the unit after this
        // one; without one (the first unit, or a refused tile), ask.
        let mut lost_while_rendering = None;
        match delivered(config, sending.take(), report, &mut stream).await? {
            Delivered::Next(Asked::Assignment(a)) => ahead = Some(a),
            Delivered::Next(Asked::Wait(_) | Asked::Finished) => {}
            Delivered::Lost(status) => lost_while_rendering = Some(status),
            Delivered::Nothing if !*stop.borrow() => {
                match ask(client, worker_id, scenes.known()).await {
                    Ok(Asked::Assignment(a)) => ahead = Some(a),
                    Ok(Asked::Wait(_) | Asked::Finished) => {}
                    Err(status) => lost_while_rendering = Some(status),
                }
            }
            Delivered::Nothing => {}
        }
        // Queue the unit ahead on the pool behind this one: the render threads
        // take it up the moment they are free, without waiting for this thread
        // to hear that the current unit is done. (One that cannot be started
        // stays ahead, and is given back with the reason when its turn comes.)
        if lost_while_rendering.is_none()
            && !*stop.borrow()
            && let Some(a) = ahead.take()
        {
            // A new scene's files are fetched while the current unit renders
            // (one that fails to arrive is tried again when its turn comes).
            let started = match fetch_assets(client, worker_id, scenes, &a).await {
                Ok(fetched) => {
                    start_render(&a, (pool, withdrawn), (scenes, &fetched), config.fault)
                }
                Err(e) => Err(e),
            };
            match started {
                Ok(rendering) => queued = Some((a, rendering)),
                Err(_) => ahead = Some(a),
            }
        }
        let rendered = rendering
            .await
            .unwrap_or_else(|_| Err("the render task ended without a result".into()));
        let (unit, pixels, cpu) = match rendered {
            Ok(Some(tile)) => tile,
            Ok(None) => {
                // Taken back while it rendered (or before it started): no
                // tile, the next unit.
                report.withdrawn += 1;
                tracing::debug!(
                    "dropped assignment {}: the coordinator took it back",
                    assignment.assignment_id
                );
                if let Some(status) = lost_while_rendering {
                    return lost(config, status);
                }
                continue;
            }
            Err(reason) => {
                if let Some(status) = lost_while_rendering {
                    return lost(config, status);
                }
                if let Err(status) =
                    report_failure(client, worker_id, &assignment, FailureKind::Render, &reason)
                        .await
                {
                    return lost(config, status);
                }
                continue;
            }
        };
        let tile = pb::SubmitTileParams {
            worker_id: worker_id.to_string(),
            assignment_id: assignment.assignment_id,
            unit: Some(convert::unit_to_wire(&unit)),
            pixels,
            render_cpu_micros: cpu,
            calls_cpu_micros: calls_cpu.since_last(),
            // The unit after the one ahead, to render while the next tile travels.
            want_next: !*stop.borrow() && lost_while_rendering.is_none(),
            known_scene_hash: scenes.known(),
        };
        sending = Some(send_tile(client, stream.take(), tile));
        if let Some(status) = lost_while_rendering {
            let _ = delivered(config, sending.take(), report, &mut stream).await;
            return lost(config, status);
        }
    }
}

/// Gives an assignment back to the coordinator with the reason it could not be
/// rendered (logged here too). Errors are the call's own (connection lost, or
/// the coordinator forgot this worker).
async fn report_failure(
    client: &mut Client,
    worker_id: &str,
    assignment: &pb::Assignment,
    kind: FailureKind,
    reason: &str,
) -> Result<(), Status> {
    tracing::error!(
        "cannot render assignment {} ({kind}): {}",
        assignment.assignment_id,
        shown(reason)
    );
    client
        .report_failure(pb::ReportFailureParams {
            worker_id: worker_id.to_string(),
            assignment_id: assignment.assignment_id,
            kind: convert::failure_kind_to_wire(kind) as i32,
            reason: reason.to_string(),
        })
        .await
        .map(|_| ())
}

/// What became of a tile in flight.
enum Delivered {
    /// No tile was in flight, it was refused, or the reply carried no next unit.
    Nothing,
    /// Delivered; the reply's next unit (or wait, or finished).
    Next(Asked),
    /// The connection failed, or the coordinator forgot this worker: reconnect.
    Lost(Status),
}

/// Waits for a tile in flight. A refused tile is logged (the unit was taken back
/// or is malformed: not fatal); only refusals of the worker itself are errors.
async fn delivered(
    config: &WorkerConfig,
    sending: Option<Sending>,
    report: &mut WorkerReport,
    stream: &mut Option<TileStream>,
) -> Result<Delivered, WorkerError> {
    let Some(task) = sending else {
        return Ok(Delivered::Nothing);
    };
    let outcome = task.await.map(|(back, result)| {
        *stream = back;
        result
    });
    Ok(match outcome {
        Ok(Ok(result)) => {
            if result.accepted {
                report.units += 1;
            }
            result
                .next
                .map_or(Delivered::Nothing, |next| Delivered::Next(next.into()))
        }
        Ok(Err(status))
            if status.code() == Code::InvalidArgument
                || status.code() == Code::FailedPrecondition =>
        {
            tracing::warn!("tile refused: {}", said(&status));
            Delivered::Nothing
        }
        Ok(Err(status)) => {
            if is_refusal(&status) {
                return Err(WorkerError::Refused(said(&status)));
            }
            tracing::warn!(
                "a tile was not delivered to {}: {}",
                config.coordinator,
                said(&status)
            );
            Delivered::Lost(status)
        }
        Err(e) => {
            tracing::error!("the tile sender failed: {e}");
            Delivered::Nothing
        }
    })
}

/// What the coordinator said, safe to log: a message off the network is
/// escaped and capped like every other ([`convert::untrusted`]).
fn said(status: &Status) -> String {
    shown(status.message())
}

/// A string that came from the coordinator (a scene's name, a file's path,
/// a message that holds them), safe to log: escaped and capped as the
/// coordinator logs what workers send ([`convert::untrusted`]).
fn shown(s: &str) -> String {
    convert::untrusted(s, convert::MAX_REASON_CHARS)
}

/// What to do after a failed call: give up on refusal, otherwise reconnect.
fn lost(config: &WorkerConfig, status: Status) -> Result<Leave, WorkerError> {
    if is_refusal(&status) {
        return Err(WorkerError::Refused(said(&status)));
    }
    if status.code() == Code::NotFound {
        tracing::info!("the coordinator does not know this worker any more: registering again");
    } else {
        tracing::warn!("lost {}: {}", config.coordinator, said(&status));
    }
    Ok(Leave::Reconnect)
}

/// Refusals that retrying cannot fix.
fn is_refusal(status: &Status) -> bool {
    matches!(
        status.code(),
        Code::Unauthenticated | Code::PermissionDenied | Code::FailedPrecondition
    )
}

/// A rendered tile: the unit, its pixels on the wire, the CPU microseconds.
type Tile = (WorkUnit, hypertexture_proto::Bytes, u64);

/// A unit on the render pool: its tile, or why it could not be rendered.
/// The result of a unit: its tile, nothing when it was withdrawn, or the
/// message of a panic.
type Rendering = oneshot::Receiver<Result<Option<Tile>, String>>;

/// The assignments the coordinator has taken back from this worker, and the
/// stop flags of those rendering: a withdrawn unit stops before its next
/// pixel, and one not started yet never starts.
#[derive(Default)]
struct Withdrawn(Mutex<WithdrawnState>);

#[derive(Default)]
struct WithdrawnState {
    rendering: HashMap<u64, Arc<AtomicBool>>,
    /// Withdrawn before this worker started them (the newest few).
    before_start: VecDeque<u64>,
}

/// How many withdrawn assignments not started yet are remembered.
const WITHDRAWN_REMEMBERED: usize = 1024;

impl Withdrawn {
    fn lock(&self) -> std::sync::MutexGuard<'_, WithdrawnState> {
        self.0.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// The stop flag of an assignment about to render; `None` when it has
    /// been withdrawn already.
    fn start(&self, assignment_id: u64) -> Option<Arc<AtomicBool>> {
        let mut s = self.lock();
        if s.before_start.contains(&assignment_id) {
            return None;
        }
        let flag = Arc::new(AtomicBool::new(false));
        s.rendering.insert(assignment_id, Arc::clone(&flag));
        Some(flag)
    }

    fn finish(&self, assignment_id: u64) {
        self.lock().rendering.remove(&assignment_id);
    }

    fn withdraw(&self, assignment_ids: &[u64]) {
        let mut s = self.lock();
        for id in assignment_ids {
            match s.rendering.get(id) {
                Some(flag) => flag.store(true, Ordering::Relaxed),
                None => {
                    if s.before_start.len() == WITHDRAWN_REMEMBERED {
                        s.before_start.pop_front();
                    }
                    s.before_start.push_back(*id);
                }
            }
        }
    }
}

/// Listens for the assignments the coordinator takes back, for as long as
/// this registration lasts. A coordinator without the call (UNIMPLEMENTED)
/// or a broken stream leaves withdrawn units to render to the end, as their
/// tiles are ignored.
async fn listen_for_withdrawals(mut client: Client, worker_id: String, withdrawn: Arc<Withdrawn>) {
    let Ok(response) = client
        .withdrawals(pb::WithdrawalsParams { worker_id })
        .await
    else {
        return;
    };
    let mut stream = response.into_inner();
    while let Ok(Some(w)) = stream.message().await {
        withdrawn.withdraw(&w.assignment_ids);
    }
}

/// Starts rendering an assignment on the pool (the async thread goes on with
/// heartbeats and tiles). The result comes straight from the render thread: the
/// tile, or the message of a panic. An assignment that cannot be started (its
/// scene does not build here, it is malformed) is an error with its kind.
fn start_render(
    assignment: &pb::Assignment,
    (pool, withdrawn): (&RenderPool, &Arc<Withdrawn>),
    (scenes, fetched): (&mut SceneCache, &Fetched),
    fault: Option<Fault>,
) -> Result<Rendering, (FailureKind, String)> {
    let job = assignment
        .job
        .as_ref()
        .ok_or((FailureKind::Assignment, "the assignment has no job".into()))?;
    let scene = match fault {
        Some(Fault::Scene) => Err((
            FailureKind::Scene,
            format!(
                "{}: the scene fails to build on purpose (fault injection)",
                job.scene_name
            ),
        )),
        _ => scenes.get(job, fetched),
    }?;
    if fault == Some(Fault::RenderClaim) {
        return Err((
            FailureKind::Render,
            "this unit cannot be rendered here (fault injection)".into(),
        ));
    }
    let unit = assignment
        .unit
        .as_ref()
        .ok_or(convert::WireError::Missing("unit"))
        .and_then(|u| convert::unit_from_wire(u, scene.width(), scene.height()))
        .map_err(|e| (FailureKind::Assignment, e.to_string()))?;
    let format = convert::pixel_format_from_wire(job.pixel_format)
        .map_err(|e| (FailureKind::Assignment, e.to_string()))?;
    // A bake's pixels are the voxels of its lattice (`hypertexture::render::bake`).
    let bake = job
        .bake
        .as_ref()
        .map(|l| convert::lattice_from_wire(l, scene.width(), scene.height()))
        .transpose()
        .map_err(|e| (FailureKind::Assignment, e.to_string()))?;
    let frame = job.frame;
    let (done, result) = oneshot::channel();
    let assignment_id = assignment.assignment_id;
    let Some(stop) = withdrawn.start(assignment_id) else {
        let _ = done.send(Ok(None));
        return Ok(result);
    };
    let withdrawn = Arc::clone(withdrawn);
    let async_clock = pool.async_clock;
    let one_thread = pool.threads.current_num_threads() == 1;
    pool.threads.spawn(move || {
        let render = || {
            if fault == Some(Fault::Panic) {
                panic!("the render panics on purpose (fault injection)");
            }
            let pixels: Vec<(u32, u32)> = unit.pixels(scene.width()).collect();
            // The render threads' CPU while this unit renders and its tile
            // is encoded: the worker's whole cost of the unit's pixels. With
            // one render thread, that thread's own clock: exact, and blind to
            // other workers in the same process (the coordinator's in-process
            // fallback). With several, the process's CPU but the async
            // thread's; the next unit's first pixels may overlap this one's
            // last: an estimate.
            let own = CpuClock::of_this_thread();
            let render_cpu = || {
                if one_thread {
                    own.micros()
                } else {
                    process_cpu_micros().saturating_sub(async_clock.micros())
                }
            };
            let before = render_cpu();
            let mut tile = render_tile(&scene, &pixels, frame, format, bake.as_ref(), &stop)?;
            let lies = match fault {
                Some(Fault::Garbage) => true,
                Some(Fault::GarbageFrom(first)) => frame >= first,
                _ => false,
            };
            if lies {
                tile = garbage(&tile, format).into();
            }
            let cpu = render_cpu().saturating_sub(before);
            Some((unit, tile, cpu))
        };
        let tile = std::panic::catch_unwind(std::panic::AssertUnwindSafe(render))
            .map_err(|payload| format!("the render panicked: {}", panic_message(&*payload)));
        withdrawn.finish(assignment_id);
        let _ = done.send(tile);
    });
    Ok(result)
}

/// The tile of `pixels` encoded as the farm carries it: what a worker sends
/// and what the coordinator's own check of a unit compares. `None`: stopped.
fn render_tile(
    scene: &Scene,
    pixels: &[(u32, u32)],
    frame: u32,
    format: hypertexture::PixelFormat,
    bake: Option<&hypertexture::render::bake::Lattice>,
    stop: &AtomicBool,
) -> Option<hypertexture_proto::Bytes> {
    let samples = match bake {
        Some(lattice) => {
            hypertexture::render::bake::sample_pixels(scene, lattice, frame, scene.width(), pixels)
        }
        None => hypertexture::render::render_pixels_until(scene, frame, pixels, stop)?,
    };
    Some(convert::tile_to_wire(&samples, format))
}

/// Renders units exactly as a worker does, outside the farm: the
/// coordinator's own check of a unit (verified rendering) builds the scene
/// from the assignment's wire job with the worker's code and renders the
/// tile with the worker's function, so the bytes are those every worker of
/// this build must send. It renders on the caller's rayon pool.
pub struct UnitRenderer {
    scenes: SceneCache,
}

impl Default for UnitRenderer {
    fn default() -> UnitRenderer {
        UnitRenderer {
            scenes: SceneCache::new(cache::DEFAULT_ASSET_CACHE_MB << 20),
        }
    }
}

impl UnitRenderer {
    /// Builds the scene of `job` (which carries its text), with the files it
    /// names from `files` (by content hash), as a worker would.
    pub fn build(
        &mut self,
        job: &pb::Job,
        files: &dyn Fn(u64) -> Option<Arc<Vec<u8>>>,
    ) -> Result<Arc<Scene>, (FailureKind, String)> {
        let mut fetched = Fetched::new();
        for a in self.scenes.missing(job) {
            let bytes = files(a.hash).ok_or_else(|| {
                (
                    FailureKind::Assignment,
                    format!(
                        "{}: no file {} with hash {:016x}",
                        job.scene_name, a.path, a.hash
                    ),
                )
            })?;
            let mesh = hypertexture::mesh::Mesh::from_obj(&a.path, &bytes, Default::default())
                .map_err(|e| (FailureKind::Scene, format!("{}: {e}", job.scene_name)))?;
            fetched.insert(a.hash, Arc::new(mesh));
        }
        self.scenes.get(job, &fetched)
    }

    /// The tile of `unit` of `job` (which carries its scene text and frame),
    /// as a worker sends it; `None` when `stop` was set before the end.
    pub fn render(
        &mut self,
        job: &pb::Job,
        unit: &WorkUnit,
        files: &dyn Fn(u64) -> Option<Arc<Vec<u8>>>,
        stop: &AtomicBool,
    ) -> Result<Option<Vec<u8>>, (FailureKind, String)> {
        let scene = self.build(job, files)?;
        let format = convert::pixel_format_from_wire(job.pixel_format)
            .map_err(|e| (FailureKind::Assignment, e.to_string()))?;
        let bake = job
            .bake
            .as_ref()
            .map(|l| convert::lattice_from_wire(l, scene.width(), scene.height()))
            .transpose()
            .map_err(|e| (FailureKind::Assignment, e.to_string()))?;
        let pixels: Vec<(u32, u32)> = unit.pixels(scene.width()).collect();
        Ok(
            render_tile(&scene, &pixels, job.frame, format, bake.as_ref(), stop)
                .map(|t| t.to_vec()),
        )
    }
}

/// The message a panic was raised with.
fn panic_message(payload: &(dyn std::any::Any + Send)) -> &str {
    payload
        .downcast_ref::<&str>()
        .copied()
        .or_else(|| payload.downcast_ref::<String>().map(String::as_str))
        .unwrap_or("(no message)")
}

/// Meshes fetched for one assignment and not kept yet: the cache takes them
/// only once the scene's hash has matched and the scene has built.
type Fetched = HashMap<u64, Arc<hypertexture::mesh::Mesh>>;

/// Scenes built from assignments, by content hash (a worker holds a few at
/// most), and the meshes they name ([`cache::AssetCache`], within a budget).
struct SceneCache {
    scenes: HashMap<u64, CachedScene>,
    /// The files scenes name (meshes), fetched, verified and built, by
    /// content hash; kept only for scenes whose hash matched.
    assets: cache::AssetCache,
    /// The hash of the scene used last (0: none): the coordinator leaves its
    /// text out of the assignments that follow.
    last: u64,
    /// Counts uses: a scene's `used` is the count at its last use.
    clock: u64,
}

struct CachedScene {
    scene: Arc<Scene>,
    /// The content hashes of the meshes it names.
    assets: Vec<u64>,
    used: u64,
}

impl SceneCache {
    const CAPACITY: usize = 4;

    /// An empty cache that keeps at most `asset_bytes` of meshes, but for
    /// those of the scene in use.
    fn new(asset_bytes: u64) -> SceneCache {
        SceneCache {
            scenes: HashMap::new(),
            assets: cache::AssetCache::new(asset_bytes),
            last: 0,
            clock: 0,
        }
    }

    /// The hash of a scene this worker has built and still holds (0: none).
    fn known(&self) -> u64 {
        if self.scenes.contains_key(&self.last) {
            self.last
        } else {
            0
        }
    }

    /// The files of `job` this worker must fetch before its scene can be
    /// built: none when that scene is built already, else those it does not
    /// hold (each once).
    fn missing<'a>(&self, job: &'a pb::Job) -> Vec<&'a pb::AssetRef> {
        if job.scene_text.is_empty() || self.scenes.contains_key(&job.scene_hash) {
            return Vec::new();
        }
        let mut missing: Vec<&pb::AssetRef> = Vec::new();
        for a in &job.assets {
            if !self.assets.contains(a.hash) && !missing.iter().any(|m| m.hash == a.hash) {
                missing.push(a);
            }
        }
        missing
    }

    /// A built scene, now the most recently used (with its meshes).
    fn touch(&mut self, hash: u64) -> Option<Arc<Scene>> {
        self.clock += 1;
        let cached = self.scenes.get_mut(&hash)?;
        cached.used = self.clock;
        for a in &cached.assets {
            self.assets.get(*a);
        }
        Some(Arc::clone(&cached.scene))
    }

    /// The built scene of a job, with the meshes `fetched` for it or kept.
    /// Errors say whether the scene itself fails here (every unit of the job
    /// would: [`FailureKind::Scene`]) or only this assignment was unusable.
    /// The scene and the meshes fetched for it are kept only once its hash
    /// has matched and it has built.
    fn get(
        &mut self,
        job: &pb::Job,
        fetched: &Fetched,
    ) -> Result<Arc<Scene>, (FailureKind, String)> {
        if job.scene_text.is_empty() {
            // Left out by the coordinator: this worker said it has the scene.
            return self.touch(job.scene_hash).ok_or_else(|| {
                // Say "none" from now on, so the next assignment brings the text.
                self.last = 0;
                (
                    FailureKind::Assignment,
                    format!(
                        "the assignment leaves out the text of scene {:016x}, which this worker has not built",
                        job.scene_hash
                    ),
                )
            });
        }
        let scene_failure = |e: String| (FailureKind::Scene, e);
        let request = hypertexture_proto::request::from_wire(job)
            .map_err(|e| scene_failure(e.to_string()))?;
        let hashes: Vec<(String, u64)> = job
            .assets
            .iter()
            .map(|a| (a.path.clone(), a.hash))
            .collect();
        let hash = hypertexture_proto::request::content_hash(&request, &hashes);
        if hash != job.scene_hash {
            return Err(scene_failure(format!(
                "{}: content hash mismatch ({hash:016x} ≠ {:016x})",
                job.scene_name, job.scene_hash
            )));
        }
        if let Some(scene) = self.touch(hash) {
            self.last = hash;
            return Ok(scene);
        }
        let mut assets = hypertexture::scene::Assets::none();
        for a in &job.assets {
            let mesh = match fetched.get(&a.hash) {
                Some(mesh) => Arc::clone(mesh),
                None => self.assets.get(a.hash).ok_or_else(|| {
                    (
                        FailureKind::Assignment,
                        format!("{}: the file {} has not arrived", job.scene_name, a.path),
                    )
                })?,
            };
            assets.insert(&a.path, mesh);
        }
        // Only the files that came with the job: a worker reads none from
        // disk. The scene the coordinator of this process built is taken as it is.
        let scene = request
            .build_shared(hash, Some(&assets))
            .map_err(|e| scene_failure(e.to_string()))?;
        self.keep(hash, &scene, job, fetched);
        Ok(scene)
    }

    /// Keeps a scene that has built and the meshes fetched for it. Scenes
    /// that name a mesh the budget pushed out go too (they would hold it).
    fn keep(&mut self, hash: u64, scene: &Arc<Scene>, job: &pb::Job, fetched: &Fetched) {
        let pinned: Vec<u64> = job.assets.iter().map(|a| a.hash).collect();
        let mut dropped = Vec::new();
        for (h, mesh) in fetched.iter().filter(|(h, _)| pinned.contains(h)) {
            dropped.extend(self.assets.keep(*h, Arc::clone(mesh), &pinned));
        }
        self.scenes
            .retain(|_, s| !s.assets.iter().any(|a| dropped.contains(a)));
        if self.scenes.len() >= Self::CAPACITY {
            let oldest = self
                .scenes
                .iter()
                .min_by_key(|(_, s)| s.used)
                .map(|(h, _)| *h);
            if let Some(oldest) = oldest {
                self.scenes.remove(&oldest);
            }
        }
        self.clock += 1;
        self.scenes.insert(
            hash,
            CachedScene {
                scene: Arc::clone(scene),
                assets: pinned,
                used: self.clock,
            },
        );
        self.last = hash;
    }
}

/// Fetches the files an assignment's scene names that this worker does not
/// hold (`GetAsset`), checks each against its size and hash, and builds its
/// mesh off the async thread. They are the caller's to hand to
/// [`SceneCache::get`], which keeps them once the scene's hash has matched.
/// A file that does not arrive whole and intact fails the assignment; one
/// that arrives but is not a usable mesh fails the scene.
async fn fetch_assets(
    client: &mut Client,
    worker_id: &str,
    scenes: &SceneCache,
    assignment: &pb::Assignment,
) -> Result<Fetched, (FailureKind, String)> {
    let mut fetched = Fetched::new();
    let Some(job) = &assignment.job else {
        return Ok(fetched);
    };
    for a in scenes.missing(job) {
        let failed = |e: String| {
            (
                FailureKind::Assignment,
                format!("{}: fetching {}: {e}", job.scene_name, a.path),
            )
        };
        if a.size > hypertexture::mesh::MAX_OBJ_BYTES {
            return Err(failed(format!(
                "{} bytes is more than a mesh file may be",
                a.size
            )));
        }
        let started = std::time::Instant::now();
        let mut stream = client
            .get_asset(pb::GetAssetParams {
                worker_id: worker_id.to_string(),
                hash: a.hash,
            })
            .await
            .map_err(|s| failed(s.message().to_string()))?
            .into_inner();
        let mut bytes = Vec::with_capacity(a.size as usize);
        while let Some(chunk) = stream
            .message()
            .await
            .map_err(|s| failed(s.message().to_string()))?
        {
            if bytes.len() as u64 + chunk.chunk.len() as u64 > a.size {
                return Err(failed(format!("more than the {} bytes announced", a.size)));
            }
            bytes.extend_from_slice(&chunk.chunk);
        }
        let got = hypertexture::mesh::content_hash(&bytes);
        if bytes.len() as u64 != a.size || got != a.hash {
            return Err(failed(format!(
                "{} bytes with hash {got:016x} arrived, not {} with hash {:016x}",
                bytes.len(),
                a.size,
                a.hash
            )));
        }
        let fetched_in = started.elapsed();
        let path = a.path.clone();
        let mesh = tokio::task::spawn_blocking(move || {
            hypertexture::mesh::Mesh::from_obj(&path, &bytes, Default::default())
        })
        .await
        .map_err(|e| failed(format!("the mesh build stopped: {e}")))?
        .map_err(|e| (FailureKind::Scene, format!("{}: {e}", job.scene_name)))?;
        tracing::info!(
            "{}: {} ({} bytes, {} triangles) fetched in {:.1} ms, its distance tree built in {:.1} ms",
            shown(&job.scene_name),
            shown(&a.path),
            a.size,
            mesh.triangle_count(),
            fetched_in.as_secs_f64() * 1e3,
            (started.elapsed() - fetched_in).as_secs_f64() * 1e3
        );
        fetched.insert(a.hash, Arc::new(mesh));
    }
    Ok(fetched)
}

/// Beats every `every` until aborted. Failures are left to the work loop to notice.
async fn heartbeat(mut client: Client, worker_id: String, every: Duration) {
    let mut tick = tokio::time::interval(every);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    loop {
        tick.tick().await;
        let _ = client
            .heartbeat(pb::HeartbeatParams {
                worker_id: worker_id.clone(),
            })
            .await;
    }
}

/// The endpoint for the coordinator URL, with TLS when it is https.
fn endpoint(config: &WorkerConfig) -> Result<Endpoint, WorkerError> {
    let bad = |message: String| WorkerError::Address {
        url: config.coordinator.clone(),
        message,
    };
    let mut endpoint = Endpoint::from_shared(config.coordinator.clone())
        .map_err(|e| bad(e.to_string()))?
        .connect_timeout(Duration::from_secs(5))
        .timeout(Duration::from_secs(60))
        .tcp_nodelay(true);
    let uri = endpoint.uri().clone();
    match (uri.scheme_str(), &config.ca) {
        (Some("http"), None) => {}
        (Some("http"), Some(_)) => return Err(bad("--ca needs an https:// address".into())),
        (Some("https"), Some(ca)) => {
            let tls = ClientTlsConfig::new().ca_certificate(Certificate::from_pem(ca));
            endpoint = endpoint.tls_config(tls).map_err(|e| bad(e.to_string()))?;
        }
        (Some("https"), None) => {
            return Err(bad(
                "https:// needs --ca FILE to verify the coordinator".into()
            ));
        }
        _ => return Err(bad("expected http://HOST:PORT or https://HOST:PORT".into())),
    }
    if uri.host().is_none() {
        return Err(bad("no host".into()));
    }
    Ok(endpoint)
}

/// An error with its causes, on one line.
fn error_chain(e: &dyn std::error::Error) -> String {
    let mut s = e.to_string();
    let mut source = e.source();
    while let Some(cause) = source {
        s.push_str(": ");
        s.push_str(&cause.to_string());
        source = cause.source();
    }
    s
}

#[cfg(test)]
mod tests {
    use super::*;

    fn job(text: &str) -> pb::Job {
        pb::Job {
            scene_hash: convert::scene_hash(text, 8, 8, 0, 0, &[]),
            scene_text: text.to_string(),
            scene_name: "test.ron".into(),
            width: 8,
            height: 8,
            pixel_format: pb::PixelFormat::Srgb8 as i32,
            ..Default::default()
        }
    }

    #[test]
    fn a_scene_is_built_once_and_then_needs_no_text() {
        let text = std::fs::read_to_string(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/../scenes/noisy_sphere.ron"
        ))
        .unwrap();
        let mut scenes = SceneCache::new(1 << 20);
        assert_eq!(scenes.known(), 0);
        let full = job(&text);
        let without_text = pb::Job {
            scene_text: String::new(),
            ..full.clone()
        };
        assert!(
            scenes.get(&without_text, &Fetched::new()).is_err(),
            "no text and never built: refused"
        );
        let built = scenes.get(&full, &Fetched::new()).unwrap();
        assert_eq!(scenes.known(), full.scene_hash);
        assert!(Arc::ptr_eq(
            &built,
            &scenes.get(&without_text, &Fetched::new()).unwrap()
        ));
        let forged = pb::Job {
            scene_hash: full.scene_hash ^ 1,
            ..full
        };
        assert!(
            scenes.get(&forged, &Fetched::new()).is_err(),
            "a hash that does not match the text"
        );
    }

    /// A scene naming one mesh, `t.obj` (tetrahedron `k`), as a coordinator
    /// sends it, and the mesh as the worker builds it.
    fn mesh_job(k: u32, hash_of_text: Option<u64>) -> (pb::Job, Fetched) {
        let text = "Scene(\n    image: (width: 8, height: 8),\n    camera: (eye: (0.3, 0.3, 3.0), look_at: (0.3, 0.3, 0.3), up: (0.0, 1.0, 0.0), projection: Perspective(fov_y: 40.0)),\n    march: (bounds: (min: (-0.2, -0.2, -0.2), max: (1.2, 1.2, 1.2)), step: Length(0.05), opacity: 40.0, threshold: 0.99),\n    object: Mesh(path: \"t.obj\", softness: 0.1),\n)\n";
        let obj = cache::tetrahedron_obj(k);
        let hash = hypertexture::mesh::content_hash(obj.as_bytes());
        let mesh = hypertexture::mesh::Mesh::from_obj("t.obj", obj.as_bytes(), Default::default())
            .unwrap();
        let job = pb::Job {
            scene_hash: hash_of_text.unwrap_or_else(|| {
                convert::scene_hash_with_assets(
                    convert::scene_hash(text, 8, 8, 0, 0, &[]),
                    &[("t.obj".to_string(), hash)],
                )
            }),
            scene_text: text.to_string(),
            scene_name: "mesh.ron".into(),
            width: 8,
            height: 8,
            assets: vec![pb::AssetRef {
                path: "t.obj".into(),
                hash,
                size: obj.len() as u64,
            }],
            pixel_format: pb::PixelFormat::Srgb8 as i32,
            ..Default::default()
        };
        (job, Fetched::from([(hash, Arc::new(mesh))]))
    }

    #[test]
    fn a_mesh_is_kept_only_once_its_scenes_hash_matches() {
        let mut scenes = SceneCache::new(1 << 20);
        let (forged, fetched) = mesh_job(0, Some(42));
        let (kind, message) = scenes.get(&forged, &fetched).unwrap_err();
        assert_eq!(kind, FailureKind::Scene);
        assert!(message.contains("content hash mismatch"), "{message}");
        assert!(
            scenes.assets.is_empty(),
            "a mesh of a forged scene is not kept"
        );
        assert_eq!(scenes.missing(&forged).len(), 1, "it is fetched again");

        let (job, fetched) = mesh_job(0, None);
        scenes.get(&job, &fetched).unwrap();
        assert_eq!(scenes.assets.len(), 1);
        assert!(scenes.missing(&job).is_empty());
        assert_eq!(scenes.known(), job.scene_hash);
    }

    #[test]
    fn meshes_past_the_budget_go_with_their_scenes() {
        let one = mesh_job(0, None).1.values().next().unwrap().memory_bytes() as u64;
        let mut scenes = SceneCache::new(2 * one);
        for k in 0..50 {
            let (job, fetched) = mesh_job(k, None);
            scenes.get(&job, &fetched).unwrap();
            assert!(scenes.assets.bytes() <= 2 * one, "{k}");
            assert!(scenes.scenes.len() <= 2, "{k}: a scene holds its mesh");
            assert_eq!(scenes.known(), job.scene_hash);
        }
        // The last two are kept; the first was dropped and is fetched again.
        assert!(scenes.missing(&mesh_job(49, None).0).is_empty());
        assert!(scenes.missing(&mesh_job(48, None).0).is_empty());
        assert_eq!(scenes.missing(&mesh_job(0, None).0).len(), 1);
    }
}
