//! `coordinator serve`: the farm kept running, with a job queue that
//! survives restarts.
//!
//! The same [`Farm`] as the one-shot render (serve, supervise, finish), with
//! three things around it: the [`Store`] (SQLite under `--data`), which keeps
//! every job and every accepted tile of the frames in flight, so a restart
//! resumes where the last process stopped; the [`Control`] the HTTP API
//! (`crate::service::api`) calls to submit, list and cancel jobs; and the supervisor
//! loop, which writes each completed frame to its output, ends failed jobs and,
//! on SIGTERM or Ctrl-C, drains: nothing more is handed out, the units in
//! flight get `--drain-timeout` to arrive, and the process exits 0.
//!
//! Lock order: a job table lock, then the farm's state, then the store.

pub mod api;
pub mod client;
pub mod config;
pub mod health;
pub mod jobs;
pub mod limits;
pub mod metrics;
pub mod params;
pub mod store;
pub mod studio;

pub use config::{ServeConfig, StudioConfig, run, run_studio};

use std::collections::BTreeMap;
use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::{Arc, Mutex, OnceLock};
use std::time::{Duration, Instant, SystemTime, UNIX_EPOCH};

use hypertexture::FrameRange;
use hypertexture::render::interleave::farm_units;
use serde::{Deserialize, Serialize};

use crate::farm::scheduler::{Accepted, CompletedFrame, JobId, JobPlan, Resume, Scheduler};
use crate::farm::{self, Farm, FarmConfig, FarmError, Shared, TileSink, WireJob};
use crate::pipeline::destination::{self, expand_pattern};
use crate::service::jobs::{ApiError, Control, JobSpec, JobState, JobView, WorkerView};
use crate::service::store::{Store, StoreError};

/// How the service runs.
#[derive(Clone, Debug)]
pub struct ServiceConfig {
    /// Where the store lives.
    pub data: PathBuf,
    /// The farm: listen address, token, TLS, local workers, lease.
    pub farm: FarmConfig,
    /// On shutdown, how long units in flight get to arrive.
    pub drain_timeout: Duration,
    /// The scene the studio (at `/`) opens, if any (`coordinator studio SCENE`).
    pub studio_scene: Option<PathBuf>,
    /// The directory the studio's scene browser lists, and whether the page
    /// opens with it shown.
    pub studio_root: Option<(PathBuf, bool)>,
    /// Open a store older than its generation file (`--accept-older-store`).
    pub accept_older_store: bool,
    /// The directories outputs may be written in.
    pub output_roots: destination::OutputRoots,
    /// Jobs not ended the queue holds; one more submission is refused (429).
    pub max_queued: usize,
    /// How long ended jobs are kept.
    pub keep_ended: limits::KeepEnded,
}

