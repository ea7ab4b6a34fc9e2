//! The scheduler's state: [`Scheduler`] with the state it keeps per job,
//! per worker and per assignment, the plans and frames of jobs, the checks it
//! asks for, what it reports, why it refuses a call, and its limits. Every
//! other module of the scheduler builds on these; this one uses none of them.

use std::collections::{BTreeMap, BTreeSet, HashMap, HashSet, VecDeque};
use std::time::{Duration, Instant};

use hypertexture::render::interleave::WorkUnit;
use hypertexture::{FrameRange, PixelFormat};
use hypertexture_proto::FailureKind;

use crate::image::canvas::{Canvas, FrameImage};
use hypertexture_proto::convert::{self, WireError};

/// A unit that fails to render this many times (on different workers when
/// there are any) fails its job; a worker that fails this many units of a
/// job is blocklisted for it.
pub const MAX_FAILURES: usize = 3;

/// How far back a worker's pixels per second are measured.
pub(super) const RATE_WINDOW: Duration = Duration::from_secs(60);

/// A job's id: unique, increasing in the order of submission.
pub type JobId = u64;

/// The job of a one-shot render ([`Scheduler::new`]).
pub const ONE_SHOT_JOB: JobId = 1;

/// Why a call was refused.
#[derive(Debug, thiserror::Error, PartialEq)]
pub enum Refusal {
    /// The worker is not registered (or was dropped after its lease ran out).
    #[error("unknown worker {0}: register again")]
    UnknownWorker(String),
    /// The assignment id was never issued.
    #[error("assignment {0} was never issued")]
    NeverAssigned(u64),
    /// The assignment was taken back (lease ran out) or belongs to another worker.
    #[error("assignment {0} is no longer held by this worker")]
    NotHeld(u64),
    /// The tile's unit differs from the assignment's.
    #[error("assignment {0} is for another unit")]
    WrongUnit(u64),
    /// A failure report is malformed.
    #[error("malformed failure report: {0}")]
    BadReport(WireError),
    /// The tile itself is malformed.
    #[error("malformed tile for assignment {id}: {error}")]
    Malformed {
        /// The assignment.
        id: u64,
        /// What is wrong.
        error: WireError,
    },
    /// The tile is valid but could not be kept (the service's store cannot
    /// write): it is not accepted, and its unit is handed out again later.
    #[error(
        "the coordinator cannot keep the tile of assignment {id} now ({reason}); its unit is handed out again later"
    )]
    Unstored {
        /// The assignment.
        id: u64,
        /// Why it could not be kept.
        reason: String,
    },
}

/// A tile accepted into a canvas: what the service stores.
#[derive(Clone, Debug, PartialEq)]
pub struct Accepted {
    /// The job.
    pub job: JobId,
    /// The frame.
    pub frame: u32,
    /// The unit's index.
    pub unit: usize,
    /// The name of the worker that rendered it.
    pub worker: String,
    /// From the unit's assignment to its tile.
    pub latency: Duration,
    /// Sampled for a second rendering and not yet confirmed: the service
    /// stores it once it is ([`Scheduler::take_confirmed`]), so a restart
    /// never takes an unchecked tile for a checked one.
    pub held: bool,
}

/// A job's progress, as the service reports it.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct JobProgress {
    /// Units complete, over every frame.
    pub units_done: u64,
    /// Units in all.
    pub units_total: u64,
    /// Frames complete in the scheduler (written or being written).
    pub frames_complete: u32,
    /// Whether a unit of it has ever been handed out.
    pub started: bool,
    /// Units waiting to be handed out (this frame).
    pub units_queued: u64,
    /// Units held by workers now.
    pub units_in_flight: u64,
}

