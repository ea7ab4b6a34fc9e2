//! The service's vocabulary: what a client submits (a [`JobSpec`], as JSON a
//! [`JobJson`]), what it is
//! shown ([`JobView`], [`WorkerView`]), and the [`Control`] interface through
//! which the HTTP API (`api.rs`) reaches the running farm.
//!
//! These types are the JSON of `/api/v1/…` and the rows of the store; the
//! OpenAPI document is generated from them.

use std::collections::BTreeMap;

use hypertexture::{FrameRange, Overrides, Quality, RenderRequest};
use serde::{Deserialize, Serialize};
use utoipa::ToSchema;

/// A job as submitted: what to render, where its images go, and how it is
/// queued. Its JSON is [`JobJson`]'s (the API's `JobSpec`), and so is its
/// stored form.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(from = "JobJson", into = "JobJson")]
pub struct JobSpec {
    /// The scene (at most 64 KiB), its overrides, frames and pixel format
    /// (what the output's extension needs).
    pub request: RenderRequest,
    /// The output path pattern ([`JobJson::out`]).
    pub out: String,
    /// Higher runs first; ties run oldest first.
    pub priority: i32,
    /// Only workers carrying every one of these tags render the job.
    pub require_tags: Vec<String>,
}

/// A job as submitted, as JSON (named `JobSpec` in the API's document and
/// its messages).
pub use json::JobSpec as JobJson;

mod json {
    use super::*;

    /// A job as submitted, as JSON: `POST /api/v1/jobs`'s body and the store's
    /// record (both read by [`super::JobSpec`]).
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
        #[schema(schema_with = super::optional_quality_schema)]
        pub quality: Option<Quality>,
        /// Knob overrides, applied in name order.
        #[serde(default)]
        pub knobs: BTreeMap<String, f64>,
        /// Only workers carrying every one of these tags render the job.
        #[serde(default)]
        pub require_tags: Vec<String>,
    }
}

/// The longest scene name kept (in characters); the rest is cut.
pub const MAX_SCENE_NAME_CHARS: usize = 256;

impl From<JobJson> for JobSpec {
    /// The job `json` asks for: its scene name made safe to log
    /// ([`hypertexture_proto::convert::untrusted`]; `scene.ron` when absent),
    /// its knobs in name order, frame 0 when no frames are given, and the
    /// pixel format the output's extension needs. The frames and the output
    /// are checked when the job is submitted.
    fn from(json: JobJson) -> JobSpec {
        let name = json
            .scene_name
            .filter(|n| !n.is_empty())
            .unwrap_or_else(|| "scene.ron".into());
        let frames = json
            .frames
            .map_or(FrameRange::one(0), |[first, last]| FrameRange {
                first,
                last,
            });
        let request = RenderRequest {
            scene_text: json.scene,
            scene_name: hypertexture_proto::convert::untrusted(&name, MAX_SCENE_NAME_CHARS),
            overrides: Overrides {
                width: json.width,
                height: json.height,
                spp: json.spp,
                quality: json.quality,
                knobs: Overrides::knob_list(json.knobs),
            },
            frames,
            pixel_format: crate::image::output::pixel_format_for([std::path::Path::new(&json.out)]),
            bake: None,
        };
        JobSpec {
            request,
            out: json.out,
            priority: json.priority,
            require_tags: json.require_tags,
        }
    }
}

impl From<JobSpec> for JobJson {
    fn from(spec: JobSpec) -> JobJson {
        let RenderRequest {
            scene_text,
            scene_name,
            overrides,
            frames,
            ..
        } = spec.request;
        JobJson {
            scene: scene_text,
            scene_name: Some(scene_name),
            out: spec.out,
            frames: Some([frames.first, frames.last]),
            priority: spec.priority,
            width: overrides.width,
            height: overrides.height,
            spp: overrides.spp,
            quality: overrides.quality,
            knobs: overrides.knobs.into_iter().collect(),
            require_tags: spec.require_tags,
        }
    }
}

/// The name of [`Quality`]'s schema in the API's document.
pub const QUALITY_SCHEMA: &str = "QualitySpec";

/// [`Quality`]'s schema in the API's document (the component
/// [`QUALITY_SCHEMA`]): its names, [`Quality::NAMES`].
pub fn quality_schema() -> utoipa::openapi::schema::Object {
    utoipa::openapi::schema::ObjectBuilder::new()
        .schema_type(utoipa::openapi::schema::Type::String)
        .description(Some(
            "The marching step preset: `interactive` (the scene's interactive step) or `high` \
             (the scene's step).",
        ))
        .enum_values(Some(Quality::NAMES))
        .build()
}