/// Why the service stopped with an error.
#[derive(Debug, thiserror::Error)]
pub enum ServiceError {
    /// The store could not be opened or written.
    #[error(transparent)]
    Store(#[from] StoreError),
    /// The farm failed.
    #[error(transparent)]
    Farm(#[from] FarmError),
    /// A stored job could not be read back.
    #[error("{path}: job {id}: {message}")]
    StoredJob {
        /// The store's file.
        path: PathBuf,
        /// The job.
        id: u64,
        /// What is wrong.
        message: String,
    },
    /// The async runtime could not be started.
    #[error("cannot start the async runtime: {0}")]
    Runtime(std::io::Error),
    /// A TLS file could not be read.
    #[error("TLS: {0}")]
    Tls(String),
    /// The studio's scene file could not be read.
    #[error("{0}")]
    Studio(String),
    /// The output roots cannot be used.
    #[error("{0}")]
    Roots(String),
}

/// A job as the store keeps it: as submitted, and the unit layout it was
/// given (so a restart with other flags resumes the same units).
#[derive(Clone, Debug, Serialize, Deserialize)]
struct StoredSpec {
    spec: JobSpec,
    interleave: u32,
    expected_workers: usize,
}

/// What the service knows of a job beyond the scheduler.
struct JobMeta {
    stored: StoredSpec,
    state: JobState,
    error: Option<String>,
    outputs: Vec<String>,
    frames: FrameRange,
    units_per_frame: u64,
    scene_name: String,
    /// What its images record (`None` for a job that has ended).
    metadata: Option<Arc<crate::image::output::ImageMetadata>>,
    /// Its scene while it is in the farm: the farm's checks and in-process
    /// workers render this one rather than build it again.
    scene: Option<Arc<hypertexture::Scene>>,
    /// When it first ran in this process, and its units done then (for the ETA).
    running_since: Option<(Instant, u64)>,
    /// Its progress when it left the scheduler (ended jobs).
    final_units: u64,
    /// The workers blocklisted for it when it left the scheduler.
    final_blocklisted: Vec<String>,
    /// When it ended (milliseconds since the Unix epoch; for a job that
    /// ended before this process started, when it was submitted).
    ended_unix_ms: u64,
}

/// The running service's state: the API's [`Control`].
pub struct Service {
    store: Mutex<Store>,
    jobs: Mutex<BTreeMap<JobId, JobMeta>>,
    farm: OnceLock<Arc<Shared>>,
    draining: std::sync::atomic::AtomicBool,
    /// Whether the store writes, and the tiles dropped for a bad checksum.
    health: health::Health,
    /// Records the store could not take yet, in order: retried while it fails.
    pending: Mutex<Vec<Pending>>,
    /// Where outputs may be written.
    roots: destination::OutputRoots,
    /// What relative outputs are relative to: the directory serve started in.
    base: PathBuf,
    /// Jobs not ended the queue holds.
    max_queued: usize,
    /// How long ended jobs are kept.
    keep_ended: limits::KeepEnded,
}

/// A record of the supervisor's that waits for the store to write again.
#[derive(Clone, Debug)]
enum Pending {
    /// A frame written to `path`, not yet recorded as finished.
    Frame {
        job: JobId,
        frame: u32,
        path: String,
    },
    /// A job's final state, not yet recorded.
    End {
        job: JobId,
        state: JobState,
        error: Option<String>,
    },
}

/// Tiles go to the store as they are accepted; the studio's live frames'
/// tiles go to the studio instead.
struct StoreSink(Arc<Service>, Arc<studio::Studio>);

impl TileSink for StoreSink {
    fn tile(&self, a: &Accepted, pixels: &[u8]) -> Result<(), String> {
        if self.1.owns(a.job) {
            self.1.tile(a, pixels);
            return Ok(());
        }
        if a.held {
            // Stored once its second rendering confirms it: a restart
            // renders it again rather than trusting it unchecked.
            return Ok(());
        }
        let put = self
            .0
            .store()
            .put_tile(a.job, a.frame, a.unit as u32, pixels);
        self.0
            .health
            .outcome(put, || {
                format!("job {} frame {} unit {}", a.job, a.frame, a.unit)
            })
            .map_err(|e| e.to_string())
    }

    fn redo(&self, job: JobId, frames: &[u32]) {
        let added = self.0.store().add_redo(job, frames);
        if let Err(e) = self.0.health.outcome(added, || format!("job {job}")) {
            tracing::error!("job {job}: cannot record frames {frames:?} to render again: {e}");
        }
    }
}

/// The API's answer to a job the store could not take: 507 when its disk is
/// full, 503 otherwise; no id is given.
fn not_stored(e: &StoreError) -> ApiError {
    let message = format!("the job is not queued: the store cannot write ({e}); try again later");
    if e.is_full() {
        ApiError::InsufficientStorage(message)
    } else {
        ApiError::Unavailable(message)
    }
}

fn unix_ms() -> u64 {
    SystemTime::now()
        .duration_since(UNIX_EPOCH)
        .map_or(0, |d| d.as_millis() as u64)
}

/// The frames of a job.
fn frames_of(spec: &JobSpec) -> Result<FrameRange, String> {
    match spec.request.frames {
        frames @ FrameRange { first, last } if first <= last && last - first < 100_000 => {
            Ok(frames)
        }
        FrameRange { first, last } => Err(format!(
            "frames [{first}, {last}]: the first must not be after the last, and a job has at most 100000"
        )),
    }
}

/// A job's spec, checked: its scene built, its frames.
struct Checked {
    /// The scene, and the request as the farm sends it.
    built: hypertexture_proto::request::Built,
    frames: FrameRange,
    /// What its images record.
    metadata: Arc<crate::image::output::ImageMetadata>,
}

/// Units per job, for the metrics.
type PerJob = Vec<(JobId, u64)>;

/// Builds the scene of a job (its checks) and the job's plan pieces. Its
/// output pattern is checked ([`destination::check_pattern`]) and its first
/// frame's file placed inside `roots` (relative paths against `base`); no
/// other frame is expanded.
fn check_spec(
    spec: &JobSpec,
    roots: &destination::OutputRoots,
    base: &Path,
) -> Result<Checked, ApiError> {
    let bad = ApiError::BadRequest;
    let request = &spec.request;
    if request.scene_text.len() > hypertexture::scene::MAX_SCENE_BYTES {
        return Err(bad(format!(
            "the scene is {} bytes; a scene may be at most {} bytes",
            request.scene_text.len(),
            hypertexture::scene::MAX_SCENE_BYTES
        )));
    }
    let frames = frames_of(spec).map_err(bad)?;
    destination::check_pattern(&spec.out, frames, base).map_err(|e| bad(e.to_string()))?;
    // Every frame's file has the first one's extension: a `#` run in it
    // would make digits, and no format is named by digits.
    let first = PathBuf::from(expand_pattern(&spec.out, frames.first));
    crate::image::output::ImageFormat::from_path(&first).map_err(|e| bad(e.to_string()))?;
    roots
        .resolve(&spec.out, &first, base)
        .map_err(|e| ApiError::Forbidden(e.to_string()))?;
    farm::tags_from_wire(&spec.require_tags).map_err(|e| bad(format!("require_tags: {e}")))?;
    // A scene sent over HTTP brings no files (the service reads none on a
    // client's word): one that names a mesh is refused.
    let built =
        hypertexture_proto::request::build(request, Some(&hypertexture::scene::Assets::none()))
            .map_err(|e| bad(e.to_string()))?;
    let metadata = Arc::new(crate::image::output::ImageMetadata::new(
        &built.scene,
        request,
    ));
    Ok(Checked {
        built,
        frames,
        metadata,
    })
}

impl Service {
    fn farm(&self) -> Result<&Arc<Shared>, ApiError> {
        self.farm
            .get()
            .ok_or_else(|| ApiError::Unavailable("the farm is starting".into()))
    }

    /// Puts a checked job into the farm, resuming from the store.
    fn enqueue(
        &self,
        id: JobId,
        stored: &StoredSpec,
        checked: &Checked,
        resume: Resume,
    ) -> Result<u64, String> {
        let spec = &stored.spec;
        let (scene, frames, format) = (
            &checked.built.scene,
            checked.frames,
            checked.built.request.pixel_format,
        );
        let units = farm_units(
            scene.width(),
            scene.height(),
            stored.interleave,
            stored.expected_workers,
        );
        let units_per_frame = units.len() as u64;
        let frame_job = farm::FrameJob {
            request: checked.built.request.clone(),
            // The wire form takes the first frame (each assignment sets its
            // own); the files are expanded as each frame is written.
            frames: vec![farm::FrameOut {
                frame: frames.first,
                out: PathBuf::from(expand_pattern(&spec.out, frames.first)),
            }],
            metadata: checked.metadata.clone(),
            assets: Vec::new(),
        };
        let plan = JobPlan {
            id,
            priority: spec.priority,
            units,
            width: scene.width(),
            height: scene.height(),
            format,
            frames,
            require_tags: spec.require_tags.clone(),
        };
        let shared = self.farm().map_err(|e| e.to_string())?;
        shared
            .add_verified_job(plan, resume, WireJob::of(&frame_job))
            .map_err(|e| format!("a stored tile does not fit the job: {e}"))?;
        Ok(units_per_frame)
    }

    fn view(&self, id: JobId, meta: &JobMeta, now: Instant) -> JobView {
        let progress = self.farm.get().and_then(|f| f.job_progress(id));
        let frames_total = meta.frames.len() as u32;
        let units_total = meta.units_per_frame * u64::from(frames_total);
        let units_done = match (&progress, meta.state) {
            (_, JobState::Done) => units_total,
            (Some(p), _) => p.units_done,
            (None, _) => meta.final_units,
        };
        let eta_seconds = match (meta.state, meta.running_since) {
            (JobState::Running, Some((since, at_start))) if units_done > at_start => {
                let rate = (units_done - at_start) as f64
                    / now.saturating_duration_since(since).as_secs_f64().max(1e-3);
                Some((units_total - units_done) as f64 / rate)
            }
            _ => None,
        };
        let blocklisted = match self.farm.get() {
            Some(f) if !meta.state.is_final() => f.blocklisted(id),
            _ => meta.final_blocklisted.clone(),
        };
        JobView {
            id,
            state: meta.state,
            priority: meta.stored.spec.priority,
            scene_name: meta.scene_name.clone(),
            out: meta.stored.spec.out.clone(),
            frames_done: meta.outputs.len() as u32,
            frames_total,
            units_done,
            units_total,
            eta_seconds,
            error: meta.error.clone(),
            outputs: meta.outputs.clone(),
            require_tags: meta.stored.spec.require_tags.clone(),
            blocklisted,
        }
    }

    fn store(&self) -> std::sync::MutexGuard<'_, Store> {
        self.store.lock().unwrap_or_else(|p| p.into_inner())
    }

    fn jobs_lock(&self) -> std::sync::MutexGuard<'_, BTreeMap<JobId, JobMeta>> {
        self.jobs.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Ends a job: takes it out of the farm and records its final state.
    /// When the store cannot record it, the record waits in [`Pending`]
    /// (retried by [`Service::watch_store`]) and the job shows its state
    /// once recorded.
    fn end(&self, id: JobId, state: JobState, error: Option<String>) {
        {
            let mut jobs = self.jobs_lock();
            let Some(meta) = jobs.get_mut(&id) else {
                return;
            };
            if meta.state.is_final() {
                return;
            }
            self.leave_farm(id, meta);
        }
        let mut pending = self.pending_lock();
        if !pending.is_empty() {
            // After the records waiting before it.
            pending.push(Pending::End {
                job: id,
                state,
                error,
            });
            return;
        }
        drop(pending);
        if let Err(e) = self.record_end(id, state, error.clone()) {
            tracing::error!(
                "job {id}: cannot record that it is {} yet ({e}): retried while the store fails",
                state.as_str()
            );
            self.pending_lock().push(Pending::End {
                job: id,
                state,
                error,
            });
        }
    }

    /// At a clean stop: copies the store's WAL into its database file, so the
    /// file alone holds everything (a backup of it is whole).
    fn checkpoint(&self) {
        let store = self.store();
        if let Err(e) = store.checkpoint() {
            tracing::warn!(
                "cannot checkpoint the store ({e}): it is whole with its -wal file beside it"
            );
        }
    }

    /// Takes a job out of the farm, keeping its progress for its view.
    fn leave_farm(&self, id: JobId, meta: &mut JobMeta) {
        if let Some(shared) = self.farm.get() {
            let (progress, blocklisted) = shared.job_standing(id);
            if let Some(p) = progress {
                meta.final_units = p.units_done;
            }
            meta.final_blocklisted = blocklisted;
            shared.remove_job(id);
        }
        meta.scene = None;
    }

    /// Records a job's final state in the store, then in its view.
    fn record_end(
        &self,
        id: JobId,
        state: JobState,
        error: Option<String>,
    ) -> Result<(), StoreError> {
        let set = self.store().set_state(id, state, error.as_deref());
        self.health.outcome(set, || format!("job {id}'s end"))?;
        if let Some(meta) = self.jobs_lock().get_mut(&id) {
            meta.state = state;
            meta.error = error.clone();
            meta.ended_unix_ms = unix_ms();
        }
        match (state, &error) {
            (JobState::Failed, Some(e)) => tracing::error!("job {id} failed: {e}"),
            _ => tracing::info!("job {id} {}", state.as_str()),
        }
        Ok(())
    }

    /// Why the store does not keep what it is given: its last write failed,
    /// or records still wait for it (other writes may succeed meanwhile, as
    /// the tiles of a frame whose record a full table refuses).
    fn store_failure(&self) -> Option<String> {
        if let Some((why, _)) = self.health.failure() {
            return Some(why);
        }
        match self.pending_lock().len() {
            0 => None,
            1 => Some("a record waits for the store".into()),
            n => Some(format!("{n} records wait for the store")),
        }
    }

    fn pending_lock(&self) -> std::sync::MutexGuard<'_, Vec<Pending>> {
        self.pending.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// While the store fails: probes it once a [`health::PROBE_EVERY`],
    /// holds the farm's units back, and retries the records waiting, in
    /// order; once it writes, the units go out again.
    fn watch_store(&self, now: Instant) {
        if self.health.probe_due(now) {
            let probed = self.store().probe();
            let _ = self.health.outcome(probed, || "a probe".into());
        }
        let waiting: Vec<Pending> = std::mem::take(&mut *self.pending_lock());
        let mut left = Vec::new();
        for p in waiting {
            if !left.is_empty() || !self.health.writable() {
                left.push(p);
                continue;
            }
            let done = match &p {
                Pending::Frame { job, frame, path } => self.record_frame(*job, *frame, path),
                Pending::End { job, state, error } => self.record_end(*job, *state, error.clone()),
            };
            if done.is_err() {
                left.push(p);
            }
        }
        if !left.is_empty() {
            let mut pending = self.pending_lock();
            left.append(&mut pending);
            *pending = left;
        }
        if let Some(shared) = self.farm.get() {
            shared.set_writable(self.health.writable());
        }
    }

    /// Forgets the ended jobs `--keep-ended` no longer keeps, in memory and
    /// in the store; their files stay where they were written.
    fn prune_ended(&self) {
        let now = unix_ms();
        let ended: Vec<(u64, Duration)> = self
            .jobs_lock()
            .iter()
            .filter(|(_, m)| m.state.is_final())
            .map(|(&id, m)| {
                let age = Duration::from_millis(now.saturating_sub(m.ended_unix_ms));
                (id, age)
            })
            .collect();
        let prune = self.keep_ended.to_prune(ended);
        if prune.is_empty() {
            return;
        }
        let mut jobs = self.jobs_lock();
        let store = self.store();
        for &id in &prune {
            if let Err(e) = store.delete_job(id) {
                tracing::error!("job {id}: cannot prune it from the store: {e}");
                continue;
            }
            jobs.remove(&id);
        }
        tracing::info!("pruned {} ended jobs (--keep-ended)", prune.len());
    }

    /// Notes jobs whose first unit has gone out as running.
    fn note_running(&self, now: Instant) {
        let Some(shared) = self.farm.get() else {
            return;
        };
        let mut jobs = self.jobs_lock();
        for (&id, meta) in jobs.iter_mut() {
            if meta.state.is_final() {
                continue;
            }
            let Some(p) = shared.job_progress(id) else {
                continue;
            };
            if meta.running_since.is_none() && p.units_in_flight + p.units_done > 0 {
                meta.running_since = Some((now, p.units_done));
            }
            if meta.state == JobState::Queued && p.started {
                meta.state = JobState::Running;
                // Not kept when the store fails: a restart resumes a queued
                // job as a running one.
                let set = self.store().set_state(id, JobState::Running, None);
                let _ = self.health.outcome(set, || format!("job {id}'s start"));
            }
        }
    }

    /// A frame is complete: its image goes to its output (off the async
    /// thread), then the store forgets its tiles and records the file.
    async fn write_frame(self: &Arc<Self>, done: CompletedFrame) {
        let id = done.job;
        let (path, metadata) = {
            let jobs = self.jobs_lock();
            match jobs.get(&id) {
                Some(JobMeta {
                    state,
                    stored,
                    metadata: Some(metadata),
                    ..
                }) if !state.is_final() => (stored.spec.out.clone(), metadata.at_frame(done.frame)),
                _ => return,
            }
        };
        let path = expand_pattern(&path, done.frame);
        let image = done.image;
        let (service, pattern, target) = (Arc::clone(self), path.clone(), PathBuf::from(&path));
        let written = tokio::task::spawn_blocking(move || {
            // Placed again as it is written: a `#` in a directory makes
            // each frame's directory its own, and one may have changed.
            let target = service
                .roots
                .prepare(&pattern, &target, &service.base)
                .map_err(|e| e.to_string())?;
            crate::image::output::write_frame_image(&image, &target, &metadata)
                .map_err(|e| e.to_string())
        })
        .await;
        let written = match written {
            Ok(r) => r,
            Err(e) => Err(format!("the writer failed: {e}")),
        };
        if let Err(e) = written {
            self.end(id, JobState::Failed, Some(e));
            return;
        }
        tracing::info!(
            "job {id}: frame {} in {:.3} s → {path}",
            done.frame,
            done.render_time.as_secs_f64()
        );
        let waiting = !self.pending_lock().is_empty();
        if waiting || self.record_frame(id, done.frame, &path).is_err() {
            // Written but not recorded: the job does not count it (nor end)
            // until the store has it.
            self.pending_lock().push(Pending::Frame {
                job: id,
                frame: done.frame,
                path,
            });
        }
    }

    /// Records a frame written to `path` in the store, then in the job's
    /// view; the last frame ends the job as done.
    fn record_frame(&self, id: JobId, frame: u32, path: &str) -> Result<(), StoreError> {
        let recorded = self.store().finish_frame(id, frame, path);
        self.health
            .outcome(recorded, || format!("job {id} frame {frame}'s record"))?;
        let path = path.to_string();
        // A frame rendered again (it held a liar's tiles) replaced its file.
        let rendering_again = self.farm.get().is_some_and(|farm| !farm.job_finished(id));
        let finished = {
            let mut jobs = self.jobs_lock();
            match jobs.get_mut(&id) {
                Some(meta) => {
                    if !meta.outputs.contains(&path) {
                        meta.outputs.push(path);
                    }
                    meta.outputs.len() == meta.frames.len() && !rendering_again
                }
                None => false,
            }
        };
        if finished {
            self.end(id, JobState::Done, None);
        }
        Ok(())
    }

    /// The stored tiles of a frame that pass their checksum. A tile that does
    /// not is logged, counted, deleted from the store, and so rendered again.
    fn sound_tiles(&self, job: JobId, frame: u32) -> Result<Vec<(usize, Vec<u8>)>, StoreError> {
        let store = self.store();
        let read = store.tiles(job, frame)?;
        if !read.rotten.is_empty() {
            for unit in &read.rotten {
                tracing::warn!(
                    "job {job} frame {frame} unit {unit}: the stored tile's bytes do not match \
                     its checksum ({}): dropped, the unit is rendered again",
                    store.path().display()
                );
            }
            self.health.dropped(read.rotten.len() as u64);
            store.drop_tiles(job, frame, &read.rotten)?;
        }
        Ok(read
            .tiles
            .into_iter()
            .map(|(u, t)| (u as usize, t))
            .collect())
    }

    /// Restores the jobs the store holds: ended ones as they were, the others
    /// back into the farm from their stored tiles.
    fn restore(&self) -> Result<usize, ServiceError> {
        let (stored_jobs, path) = {
            let store = self.store();
            (store.jobs()?, store.path().to_path_buf())
        };
        let mut resumed = 0;
        for job in stored_jobs {
            if self.restore_job(&job, &path)? {
                resumed += 1;
            }
        }
        Ok(resumed)
    }

    /// Restores one stored job (from the store's file `path`): an ended one
    /// (or one whose every frame is recorded) as it is, one that no longer
    /// passes its checks as failed, the others back into the farm. Returns
    /// whether it went back into the farm.
    fn restore_job(&self, job: &store::StoredJob, path: &Path) -> Result<bool, ServiceError> {
        let bad = |message: String| ServiceError::StoredJob {
            path: path.to_path_buf(),
            id: job.id,
            message,
        };
        let stored: StoredSpec = serde_json::from_str(&job.spec_json)
            .map_err(|e| bad(format!("unreadable job: {e}")))?;
        let frames = frames_of(&stored.spec).map_err(bad)?;
        // By frame number: which frames were recorded, not how many.
        let finished: std::collections::BTreeSet<u32> =
            self.store().finished_frames(job.id)?.into_iter().collect();
        let mut state = job.state;
        if !state.is_final() && frames.iter().all(|f| finished.contains(&f)) && job.redo.is_empty()
        {
            state = JobState::Done;
            self.store().set_state(job.id, state, None)?;
        }
        let mut meta = JobMeta {
            scene_name: stored.spec.request.scene_name.clone(),
            units_per_frame: 0,
            metadata: None,
            scene: None,
            frames,
            state,
            error: job.error.clone(),
            outputs: job.outputs.clone(),
            running_since: None,
            final_units: 0,
            final_blocklisted: Vec::new(),
            ended_unix_ms: job.submitted_unix_ms,
            stored,
        };
        if state.is_final() {
            if let Ok(checked) = check_spec(&meta.stored.spec, &self.roots, &self.base) {
                meta.units_per_frame = farm_units(
                    checked.built.scene.width(),
                    checked.built.scene.height(),
                    meta.stored.interleave,
                    meta.stored.expected_workers,
                )
                .len() as u64;
            }
            meta.final_units = meta.units_per_frame * u64::from(job.frames_done);
            self.jobs_lock().insert(job.id, meta);
            return Ok(false);
        }
        match check_spec(&meta.stored.spec, &self.roots, &self.base) {
            Ok(checked) => {
                self.resume(job, meta, &checked, &finished, &bad)?;
                Ok(true)
            }
            Err(e) => {
                // Checked when submitted: the machine changed (a deleted
                // output directory, say). The job fails; others go on.
                self.jobs_lock().insert(job.id, meta);
                self.end(job.id, JobState::Failed, Some(e.to_string()));
                Ok(false)
            }
        }
    }

    /// Puts a stored job that has not ended back into the farm: the run of
    /// `finished` frames from its first is skipped, and any recorded after
    /// a gap render again (to the same bytes); the next frame starts from
    /// its sound stored tiles. A stored tile that does not fit is `bad`.
    fn resume(
        &self,
        job: &store::StoredJob,
        mut meta: JobMeta,
        checked: &Checked,
        finished: &std::collections::BTreeSet<u32>,
        bad: &dyn Fn(String) -> ServiceError,
    ) -> Result<(), ServiceError> {
        let frames_done = checked
            .frames
            .iter()
            .take_while(|f| finished.contains(f))
            .count();
        let tiles = match checked.frames.get(frames_done) {
            Some(frame) => self.sound_tiles(job.id, frame)?,
            None => Vec::new(),
        };
        let tile_count = tiles.len();
        meta.units_per_frame = self
            .enqueue(
                job.id,
                &meta.stored,
                checked,
                Resume {
                    frames_done,
                    tiles,
                    redo: job.redo.clone(),
                },
            )
            .map_err(bad)?;
        meta.metadata = Some(checked.metadata.clone());
        meta.scene = Some(Arc::clone(&checked.built.scene));
        tracing::info!(
            "job {} resumed: {frames_done} of {} frames written, {tile_count} units of the next stored",
            job.id,
            checked.frames.len()
        );
        self.jobs_lock().insert(job.id, meta);
        Ok(())
    }
}

impl Control for Arc<Service> {
    fn submit(&self, spec: JobSpec) -> Result<JobView, ApiError> {
        if self.draining.load(std::sync::atomic::Ordering::Relaxed) {
            return Err(ApiError::Unavailable(
                "the coordinator is shutting down and takes no new jobs".into(),
            ));
        }
        let active = self
            .jobs_lock()
            .values()
            .filter(|m| !m.state.is_final())
            .count();
        if active >= self.max_queued {
            return Err(ApiError::TooMany(format!(
                "the queue holds {active} jobs not ended, its limit (--max-queued {}); \
                 try again when some have ended",
                self.max_queued
            )));
        }
        let checked = check_spec(&spec, &self.roots, &self.base)?;
        let shared = self.farm()?;
        let (interleave, expected_workers) = shared.unit_layout();
        let stored = StoredSpec {
            spec,
            interleave,
            expected_workers,
        };
        let json = serde_json::to_string(&stored)
            .map_err(|e| ApiError::Internal(format!("cannot encode the job: {e}")))?;
        let inserted = self
            .store()
            .insert_job(&json, stored.spec.priority, unix_ms());
        let id = self
            .health
            .outcome(inserted, || "a new job".into())
            .map_err(|e| not_stored(&e))?;
        let mut jobs = self.jobs_lock();
        let units_per_frame = self
            .enqueue(id, &stored, &checked, Resume::default())
            .map_err(ApiError::Internal)?;
        let Checked {
            frames,
            metadata,
            built,
        } = checked;
        let name = stored.spec.request.scene_name.clone();
        tracing::info!(
            "job {id} queued: {name}, {} frame{}, priority {}",
            frames.len(),
            if frames.len() == 1 { "" } else { "s" },
            stored.spec.priority
        );
        let meta = JobMeta {
            stored,
            state: JobState::Queued,
            error: None,
            outputs: Vec::new(),
            frames,
            units_per_frame,
            scene_name: name,
            metadata: Some(metadata),
            scene: Some(built.scene),
            running_since: None,
            final_units: 0,
            final_blocklisted: Vec::new(),
            ended_unix_ms: 0,
        };
        let view = self.view(id, &meta, Instant::now());
        jobs.insert(id, meta);
        Ok(view)
    }