pub(super) struct Job {
    pub(super) plan: JobPlan,
    /// Index in `plan.frames` of the frame rendering.
    pub(super) current: usize,
    /// Counts the frames completed in this scheduler: what an assignment or
    /// a check was of, to tell it from the frame rendering now.
    pub(super) pass: u64,
    /// While a complete frame is rendered again: the index in `plan.frames`
    /// to go on with afterwards (the number of the plan's frames complete).
    pub(super) resume_at: Option<usize>,
    /// Indices in `plan.frames` of complete frames to render again, whole,
    /// because they hold a liar's tiles.
    pub(super) redo: BTreeSet<usize>,
    /// When the current frame's first unit went out.
    pub(super) frame_started: Option<Instant>,
    pub(super) pending: VecDeque<usize>,
    pub(super) done: Vec<bool>,
    pub(super) remaining: usize,
    pub(super) canvas: Canvas,
    /// Per unit: the CPU microseconds the accepted tile cost.
    pub(super) unit_cpu: Vec<u64>,
    /// Per unit: the async-thread CPU microseconds its last tile reported.
    pub(super) unit_calls: Vec<u64>,
    /// Per unit: the workers (by id) that failed it, and how.
    pub(super) failures: Vec<Vec<(u64, UnitFailure)>>,
    /// Per worker: units of this job it failed (blocklisted at [`MAX_FAILURES`]).
    pub(super) worker_failures: HashMap<u64, usize>,
    /// Workers whose scene for this job does not build, and what they said.
    pub(super) cannot_build: HashMap<u64, String>,
    /// The fraction of units rendered twice (0: none, 1: every one).
    pub(super) verify: f64,
    /// Per unit of the frame rendering: the worker whose tile is in the
    /// canvas (`None`: not in, stored before a restart, or the coordinator's).
    pub(super) delivered: Vec<Option<u64>>,
    /// Units of the frame rendering sampled for a second rendering whose
    /// tile is in and not yet confirmed: who delivered it, and its bytes.
    pub(super) held: BTreeMap<usize, (u64, Vec<u8>)>,
    /// Held units waiting for their second rendering, oldest first.
    pub(super) to_check: VecDeque<usize>,
    /// Second renderings that differ from a held tile, per unit, for the
    /// coordinator to decide: who rendered it, and its bytes.
    pub(super) disputed: BTreeMap<usize, Vec<(u64, Vec<u8>)>>,
    /// Workers caught lying about this job: blocklisted for it.
    pub(super) liars: HashSet<u64>,
    /// Per worker: the frames already complete (indices in `plan.frames`)
    /// that hold its tiles.
    pub(super) frames_delivered: HashMap<u64, BTreeSet<usize>>,
    pub(super) gave_up: Option<GiveUp>,
    /// Cancelled or given up: nothing more is handed out.
    pub(super) ended: bool,
    pub(super) started: bool,
}

impl Job {
    pub(super) fn new(plan: JobPlan, resume: Resume) -> Result<Job, WireError> {
        hypertexture::render::interleave::check_partition(&plan.units, plan.width, plan.height)
            .map_err(WireError::InvalidUnit)?;
        let n = plan.units.len();
        let interleave = plan.units.first().map_or(1, |u| u.set.interleave);
        let mut job = Job {
            current: resume.frames_done.min(plan.frames.len()),
            pass: 0,
            resume_at: None,
            redo: resume
                .redo
                .iter()
                .filter_map(|&f| plan.frames.index_of(f))
                .filter(|&i| i < resume.frames_done)
                .collect(),
            frame_started: None,
            pending: (0..n).collect(),
            done: vec![false; n],
            remaining: n,
            canvas: Canvas::new(plan.width, plan.height, interleave, plan.format),
            unit_cpu: vec![0; n],
            unit_calls: vec![0; n],
            failures: vec![Vec::new(); n],
            worker_failures: HashMap::new(),
            cannot_build: HashMap::new(),
            verify: 0.0,
            delivered: vec![None; n],
            held: BTreeMap::new(),
            to_check: VecDeque::new(),
            disputed: BTreeMap::new(),
            liars: HashSet::new(),
            frames_delivered: HashMap::new(),
            gave_up: None,
            ended: false,
            started: resume.frames_done > 0 || !resume.tiles.is_empty(),
            plan,
        };
        if job.current == job.plan.frames.len() {
            if let Some(first) = job.redo.pop_first() {
                // Every frame is written, but some hold a liar's tiles.
                job.resume_at = Some(job.current);
                job.current = first;
                return Ok(job);
            }
            job.remaining = 0;
            job.pending.clear();
            return Ok(job);
        }
        for (unit, bytes) in resume.tiles {
            let Some(u) = job.plan.units.get(unit).copied() else {
                return Err(WireError::Missing("a stored tile's unit"));
            };
            if job.done[unit] {
                continue;
            }
            let tile =
                convert::tile_from_wire(&bytes, u.pixel_count(job.plan.width), job.plan.format)?;
            job.canvas.store(&u, tile);
            job.done[unit] = true;
            job.remaining -= 1;
        }
        job.pending.retain(|&u| !job.done[u]);
        Ok(job)
    }