/// The schema of an optional [`Quality`] field: null or [`QUALITY_SCHEMA`].
fn optional_quality_schema() -> utoipa::openapi::RefOr<utoipa::openapi::schema::Schema> {
    use utoipa::openapi::schema::{Object, OneOfBuilder, Ref, Schema, Type};
    let one_of = OneOfBuilder::new()
        .item(Object::with_type(Type::Null))
        .item(Ref::from_schema_name(QUALITY_SCHEMA))
        .build();
    Schema::OneOf(one_of).into()
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

#[cfg(test)]
mod tests {
    use super::*;
    use hypertexture::{PixelFormat, Quality};

    #[test]
    fn a_jobs_json_reads_into_one_request_and_back() {
        let json = r#"{"scene":"Scene()","scene_name":"fur.ron","out":"out/f.####.exr",
            "frames":[2,5],"priority":3,"width":64,"spp":4,"quality":"interactive",
            "knobs":{"b":1.0,"a":0.5},"require_tags":["gpu"]}"#;
        let spec: JobSpec = serde_json::from_str(json).unwrap();
        let r = &spec.request;
        assert_eq!(
            (r.scene_text.as_str(), r.scene_name.as_str()),
            ("Scene()", "fur.ron")
        );
        assert_eq!(r.frames, FrameRange { first: 2, last: 5 });
        assert_eq!(
            r.overrides,
            Overrides {
                width: Some(64),
                height: None,
                spp: Some(4),
                quality: Some(Quality::Interactive),
                knobs: vec![("a".into(), 0.5), ("b".into(), 1.0)],
            }
        );
        assert_eq!(
            r.pixel_format,
            PixelFormat::Samples,
            "an EXR needs every sample"
        );
        assert_eq!(r.bake, None);
        assert_eq!(
            (spec.priority, spec.require_tags.clone()),
            (3, vec!["gpu".into()])
        );
        let again: JobSpec = serde_json::from_str(&serde_json::to_string(&spec).unwrap()).unwrap();
        assert_eq!(again, spec);
    }

    #[test]
    fn a_bare_job_takes_the_defaults() {
        let spec: JobSpec = serde_json::from_str(r#"{"scene":"S","out":"a.png"}"#).unwrap();
        assert_eq!(
            spec.request,
            RenderRequest {
                pixel_format: PixelFormat::Srgb8,
                ..RenderRequest::new("S", "scene.ron")
            }
        );
        assert_eq!((spec.priority, spec.require_tags.len()), (0, 0));
        let empty_name: JobSpec =
            serde_json::from_str(r#"{"scene":"S","scene_name":"","out":"a.png"}"#).unwrap();
        assert_eq!(empty_name.request.scene_name, "scene.ron");
    }

    #[test]
    fn a_scene_name_is_made_safe_to_log() {
        let json = format!(
            r#"{{"scene":"S","scene_name":"a\nb\u202e{}","out":"a.png"}}"#,
            "x".repeat(300)
        );
        let spec: JobSpec = serde_json::from_str(&json).unwrap();
        let name = &spec.request.scene_name;
        assert!(name.starts_with("a\\nb\\u{202e}x"), "{name}");
        // Cut after 256 characters of the name (4 of them escaped), with `…`.
        assert_eq!(name.matches('x').count(), MAX_SCENE_NAME_CHARS - 4);
        assert!(name.ends_with('…'), "{name}");
    }

    #[test]
    fn refusals_of_the_json_name_the_field() {
        let e = serde_json::from_str::<JobSpec>(r#"{"scene":"S","out":"a.png","colour":1}"#)
            .unwrap_err()
            .to_string();
        assert!(e.contains("unknown field `colour`"), "{e}");
        let e = serde_json::from_str::<JobSpec>(r#"{"scene":"S"}"#)
            .unwrap_err()
            .to_string();
        assert!(e.contains("missing field `out`"), "{e}");
        let e = serde_json::from_str::<JobSpec>(r#"{"scene":"S","out":"a.png","quality":"best"}"#)
            .unwrap_err()
            .to_string();
        assert!(e.contains("unknown variant `best`"), "{e}");
        let e = serde_json::from_str::<JobSpec>("[]")
            .unwrap_err()
            .to_string();
        assert!(e.contains("struct JobSpec"), "{e}");
    }

    #[test]
    fn qualities_are_spelt_as_the_library_names_them() {
        for q in Quality::ALL {
            let json = serde_json::to_string(&q).unwrap();
            assert_eq!(json, format!("\"{q}\""));
            assert_eq!(serde_json::from_str::<Quality>(&json).unwrap(), q);
        }
        let schema = serde_json::to_value(quality_schema()).unwrap();
        assert_eq!(schema["enum"], serde_json::json!(Quality::NAMES));
    }
}