    fn jobs(&self) -> Vec<JobView> {
        let now = Instant::now();
        let jobs = self.jobs_lock();
        jobs.iter()
            .rev()
            .map(|(&id, meta)| self.view(id, meta, now))
            .collect()
    }

    fn jobs_page(&self, before: Option<u64>, limit: usize) -> (Vec<JobView>, Option<u64>) {
        let now = Instant::now();
        let jobs = self.jobs_lock();
        let older = jobs
            .range(..before.unwrap_or(u64::MAX))
            .rev()
            .map(|(&id, meta)| self.view(id, meta, now));
        crate::service::jobs::page(older, limit)
    }

    fn job(&self, id: u64) -> Result<JobView, ApiError> {
        let jobs = self.jobs_lock();
        jobs.get(&id)
            .map(|meta| self.view(id, meta, Instant::now()))
            .ok_or(ApiError::NotFound(id))
    }

    fn cancel(&self, id: u64) -> Result<JobView, ApiError> {
        let state = self
            .jobs_lock()
            .get(&id)
            .map(|m| m.state)
            .ok_or(ApiError::NotFound(id))?;
        if state.is_final() {
            return Err(ApiError::Conflict(format!(
                "job {id} has already ended ({})",
                state.as_str()
            )));
        }
        // Recorded first: a cancel the store cannot keep is refused, and the
        // job goes on.
        self.record_end(id, JobState::Cancelled, None)
            .map_err(|e| not_stored(&e))?;
        if let Some(meta) = self.jobs_lock().get_mut(&id) {
            self.leave_farm(id, meta);
        }
        self.job(id)
    }