    pub(super) fn frame(&self) -> u32 {
        let frames = &self.plan.frames;
        frames.get(self.current).unwrap_or(frames.last)
    }

    pub(super) fn finished(&self) -> bool {
        if !self.redo.is_empty() {
            return false;
        }
        match self.resume_at {
            None if self.current >= self.plan.frames.len() => true,
            next => {
                next.unwrap_or(self.current + 1) >= self.plan.frames.len() && self.frame_settled()
            }
        }
    }

    /// The number of the plan's frames complete (frames rendered again
    /// included).
    pub(super) fn frames_complete(&self) -> usize {
        self.resume_at
            .unwrap_or(self.current)
            .min(self.plan.frames.len())
    }

    /// Every unit of the frame rendering is in, and every sampled one confirmed.
    pub(super) fn frame_settled(&self) -> bool {
        self.remaining == 0 && self.held.is_empty()
    }

    /// Units to hand out: waiting to be rendered, or to be rendered again.
    pub(super) fn has_work(&self) -> bool {
        self.remaining > 0 || !self.to_check.is_empty()
    }

    pub(super) fn blocklisted(&self, worker: u64) -> bool {
        self.liars.contains(&worker)
            || self
                .worker_failures
                .get(&worker)
                .is_some_and(|&n| n >= MAX_FAILURES)
    }

    /// Whether the unit's tile, just in, gets a second rendering: a keyed
    /// hash of (job, frame, unit) below the job's fraction. The key is drawn
    /// when the scheduler starts, so no worker can tell which units are checked.
    pub(super) fn sampled(&self, key: u64, unit: usize) -> bool {
        if self.verify <= 0.0 {
            return false;
        }
        let h = hypertexture::math::random::hash(&[
            key,
            self.plan.id,
            u64::from(self.frame()),
            unit as u64,
        ]);
        ((h >> 11) as f64) < self.verify * (1u64 << 53) as f64
    }

    /// Whether `worker` may be handed units of this job.
    pub(super) fn open_to(&self, worker: u64, w: &WorkerState) -> bool {
        !self.ended
            && self.has_work()
            && !self.cannot_build.contains_key(&worker)
            && !self.blocklisted(worker)
            && self.plan.require_tags.iter().all(|t| w.tags.contains(t))
    }

    pub(super) fn failed_by(&self, unit: usize, worker: u64) -> bool {
        self.failures[unit].iter().any(|(w, _)| *w == worker)
    }
}

