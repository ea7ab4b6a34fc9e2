//! The scheduler: who renders which unit of which job, and what comes back.
//!
//! Pure state, no I/O and no clock of its own (callers pass `now`), so every rule
//! is unit-tested here. The farm holds any number of jobs; a job is one scene
//! over a list of frames, each frame split into the same units. A worker asking
//! for work gets a unit of the first job it may render in the queue's order:
//! highest priority first, ties oldest first, so a job submitted with a higher
//! priority starts on the next unit each worker takes, and no worker idles
//! while any job it may render has units left. Within a job, units go out in
//! coarse-to-fine order; a unit whose worker stops heartbeating goes back to
//! the front of its job's queue; when no job has a unit waiting, idle workers
//! get speculative duplicates of units still out (first tile wins — results are
//! identical by construction). A tile is checked completely before it touches
//! a canvas.
//!
//! This module holds [`Scheduler`], the state it keeps per job, and what it
//! reports (progress, previews). Its rules live in one module per role, in
//! the order they may import one another (each only from those above it):
//!
//! - `frames`: a job's frames, rendered one after another;
//! - `workers`: registration, the ids workers present, heartbeats, rates;
//! - `leases`: assignments outstanding, taken back, and their units queued again;
//! - `queue`: jobs in the queue's order, and which unit goes to which worker;
//! - `failures`: units that cannot be rendered, blocklists, jobs given up;
//! - `verify`: verified rendering, and the coordinator's checks of claims;
//! - `tiles`: a tile checked and accepted into its frame's canvas.

use std::collections::{BTreeMap, BTreeSet, HashMap, HashSet, VecDeque};
use std::time::{Duration, Instant};

use hypertexture::PixelFormat;
use hypertexture::render::interleave::WorkUnit;

use crate::image::canvas::{Canvas, FrameImage};
use hypertexture_proto::convert::{self, WireError};

mod failures;
mod frames;
mod leases;
mod queue;
mod tiles;
mod verify;
mod workers;

pub use failures::{Counted, GiveUp, UnitFailure, describe};
pub use frames::{CompletedFrame, Frames};
use leases::Lease;
pub use queue::{JobPlan, Next, Resume};
pub use tiles::Keep;
pub use verify::{Check, CheckOutcome, CheckWhy, Liar, Verdict};
pub use workers::WorkerState;

/// A unit that fails to render this many times (on different workers when
/// there are any) fails its job; a worker that fails this many units of a
/// job is blocklisted for it.
pub const MAX_FAILURES: usize = 3;

/// How far back a worker's pixels per second are measured.
const RATE_WINDOW: Duration = Duration::from_secs(60);

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

struct Job {
    plan: JobPlan,
    /// Index in `plan.frames` of the frame rendering.
    current: usize,
    /// Counts the frames completed in this scheduler: what an assignment or
    /// a check was of, to tell it from the frame rendering now.
    pass: u64,
    /// While a complete frame is rendered again: the index in `plan.frames`
    /// to go on with afterwards (the number of the plan's frames complete).
    resume_at: Option<usize>,
    /// Indices in `plan.frames` of complete frames to render again, whole,
    /// because they hold a liar's tiles.
    redo: BTreeSet<usize>,
    /// When the current frame's first unit went out.
    frame_started: Option<Instant>,
    pending: VecDeque<usize>,
    done: Vec<bool>,
    remaining: usize,
    canvas: Canvas,
    /// Per unit: the CPU microseconds the accepted tile cost.
    unit_cpu: Vec<u64>,
    /// Per unit: the async-thread CPU microseconds its last tile reported.
    unit_calls: Vec<u64>,
    /// Per unit: the workers (by id) that failed it, and how.
    failures: Vec<Vec<(u64, UnitFailure)>>,
    /// Per worker: units of this job it failed (blocklisted at [`MAX_FAILURES`]).
    worker_failures: HashMap<u64, usize>,
    /// Workers whose scene for this job does not build, and what they said.
    cannot_build: HashMap<u64, String>,
    /// The fraction of units rendered twice (0: none, 1: every one).
    verify: f64,
    /// Per unit of the frame rendering: the worker whose tile is in the
    /// canvas (`None`: not in, stored before a restart, or the coordinator's).
    delivered: Vec<Option<u64>>,
    /// Units of the frame rendering sampled for a second rendering whose
    /// tile is in and not yet confirmed: who delivered it, and its bytes.
    held: BTreeMap<usize, (u64, Vec<u8>)>,
    /// Held units waiting for their second rendering, oldest first.
    to_check: VecDeque<usize>,
    /// Second renderings that differ from a held tile, per unit, for the
    /// coordinator to decide: who rendered it, and its bytes.
    disputed: BTreeMap<usize, Vec<(u64, Vec<u8>)>>,
    /// Workers caught lying about this job: blocklisted for it.
    liars: HashSet<u64>,
    /// Per worker: the frames already complete (indices in `plan.frames`)
    /// that hold its tiles.
    frames_delivered: HashMap<u64, BTreeSet<usize>>,
    gave_up: Option<GiveUp>,
    /// Cancelled or given up: nothing more is handed out.
    ended: bool,
    started: bool,
}