    fn workers(&self) -> Vec<WorkerView> {
        let Some(shared) = self.farm.get() else {
            return Vec::new();
        };
        let mut views: Vec<(Instant, WorkerView)> = shared
            .workers(Instant::now())
            .into_iter()
            .map(|w| {
                (
                    w.joined,
                    WorkerView {
                        id: w.id,
                        name: w.name,
                        tags: w.tags,
                        threads: w.threads,
                        pixels_per_second: w.pixels_per_second,
                        current_job: w.current_job,
                        units: w.units,
                        blocklisted_for: w.blocklisted_for,
                    },
                )
            })
            .collect();
        views.sort_by(|a, b| a.0.cmp(&b.0).then(a.1.name.cmp(&b.1.name)));
        views.into_iter().map(|(_, v)| v).collect()
    }

    fn metrics(&self) -> String {
        // Only running jobs are shown by job: the series are bounded by the
        // jobs being rendered, not by the queue or its history.
        let (running, states) = {
            let now = Instant::now();
            let jobs = self.jobs_lock();
            let mut states = [0; JobState::ALL.len()];
            let mut running = Vec::new();
            for (&id, meta) in jobs.iter() {
                if let Some(i) = JobState::ALL.iter().position(|&s| s == meta.state) {
                    states[i] += 1;
                }
                if meta.state == JobState::Running {
                    running.push(self.view(id, meta, now));
                }
            }
            (running, states)
        };
        let workers = Control::workers(self);
        let (stats, queued_all, queued, in_flight): (_, u64, PerJob, PerJob) = match self.farm.get()
        {
            Some(shared) => {
                let queue = shared.queue();
                (
                    queue.stats,
                    queue.queued_all,
                    queue.started.iter().map(|&(id, q, _)| (id, q)).collect(),
                    queue.started.iter().map(|&(id, _, f)| (id, f)).collect(),
                )
            }
            None => Default::default(),
        };
        metrics::render(&metrics::Snapshot {
            jobs: &running,
            job_states: &states,
            workers: &workers,
            stats: &stats,
            queued_all,
            queued: &queued,
            in_flight: &in_flight,
            store: metrics::StoreHealth {
                writable: self.store_failure().is_none(),
                tiles_dropped: self
                    .health
                    .tiles_dropped
                    .load(std::sync::atomic::Ordering::Relaxed),
            },
        })
    }