/// The state of the farm: its jobs and its workers.
pub struct Scheduler {
    pub(super) jobs: BTreeMap<JobId, Job>,
    /// Frames complete and not yet taken.
    pub(super) completed: Vec<CompletedFrame>,
    /// Outstanding assignments.
    pub(super) leases: HashMap<u64, Lease>,
    /// The job, frame index and unit of every assignment of a job that has
    /// not ended (to tell late duplicates from forgeries).
    pub(super) issued: HashMap<u64, (JobId, u64, usize)>,
    pub(super) next_assignment: u64,
    pub(super) workers: HashMap<u64, WorkerState>,
    pub(super) next_worker: u64,
    pub(super) lease: Duration,
    /// A one-shot render: workers hear `Finished` once every job is done, and
    /// a job nobody present can render is given up.
    pub(super) one_shot: bool,
    /// Draining: nothing more is handed out.
    pub(super) draining: bool,
    /// Units are held back: the tiles cannot be kept now ([`Scheduler::pause`]).
    pub(super) paused: bool,
    /// Assignments taken back from their workers by [`Scheduler::remove_job`]
    /// and not yet told them: (worker id, assignment id).
    pub(super) withdrawn: Vec<(String, u64)>,
    /// Keys the secret half of the ids handed to workers at registration.
    pub(super) id_keys: std::collections::hash_map::RandomState,
    /// The fraction of units of jobs added from now on rendered twice.
    pub(super) verify: f64,
    /// Keys the choice of units rendered twice.
    pub(super) verify_key: u64,
    /// Sampled units whose second rendering has been compared with the
    /// first (by another worker's tile or the coordinator's own).
    pub(super) verified: u64,
    /// Claims and disputes for the coordinator to check, oldest first.
    pub(super) urgent: VecDeque<Check>,
    /// Held tiles whose second rendering agreed, not yet taken for the store.
    pub(super) confirmed: Vec<(Accepted, Vec<u8>)>,
}

impl Scheduler {
    /// A one-shot render of `units` of a `width × height` frame whose tiles
    /// come in `format` (job [`ONE_SHOT_JOB`], frame 0); a worker silent for
    /// `lease` loses its units. The units must cover every pixel exactly once
    /// ([`hypertexture::render::interleave::check_partition`], which the caller runs).
    pub fn new(
        units: Vec<WorkUnit>,
        width: u32,
        height: u32,
        format: PixelFormat,
        lease: Duration,
    ) -> Scheduler {
        let mut s = Scheduler::service(lease);
        s.one_shot = true;
        s.add_job(
            JobPlan::one_frame(ONE_SHOT_JOB, 0, units, (width, height), format),
            Resume::default(),
        )
        .expect("a new job has no stored tiles, and the caller checked its units");
        s
    }

    /// A scheduler without jobs that waits for them ([`Scheduler::add_job`]).
    pub fn service(lease: Duration) -> Scheduler {
        Scheduler {
            jobs: BTreeMap::new(),
            completed: Vec::new(),
            leases: HashMap::new(),
            issued: HashMap::new(),
            next_assignment: 1,
            workers: HashMap::new(),
            next_worker: 1,
            lease,
            one_shot: false,
            draining: false,
            paused: false,
            withdrawn: Vec::new(),
            id_keys: std::collections::hash_map::RandomState::new(),
            verify: 0.0,
            verify_key: {
                use std::hash::BuildHasher;
                std::collections::hash_map::RandomState::new().hash_one(Instant::now())
            },
            verified: 0,
            urgent: VecDeque::new(),
            confirmed: Vec::new(),
        }
    }

    /// Renders these frames of the one-shot job (in order, at least one) instead of frame 0.
    pub fn with_frames(mut self, frames: FrameRange) -> Scheduler {
        if let Some(job) = self.jobs.get_mut(&ONE_SHOT_JOB) {
            job.plan.frames = frames;
        }
        self
    }

    /// Stops handing out units (a draining service).
    pub fn drain(&mut self) {
        self.draining = true;
    }

    /// Stops (`true`) or resumes (`false`) handing out units while the tiles
    /// cannot be kept (a service whose store cannot write).
    pub fn pause(&mut self, paused: bool) {
        self.paused = paused;
    }

    /// Whether units are held back by [`Scheduler::pause`].
    pub fn paused(&self) -> bool {
        self.paused
    }

    /// Units held by workers now.
    pub fn in_flight(&self) -> usize {
        self.leases.len()
    }