impl Job {
    fn new(plan: JobPlan, resume: Resume) -> Result<Job, WireError> {
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

    fn frame(&self) -> u32 {
        let frames = &self.plan.frames;
        frames.get(self.current).unwrap_or(frames.last())
    }

    fn finished(&self) -> bool {
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
    fn frames_complete(&self) -> usize {
        self.resume_at
            .unwrap_or(self.current)
            .min(self.plan.frames.len())
    }

    /// Every unit of the frame rendering is in, and every sampled one confirmed.
    fn frame_settled(&self) -> bool {
        self.remaining == 0 && self.held.is_empty()
    }

    /// Units to hand out: waiting to be rendered, or to be rendered again.
    fn has_work(&self) -> bool {
        self.remaining > 0 || !self.to_check.is_empty()
    }

    fn blocklisted(&self, worker: u64) -> bool {
        self.liars.contains(&worker)
            || self
                .worker_failures
                .get(&worker)
                .is_some_and(|&n| n >= MAX_FAILURES)
    }

    /// Whether the unit's tile, just in, gets a second rendering: a keyed
    /// hash of (job, frame, unit) below the job's fraction. The key is drawn
    /// when the scheduler starts, so no worker can tell which units are checked.
    fn sampled(&self, key: u64, unit: usize) -> bool {
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
    fn open_to(&self, worker: u64, w: &WorkerState) -> bool {
        !self.ended
            && self.has_work()
            && !self.cannot_build.contains_key(&worker)
            && !self.blocklisted(worker)
            && self.plan.require_tags.iter().all(|t| w.tags.contains(t))
    }

    fn failed_by(&self, unit: usize, worker: u64) -> bool {
        self.failures[unit].iter().any(|(w, _)| *w == worker)
    }
}

/// The state of the farm: its jobs and its workers.
pub struct Scheduler {
    jobs: BTreeMap<JobId, Job>,
    /// Frames complete and not yet taken.
    completed: Vec<CompletedFrame>,
    /// Outstanding assignments.
    leases: HashMap<u64, Lease>,
    /// The job, frame index and unit of every assignment of a job that has
    /// not ended (to tell late duplicates from forgeries).
    issued: HashMap<u64, (JobId, u64, usize)>,
    next_assignment: u64,
    workers: HashMap<u64, WorkerState>,
    next_worker: u64,
    lease: Duration,
    /// A one-shot render: workers hear `Finished` once every job is done, and
    /// a job nobody present can render is given up.
    one_shot: bool,
    /// Draining: nothing more is handed out.
    draining: bool,
    /// Units are held back: the tiles cannot be kept now ([`Scheduler::pause`]).
    paused: bool,
    /// Assignments taken back from their workers by [`Scheduler::remove_job`]
    /// and not yet told them: (worker id, assignment id).
    withdrawn: Vec<(String, u64)>,
    /// Keys the secret half of the ids handed to workers at registration.
    id_keys: std::collections::hash_map::RandomState,
    /// The fraction of units of jobs added from now on rendered twice.
    verify: f64,
    /// Keys the choice of units rendered twice.
    verify_key: u64,
    /// Claims and disputes for the coordinator to check, oldest first.
    urgent: VecDeque<Check>,
    /// Held tiles whose second rendering agreed, not yet taken for the store.
    confirmed: Vec<(Accepted, Vec<u8>)>,
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
            urgent: VecDeque::new(),
            confirmed: Vec::new(),
        }
    }

    /// Renders these frames of the one-shot job (in order, at least one) instead of frame 0.
    pub fn with_frames(mut self, frames: Frames) -> Scheduler {
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

fn job_progress(j: &Job, leases: &HashMap<u64, Lease>) -> JobProgress {
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

#[cfg(test)]
mod testing;