    fn ready(&self) -> Result<(), String> {
        if self.draining.load(std::sync::atomic::Ordering::Relaxed) {
            return Err("the coordinator is shutting down".into());
        }
        match self.store_failure() {
            Some(why) => Err(why),
            None => Ok(()),
        }
    }
}

/// Serves `config` on a runtime of one thread until SIGTERM or Ctrl-C.
pub(crate) fn serve_until_signal(config: ServiceConfig) -> Result<(), ServiceError> {
    // One thread serves the farm and the API: per unit it checks, stores and
    // persists a tile, and any thread more competes with the local workers.
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .map_err(ServiceError::Runtime)?;
    runtime.block_on(serve(config, worker::shutdown_signal()))
}

/// Serves until `shutdown` resolves, then drains and returns.
pub async fn serve(
    config: ServiceConfig,
    shutdown: impl std::future::Future<Output = ()>,
) -> Result<(), ServiceError> {
    let service = open_service(&config)?;
    let control: Arc<dyn Control> = Arc::new(Arc::clone(&service));
    let studio = studio::Studio::new(
        config.studio_scene.as_deref(),
        &config.data,
        config.farm.token.clone(),
    )
    .map_err(ServiceError::Studio)?;
    let studio = Arc::new(match &config.studio_root {
        Some((root, first)) => studio.browsing(root.clone(), *first),
        None => studio,
    });
    let routes = studio::router(Arc::clone(&studio), Arc::clone(&control))
        .merge(crate::service::api::router(
            control,
            config.farm.token.clone(),
        ))
        // Every refusal of these routes is a JSON error, the studio's and
        // axum's own (405 on `/`) included; the gRPC routes come after.
        .layer(axum::middleware::from_fn(crate::service::api::json_errors));
    // Units sized as for a LAN farm of the paper's 64 processors (at least one
    // unit each), or for the local workers when there are more.
    let expected = config.farm.local_workers.max(64);
    let mut farm = Farm::start(
        config.farm.clone(),
        Scheduler::service(config.farm.lease),
        Some(routes),
        Some(Arc::new(StoreSink(
            Arc::clone(&service),
            Arc::clone(&studio),
        ))),
    )
    .await?;
    farm.shared()
        .set_unit_layout(config.farm.interleave, expected);
    let _ = service.farm.set(Arc::clone(farm.shared()));
    let started = Instant::now();
    let resumed = service.restore()?;
    studio.attach(Arc::clone(farm.shared()));
    announce(&farm, &config, &studio);
    tracing::info!(
        "serving on {}://{} (API at /api/v1, metrics at /metrics); {resumed} jobs resumed in {:.3} s",
        farm.scheme(),
        farm.addr(),
        started.elapsed().as_secs_f64()
    );
    let (failed, drain_deadline) =
        supervise(&mut farm, &service, &studio, config.drain_timeout, shutdown).await;
    // Past the drain time the workers get no more: the process exits within
    // `--drain-timeout` and a moment, whatever they do.
    let grace = drain_deadline.map_or(Duration::from_secs(5), |d| {
        d.saturating_duration_since(Instant::now())
    });
    farm.finish(grace, true).await;
    service.checkpoint();
    tracing::info!(
        "stopped; every job and stored unit is kept in {}",
        config.data.display()
    );
    match failed {
        Some(e) => Err(e.into()),
        None => Ok(()),
    }
}

/// The service's state over the store opened under `config.data`, with
/// nothing queued yet.
fn open_service(config: &ServiceConfig) -> Result<Arc<Service>, ServiceError> {
    let store = Store::open_with(&config.data, config.accept_older_store)?;
    tracing::info!("store {}", store.path().display());
    let base = std::env::current_dir()
        .map_err(|e| ServiceError::Roots(format!("cannot read the working directory: {e}")))?;
    tracing::info!(
        "outputs are written inside {}",
        config
            .output_roots
            .roots()
            .iter()
            .map(|r| r.display().to_string())
            .collect::<Vec<_>>()
            .join(", ")
    );
    Ok(Arc::new(Service {
        store: Mutex::new(store),
        jobs: Mutex::new(BTreeMap::new()),
        farm: OnceLock::new(),
        draining: std::sync::atomic::AtomicBool::new(false),
        health: health::Health::default(),
        pending: Mutex::new(Vec::new()),
        roots: config.output_roots.clone(),
        base,
        max_queued: config.max_queued,
        keep_ended: config.keep_ended,
    }))
}

/// Prints the studio's URL (and its scene's error) when the service is a
/// studio.
fn announce(farm: &Farm, config: &ServiceConfig, studio: &studio::Studio) {
    if config.studio_scene.is_none() {
        return;
    }
    let mut at = farm.addr();
    if at.ip().is_unspecified() {
        at.set_ip(std::net::Ipv4Addr::LOCALHOST.into());
    }
    println!("studio: {}://{at}/", farm.scheme());
    if let Some(error) = studio.error() {
        // The studio opens all the same: the text is edited in the page.
        eprintln!("studio: {error} (fix it in the page or in the file)");
    }
}

/// The supervisor loop: hands finished frames and failed jobs to the
/// service or the studio, keeps the store and the queue in shape, and on
/// `shutdown` drains (nothing more handed out; units in flight get
/// `drain_timeout`). Returns the farm's failure, if any, and the drain's
/// deadline once draining began.
async fn supervise(
    farm: &mut Farm,
    service: &Arc<Service>,
    studio: &studio::Studio,
    drain_timeout: Duration,
    shutdown: impl std::future::Future<Output = ()>,
) -> (Option<FarmError>, Option<Instant>) {
    tokio::pin!(shutdown);
    let mut pruned_at = Instant::now();
    let mut drain_deadline: Option<Instant> = None;
    loop {
        tokio::select! {
            () = farm.wait(Duration::from_millis(100)) => {}
            () = &mut shutdown, if drain_deadline.is_none() => {
                tracing::info!(
                    "draining: no new units; units in flight get {:.0} s to arrive",
                    drain_timeout.as_secs_f64()
                );
                service.draining.store(true, std::sync::atomic::Ordering::Relaxed);
                studio.stop();
                farm.shared().drain();
                drain_deadline = Some(Instant::now() + drain_timeout);
            }
        }
        let now = Instant::now();
        let tick = farm.tick(now);
        if let Some(p) = tick.panicked {
            return (Some(FarmError::Panicked(p)), drain_deadline);
        }
        hand_over(tick, service, studio).await;
        service.note_running(now);
        service.watch_store(now);
        if now.duration_since(pruned_at) >= limits::PRUNE_EVERY {
            pruned_at = now;
            service.prune_ended();
        }
        if let Some(deadline) = drain_deadline
            && drained(farm, now, deadline)
        {
            return (None, drain_deadline);
        }
    }
}

/// Ends the jobs a tick gave up and writes the frames it completed (the
/// studio's live frames go back to the studio).
async fn hand_over(tick: farm::Tick, service: &Arc<Service>, studio: &studio::Studio) {
    for (id, why) in tick.gave_up {
        if studio.owns(id) {
            studio.leave(id, Some(why.to_string()));
        } else {
            service.end(id, JobState::Failed, Some(why.to_string()));
        }
    }
    for done in tick.completed {
        if studio.owns(done.job) {
            studio.leave(done.job, None);
        } else {
            service.write_frame(done).await;
        }
    }
}

/// Whether a drain is over: every unit in flight has arrived, or
/// `deadline` has passed (the rest are left for the next start).
fn drained(farm: &Farm, now: Instant, deadline: Instant) -> bool {
    let in_flight = farm.shared().in_flight();
    if in_flight == 0 {
        tracing::info!("drained: every unit in flight has arrived");
        return true;
    }
    if now >= deadline {
        tracing::warn!("drain time-out: {in_flight} units in flight are left for the next start");
        return true;
    }
    false
}

/// A job as the store keeps it (its JSON), for tools that fill a store
/// directly: the spec as submitted and the unit layout it is rendered with.
pub fn stored_spec_json(
    spec: &JobSpec,
    interleave: u32,
    expected_workers: usize,
) -> Result<String, serde_json::Error> {
    serde_json::to_string(&StoredSpec {
        spec: spec.clone(),
        interleave,
        expected_workers,
    })
}

/// The address a service listens on by default.
pub fn default_listen() -> SocketAddr {
    SocketAddr::from(([127, 0, 0, 1], 47000))
}

#[cfg(test)]
mod tests {
    use super::*;
    use hypertexture::{Overrides, PixelFormat, Quality, RenderRequest};