    /// The frame the one-shot job is rendering.
    pub fn frame(&self) -> u32 {
        self.jobs.get(&ONE_SHOT_JOB).map_or(0, Job::frame)
    }

    /// Whether the job has nothing left to render (true when unknown): every
    /// frame of its plan complete, none waiting to be rendered again.
    pub fn job_finished(&self, job: JobId) -> bool {
        self.jobs.get(&job).is_none_or(Job::finished)
    }

    /// Whether every unit of every frame of every job is complete.
    pub fn finished(&self) -> bool {
        self.jobs.values().all(Job::finished)
    }

    /// Units complete and in all, over every frame of the one-shot job.
    pub fn progress(&self) -> (usize, usize) {
        self.jobs.get(&ONE_SHOT_JOB).map_or((0, 0), |j| {
            let p = job_progress(j, &self.leases);
            (p.units_done as usize, p.units_total as usize)
        })
    }

    /// A job's progress.
    pub fn job_progress(&self, job: JobId) -> Option<JobProgress> {
        self.jobs.get(&job).map(|j| job_progress(j, &self.leases))
    }

    /// Units waiting to be handed out, over every job.
    pub fn queued_units(&self) -> usize {
        self.jobs
            .values()
            .filter(|j| !j.ended)
            .map(|j| j.pending.len())
            .sum()
    }

    /// Tiles held for a second rendering that it confirmed since the last
    /// call (with their bytes), for the service's store.
    pub fn take_confirmed(&mut self) -> Vec<(Accepted, Vec<u8>)> {
        std::mem::take(&mut self.confirmed)
    }

    /// The one-shot job's image so far, gaps filled from coarser pixel sets
    /// ([`Canvas::preview`]).
    pub fn preview(&self) -> FrameImage {
        self.preview_of(ONE_SHOT_JOB)
            .unwrap_or_else(|| Canvas::new(1, 1, 1, PixelFormat::Srgb8).preview())
    }

    /// A job's current frame and its image so far, gaps filled from coarser
    /// pixel sets.
    pub fn preview_of(&self, job: JobId) -> Option<FrameImage> {
        self.jobs.get(&job).map(|j| j.canvas.preview())
    }

    /// The ids of the jobs in the scheduler.
    pub fn job_ids(&self) -> Vec<JobId> {
        self.jobs.keys().copied().collect()
    }
}

pub(super) fn job_progress(j: &Job, leases: &HashMap<u64, Lease>) -> JobProgress {
    let n = j.plan.units.len() as u64;
    let frames = j.plan.frames.len() as u64;
    let complete = j.frames_complete() as u64;
    let done_now = if j.resume_at.is_some() || complete >= frames {
        // A frame rendered again adds nothing to the plan's progress.
        0
    } else {
        n - j.remaining as u64
    };
    let frames_complete = if j.finished() { frames } else { complete };
    JobProgress {
        units_done: (complete * n + done_now).min(frames * n),
        units_total: frames * n,
        frames_complete: frames_complete as u32,
        started: j.started,
        units_queued: if j.ended { 0 } else { j.pending.len() as u64 },
        units_in_flight: leases.values().filter(|l| l.job == j.plan.id).count() as u64,
    }
}

/// One worker's failure to render a unit.
#[derive(Clone, Debug, PartialEq)]
pub struct UnitFailure {
    /// The worker's name.
    pub worker: String,
    /// What kind of failure.
    pub kind: FailureKind,
    /// What the worker said.
    pub reason: String,
}

impl std::fmt::Display for UnitFailure {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "worker {} ({}): {}", self.worker, self.kind, self.reason)
    }
}

/// Why a job was given up.
#[derive(Clone, Debug, PartialEq)]
pub enum GiveUp {
    /// A unit failed [`MAX_FAILURES`] times.
    Unit {
        /// The unit's index in the frame's unit list.
        index: usize,
        /// The unit.
        unit: WorkUnit,
        /// Each failure, oldest first.
        failures: Vec<UnitFailure>,
    },
    /// Every worker present failed to build the scene (one-shot renders).
    Scene {
        /// One failure per worker that cannot build it.
        failures: Vec<UnitFailure>,
    },
    /// Every worker present is blocklisted for the job (one-shot renders).
    Blocklisted {
        /// The workers' names.
        workers: Vec<String>,
    },
}

