//! The service's vocabulary: what a client submits (a [`JobSpec`]), what it is
//! shown ([`JobView`], [`WorkerView`]), and the [`Control`] interface through
//! which the HTTP API (`api.rs`) reaches the running farm.
//!
//! These types are the JSON of `/api/v1/…` and the rows of the store; the
//! OpenAPI document is generated from them.

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};
use utoipa::ToSchema;

/// A job as submitted: a scene and how to render it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, ToSchema)]
#[serde(deny_unknown_fields)]
pub struct JobSpec {
    /// The scene's RON text (at most 64 KiB).
    pub scene: String,
    /// The scene's name for messages (its file path); default `scene.ron`.
    #[serde(default)]
    pub scene_name: Option<String>,
    /// The output path pattern, on the coordinator's machine. `#` runs are the
    /// frame number padded to their length (`out/fur.####.exr` →
    /// `out/fur.0007.exr`); without `#` the job has one frame. The extension
    /// (`.png`, `.exr`) chooses the format.
    pub out: String,
    /// The first and last frame (inclusive); default: frame 0 only.
    #[serde(default)]
    pub frames: Option<[u32; 2]>,
    /// Higher runs first; ties run oldest first. Default 0.
    #[serde(default)]
    pub priority: i32,
    /// Image width (the scene's when absent).
    #[serde(default)]
    pub width: Option<u32>,
    /// Image height (the scene's when absent).
    #[serde(default)]
    pub height: Option<u32>,
    /// Samples per pixel (the scene's when absent).
    #[serde(default)]
    pub spp: Option<u32>,
    /// `interactive` or `high` (the scene's step when absent).
    #[serde(default)]
    pub quality: Option<QualitySpec>,
    /// Knob overrides, applied in name order.
    #[serde(default)]
    pub knobs: BTreeMap<String, f64>,
    /// Only workers carrying every one of these tags render the job.
    #[serde(default)]
    pub require_tags: Vec<String>,
}

/// The marching step preset.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, ToSchema)]
#[serde(rename_all = "lowercase")]
pub enum QualitySpec {
    /// The scene's interactive step.
    Interactive,
    /// The scene's step.
    High,
}

impl From<QualitySpec> for hypertexture::Quality {
    fn from(q: QualitySpec) -> Self {
        match q {
            QualitySpec::Interactive => hypertexture::Quality::Interactive,
            QualitySpec::High => hypertexture::Quality::High,
        }
    }
}

/// Where a job is in its life.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize, ToSchema)]
#[serde(rename_all = "lowercase")]
pub enum JobState {
    /// Waiting for workers.
    Queued,
    /// At least one unit has been handed out.
    Running,
    /// Every frame written.
    Done,
    /// Gave up (see `error`).
    Failed,
    /// Cancelled by a client.
    Cancelled,
}

impl JobState {
    /// Every state, in the order of the metrics.
    pub const ALL: [JobState; 5] = [
        JobState::Queued,
        JobState::Running,
        JobState::Done,
        JobState::Failed,
        JobState::Cancelled,
    ];

    /// Whether the job has ended.
    pub fn is_final(self) -> bool {
        matches!(
            self,
            JobState::Done | JobState::Failed | JobState::Cancelled
        )
    }

    /// The lower-case name (as in JSON).
    pub fn as_str(self) -> &'static str {
        match self {
            JobState::Queued => "queued",
            JobState::Running => "running",
            JobState::Done => "done",
            JobState::Failed => "failed",
            JobState::Cancelled => "cancelled",
        }
    }

    /// The state named `s` (as in JSON).
    pub fn parse(s: &str) -> Option<JobState> {
        JobState::ALL.into_iter().find(|j| j.as_str() == s)
    }
}