    const SCENE: &str = include_str!("../../../scenes/noisy_sphere.ron");

    /// A stored job as the store has kept it: every field of the spec
    /// written, absent ones as null.
    const STORED: &str = r#"{"spec":{"scene":"Scene()","scene_name":null,"out":"/tmp/r/f_##.png",
        "frames":null,"priority":2,"width":null,"height":48,"spp":null,"quality":"high",
        "knobs":{"curliness":0.5},"require_tags":[]},"interleave":8,"expected_workers":64}"#;

    #[test]
    fn stored_jobs_are_read_in_the_form_the_store_keeps() {
        let stored: StoredSpec = serde_json::from_str(STORED).unwrap();
        let spec = &stored.spec;
        assert_eq!(
            spec.request,
            RenderRequest {
                overrides: Overrides {
                    height: Some(48),
                    quality: Some(Quality::High),
                    knobs: vec![("curliness".into(), 0.5)],
                    ..Overrides::default()
                },
                pixel_format: PixelFormat::Srgb8,
                ..RenderRequest::new("Scene()", "scene.ron")
            }
        );
        assert_eq!((spec.out.as_str(), spec.priority), ("/tmp/r/f_##.png", 2));
        assert_eq!((stored.interleave, stored.expected_workers), (8, 64));
        assert_eq!(frames_of(spec), Ok(FrameRange::one(0)));
        // Written again and read back: the same job.
        let json = stored_spec_json(spec, 8, 64).unwrap();
        let again: StoredSpec = serde_json::from_str(&json).unwrap();
        assert_eq!(again.spec, stored.spec);
    }

    /// A job writing `out` (relative to `dir`), its request from `json`'s
    /// fields over the scene.
    fn spec(out: &str, request: RenderRequest) -> JobSpec {
        JobSpec {
            request,
            out: out.into(),
            priority: 0,
            require_tags: Vec::new(),
        }
    }

    fn check(spec: &JobSpec) -> Result<Checked, ApiError> {
        let dir = std::env::temp_dir();
        let roots =
            crate::pipeline::destination::OutputRoots::new(std::slice::from_ref(&dir)).unwrap();
        check_spec(spec, &roots, &dir)
    }

    #[test]
    fn a_checked_job_is_built_once_and_sized_for_the_farm() {
        let request = RenderRequest {
            overrides: Overrides {
                width: Some(40),
                spp: Some(2),
                ..Overrides::default()
            },
            frames: FrameRange { first: 3, last: 4 },
            ..RenderRequest::new(SCENE, "noisy_sphere.ron")
        };
        let checked = check(&spec("service-test-##.png", request.clone())).unwrap();
        let built = &checked.built;
        assert_eq!((built.scene.width(), built.scene.spp()), (40, 2));
        assert_eq!(built.request.overrides.width, Some(40));
        assert_eq!(built.request.overrides.height, Some(built.scene.height()));
        assert_eq!(checked.frames, FrameRange::new(3, 4));
        assert_eq!(checked.metadata.request.overrides.spp, Some(2));
        let shared = hypertexture::render::request::shared_scene(built.hash).unwrap();
        assert!(
            Arc::ptr_eq(&shared, &built.scene),
            "workers in this process take it"
        );
    }

    #[test]
    fn refusals_name_what_is_wrong() {
        let good = RenderRequest::new(SCENE, "noisy_sphere.ron");
        let refused = |spec: JobSpec| match check(&spec) {
            Err(e) => e,
            Ok(_) => panic!("{:?} was accepted", spec.out),
        };
        let e = refused(spec(
            "a.png",
            RenderRequest {
                frames: FrameRange { first: 5, last: 2 },
                ..good.clone()
            },
        ));
        assert!(
            matches!(&e, ApiError::BadRequest(m) if m.contains("frames [5, 2]")),
            "{e}"
        );
        let e = refused(spec(
            "a.png",
            RenderRequest {
                scene_text: "x".repeat(hypertexture::scene::MAX_SCENE_BYTES + 1),
                ..good.clone()
            },
        ));
        assert!(e.to_string().contains("a scene may be at most"), "{e}");
        let e = refused(spec(
            "a.png",
            RenderRequest {
                overrides: Overrides {
                    knobs: vec![("nope".into(), 1.0)],
                    ..Overrides::default()
                },
                ..good.clone()
            },
        ));
        assert!(e.to_string().contains("--set nope"), "{e}");
        let e = refused(spec("a.jpg", good.clone()));
        assert!(
            matches!(e, ApiError::BadRequest(_)) && e.to_string().contains("a.jpg"),
            "{e}"
        );
        let e = refused(spec("/a.png", good.clone()));
        assert!(matches!(e, ApiError::Forbidden(_)), "{e}");
        let e = refused(JobSpec {
            require_tags: vec!["no spaces".into()],
            ..spec("a.png", good)
        });
        assert!(e.to_string().contains("require_tags"), "{e}");
    }
}