impl std::fmt::Display for GiveUp {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let list = |failures: &[UnitFailure]| {
            failures
                .iter()
                .map(ToString::to_string)
                .collect::<Vec<_>>()
                .join("; ")
        };
        match self {
            GiveUp::Unit {
                index,
                unit,
                failures,
            } => write!(
                f,
                "unit {index} ({}) failed {} times, giving up: {}",
                describe(unit),
                failures.len(),
                list(failures)
            ),
            GiveUp::Scene { failures } => write!(
                f,
                "no worker present can build the scene, giving up: {}",
                list(failures)
            ),
            GiveUp::Blocklisted { workers } => write!(
                f,
                "every worker present failed {MAX_FAILURES} units and is blocklisted ({}), giving up",
                workers.join(", ")
            ),
        }
    }
}

/// A unit in words: its pixel set and rows.
pub fn describe(unit: &WorkUnit) -> String {
    let b = unit.set.interleave;
    format!(
        "pixel set {} of {b}×{b}, set rows {} + i·{} for i < {}",
        unit.set.index, unit.first_row, unit.row_stride, unit.row_count
    )
}

/// A frame whose every unit is in.
#[derive(Clone, Debug)]
pub struct CompletedFrame {
    /// The job.
    pub job: JobId,
    /// The frame number.
    pub frame: u32,
    /// Its image.
    pub image: FrameImage,
    /// The CPU microseconds each unit's accepted tile cost.
    pub unit_costs: Vec<u64>,
    /// The CPU microseconds of its worker's async thread each unit's last
    /// tile reported (its calls since the tile before).
    pub unit_calls: Vec<u64>,
    /// From its first unit handed out to its last tile in.
    pub render_time: Duration,
}

#[derive(Clone, Copy, Debug)]
pub(super) struct Lease {
    pub(super) job: JobId,
    pub(super) unit: usize,
    pub(super) worker: u64,
    pub(super) issued: Instant,
    /// A second rendering of a unit whose tile is in (verified rendering).
    pub(super) check: bool,
}

/// What the scheduler needs of a job.
#[derive(Clone, Debug)]
pub struct JobPlan {
    /// Its id (the queue's order among equal priorities).
    pub id: JobId,
    /// Higher runs first.
    pub priority: i32,
    /// The units of every frame.
    pub units: Vec<WorkUnit>,
    /// Image width.
    pub width: u32,
    /// Image height.
    pub height: u32,
    /// What its tiles carry.
    pub format: PixelFormat,
    /// Its frames, in order (at least one).
    pub frames: FrameRange,
    /// Tags a worker must carry to render it.
    pub require_tags: Vec<String>,
}

impl JobPlan {
    /// A job of the one frame 0, `width × height` pixels in `units`, that
    /// any worker may render.
    pub fn one_frame(
        id: JobId,
        priority: i32,
        units: Vec<WorkUnit>,
        (width, height): (u32, u32),
        format: PixelFormat,
    ) -> JobPlan {
        JobPlan {
            id,
            priority,
            units,
            width,
            height,
            format,
            frames: FrameRange::one(0),
            require_tags: Vec::new(),
        }
    }
}

/// Where a job restored from the store stands.
#[derive(Clone, Debug, Default)]
pub struct Resume {
    /// Frames already complete and written (the first ones of the plan).
    pub frames_done: usize,
    /// Frames among those complete to render again (they hold a liar's
    /// tiles), by frame number.
    pub redo: Vec<u32>,
    /// Tiles of the next frame received before (unit index, tile bytes).
    pub tiles: Vec<(usize, Vec<u8>)>,
}