/// A job as the API shows it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct JobView {
    /// The job's id.
    pub id: u64,
    /// Its state.
    pub state: JobState,
    /// Its priority.
    pub priority: i32,
    /// The scene's name.
    pub scene_name: String,
    /// The output pattern.
    pub out: String,
    /// Frames written.
    pub frames_done: u32,
    /// Frames in all.
    pub frames_total: u32,
    /// Units complete, over every frame.
    pub units_done: u64,
    /// Units in all, over every frame.
    pub units_total: u64,
    /// Seconds until done at the rate so far (null until known, or once ended).
    pub eta_seconds: Option<f64>,
    /// Why it failed (null unless failed).
    pub error: Option<String>,
    /// The files written so far.
    pub outputs: Vec<String>,
    /// Tags a worker must carry to render it.
    pub require_tags: Vec<String>,
    /// Workers blocklisted for this job (they failed 3 of its units).
    pub blocklisted: Vec<String>,
}

/// A worker as the API shows it.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, ToSchema)]
pub struct WorkerView {
    /// Its id (`w7`).
    pub id: String,
    /// Its name.
    pub name: String,
    /// Its tags.
    pub tags: Vec<String>,
    /// Render threads it announced.
    pub threads: u32,
    /// Pixels per second over the last minute of its tiles.
    pub pixels_per_second: f64,
    /// The job it is rendering (null when idle).
    pub current_job: Option<u64>,
    /// Units accepted from it.
    pub units: u64,
    /// Jobs it is blocklisted for.
    pub blocklisted_for: Vec<u64>,
}

/// A refusal of the API, with its HTTP status.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum ApiError {
    /// 400: the request is malformed (a bad scene names file:line:column).
    #[error("{0}")]
    BadRequest(String),
    /// 403: an output outside the service's output roots.
    #[error("{0}")]
    Forbidden(String),
    /// 404: no such job.
    #[error("no job {0}")]
    NotFound(u64),
    /// 409: the request conflicts with the job's state (cancelling an ended job).
    #[error("{0}")]
    Conflict(String),
    /// 429: the queue is full (`--max-queued`); answered with `Retry-After`.
    #[error("{0}")]
    TooMany(String),
    /// 503: the coordinator is draining and takes no new jobs.
    #[error("{0}")]
    Unavailable(String),
    /// 500: the coordinator's own fault (the store failed).
    #[error("{0}")]
    Internal(String),
    /// 507: the store's disk is full; nothing was kept.
    #[error("{0}")]
    InsufficientStorage(String),
}

/// The first `limit` of `jobs` (newest first), and the id that starts the
/// next page when more follow.
pub fn page(jobs: impl Iterator<Item = JobView>, limit: usize) -> (Vec<JobView>, Option<u64>) {
    let mut page: Vec<JobView> = jobs.take(limit.saturating_add(1)).collect();
    let more = page.len() > limit;
    page.truncate(limit);
    let next = if more {
        page.last().map(|j| j.id)
    } else {
        None
    };
    (page, next)
}

/// What the HTTP API asks of the running farm. Implemented by the service;
/// every method is quick (no rendering, at most a store transaction).
pub trait Control: Send + Sync + 'static {
    /// Checks and queues a job; returns it as queued.
    fn submit(&self, spec: JobSpec) -> Result<JobView, ApiError>;
    /// Every job, newest first.
    fn jobs(&self) -> Vec<JobView>;
    /// At most `limit` jobs older than the job `before` (all when `None`),
    /// newest first, and the id to pass as `before` for the next page (`None`
    /// on the last page).
    fn jobs_page(&self, before: Option<u64>, limit: usize) -> (Vec<JobView>, Option<u64>) {
        let older = self
            .jobs()
            .into_iter()
            .filter(|j| before.is_none_or(|b| j.id < b));
        page(older, limit)
    }
    /// One job.
    fn job(&self, id: u64) -> Result<JobView, ApiError>;
    /// Cancels a job that has not ended; returns it.
    fn cancel(&self, id: u64) -> Result<JobView, ApiError>;
    /// Every connected worker.
    fn workers(&self) -> Vec<WorkerView>;
    /// The Prometheus text exposition of the farm's metrics.
    fn metrics(&self) -> String;
    /// Whether the service takes work (`/readyz`): `Err` says why not (its
    /// store cannot write, it is shutting down).
    fn ready(&self) -> Result<(), String> {
        Ok(())
    }
}