/// What the coordinator knows of a worker.
#[derive(Clone, Debug)]
pub struct WorkerState {
    /// Its id as views and logs show it (`w7`).
    pub id: String,
    /// The secret half of the id handed to it at registration (`w7-<secret>`):
    /// calls that do not carry it are not this worker's.
    pub(super) secret: u64,
    /// Its name.
    pub name: String,
    /// Its tags: it renders only jobs whose required tags it carries.
    pub tags: Vec<String>,
    /// Render threads it announced.
    pub threads: u32,
    /// Last time it called.
    pub last_seen: Instant,
    /// When it registered.
    pub joined: Instant,
    /// Units accepted from it.
    pub units: u64,
    /// Pixels accepted from it.
    pub pixels: u64,
    /// CPU time it reported for rendering accepted units.
    pub render_cpu_micros: u64,
    /// Its process CPU time, reported on goodbye.
    pub process_cpu_micros: Option<u64>,
    /// Still part of the farm.
    pub alive: bool,
    /// Why the scene of the one-shot job does not build on this worker, if
    /// it said so: it gets no more units of it.
    pub cannot_build: Option<String>,
    /// It has been told that the one-shot render is finished.
    pub told_finished: bool,
    /// Its accepted tiles of the last minute: when, and how many pixels.
    pub(super) recent: VecDeque<(Instant, u64)>,
}

impl WorkerState {
    /// The id the worker presents on its calls: its number and its secret.
    pub(super) fn wire_id_of(number: u64, secret: u64) -> String {
        format!("w{number}-{secret:016x}")
    }

    /// The id this worker presents on its calls: its number and its secret.
    pub fn wire_id(&self) -> String {
        let number = self.id.trim_start_matches('w').parse().unwrap_or(0);
        WorkerState::wire_id_of(number, self.secret)
    }

    /// Counts a tile accepted from it: `pixels` rendered in
    /// `render_cpu_micros`, and in its rate of the last minute.
    pub(super) fn credit(&mut self, pixels: u64, render_cpu_micros: u64, now: Instant) {
        self.units += 1;
        self.pixels += pixels;
        self.render_cpu_micros += render_cpu_micros;
        self.recent.push_back((now, pixels));
        while self
            .recent
            .front()
            .is_some_and(|(t, _)| now.saturating_duration_since(*t) > RATE_WINDOW)
        {
            self.recent.pop_front();
        }
    }

    /// Pixels per second over the last minute of its tiles (since it joined,
    /// when that is sooner).
    pub fn pixels_per_second(&self, now: Instant) -> f64 {
        let since = now
            .checked_sub(RATE_WINDOW)
            .map_or(self.joined, |t| t.max(self.joined));
        let pixels: u64 = self
            .recent
            .iter()
            .filter(|(t, _)| *t >= since)
            .map(|(_, p)| p)
            .sum();
        pixels as f64 / now.saturating_duration_since(since).as_secs_f64().max(1e-3)
    }
}

/// Why the coordinator renders a unit itself.
#[derive(Clone, Debug, PartialEq)]
pub enum CheckWhy {
    /// The unit is among those sampled for a second rendering.
    Sample,
    /// Two renderings of the unit differ.
    Dispute,
    /// A worker says it cannot build the scene or render the unit.
    Claim {
        /// The worker.
        worker: u64,
        /// Its name (escaped).
        name: String,
        /// What it claims.
        kind: FailureKind,
        /// What it said (escaped).
        reason: String,
    },
}

/// A unit the coordinator renders itself ([`Scheduler::take_check`]), and why.
#[derive(Clone, Debug, PartialEq)]
pub struct Check {
    /// The job.
    pub job: JobId,
    /// The job's pass when the check was asked for (a check of a frame
    /// already complete is stale).
    pub(super) pass: u64,
    /// The frame number.
    pub frame: u32,
    /// The unit's index.
    pub index: usize,
    /// The unit.
    pub unit: WorkUnit,
    /// Why.
    pub why: CheckWhy,
}
