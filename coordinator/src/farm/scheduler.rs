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
//! A job's frames are rendered one after another: the tile that completes a
//! frame moves its image to [`Scheduler::take_completed`] and starts the job's
//! next frame at once. Assignment ids are unique over the scheduler's life; a
//! late tile of a frame that is complete (or of a job that has ended) is valid
//! and unused.
//!
//! A worker that cannot render a unit reports it ([`Scheduler::fail`]): the unit
//! goes back to the queue, to a worker that has not failed it when there is
//! one; a worker that has failed [`MAX_FAILURES`] units of a job is blocklisted
//! for that job; a worker whose scene does not build gets no more units of that
//! job; and a job is given up ([`GiveUp`]) when one of its units has failed
//! [`MAX_FAILURES`] times (on different workers when there are any) or, in a
//! one-shot render, when no worker present can render it. Other jobs go on.
//!
//! Verified rendering: a pixel is a pure function of (scene, pixel, frame,
//! sample) and every worker proved its arithmetic at registration, so two
//! renderings of a unit are the same bytes. A job's `verify` fraction of
//! units, chosen by a keyed hash no worker can predict, is rendered a second
//! time once its tile is in: by another worker ([`Scheduler::next`]) or by
//! the coordinator itself ([`Scheduler::take_check`]); the frame is complete
//! only when each such unit's two renderings agree. When they differ, the
//! coordinator's own rendering decides ([`Scheduler::checked`]): a worker
//! whose bytes differ from it lied, is blocklisted for the job, and every
//! unit of the frame rendering it delivered is rendered again. A worker's
//! claim that the scene does not build or a unit does not render
//! ([`Scheduler::report`]) is checked the same way before it counts towards
//! failing the job: when the coordinator can render the unit, the claim was a
//! lie.

use std::collections::{BTreeMap, BTreeSet, HashMap, HashSet, VecDeque};
use std::time::{Duration, Instant};

use hypertexture::PixelFormat;
use hypertexture::render::interleave::WorkUnit;

use crate::farm::canvas::{Canvas, FrameImage};
use hypertexture_proto::convert::{self, WireError};
use hypertexture_proto::{FailureKind, pb};

/// At most this many workers hold the same unit at once.
const MAX_HOLDERS: usize = 2;

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

/// What a worker is told when it asks for work.
#[derive(Clone, Debug, PartialEq)]
pub enum Next {
    /// Render this unit of this frame of this job under this assignment id.
    Assign {
        assignment_id: u64,
        job: JobId,
        unit: WorkUnit,
        frame: u32,
    },
    /// Nothing to hand out now; ask again later.
    Wait,
    /// Every frame is complete (one-shot renders only: a service waits for jobs).
    Finished,
}

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

/// A failure report that counted: what the coordinator logs.
#[derive(Clone, Debug, PartialEq)]
pub struct Counted {
    /// The job.
    pub job: JobId,
    /// The reporting worker's name.
    pub worker: String,
    /// The unit's index.
    pub index: usize,
    /// The unit given back.
    pub unit: WorkUnit,
    /// The unit's failures so far (scene failures are the worker's, not the unit's).
    pub failures: usize,
    /// The worker has just been blocklisted for the job.
    pub blocklisted: bool,
}

/// What [`Scheduler::accept_kept`] calls to keep a tile before accepting it:
/// `Err` (why) refuses the tile.
pub type Keep<'a> = dyn FnMut(&Accepted, &[u8]) -> Result<(), String> + 'a;

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

/// What the coordinator knows of a worker.
#[derive(Clone, Debug)]
pub struct WorkerState {
    /// Its id as views and logs show it (`w7`).
    pub id: String,
    /// The secret half of the id handed to it at registration (`w7-<secret>`):
    /// calls that do not carry it are not this worker's.
    secret: u64,
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
    recent: VecDeque<(Instant, u64)>,
}

impl WorkerState {
    /// The id the worker presents on its calls: its number and its secret.
    fn wire_id_of(number: u64, secret: u64) -> String {
        format!("w{number}-{secret:016x}")
    }

    /// The id this worker presents on its calls: its number and its secret.
    pub fn wire_id(&self) -> String {
        let number = self.id.trim_start_matches('w').parse().unwrap_or(0);
        WorkerState::wire_id_of(number, self.secret)
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

#[derive(Clone, Copy, Debug)]
struct Lease {
    job: JobId,
    unit: usize,
    worker: u64,
    issued: Instant,
    /// A second rendering of a unit whose tile is in (verified rendering).
    check: bool,
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
    pass: u64,
    /// The frame number.
    pub frame: u32,
    /// The unit's index.
    pub index: usize,
    /// The unit.
    pub unit: WorkUnit,
    /// Why.
    pub why: CheckWhy,
}

/// What the coordinator's own rendering of a [`Check`] gave.
#[derive(Clone, Debug, PartialEq)]
pub enum CheckOutcome {
    /// The tile, encoded as workers send it.
    Rendered(Vec<u8>),
    /// The scene did not build or the unit did not render here either.
    Failed(FailureKind, String),
    /// The check did not end within its time.
    TimedOut,
}

/// A worker caught lying about a job.
#[derive(Clone, Debug, PartialEq)]
pub struct Liar {
    /// The job.
    pub job: JobId,
    /// Its name (escaped).
    pub name: String,
    /// Units of the frame rendering it had delivered, now rendered again.
    pub redone: usize,
    /// Frames of the job already complete that hold its tiles: each is
    /// rendered again, whole, once the frame rendering is complete, and
    /// handed out again ([`Scheduler::take_completed`]).
    pub earlier_frames: Vec<u32>,
}

/// What a [`Check`] decided.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Verdict {
    /// Workers found lying (blocklisted for the job).
    pub liars: Vec<Liar>,
    /// The coordinator's tile, stored as the unit's: for the service's store.
    pub stored: Option<(Accepted, Vec<u8>)>,
    /// A failure claim the coordinator confirmed, counted towards failing the job.
    pub confirmed: Option<Counted>,
    /// The unit's renderings agreed.
    pub agreed: bool,
}

/// The number of a worker's id as views show it (`w7`), or as it was handed
/// to the worker (`w7-…`).
fn number(worker_id: &str) -> Option<u64> {
    let rest = worker_id.strip_prefix('w')?;
    rest.split_once('-').map_or(rest, |(n, _)| n).parse().ok()
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
    pub frames: Frames,
    /// Tags a worker must carry to render it.
    pub require_tags: Vec<String>,
}

/// A job's frames: the consecutive numbers `first..=last`, held as their two
/// ends, so a job of 100,000 frames takes the room of a job of one and is
/// added (or restored) as quickly.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Frames {
    first: u32,
    last: u32,
}

impl Frames {
    /// The frames `first..=last` (`last` before `first` is taken as `first`).
    pub fn new(first: u32, last: u32) -> Frames {
        Frames {
            first,
            last: last.max(first),
        }
    }

    /// The one frame `frame`.
    pub fn one(frame: u32) -> Frames {
        Frames::new(frame, frame)
    }

    /// The frames of `numbers` when they are consecutive and increasing (and
    /// at least one), else `None`.
    pub fn consecutive(mut numbers: impl Iterator<Item = u32>) -> Option<Frames> {
        let first = numbers.next()?;
        let mut last = first;
        for n in numbers {
            if last.checked_add(1) != Some(n) {
                return None;
            }
            last = n;
        }
        Some(Frames { first, last })
    }

    /// How many frames.
    pub fn len(&self) -> usize {
        (self.last - self.first) as usize + 1
    }

    /// Never: a job has at least one frame (for clippy's `len_without_is_empty`).
    pub fn is_empty(&self) -> bool {
        false
    }

    /// The first frame.
    pub fn first(&self) -> u32 {
        self.first
    }

    /// The last frame.
    pub fn last(&self) -> u32 {
        self.last
    }

    /// The `index`-th frame (from 0).
    pub fn get(&self, index: usize) -> Option<u32> {
        u32::try_from(index)
            .ok()
            .and_then(|i| self.first.checked_add(i))
            .filter(|&f| f <= self.last)
    }

    /// The index of frame `frame` (from 0).
    pub fn index_of(&self, frame: u32) -> Option<usize> {
        (self.first..=self.last)
            .contains(&frame)
            .then(|| (frame - self.first) as usize)
    }

    /// Every frame, in order.
    pub fn iter(&self) -> std::ops::RangeInclusive<u32> {
        self.first..=self.last
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
            JobPlan {
                id: ONE_SHOT_JOB,
                priority: 0,
                units,
                width,
                height,
                format,
                frames: Frames::one(0),
                require_tags: Vec::new(),
            },
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

    /// Renders `fraction` (0 to 1) of the units of jobs added from now on,
    /// and of the one-shot job, a second time (verified rendering).
    pub fn set_verify(&mut self, fraction: f64) {
        let fraction = if fraction.is_finite() {
            fraction.clamp(0.0, 1.0)
        } else {
            0.0
        };
        self.verify = fraction;
        if let Some(job) = self.jobs.get_mut(&ONE_SHOT_JOB) {
            job.verify = fraction;
        }
    }

    /// [`Scheduler::set_verify`] for one job.
    pub fn set_job_verify(&mut self, job: JobId, fraction: f64) {
        if let Some(job) = self.jobs.get_mut(&job) {
            job.verify = if fraction.is_finite() {
                fraction.clamp(0.0, 1.0)
            } else {
                0.0
            };
        }
    }

    /// Renders these frames of the one-shot job (in order, at least one) instead of frame 0.
    pub fn with_frames(mut self, frames: Frames) -> Scheduler {
        if let Some(job) = self.jobs.get_mut(&ONE_SHOT_JOB) {
            job.plan.frames = frames;
        }
        self
    }

    /// Adds a job to the queue, resuming it where the store left it (a frame
    /// whose every tile was stored is complete at once). Fails when a stored
    /// tile does not fit the job.
    pub fn add_job(&mut self, plan: JobPlan, resume: Resume) -> Result<(), WireError> {
        let id = plan.id;
        let mut job = Job::new(plan, resume)?;
        job.verify = self.verify;
        let complete = job.current < job.plan.frames.len() && job.remaining == 0;
        self.jobs.insert(id, job);
        if complete {
            self.complete_frame(id, Instant::now());
        }
        Ok(())
    }

    /// Cancels a job: nothing more of it is handed out, its units in flight
    /// are dropped, and it leaves the scheduler. False when unknown.
    pub fn cancel(&mut self, job: JobId) -> bool {
        self.remove_job(job).is_some()
    }

    /// Takes a job out of the scheduler (cancelled, given up, or done and
    /// written).
    pub fn remove_job(&mut self, job: JobId) -> Option<JobPlan> {
        let removed = self.jobs.remove(&job)?;
        let workers = &self.workers;
        self.withdrawn.extend(
            self.leases
                .iter()
                .filter(|(_, l)| l.job == job)
                .filter_map(|(&id, l)| Some((workers.get(&l.worker)?.wire_id(), id))),
        );
        self.leases.retain(|_, l| l.job != job);
        self.issued.retain(|_, (j, _, _)| *j != job);
        Some(removed.plan)
    }

    /// The assignments [`Scheduler::remove_job`] took back since the last
    /// call, to tell their workers: (worker id, assignment id).
    pub fn take_withdrawn(&mut self) -> Vec<(String, u64)> {
        std::mem::take(&mut self.withdrawn)
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

    /// Registers a worker; returns its id.
    pub fn register(&mut self, name: &str, threads: u32, now: Instant) -> String {
        self.register_tagged(name, threads, Vec::new(), now)
    }

    /// Registers a worker carrying `tags`; returns its id.
    pub fn register_tagged(
        &mut self,
        name: &str,
        threads: u32,
        tags: Vec<String>,
        now: Instant,
    ) -> String {
        use std::hash::BuildHasher;
        let id = self.next_worker;
        self.next_worker += 1;
        // The id a worker presents is bound to its registration: its number
        // (`w7`, what views and logs show) and a secret drawn for it here,
        // which no other caller can guess.
        let secret = self.id_keys.hash_one((id, now));
        let wire_id = WorkerState::wire_id_of(id, secret);
        self.workers.insert(
            id,
            WorkerState {
                id: format!("w{id}"),
                secret,
                name: name.to_string(),
                tags,
                threads,
                last_seen: now,
                joined: now,
                units: 0,
                pixels: 0,
                render_cpu_micros: 0,
                process_cpu_micros: None,
                alive: true,
                cannot_build: None,
                told_finished: false,
                recent: VecDeque::new(),
            },
        );
        wire_id
    }

    fn worker_mut(&mut self, worker_id: &str) -> Result<(u64, &mut WorkerState), Refusal> {
        let unknown =
            || Refusal::UnknownWorker(hypertexture_proto::convert::name_from_wire(worker_id));
        let (id, secret) = worker_id
            .strip_prefix('w')
            .and_then(|rest| rest.split_once('-'))
            .and_then(|(n, s)| Some((n.parse::<u64>().ok()?, u64::from_str_radix(s, 16).ok()?)))
            .ok_or_else(unknown)?;
        match self.workers.get_mut(&id) {
            // A made-up or altered id names no worker.
            Some(w) if w.alive && w.secret == secret => Ok((id, w)),
            _ => Err(unknown()),
        }
    }

    /// Records that the worker is alive.
    pub fn heartbeat(&mut self, worker_id: &str, now: Instant) -> Result<(), Refusal> {
        self.worker_mut(worker_id)?.1.last_seen = now;
        Ok(())
    }

    /// The jobs in the queue's order: highest priority first, ties oldest first.
    fn queue_order(&self) -> Vec<JobId> {
        let mut ids: Vec<(i32, JobId)> = self
            .jobs
            .values()
            .filter(|j| !j.ended && j.has_work())
            .map(|j| (j.plan.priority, j.plan.id))
            .collect();
        ids.sort_by(|a, b| b.0.cmp(&a.0).then(a.1.cmp(&b.1)));
        ids.into_iter().map(|(_, id)| id).collect()
    }

    /// The next thing for this worker to do.
    pub fn next(&mut self, worker_id: &str, now: Instant) -> Result<Next, Refusal> {
        let (wid, w) = self.worker_mut(worker_id)?;
        w.last_seen = now;
        if self.one_shot && self.jobs.values().all(Job::finished) {
            if let Some(w) = self.workers.get_mut(&wid) {
                w.told_finished = true;
            }
            return Ok(Next::Finished);
        }
        if self.draining || self.paused {
            return Ok(Next::Wait);
        }
        let order = self.queue_order();
        let worker = &self.workers[&wid];
        let open: Vec<JobId> = order
            .into_iter()
            .filter(|id| self.jobs[id].open_to(wid, worker))
            .collect();
        let mut chosen = None;
        for &id in &open {
            if let Some(unit) = self.pending_for(id, wid) {
                chosen = Some((id, unit, false));
                break;
            }
        }
        if chosen.is_none() {
            chosen = open
                .iter()
                .find_map(|&id| self.check_for(id, wid).map(|u| (id, u, true)));
        }
        if chosen.is_none() {
            chosen = open
                .iter()
                .find_map(|&id| self.speculative(id, wid).map(|u| (id, u, false)));
        }
        Ok(match chosen {
            Some((job_id, unit, check)) => {
                let assignment_id = self.next_assignment;
                self.next_assignment += 1;
                let job = self.jobs.get_mut(&job_id).expect("chosen above");
                job.started = true;
                job.frame_started.get_or_insert(now);
                self.issued.insert(assignment_id, (job_id, job.pass, unit));
                self.leases.insert(
                    assignment_id,
                    Lease {
                        job: job_id,
                        unit,
                        worker: wid,
                        issued: now,
                        check,
                    },
                );
                Next::Assign {
                    assignment_id,
                    job: job_id,
                    unit: job.plan.units[unit],
                    frame: job.frame(),
                }
            }
            None => Next::Wait,
        })
    }

    /// Takes the job's first pending unit this worker has not failed. In a
    /// one-shot render, also one that no other worker could take instead (so
    /// a lone worker retries, up to the limit); a service waits for another
    /// worker, so a unit's failures are on different workers.
    fn pending_for(&mut self, job_id: JobId, worker: u64) -> Option<usize> {
        let job = &self.jobs[&job_id];
        let position = job.pending.iter().position(|&u| {
            !job.failed_by(u, worker) || (self.one_shot && !self.another_could_take(job, u, worker))
        })?;
        self.jobs.get_mut(&job_id)?.pending.remove(position)
    }

    /// Takes a held unit of the job for its second rendering by `worker`,
    /// which did not deliver it.
    fn check_for(&mut self, job_id: JobId, worker: u64) -> Option<usize> {
        let job = self.jobs.get_mut(&job_id)?;
        let position = job
            .to_check
            .iter()
            .position(|u| job.held.get(u).is_some_and(|(w, _)| *w != worker))?;
        job.to_check.remove(position)
    }

    /// The next unit the coordinator renders itself: a failure claim or a
    /// dispute first, then a sampled unit waiting for its second rendering
    /// (the coordinator takes these while it has nothing else to check).
    pub fn take_check(&mut self) -> Option<Check> {
        while let Some(check) = self.urgent.pop_front() {
            let Some(job) = self.jobs.get(&check.job) else {
                continue;
            };
            if job.ended || job.pass != check.pass {
                continue;
            }
            if let CheckWhy::Claim { worker, .. } = &check.why
                && job.liars.contains(worker)
            {
                // Already caught: its other claims need no rendering.
                continue;
            }
            return Some(check);
        }
        let order = self.queue_order();
        for id in order {
            let job = self.jobs.get_mut(&id).expect("in the queue");
            while let Some(index) = job.to_check.pop_front() {
                if job.held.contains_key(&index) {
                    return Some(Check {
                        job: id,
                        pass: job.pass,
                        frame: job.frame(),
                        index,
                        unit: job.plan.units[index],
                        why: CheckWhy::Sample,
                    });
                }
            }
        }
        None
    }

    /// Whether a claim or a dispute waits for the coordinator's check.
    pub fn has_checks(&self) -> bool {
        !self.urgent.is_empty() || self.jobs.values().any(|j| !j.to_check.is_empty())
    }

    /// Takes the coordinator's own rendering of a [`Check`] into account.
    ///
    /// A sampled unit: equal bytes confirm it; different bytes convict its
    /// worker. A dispute: each worker whose bytes differ from the
    /// coordinator's is convicted. A claim: when the coordinator rendered the
    /// unit, the claim was a lie and its worker is convicted; when it could
    /// not, the failure counts ([`Scheduler::fail`]'s rules). Wherever the
    /// unit is not settled afterwards, the coordinator's tile is stored as
    /// its own. A convicted worker is blocklisted for the job, and every unit
    /// of the frame rendering it delivered is rendered again.
    pub fn checked(&mut self, check: &Check, outcome: CheckOutcome, now: Instant) -> Verdict {
        let mut verdict = Verdict::default();
        let Some(job) = self.jobs.get(&check.job) else {
            return verdict;
        };
        if job.ended || job.pass != check.pass {
            return verdict;
        }
        let index = check.index;
        match (&check.why, outcome) {
            (CheckWhy::Claim { worker, .. }, CheckOutcome::Rendered(bytes)) => {
                verdict.liars.extend(self.convict(check.job, *worker));
                self.decide(check.job, index, &bytes, now, &mut verdict);
            }
            (
                CheckWhy::Claim {
                    worker,
                    name,
                    kind,
                    reason,
                },
                CheckOutcome::Failed(..) | CheckOutcome::TimedOut,
            ) => {
                verdict.confirmed =
                    self.count_failure(check.job, index, *worker, name, *kind, reason, true);
            }
            (CheckWhy::Sample | CheckWhy::Dispute, CheckOutcome::Rendered(bytes)) => {
                self.decide(check.job, index, &bytes, now, &mut verdict);
            }
            (
                CheckWhy::Sample | CheckWhy::Dispute,
                CheckOutcome::Failed(..) | CheckOutcome::TimedOut,
            ) => {
                // Nothing to decide by: the unit is rendered again by a worker.
                let job = self.jobs.get_mut(&check.job).expect("checked above");
                job.held.remove(&index);
                job.disputed.remove(&index);
                if job.done[index] {
                    job.done[index] = false;
                    job.delivered[index] = None;
                    job.remaining += 1;
                    job.pending.push_front(index);
                }
            }
        }
        verdict
    }

    /// Decides a unit by the coordinator's own tile `bytes`: every worker
    /// whose rendering of it (held, or disputing) differs is convicted, and
    /// the coordinator's tile is stored wherever the unit is not settled.
    fn decide(
        &mut self,
        job_id: JobId,
        index: usize,
        bytes: &[u8],
        now: Instant,
        verdict: &mut Verdict,
    ) {
        let Some(job) = self.jobs.get_mut(&job_id) else {
            return;
        };
        let mut renderings: Vec<(u64, Vec<u8>)> = job.disputed.remove(&index).unwrap_or_default();
        let first = job.held.remove(&index);
        verdict.agreed = first.as_ref().is_some_and(|(_, b)| b.as_slice() == bytes);
        if let Some(first) = first {
            job.held.insert(index, first.clone());
            renderings.insert(0, first);
        }
        for (w, b) in renderings {
            if b.as_slice() != bytes {
                verdict.liars.extend(self.convict(job_id, w));
            }
        }
        if let Some(job) = self.jobs.get_mut(&job_id) {
            job.held.remove(&index);
        }
        verdict.stored = self.store_trusted(job_id, index, bytes, now);
        self.settle(job_id, now);
    }

    /// Blocklists `worker` for a job it lied about, and hands every unit of
    /// the frame rendering it delivered out again. `None` when it was caught before.
    fn convict(&mut self, job_id: JobId, worker: u64) -> Option<Liar> {
        let job = self.jobs.get_mut(&job_id)?;
        if !job.liars.insert(worker) {
            return None;
        }
        let mut redone = 0;
        for unit in 0..job.plan.units.len() {
            if job.delivered[unit] == Some(worker) && job.done[unit] {
                job.done[unit] = false;
                job.delivered[unit] = None;
                job.remaining += 1;
                job.held.remove(&unit);
                if !job.pending.contains(&unit) {
                    job.pending.push_front(unit);
                }
                redone += 1;
            }
        }
        for renderings in job.disputed.values_mut() {
            renderings.retain(|(w, _)| *w != worker);
        }
        let held = &job.held;
        job.to_check.retain(|u| held.contains_key(u));
        let earlier: Vec<usize> = job
            .frames_delivered
            .remove(&worker)
            .map(|f| f.into_iter().collect())
            .unwrap_or_default();
        // The frame rendering now replaces its own tiles (`redone`).
        let current = job.current;
        let earlier: Vec<usize> = earlier.into_iter().filter(|&i| i != current).collect();
        job.redo.extend(earlier.iter().copied());
        let earlier_frames = earlier
            .iter()
            .filter_map(|&i| job.plan.frames.get(i))
            .collect();
        let name = self
            .workers
            .get(&worker)
            .map_or_else(|| format!("w{worker}"), |w| w.name.clone());
        self.release(worker, Some(job_id));
        Some(Liar {
            job: job_id,
            name,
            redone,
            earlier_frames,
        })
    }

    /// Stores the coordinator's own tile of a unit of the frame rendering
    /// that is not in (or whose tile was held for a check), and completes the
    /// frame when it was the last.
    fn store_trusted(
        &mut self,
        job_id: JobId,
        index: usize,
        bytes: &[u8],
        now: Instant,
    ) -> Option<(Accepted, Vec<u8>)> {
        let job = self.jobs.get_mut(&job_id)?;
        let unit = job.plan.units[index];
        if job.done[index] && !job.held.contains_key(&index) {
            return None;
        }
        let tile =
            convert::tile_from_wire(bytes, unit.pixel_count(job.plan.width), job.plan.format)
                .ok()?;
        job.canvas.store(&unit, tile);
        if !job.done[index] {
            job.done[index] = true;
            job.remaining -= 1;
        }
        job.delivered[index] = None;
        job.held.remove(&index);
        job.pending.retain(|&u| u != index);
        let frame = job.frame();
        self.leases
            .retain(|_, l| l.job != job_id || l.unit != index);
        let accepted = Accepted {
            job: job_id,
            frame,
            unit: index,
            worker: "the coordinator".into(),
            latency: Duration::ZERO,
            held: false,
        };
        self.settle(job_id, now);
        Some((accepted, bytes.to_vec()))
    }

    /// Completes the job's frame when every unit is in and confirmed.
    fn settle(&mut self, job_id: JobId, now: Instant) {
        if self
            .jobs
            .get(&job_id)
            .is_some_and(|j| j.current < j.plan.frames.len() && j.frame_settled())
        {
            self.complete_frame(job_id, now);
        }
    }

    /// Whether a worker other than `worker`, able to render the job, has not
    /// failed `unit`.
    fn another_could_take(&self, job: &Job, unit: usize, worker: u64) -> bool {
        self.workers.iter().any(|(&id, w)| {
            id != worker
                && w.alive
                && !job.cannot_build.contains_key(&id)
                && !job.blocklisted(id)
                && job.plan.require_tags.iter().all(|t| w.tags.contains(t))
                && !job.failed_by(unit, id)
        })
    }

    /// An outstanding unit of the job this worker does not hold and has not
    /// failed, held by fewer than [`MAX_HOLDERS`] workers: first the newest
    /// unit a worker holds queued behind the one it is rendering (workers
    /// render their units in the order given, so that one would be started
    /// last, and a copy started now ends the frame soonest), then the oldest
    /// outstanding one (a straggler).
    fn speculative(&self, job_id: JobId, worker: u64) -> Option<usize> {
        let job = &self.jobs[&job_id];
        // Each worker's oldest lease: the unit it is rendering.
        let mut rendering: HashMap<u64, u64> = HashMap::new();
        for (&id, lease) in &self.leases {
            let oldest = rendering.entry(lease.worker).or_insert(id);
            *oldest = (*oldest).min(id);
        }
        // Per unit: holders, its oldest and newest lease, whether this worker
        // holds it, whether a holder has it queued rather than rendering.
        let mut holders: HashMap<usize, (usize, u64, u64, bool, bool)> = HashMap::new();
        for (&id, lease) in self.leases.iter().filter(|(_, l)| l.job == job_id) {
            let e = holders
                .entry(lease.unit)
                .or_insert((0, id, id, false, false));
            e.0 += 1;
            e.1 = e.1.min(id);
            e.2 = e.2.max(id);
            e.3 |= lease.worker == worker;
            e.4 |= rendering[&lease.worker] != id;
        }
        holders
            .into_iter()
            .filter(|&(unit, (count, _, _, mine, _))| {
                !mine && count < MAX_HOLDERS && !job.done[unit] && !job.failed_by(unit, worker)
            })
            .min_by_key(|&(unit, (_, oldest, newest, _, queued))| {
                if queued {
                    (0, u64::MAX - newest, unit)
                } else {
                    (1, oldest, unit)
                }
            })
            .map(|(unit, _)| unit)
    }

    /// The job, frame index and unit of an assignment of a job still in the
    /// scheduler; `Err(true)` when the id was issued for a job that has
    /// ended, `Err(false)` when it never was.
    fn issued(&self, assignment_id: u64) -> Result<(JobId, u64, usize), bool> {
        match self.issued.get(&assignment_id) {
            Some(&i) => Ok(i),
            None => Err(assignment_id > 0 && assignment_id < self.next_assignment),
        }
    }

    /// Notes what a tile's worker says its calls cost it (statistics only,
    /// whether the tile is accepted or not): for the unit of `assignment_id`,
    /// when that is of the frame rendering.
    pub fn note_calls_cpu(&mut self, assignment_id: u64, calls_cpu_micros: u64) {
        if let Ok((job_id, frame, unit)) = self.issued(assignment_id)
            && let Some(job) = self.jobs.get_mut(&job_id)
            && frame == job.pass
        {
            job.unit_calls[unit] = calls_cpu_micros;
        }
    }

    /// Accepts a tile. `Ok(false)`: valid but the unit was already complete.
    pub fn submit(
        &mut self,
        worker_id: &str,
        assignment_id: u64,
        unit: Option<&pb::Unit>,
        values: &[u8],
        render_cpu_micros: u64,
        now: Instant,
    ) -> Result<bool, Refusal> {
        self.accept(
            worker_id,
            assignment_id,
            unit,
            values,
            render_cpu_micros,
            now,
        )
        .map(|a| a.is_some())
    }

    /// Accepts a tile: `Ok(Some(_))` when it was stored in its frame's canvas,
    /// `Ok(None)` when it is valid but the unit was already complete (or its
    /// job has ended).
    ///
    /// A malformed tile, or one of another unit, for an assignment its worker
    /// holds counts as a failure of the unit ([`Scheduler::fail`]): the unit
    /// goes to another worker, and [`MAX_FAILURES`] of them give the job up
    /// with the refusals as reasons, rather than waiting forever for a tile
    /// that will never be right.
    pub fn accept(
        &mut self,
        worker_id: &str,
        assignment_id: u64,
        unit: Option<&pb::Unit>,
        values: &[u8],
        render_cpu_micros: u64,
        now: Instant,
    ) -> Result<Option<Accepted>, Refusal> {
        self.accept_kept(
            worker_id,
            assignment_id,
            (unit, values),
            render_cpu_micros,
            now,
            &mut |_, _| Ok(()),
        )
    }

    /// [`Scheduler::accept`], with `keep` called on a tile about to be
    /// accepted, before anything of it is recorded: when `keep` fails the tile
    /// is refused ([`Refusal::Unstored`]), its lease is taken back and its
    /// unit queued again, so nothing the worker is told is in can be lost;
    /// and the scheduler pauses ([`Scheduler::pause`]) until told otherwise.
    pub fn accept_kept(
        &mut self,
        worker_id: &str,
        assignment_id: u64,
        (unit, values): (Option<&pb::Unit>, &[u8]),
        render_cpu_micros: u64,
        now: Instant,
        keep: &mut Keep<'_>,
    ) -> Result<Option<Accepted>, Refusal> {
        let accepted = self.accept_tile(
            worker_id,
            assignment_id,
            (unit, values),
            render_cpu_micros,
            now,
            keep,
        );
        if let Err(r @ (Refusal::Malformed { .. } | Refusal::WrongUnit(_))) = &accepted {
            // Checked like any claim that the unit cannot be rendered.
            let reason = format!("tile refused: {r}");
            let _ = self.report(worker_id, assignment_id, FailureKind::Render, &reason, now);
        }
        accepted
    }

    fn accept_tile(
        &mut self,
        worker_id: &str,
        assignment_id: u64,
        (unit, values): (Option<&pb::Unit>, &[u8]),
        render_cpu_micros: u64,
        now: Instant,
        keep: &mut Keep<'_>,
    ) -> Result<Option<Accepted>, Refusal> {
        let (wid, w) = self.worker_mut(worker_id)?;
        w.last_seen = now;
        let (job_id, issued_pass, issued_unit) = match self.issued(assignment_id) {
            Ok(i) => i,
            Err(true) => return Ok(None),
            Err(false) => return Err(Refusal::NeverAssigned(assignment_id)),
        };
        let Some(job) = self.jobs.get_mut(&job_id) else {
            return Ok(None);
        };
        if issued_pass != job.pass {
            // A duplicate of a unit of a frame that is complete.
            return Ok(None);
        }
        let (width, height) = (job.plan.width, job.plan.height);
        let claimed = unit
            .ok_or(WireError::Missing("unit"))
            .and_then(|u| convert::unit_from_wire(u, width, height))
            .map_err(|error| Refusal::Malformed {
                id: assignment_id,
                error,
            })?;
        if claimed != job.plan.units[issued_unit] {
            return Err(Refusal::WrongUnit(assignment_id));
        }
        let tile = convert::tile_from_wire(values, claimed.pixel_count(width), job.plan.format)
            .map_err(|error| Refusal::Malformed {
                id: assignment_id,
                error,
            })?;
        let (issued_at, check) = match self.leases.get(&assignment_id) {
            Some(lease) if lease.worker == wid => (lease.issued, lease.check),
            _ if job.done[issued_unit] => return Ok(None),
            _ => return Err(Refusal::NotHeld(assignment_id)),
        };
        if check {
            self.leases.remove(&assignment_id);
            let job = self.jobs.get_mut(&job_id).expect("checked above");
            match job.held.get(&issued_unit) {
                Some((_, first)) if first.as_slice() == values => {
                    // The two renderings agree: the tile is stored now.
                    let (first_worker, bytes) =
                        job.held.remove(&issued_unit).expect("matched above");
                    let frame = job.frame();
                    self.confirmed.push((
                        Accepted {
                            job: job_id,
                            frame,
                            unit: issued_unit,
                            worker: self
                                .workers
                                .get(&first_worker)
                                .map_or_else(String::new, |w| w.name.clone()),
                            latency: Duration::ZERO,
                            held: false,
                        },
                        bytes,
                    ));
                    self.settle(job_id, now);
                    return Ok(None);
                }
                Some(_) => {
                    // They differ: the coordinator's own rendering decides.
                    let fresh = !job.disputed.contains_key(&issued_unit);
                    job.disputed
                        .entry(issued_unit)
                        .or_default()
                        .push((wid, values.to_vec()));
                    if fresh {
                        self.urgent.push_back(Check {
                            job: job_id,
                            pass: job.pass,
                            frame: job.frame(),
                            index: issued_unit,
                            unit: claimed,
                            why: CheckWhy::Dispute,
                        });
                    }
                    return Ok(None);
                }
                // Confirmed or decided meanwhile.
                None if job.done[issued_unit] => return Ok(None),
                // Its first tile was a liar's: this one is the unit's tile.
                None => {}
            }
        }
        let job = self.jobs.get_mut(&job_id).expect("checked above");
        let held = job.sampled(self.verify_key, issued_unit);
        let frame = job.frame();
        let accepted = Accepted {
            job: job_id,
            frame,
            unit: issued_unit,
            worker: self.workers[&wid].name.clone(),
            latency: now.saturating_duration_since(issued_at),
            held,
        };
        if let Err(reason) = keep(&accepted, values) {
            // Nothing more goes out until whoever keeps the tiles resumes it.
            self.paused = true;
            self.leases.remove(&assignment_id);
            self.requeue(job_id, issued_unit);
            return Err(Refusal::Unstored {
                id: assignment_id,
                reason,
            });
        }
        let job = self.jobs.get_mut(&job_id).expect("checked above");
        // Checked (the whole tile, above): store it.
        job.canvas.store(&claimed, tile);
        job.done[issued_unit] = true;
        job.delivered[issued_unit] = Some(wid);
        if held {
            job.held.insert(issued_unit, (wid, values.to_vec()));
            job.to_check.push_back(issued_unit);
        }
        job.remaining -= 1;
        job.unit_cpu[issued_unit] = render_cpu_micros;
        job.pending.retain(|&u| u != issued_unit);
        self.leases
            .retain(|_, l| l.job != job_id || l.unit != issued_unit);
        let w = self.workers.get_mut(&wid).expect("checked above");
        let pixels = claimed.pixel_count(width) as u64;
        w.units += 1;
        w.pixels += pixels;
        w.render_cpu_micros += render_cpu_micros;
        w.recent.push_back((now, pixels));
        while w
            .recent
            .front()
            .is_some_and(|(t, _)| now.saturating_duration_since(*t) > RATE_WINDOW)
        {
            w.recent.pop_front();
        }
        self.settle(job_id, now);
        Ok(Some(accepted))
    }

    /// Moves the job's complete frame's image out and starts its next frame,
    /// if any: a complete frame to render again first, then the plan's next.
    fn complete_frame(&mut self, job_id: JobId, now: Instant) {
        let Some(job) = self.jobs.get_mut(&job_id) else {
            return;
        };
        let n = job.plan.units.len();
        self.completed.push(CompletedFrame {
            job: job_id,
            frame: job.frame(),
            // A blank canvas of the same size stays: late duplicates are still
            // checked against it.
            image: job.canvas.take(),
            unit_costs: std::mem::replace(&mut job.unit_cpu, vec![0; n]),
            unit_calls: std::mem::replace(&mut job.unit_calls, vec![0; n]),
            render_time: job
                .frame_started
                .take()
                .map_or(Duration::ZERO, |t| now.saturating_duration_since(t)),
        });
        // Duplicates still out belong to the frame just completed.
        self.leases.retain(|_, l| l.job != job_id);
        let index = job.current;
        // A frame rendered again holds only the tiles of this rendering.
        for frames in job.frames_delivered.values_mut() {
            frames.remove(&index);
        }
        for w in std::mem::replace(&mut job.delivered, vec![None; n])
            .into_iter()
            .flatten()
        {
            job.frames_delivered.entry(w).or_default().insert(index);
        }
        job.held.clear();
        job.to_check.clear();
        job.disputed.clear();
        job.pass += 1;
        if let Some(again) = job.redo.pop_first() {
            job.resume_at.get_or_insert(index + 1);
            job.current = again;
        } else if let Some(next) = job.resume_at.take() {
            job.current = next;
        } else {
            job.current += 1;
        }
        if job.current >= job.plan.frames.len() {
            // Past the last frame, the job is finished: late tiles are unused.
            job.remaining = 0;
            job.pending.clear();
            return;
        }
        job.pending = (0..n).collect();
        job.done = vec![false; n];
        job.remaining = n;
        job.failures = vec![Vec::new(); n];
    }

    /// Whether the job has nothing left to render (true when unknown): every
    /// frame of its plan complete, none waiting to be rendered again.
    pub fn job_finished(&self, job: JobId) -> bool {
        self.jobs.get(&job).is_none_or(Job::finished)
    }

    /// Tiles held for a second rendering that it confirmed since the last
    /// call (with their bytes), for the service's store.
    pub fn take_confirmed(&mut self) -> Vec<(Accepted, Vec<u8>)> {
        std::mem::take(&mut self.confirmed)
    }

    /// Whether a frame is complete and not yet taken.
    pub fn has_completed(&self) -> bool {
        !self.completed.is_empty()
    }

    /// The frames completed since the last call, in order.
    pub fn take_completed(&mut self) -> Vec<CompletedFrame> {
        std::mem::take(&mut self.completed)
    }

    /// A worker gives back an assignment it could not render, and its word is
    /// taken: [`Scheduler::report`] with the claim confirmed at once. The unit
    /// goes back to the front of its job's queue; a worker whose scene does
    /// not build gives back everything of that job it holds and gets nothing
    /// more of it. `Ok(None)`: the assignment was no longer this worker's,
    /// nothing changed. The job is given up ([`Scheduler::gave_up_jobs`])
    /// when the unit has failed [`MAX_FAILURES`] times or, in a one-shot
    /// render, no worker present can render it.
    pub fn fail(
        &mut self,
        worker_id: &str,
        assignment_id: u64,
        kind: FailureKind,
        reason: &str,
        now: Instant,
    ) -> Result<Option<Counted>, Refusal> {
        let Some((job_id, _, unit, wid, name)) =
            self.give_back(worker_id, assignment_id, kind, reason, now)?
        else {
            return Ok(None);
        };
        Ok(self.count_failure(job_id, unit, wid, &name, kind, reason, true))
    }

    /// A worker says it cannot render an assignment. What concerns the
    /// worker alone happens at once (the unit goes back to the front of the
    /// queue; a worker whose scene does not build gets nothing more of the
    /// job); what could fail the job waits for the coordinator's check
    /// ([`Scheduler::take_check`], [`Scheduler::checked`]): a claim that the
    /// scene does not build or the unit does not render counts only when the
    /// coordinator cannot render the unit either. A claim that the assignment
    /// is unusable counts towards the worker's blocklist and never towards
    /// failing the job. `Ok(None)`: the assignment was no longer this
    /// worker's, nothing changed.
    pub fn report(
        &mut self,
        worker_id: &str,
        assignment_id: u64,
        kind: FailureKind,
        reason: &str,
        now: Instant,
    ) -> Result<Option<Counted>, Refusal> {
        let Some((job_id, pass, unit, wid, name)) =
            self.give_back(worker_id, assignment_id, kind, reason, now)?
        else {
            return Ok(None);
        };
        if kind == FailureKind::Assignment {
            return Ok(self.count_failure(job_id, unit, wid, &name, kind, reason, false));
        }
        let job = &self.jobs[&job_id];
        self.urgent.push_back(Check {
            job: job_id,
            pass,
            frame: job.frame(),
            index: unit,
            unit: job.plan.units[unit],
            why: CheckWhy::Claim {
                worker: wid,
                name: name.clone(),
                kind,
                reason: reason.to_string(),
            },
        });
        Ok(Some(Counted {
            job: job_id,
            worker: name,
            index: unit,
            unit: job.plan.units[unit],
            failures: job.failures[unit].len(),
            blocklisted: false,
        }))
    }

    /// Takes an assignment back from the worker that could not render it:
    /// the unit goes back to the front of the queue (or, for a second
    /// rendering, to the units waiting for one); a worker whose scene does
    /// not build gives back everything of the job. `None` when the
    /// assignment is no longer this worker's.
    #[allow(clippy::type_complexity)]
    fn give_back(
        &mut self,
        worker_id: &str,
        assignment_id: u64,
        kind: FailureKind,
        reason: &str,
        now: Instant,
    ) -> Result<Option<(JobId, u64, usize, u64, String)>, Refusal> {
        let (wid, w) = self.worker_mut(worker_id)?;
        w.last_seen = now;
        let name = w.name.clone();
        let (job_id, frame, unit) = match self.issued(assignment_id) {
            Ok(i) => i,
            Err(true) => return Ok(None),
            Err(false) => return Err(Refusal::NeverAssigned(assignment_id)),
        };
        match (self.leases.get(&assignment_id), self.jobs.get(&job_id)) {
            (Some(lease), Some(job)) if lease.worker == wid && frame == job.pass => {}
            _ => return Ok(None),
        }
        self.leases.remove(&assignment_id);
        if kind == FailureKind::Scene {
            // Deterministic on this worker: every unit of the job it holds would fail too.
            let job = self.jobs.get_mut(&job_id).expect("checked above");
            job.cannot_build.insert(wid, reason.to_string());
            if job_id == ONE_SHOT_JOB
                && let Some(w) = self.workers.get_mut(&wid)
            {
                w.cannot_build = Some(reason.to_string());
            }
            self.release(wid, Some(job_id));
        }
        self.requeue(job_id, unit);
        Ok(Some((job_id, frame, unit, wid, name)))
    }

    /// Puts a unit no longer held by anyone back in its job's queue: to be
    /// rendered (at the front), or, when its tile is in and held for a
    /// second rendering, with the units waiting for one.
    fn requeue(&mut self, job_id: JobId, unit: usize) {
        let held = self
            .leases
            .values()
            .any(|l| l.job == job_id && l.unit == unit);
        let Some(job) = self.jobs.get_mut(&job_id) else {
            return;
        };
        if held {
            return;
        }
        if !job.done[unit] {
            if !job.pending.contains(&unit) {
                job.pending.push_front(unit);
            }
        } else if job.held.contains_key(&unit) && !job.to_check.contains(&unit) {
            job.to_check.push_front(unit);
        }
    }

    /// Counts a failure of a unit of the frame rendering: towards the
    /// worker's blocklist, towards the unit's failures (when `of_unit`), and
    /// gives the job up when the unit has failed [`MAX_FAILURES`] times or,
    /// in a one-shot render, no worker present can render it.
    #[allow(clippy::too_many_arguments)]
    fn count_failure(
        &mut self,
        job_id: JobId,
        unit: usize,
        wid: u64,
        name: &str,
        kind: FailureKind,
        reason: &str,
        of_unit: bool,
    ) -> Option<Counted> {
        let failure = UnitFailure {
            worker: name.to_string(),
            kind,
            reason: reason.to_string(),
        };
        let mut blocklisted = false;
        if kind != FailureKind::Scene {
            let job = self.jobs.get_mut(&job_id)?;
            if of_unit {
                job.failures[unit].push((wid, failure));
            }
            let count = job.worker_failures.entry(wid).or_insert(0);
            *count += 1;
            if *count == MAX_FAILURES {
                blocklisted = true;
                self.release(wid, Some(job_id));
            }
        }
        let one_shot = self.one_shot;
        let able = self.able_for(job_id);
        let job = self.jobs.get_mut(&job_id)?;
        if job.gave_up.is_none() {
            if job.failures[unit].len() >= MAX_FAILURES {
                job.gave_up = Some(GiveUp::Unit {
                    index: unit,
                    unit: job.plan.units[unit],
                    failures: job.failures[unit].iter().map(|(_, f)| f.clone()).collect(),
                });
            } else if one_shot && kind == FailureKind::Scene && able == 0 {
                let mut failures: Vec<(Instant, UnitFailure)> = job
                    .cannot_build
                    .iter()
                    .filter_map(|(id, reason)| {
                        let w = self.workers.get(id)?;
                        Some((
                            w.joined,
                            UnitFailure {
                                worker: w.name.clone(),
                                kind: FailureKind::Scene,
                                reason: reason.clone(),
                            },
                        ))
                    })
                    .collect();
                failures.sort_by_key(|f| f.0);
                job.gave_up = Some(GiveUp::Scene {
                    failures: failures.into_iter().map(|(_, f)| f).collect(),
                });
            } else if one_shot && blocklisted && able == 0 {
                let mut names: Vec<String> = job
                    .worker_failures
                    .iter()
                    .filter(|&(_, &n)| n >= MAX_FAILURES)
                    .filter_map(|(id, _)| self.workers.get(id).map(|w| w.name.clone()))
                    .collect();
                names.sort();
                job.gave_up = Some(GiveUp::Blocklisted { workers: names });
            }
            if job.gave_up.is_some() {
                job.ended = true;
                self.leases.retain(|_, l| l.job != job_id);
            }
        }
        let job = &self.jobs[&job_id];
        Some(Counted {
            job: job_id,
            worker: name.to_string(),
            index: unit,
            unit: job.plan.units[unit],
            failures: job.failures[unit].len(),
            blocklisted,
        })
    }

    /// Why the one-shot job cannot go on, once it cannot.
    pub fn gave_up(&self) -> Option<&GiveUp> {
        self.jobs.get(&ONE_SHOT_JOB)?.gave_up.as_ref()
    }

    /// Every job given up, and why.
    pub fn gave_up_jobs(&self) -> impl Iterator<Item = (JobId, &GiveUp)> {
        self.jobs
            .iter()
            .filter_map(|(&id, j)| j.gave_up.as_ref().map(|g| (id, g)))
    }

    /// A worker leaves cleanly; anything it still held goes back to the queue.
    /// Its process's CPU time is kept when it knows it (not 0).
    pub fn goodbye(&mut self, worker_id: &str, process_cpu_micros: u64) -> Result<(), Refusal> {
        let (wid, w) = self.worker_mut(worker_id)?;
        w.process_cpu_micros = (process_cpu_micros > 0).then_some(process_cpu_micros);
        w.alive = false;
        self.release(wid, None);
        Ok(())
    }

    /// Drops workers silent for longer than the lease; their units go back to the
    /// front of their queues. Returns the names of the workers dropped.
    pub fn expire(&mut self, now: Instant) -> Vec<String> {
        let lease = self.lease;
        let lost: Vec<u64> = self
            .workers
            .iter()
            .filter(|(_, w)| w.alive && now.saturating_duration_since(w.last_seen) > lease)
            .map(|(&id, _)| id)
            .collect();
        let mut names = Vec::new();
        for id in lost {
            if let Some(w) = self.workers.get_mut(&id) {
                w.alive = false;
                names.push(w.name.clone());
            }
            self.release(id, None);
        }
        // Workers gone for long are forgotten: a service runs for months.
        if !self.one_shot {
            self.workers.retain(|_, w| {
                w.alive || now.saturating_duration_since(w.last_seen) < 10 * RATE_WINDOW
            });
        }
        names
    }

    /// Gives back the units `worker` holds (of `job`, or of every job).
    fn release(&mut self, worker: u64, job: Option<JobId>) {
        let mut freed: Vec<(u64, JobId, usize)> = self
            .leases
            .iter()
            .filter(|(_, l)| l.worker == worker && job.is_none_or(|j| j == l.job))
            .map(|(&id, l)| (id, l.job, l.unit))
            .collect();
        freed.sort_unstable();
        for &(id, _, _) in &freed {
            self.leases.remove(&id);
        }
        // Back to the front, in their original order, unless someone else holds them.
        for &(_, job_id, unit) in freed.iter().rev() {
            self.requeue(job_id, unit);
        }
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

    /// The names of the workers blocklisted for a job.
    pub fn blocklisted(&self, job: JobId) -> Vec<String> {
        let Some(job) = self.jobs.get(&job) else {
            return Vec::new();
        };
        let mut names: Vec<String> = job
            .worker_failures
            .iter()
            .filter(|&(_, &n)| n >= MAX_FAILURES)
            .map(|(id, _)| id)
            .chain(job.liars.iter())
            .collect::<BTreeSet<_>>()
            .into_iter()
            .filter_map(|id| self.workers.get(id).map(|w| w.name.clone()))
            .collect();
        names.sort();
        names
    }

    /// The jobs a worker is blocklisted for.
    pub fn blocklisted_for(&self, worker_id: &str) -> Vec<JobId> {
        let Some(id) = number(worker_id) else {
            return Vec::new();
        };
        self.jobs
            .iter()
            .filter(|(_, j)| j.blocklisted(id))
            .map(|(&jid, _)| jid)
            .collect()
    }

    /// The job a worker is rendering (its oldest lease's), if any.
    pub fn current_job(&self, worker_id: &str) -> Option<JobId> {
        let id = number(worker_id)?;
        self.leases
            .iter()
            .filter(|(_, l)| l.worker == id)
            .min_by_key(|(a, _)| **a)
            .map(|(_, l)| l.job)
    }

    /// Units waiting to be handed out, over every job.
    pub fn queued_units(&self) -> usize {
        self.jobs
            .values()
            .filter(|j| !j.ended)
            .map(|j| j.pending.len())
            .sum()
    }

    /// Workers still in the farm.
    pub fn alive(&self) -> usize {
        self.workers.values().filter(|w| w.alive).count()
    }

    /// Workers of a finished one-shot render that have not heard so yet: still
    /// in the farm, heard from within the lease, and not told `Finished`.
    /// (None while the render is not finished, or in a service.)
    pub fn yet_to_hear_finished(&self, now: Instant) -> usize {
        if !self.one_shot || !self.finished() {
            return 0;
        }
        self.workers
            .values()
            .filter(|w| {
                w.alive
                    && !w.told_finished
                    && now.saturating_duration_since(w.last_seen) <= self.lease
            })
            .count()
    }

    /// Workers still in the farm that can render the one-shot job.
    pub fn able(&self) -> usize {
        self.able_for(ONE_SHOT_JOB)
    }

    /// Workers still in the farm that may render `job`.
    fn able_for(&self, job: JobId) -> usize {
        let Some(job) = self.jobs.get(&job) else {
            return 0;
        };
        self.workers
            .iter()
            .filter(|(id, w)| {
                w.alive
                    && !job.cannot_build.contains_key(id)
                    && !job.blocklisted(**id)
                    && job.plan.require_tags.iter().all(|t| w.tags.contains(t))
            })
            .count()
    }

    /// Every worker that ever joined (and, in a service, has not been forgotten).
    pub fn workers(&self) -> impl Iterator<Item = &WorkerState> {
        self.workers.values()
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

    /// Workers whose tags let them render `tags`, alive now.
    pub fn tagged(&self, tags: &[String]) -> usize {
        let set: HashSet<&String> = tags.iter().collect();
        self.workers
            .values()
            .filter(|w| w.alive && set.iter().all(|t| w.tags.contains(t)))
            .count()
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
mod tests {
    use super::*;
    use hypertexture::Sample;
    use hypertexture::render::interleave::work_units;

    fn tile(unit: &WorkUnit, width: u32, value: f32) -> Vec<u8> {
        let samples = vec![Sample::from_array([value; Sample::CHANNELS]); unit.pixel_count(width)];
        convert::tile_to_wire(&samples, PixelFormat::Samples).to_vec()
    }

    fn film(image: &FrameImage) -> &hypertexture::Film {
        match image {
            FrameImage::Film(film) => film,
            FrameImage::Srgb8 { .. } => panic!("a samples canvas gives a film"),
        }
    }

    fn assign(s: &mut Scheduler, w: &str, now: Instant) -> (u64, WorkUnit) {
        match s.next(w, now).unwrap() {
            Next::Assign {
                assignment_id,
                unit,
                ..
            } => (assignment_id, unit),
            other => panic!("expected an assignment, got {other:?}"),
        }
    }

    #[test]
    fn a_removed_jobs_units_in_flight_are_withdrawn_from_their_workers() {
        let now = Instant::now();
        let units = work_units(16, 16, 8, 4096);
        let mut s = Scheduler::new(units, 16, 16, PixelFormat::Samples, Duration::from_secs(5));
        let a = s.register("a", 1, now);
        let b = s.register("b", 1, now);
        let (first, _) = assign(&mut s, &a, now);
        let (second, _) = assign(&mut s, &b, now);
        let (third, _) = assign(&mut s, &a, now);
        assert!(s.take_withdrawn().is_empty());
        assert!(s.remove_job(ONE_SHOT_JOB).is_some());
        let mut withdrawn = s.take_withdrawn();
        withdrawn.sort_by_key(|w| w.1);
        // Named by the ids the workers present (their secrets included).
        assert_eq!(withdrawn, [(a.clone(), first), (b, second), (a, third)]);
        assert!(s.take_withdrawn().is_empty());
    }

    #[test]
    fn hands_out_every_unit_once_then_finishes() {
        let now = Instant::now();
        let units = work_units(16, 16, 8, 4096);
        let mut s = Scheduler::new(
            units.clone(),
            16,
            16,
            PixelFormat::Samples,
            Duration::from_secs(5),
        );
        let w = s.register("a", 1, now);
        for (k, expected) in units.iter().enumerate() {
            let (id, unit) = assign(&mut s, &w, now);
            assert_eq!(&unit, expected);
            let wire = convert::unit_to_wire(&unit);
            s.note_calls_cpu(id, 100 + k as u64);
            assert_eq!(
                s.submit(&w, id, Some(&wire), &tile(&unit, 16, 0.5), 10, now),
                Ok(true)
            );
        }
        assert!(s.finished());
        assert_eq!(s.next(&w, now), Ok(Next::Finished));
        let completed = s.take_completed();
        assert_eq!(completed.len(), 1);
        assert_eq!(completed[0].frame, 0);
        assert_eq!(completed[0].unit_costs, vec![10; units.len()]);
        let calls: Vec<u64> = (0..units.len() as u64).map(|k| 100 + k).collect();
        assert_eq!(completed[0].unit_calls, calls);
        assert!(
            film(&completed[0].image)
                .pixels()
                .iter()
                .all(|p| p.rgba[0] == 0.5)
        );
    }

    #[test]
    fn a_finished_render_counts_the_workers_yet_to_hear_it() {
        let now = Instant::now();
        let units = work_units(8, 8, 8, 4096);
        let lease = Duration::from_secs(5);
        let mut s = Scheduler::new(units.clone(), 8, 8, PixelFormat::Samples, lease);
        let (a, b, c) = (
            s.register("a", 1, now),
            s.register("b", 1, now),
            s.register("c", 1, now),
        );
        for _ in 0..units.len() {
            let (id, unit) = assign(&mut s, &a, now);
            let wire = convert::unit_to_wire(&unit);
            assert_eq!(
                s.submit(&a, id, Some(&wire), &tile(&unit, 8, 0.5), 10, now),
                Ok(true)
            );
            assert!(s.finished() || s.yet_to_hear_finished(now) == 0);
        }
        assert!(s.finished());
        assert_eq!(s.yet_to_hear_finished(now), 3);
        assert_eq!(s.next(&a, now), Ok(Next::Finished));
        assert_eq!(s.yet_to_hear_finished(now), 2);
        s.goodbye(&b, 0).unwrap();
        assert_eq!(s.yet_to_hear_finished(now), 1);
        // A worker silent for longer than the lease is not waited for.
        assert_eq!(
            s.yet_to_hear_finished(now + lease + Duration::from_millis(1)),
            0
        );
        assert_eq!(s.next(&c, now), Ok(Next::Finished));
        assert_eq!(s.yet_to_hear_finished(now), 0);
    }

    #[test]
    fn a_sequence_starts_the_next_frame_with_the_tile_that_completes_one() {
        let now = Instant::now();
        let units = work_units(8, 8, 8, 4096);
        let n = units.len();
        let mut s = Scheduler::new(units, 8, 8, PixelFormat::Samples, Duration::from_secs(5))
            .with_frames(Frames::new(3, 4));
        let (a, b) = (s.register("a", 1, now), s.register("b", 1, now));
        let mut first_frame = Vec::new();
        for _ in 0..n {
            match s.next(&a, now).unwrap() {
                Next::Assign {
                    assignment_id,
                    unit,
                    frame,
                    ..
                } => {
                    assert_eq!(frame, 3);
                    first_frame.push((assignment_id, unit));
                }
                other => panic!("{other:?}"),
            }
        }
        // b holds a speculative duplicate of frame 3's last unit.
        let (dup_id, dup) = assign(&mut s, &b, now);
        assert_eq!(dup, first_frame[n - 1].1);
        for (id, unit) in &first_frame {
            let wire = convert::unit_to_wire(unit);
            assert_eq!(
                s.submit(&a, *id, Some(&wire), &tile(unit, 8, 0.3), 1, now),
                Ok(true)
            );
        }
        assert!(!s.finished(), "frame 4 follows");
        assert_eq!(s.progress(), (n, 2 * n));
        let done = s.take_completed();
        assert_eq!((done.len(), done[0].frame), (1, 3));
        assert!(
            film(&done[0].image)
                .pixels()
                .iter()
                .all(|p| p.rgba[0] == 0.3)
        );
        // The next unit out is frame 4's first; the late duplicate of frame 3 is unused.
        match s.next(&a, now).unwrap() {
            Next::Assign { unit, frame, .. } => assert_eq!((frame, unit), (4, first_frame[0].1)),
            other => panic!("{other:?}"),
        }
        let wire = convert::unit_to_wire(&dup);
        assert_eq!(
            s.submit(&b, dup_id, Some(&wire), &tile(&dup, 8, 9.0), 1, now),
            Ok(false)
        );
        assert!(
            film(&s.preview())
                .pixels()
                .iter()
                .all(|p| *p == Sample::default())
        );
        assert_eq!(
            s.fail(&b, dup_id, FailureKind::Render, "late", now),
            Ok(None)
        );
    }

    #[test]
    fn a_silent_worker_loses_its_units_to_others() {
        let t0 = Instant::now();
        let units = work_units(8, 8, 8, 4096);
        let mut s = Scheduler::new(units, 8, 8, PixelFormat::Samples, Duration::from_secs(5));
        let (a, b) = (s.register("a", 1, t0), s.register("b", 1, t0));
        let (lost_id, lost_unit) = assign(&mut s, &a, t0);
        // b keeps working; a goes silent.
        let later = t0 + Duration::from_secs(6);
        s.heartbeat(&b, later).unwrap();
        assert_eq!(s.expire(later), vec!["a".to_string()]);
        let (_, again) = assign(&mut s, &b, later);
        assert_eq!(again, lost_unit, "the lost unit comes back first");
        // a's late tile is refused: a is gone, and its assignment is no longer held.
        let wire = convert::unit_to_wire(&lost_unit);
        assert!(matches!(
            s.submit(
                &a,
                lost_id,
                Some(&wire),
                &tile(&lost_unit, 8, 1.0),
                0,
                later
            ),
            Err(Refusal::UnknownWorker(_))
        ));
    }

    #[test]
    fn malformed_and_forged_tiles_never_touch_the_film() {
        let now = Instant::now();
        let units = work_units(8, 8, 8, 4096);
        let mut s = Scheduler::new(units, 8, 8, PixelFormat::Samples, Duration::from_secs(5));
        let (a, b) = (s.register("a", 1, now), s.register("b", 1, now));
        let (id, unit) = assign(&mut s, &a, now);
        let wire = convert::unit_to_wire(&unit);
        let good = tile(&unit, 8, 0.25);
        let mut short = good.clone();
        short.pop();
        let mut nan = good.clone();
        nan[12..16].copy_from_slice(&f32::NAN.to_le_bytes());
        let mut inf = good.clone();
        inf[..4].copy_from_slice(&f32::INFINITY.to_le_bytes());
        for bad in [&short, &nan, &inf] {
            assert!(matches!(
                s.submit(&a, id, Some(&wire), bad, 0, now),
                Err(Refusal::Malformed { .. })
            ));
        }
        assert_eq!(
            s.submit(&a, 999, Some(&wire), &good, 0, now),
            Err(Refusal::NeverAssigned(999))
        );
        assert_eq!(
            s.submit(&a, 0, Some(&wire), &good, 0, now),
            Err(Refusal::NeverAssigned(0))
        );
        assert_eq!(
            s.submit(&b, id, Some(&wire), &good, 0, now),
            Err(Refusal::NotHeld(id))
        );
        assert!(matches!(
            s.submit("w77", id, Some(&wire), &good, 0, now),
            Err(Refusal::UnknownWorker(_))
        ));
        // The right number with a made-up secret names no worker.
        let honest = s.register("honest", 1, now);
        let forged = format!("{}-0123456789abcdef", honest.split_once('-').unwrap().0);
        assert!(matches!(
            s.heartbeat(&forged, now),
            Err(Refusal::UnknownWorker(_))
        ));
        assert!(s.heartbeat(&honest, now).is_ok());
        assert!(matches!(
            s.submit(&a, id, None, &good, 0, now),
            Err(Refusal::Malformed { .. })
        ));
        // The first malformed tile counted as a failure of the unit: it went
        // back to the queue, and comes first to the next worker asking.
        let (again, unit_again) = assign(&mut s, &b, now);
        assert_eq!(unit_again, unit);
        let (_, other) = assign(&mut s, &b, now);
        let other_wire = convert::unit_to_wire(&other);
        assert_eq!(
            s.submit(&a, id, Some(&other_wire), &tile(&other, 8, 0.25), 0, now),
            Err(Refusal::WrongUnit(id))
        );
        assert!(
            film(&s.preview())
                .pixels()
                .iter()
                .all(|p| *p == Sample::default()),
            "nothing written"
        );
        assert_eq!(
            s.submit(&a, id, Some(&wire), &good, 0, now),
            Err(Refusal::NotHeld(id))
        );
        assert_eq!(s.submit(&b, again, Some(&wire), &good, 0, now), Ok(true));
    }

    /// Takes every check waiting and answers it with `outcome`.
    fn answer_checks(s: &mut Scheduler, outcome: &CheckOutcome, now: Instant) -> Vec<Verdict> {
        let mut verdicts = Vec::new();
        while let Some(check) = s.take_check() {
            verdicts.push(s.checked(&check, outcome.clone(), now));
        }
        verdicts
    }

    #[test]
    fn a_unit_whose_tiles_are_refused_three_times_gives_the_job_up_only_if_the_coordinator_fails_too()
     {
        let now = Instant::now();
        let units = work_units(8, 8, 8, 4096);
        let refuse_three = || {
            let mut s = Scheduler::new(
                units.clone(),
                8,
                8,
                PixelFormat::Samples,
                Duration::from_secs(5),
            );
            let workers: Vec<String> = ["a", "b", "c"]
                .iter()
                .map(|n| s.register(n, 1, now))
                .collect();
            for w in &workers {
                let (id, unit) = assign(&mut s, w, now);
                let wire = convert::unit_to_wire(&unit);
                let mut short = tile(&unit, 8, 0.5);
                short.truncate(short.len() - 4);
                assert!(matches!(
                    s.submit(w, id, Some(&wire), &short, 0, now),
                    Err(Refusal::Malformed { .. })
                ));
            }
            assert!(s.gave_up().is_none(), "claims count only once checked");
            s
        };
        // The coordinator cannot render the unit either: the failures count.
        let mut s = refuse_three();
        let failed = CheckOutcome::Failed(FailureKind::Render, "here too".into());
        let verdicts = answer_checks(&mut s, &failed, now);
        assert_eq!(verdicts.len(), 3);
        let given_up = s
            .gave_up()
            .expect("three confirmed failures stop the render");
        let message = given_up.to_string();
        assert!(
            matches!(given_up, GiveUp::Unit { index: 0, .. }),
            "{message}"
        );
        for needle in [
            "failed 3 times",
            "worker a (render): tile refused: malformed tile",
        ] {
            assert!(message.contains(needle), "{needle}: {message}");
        }
        // The coordinator renders it: each refused tile was a lie.
        let mut s = refuse_three();
        let good = CheckOutcome::Rendered(tile(&units[0], 8, 0.5));
        let verdicts = answer_checks(&mut s, &good, now);
        assert!(s.gave_up().is_none());
        let liars: Vec<String> = verdicts
            .iter()
            .flat_map(|v| v.liars.iter().map(|l| l.name.clone()))
            .collect();
        assert_eq!(liars, ["a", "b", "c"]);
        assert_eq!(s.blocklisted(ONE_SHOT_JOB), ["a", "b", "c"]);
        assert_eq!(s.able(), 0);
        assert!(
            s.job_progress(ONE_SHOT_JOB).unwrap().units_done == 1,
            "the coordinator's tile is the unit's"
        );
    }

    /// Renders every unit of the one-shot job with `w` (each tile `value`),
    /// as long as it is handed units; returns how many it rendered.
    fn render_all(s: &mut Scheduler, w: &str, value: f32, width: u32, now: Instant) -> usize {
        let mut n = 0;
        while let Ok(Next::Assign {
            assignment_id,
            unit,
            ..
        }) = s.next(w, now)
        {
            let wire = convert::unit_to_wire(&unit);
            s.submit(
                w,
                assignment_id,
                Some(&wire),
                &tile(&unit, width, value),
                0,
                now,
            )
            .unwrap();
            n += 1;
        }
        n
    }

    #[test]
    fn sampled_units_are_rendered_twice_and_the_frame_waits_for_them() {
        let now = Instant::now();
        let units = work_units(16, 16, 8, 4096);
        let n = units.len();
        let mut s = Scheduler::new(units, 16, 16, PixelFormat::Samples, Duration::from_secs(5));
        s.set_verify(1.0);
        let (a, b) = (s.register("a", 1, now), s.register("b", 1, now));
        for _ in 0..n {
            let (id, unit) = assign(&mut s, &a, now);
            let wire = convert::unit_to_wire(&unit);
            assert_eq!(
                s.submit(&a, id, Some(&wire), &tile(&unit, 16, 0.5), 0, now),
                Ok(true)
            );
        }
        assert!(!s.finished(), "every unit waits for its second rendering");
        assert!(s.take_completed().is_empty());
        // a never checks its own units; b renders them again, with the same bytes.
        assert_eq!(s.next(&a, now), Ok(Next::Wait));
        for _ in 0..n {
            let (id, unit) = assign(&mut s, &b, now);
            let wire = convert::unit_to_wire(&unit);
            assert_eq!(
                s.submit(&b, id, Some(&wire), &tile(&unit, 16, 0.5), 0, now),
                Ok(false),
                "a second rendering is compared, not stored"
            );
        }
        assert!(s.finished());
        assert_eq!(s.take_completed().len(), 1);
        assert!(s.blocklisted(ONE_SHOT_JOB).is_empty());

        // At 2%, about one unit in 50 is sampled, and which ones no worker can tell.
        let units = work_units(512, 512, 8, 4096);
        let n = units.len();
        let mut s = Scheduler::new(units, 512, 512, PixelFormat::Srgb8, Duration::from_secs(5));
        s.set_verify(0.02);
        let key = s.verify_key;
        let sampled = (0..n)
            .filter(|&u| s.jobs[&ONE_SHOT_JOB].sampled(key, u))
            .count();
        assert!(sampled <= n / 10, "{sampled} of {n}");
    }

    #[test]
    fn a_garbage_tile_convicts_its_worker_and_every_unit_it_delivered_is_rendered_again() {
        let now = Instant::now();
        let units = work_units(16, 16, 8, 4096);
        let n = units.len();
        let mut s = Scheduler::new(
            units.clone(),
            16,
            16,
            PixelFormat::Samples,
            Duration::from_secs(5),
        );
        s.set_verify(1.0);
        let (liar, good) = (s.register("liar", 1, now), s.register("good", 1, now));
        // The liar delivers half the frame, garbage of the right size.
        for _ in 0..n / 2 {
            let (id, unit) = assign(&mut s, &liar, now);
            let wire = convert::unit_to_wire(&unit);
            assert_eq!(
                s.submit(&liar, id, Some(&wire), &tile(&unit, 16, 1e38), 0, now),
                Ok(true)
            );
        }
        // The coordinator renders the first sampled unit itself: it differs.
        let check = s.take_check().expect("a sampled unit");
        assert_eq!(check.why, CheckWhy::Sample);
        let verdict = s.checked(
            &check,
            CheckOutcome::Rendered(tile(&check.unit, 16, 0.5)),
            now,
        );
        assert_eq!(verdict.liars.len(), 1);
        assert_eq!(verdict.liars[0].name, "liar");
        assert_eq!(verdict.liars[0].redone, n / 2);
        assert!(verdict.stored.is_some(), "the coordinator's tile is kept");
        assert_eq!(s.blocklisted(ONE_SHOT_JOB), ["liar"]);
        assert_eq!(s.next(&liar, now), Ok(Next::Wait));
        // The good worker renders the rest (and checks nothing of the liar's).
        render_all(&mut s, &good, 0.5, 16, now);
        while let Some(check) = s.take_check() {
            let verdict = s.checked(
                &check,
                CheckOutcome::Rendered(tile(&check.unit, 16, 0.5)),
                now,
            );
            assert!(verdict.agreed && verdict.liars.is_empty());
        }
        let done = s.take_completed();
        assert_eq!(done.len(), 1);
        assert!(
            film(&done[0].image)
                .pixels()
                .iter()
                .all(|p| p.rgba[0] == 0.5),
            "no garbage is left in the image"
        );
    }

    /// Renders units with `w` until it is told to wait, each tile `value`.
    fn render_frame_part(s: &mut Scheduler, w: &str, value: f32, count: usize, now: Instant) {
        for _ in 0..count {
            let (id, unit) = assign(s, w, now);
            let wire = convert::unit_to_wire(&unit);
            s.submit(w, id, Some(&wire), &tile(&unit, 16, value), 0, now)
                .unwrap();
        }
    }

    #[test]
    fn a_held_tile_is_handed_for_storing_only_once_confirmed() {
        let now = Instant::now();
        let units = work_units(16, 16, 8, 4096);
        let mut s = Scheduler::new(units, 16, 16, PixelFormat::Samples, Duration::from_secs(5));
        s.set_verify(1.0);
        let (a, b) = (s.register("a", 1, now), s.register("b", 1, now));
        let (id, unit) = assign(&mut s, &a, now);
        let wire = convert::unit_to_wire(&unit);
        let bytes = tile(&unit, 16, 0.5);
        let accepted = s
            .accept(&a, id, Some(&wire), &bytes, 0, now)
            .unwrap()
            .expect("accepted");
        assert!(accepted.held, "sampled: not to be stored yet");
        assert!(s.take_confirmed().is_empty());
        // b renders it again, the same bytes: now it is stored, as a's.
        let (again, same) = loop {
            match assign(&mut s, &b, now) {
                (i, u) if u == unit => break (i, u),
                (i, u) => {
                    let w = convert::unit_to_wire(&u);
                    s.submit(&b, i, Some(&w), &tile(&u, 16, 0.5), 0, now)
                        .unwrap();
                }
            }
        };
        assert_eq!(
            s.submit(
                &b,
                again,
                Some(&convert::unit_to_wire(&same)),
                &bytes,
                0,
                now
            ),
            Ok(false)
        );
        let confirmed = s.take_confirmed();
        assert_eq!(confirmed.len(), 1);
        assert_eq!(
            (confirmed[0].0.unit, confirmed[0].0.worker.as_str()),
            (accepted.unit, "a")
        );
        assert!(!confirmed[0].0.held);
        assert_eq!(confirmed[0].1, bytes);
    }

    #[test]
    fn frames_already_complete_that_hold_a_liars_tiles_are_rendered_again() {
        let now = Instant::now();
        let units = work_units(16, 16, 8, 4096);
        let n = units.len();
        let mut s = Scheduler::new(units, 16, 16, PixelFormat::Samples, Duration::from_secs(5))
            .with_frames(Frames::new(0, 2));
        let (liar, good) = (s.register("liar", 1, now), s.register("good", 1, now));
        // Frame 0: none of the liar's garbage is sampled, so it goes out.
        render_frame_part(&mut s, &liar, 1e38, n / 2, now);
        render_frame_part(&mut s, &good, 0.5, n - n / 2, now);
        let first = s.take_completed();
        assert_eq!(first.iter().map(|f| f.frame).collect::<Vec<_>>(), [0]);
        // Frame 1: every unit is sampled, and the liar is caught.
        s.set_verify(1.0);
        render_frame_part(&mut s, &liar, 1e38, 2, now);
        let check = s.take_check().expect("a sampled unit");
        let verdict = s.checked(
            &check,
            CheckOutcome::Rendered(tile(&check.unit, 16, 0.5)),
            now,
        );
        assert_eq!(verdict.liars.len(), 1);
        assert_eq!(verdict.liars[0].earlier_frames, [0]);
        assert_eq!(verdict.liars[0].redone, 2, "its units of frame 1");
        assert_eq!(s.next(&liar, now), Ok(Next::Wait));
        // The good worker renders (and checks) frame 1, then frame 0 again, then 2.
        let mut frames = Vec::new();
        let mut guard = 0;
        while !s.finished() {
            guard += 1;
            assert!(guard < 100, "the job never finished");
            render_all(&mut s, &good, 0.5, 16, now);
            while let Some(check) = s.take_check() {
                s.checked(
                    &check,
                    CheckOutcome::Rendered(tile(&check.unit, 16, 0.5)),
                    now,
                );
            }
            let progress = s.job_progress(ONE_SHOT_JOB).unwrap();
            assert!(progress.units_done <= progress.units_total);
            for done in s.take_completed() {
                assert!(
                    film(&done.image).pixels().iter().all(|p| p.rgba[0] == 0.5),
                    "frame {}: no garbage",
                    done.frame
                );
                frames.push(done.frame);
            }
        }
        assert_eq!(frames, [1, 0, 2]);
        assert_eq!(s.progress(), (3 * n, 3 * n));
    }

    #[test]
    fn a_job_resumed_with_frames_to_render_again_renders_them() {
        let now = Instant::now();
        let units = work_units(16, 16, 8, 4096);
        let plan = |id| JobPlan {
            id,
            priority: 0,
            units: units.clone(),
            width: 16,
            height: 16,
            format: PixelFormat::Samples,
            frames: Frames::new(4, 6),
            require_tags: Vec::new(),
        };
        let mut s = Scheduler::service(Duration::from_secs(5));
        let w = s.register("w", 1, now);
        // Every frame written, frame 5 to render again; and one in the middle.
        s.add_job(
            plan(1),
            Resume {
                frames_done: 3,
                tiles: Vec::new(),
                redo: vec![5],
            },
        )
        .unwrap();
        s.add_job(
            plan(2),
            Resume {
                frames_done: 2,
                tiles: Vec::new(),
                redo: vec![4, 6],
            },
        )
        .unwrap();
        assert!(!s.job_finished(1) && !s.job_finished(2));
        let mut frames = Vec::new();
        for _ in 0..10 {
            render_all(&mut s, &w, 0.5, 16, now);
            frames.extend(s.take_completed().iter().map(|f| (f.job, f.frame)));
        }
        // Job 2's frame 6 is not yet written: it is rendered once, then frame 4 again.
        assert_eq!(frames, [(1, 5), (2, 6), (2, 4)]);
        assert!(s.job_finished(1) && s.job_finished(2));
    }

    #[test]
    fn two_renderings_that_differ_are_decided_by_the_coordinator() {
        let now = Instant::now();
        let units = work_units(8, 8, 8, 4096);
        let mut s = Scheduler::new(units, 8, 8, PixelFormat::Samples, Duration::from_secs(5));
        s.set_verify(1.0);
        let (a, b) = (s.register("a", 1, now), s.register("b", 1, now));
        let n = render_all(&mut s, &a, 0.5, 8, now);
        let unit = s.jobs[&ONE_SHOT_JOB].plan.units[0];
        let wire = convert::unit_to_wire(&unit);
        // b checks the first, and lies.
        let (id, again) = assign(&mut s, &b, now);
        assert_eq!(again, unit);
        assert_eq!(
            s.submit(&b, id, Some(&wire), &tile(&unit, 8, 0.25), 0, now),
            Ok(false)
        );
        let check = s.take_check().expect("a dispute");
        assert_eq!(check.why, CheckWhy::Dispute);
        let verdict = s.checked(&check, CheckOutcome::Rendered(tile(&unit, 8, 0.5)), now);
        assert_eq!(
            verdict
                .liars
                .iter()
                .map(|l| l.name.as_str())
                .collect::<Vec<_>>(),
            ["b"]
        );
        assert_eq!(s.blocklisted(ONE_SHOT_JOB), ["b"]);
        assert_eq!(s.progress().0, n);
    }

    #[test]
    fn a_claim_counts_only_when_the_coordinator_cannot_render_the_unit_either() {
        let now = Instant::now();
        let units = work_units(8, 8, 8, 4096);
        for kind in [FailureKind::Scene, FailureKind::Render] {
            let mut s = Scheduler::new(
                units.clone(),
                8,
                8,
                PixelFormat::Samples,
                Duration::from_secs(5),
            );
            let a = s.register("alone", 1, now);
            let (id, unit) = assign(&mut s, &a, now);
            s.report(&a, id, kind, "cannot", now).unwrap().unwrap();
            assert!(s.gave_up().is_none(), "{kind}: not before the check");
            let check = s.take_check().expect("the claim");
            assert!(matches!(check.why, CheckWhy::Claim { .. }));
            let verdict = s.checked(&check, CheckOutcome::Rendered(tile(&unit, 8, 0.5)), now);
            assert_eq!(verdict.liars[0].name, "alone");
            assert!(s.gave_up().is_none(), "{kind}: a lie fails nothing");
            assert_eq!(s.progress().0, 1, "the coordinator's tile is the unit's");
        }
        // A scene the coordinator cannot build either: the lone worker's word stands.
        let mut s = Scheduler::new(units, 8, 8, PixelFormat::Samples, Duration::from_secs(5));
        let a = s.register("alone", 1, now);
        let (id, _) = assign(&mut s, &a, now);
        s.report(&a, id, FailureKind::Scene, "no memory", now)
            .unwrap();
        let failed = CheckOutcome::Failed(FailureKind::Scene, "no memory".into());
        assert!(answer_checks(&mut s, &failed, now)[0].confirmed.is_some());
        assert!(matches!(s.gave_up(), Some(GiveUp::Scene { .. })));
    }

    #[test]
    fn failures_under_made_up_ids_count_for_nothing() {
        let now = Instant::now();
        let units = work_units(8, 8, 8, 4096);
        let mut s = Scheduler::new(units, 8, 8, PixelFormat::Samples, Duration::from_secs(5));
        let good = s.register("good", 1, now);
        let (id, _) = assign(&mut s, &good, now);
        let number = good.split_once('-').unwrap().0;
        for forged in [
            format!("{number}-0000000000000000"),
            format!("{number}-{}", "f".repeat(16)),
            number.to_string(),
            "w99-0000000000000001".into(),
            "not an id".into(),
        ] {
            for kind in [FailureKind::Render, FailureKind::Scene] {
                assert!(
                    matches!(
                        s.report(&forged, id, kind, "forged", now),
                        Err(Refusal::UnknownWorker(_))
                    ),
                    "{forged}"
                );
            }
        }
        assert!(s.take_check().is_none());
        assert!(s.gave_up().is_none());
        assert!(s.blocklisted(ONE_SHOT_JOB).is_empty());
        assert_eq!(s.able(), 1);
        let wire = convert::unit_to_wire(&s.jobs[&ONE_SHOT_JOB].plan.units[0]);
        let unit = s.jobs[&ONE_SHOT_JOB].plan.units[0];
        assert_eq!(
            s.submit(&good, id, Some(&wire), &tile(&unit, 8, 0.5), 0, now),
            Ok(true),
            "the good worker still holds its unit"
        );
    }

    #[test]
    fn idle_workers_get_speculative_duplicates_and_first_tile_wins() {
        let now = Instant::now();
        let units = work_units(8, 8, 8, 4096);
        let n = units.len();
        let mut s = Scheduler::new(units, 8, 8, PixelFormat::Samples, Duration::from_secs(5));
        let (a, b) = (s.register("a", 1, now), s.register("b", 1, now));
        let mut held = Vec::new();
        for _ in 0..n {
            held.push(assign(&mut s, &a, now));
        }
        // The queue is empty: b gets a duplicate of the unit a would start last.
        let (dup_id, dup_unit) = assign(&mut s, &b, now);
        assert_eq!(dup_unit, held[n - 1].1);
        let wire = convert::unit_to_wire(&dup_unit);
        assert_eq!(
            s.submit(&b, dup_id, Some(&wire), &tile(&dup_unit, 8, 1.0), 0, now),
            Ok(true)
        );
        // a's copy arrives later: valid, ignored.
        assert_eq!(
            s.submit(
                &a,
                held[n - 1].0,
                Some(&wire),
                &tile(&dup_unit, 8, 1.0),
                0,
                now
            ),
            Ok(false)
        );
        // Another idle worker takes the next unit from the end of a's queue.
        let c = s.register("c", 1, now);
        assert_eq!(assign(&mut s, &c, now).1, held[n - 2].1);
    }

    #[test]
    fn a_unit_being_rendered_is_duplicated_only_when_none_waits_in_a_queue() {
        let now = Instant::now();
        let units = work_units(8, 8, 8, 4096);
        let n = units.len();
        let mut s = Scheduler::new(units, 8, 8, PixelFormat::Samples, Duration::from_secs(5));
        let (a, b, c) = (
            s.register("a", 1, now),
            s.register("b", 1, now),
            s.register("c", 1, now),
        );
        // a and b each hold one unit, the one they are rendering; a's is older.
        let mut held = Vec::new();
        for _ in 0..n - 2 {
            held.push(assign(&mut s, &a, now));
        }
        for (id, unit) in held.drain(..) {
            let wire = convert::unit_to_wire(&unit);
            assert_eq!(
                s.submit(&a, id, Some(&wire), &tile(&unit, 8, 1.0), 0, now),
                Ok(true)
            );
        }
        let (_, oldest) = assign(&mut s, &a, now);
        let (_, newer) = assign(&mut s, &b, now);
        // No unit is queued behind another: the straggler's (oldest) first.
        assert_eq!(assign(&mut s, &c, now).1, oldest);
        let d = s.register("d", 1, now);
        assert_eq!(assign(&mut s, &d, now).1, newer);
    }

    #[test]
    fn goodbye_returns_units_and_preview_fills_from_coarse_sets() {
        let now = Instant::now();
        let units = work_units(16, 16, 8, 4096);
        let mut s = Scheduler::new(units, 16, 16, PixelFormat::Samples, Duration::from_secs(5));
        let a = s.register("a", 1, now);
        let (id, first) = assign(&mut s, &a, now);
        assert_eq!(first.set.offset(), (0, 0));
        let wire = convert::unit_to_wire(&first);
        s.submit(&a, id, Some(&wire), &tile(&first, 16, 0.75), 0, now)
            .unwrap();
        let (_, second) = assign(&mut s, &a, now);
        s.goodbye(&a, 1234).unwrap();
        assert_eq!(s.alive(), 0);
        let b = s.register("b", 1, now);
        assert_eq!(assign(&mut s, &b, now).1, second);
        // After the first set alone, the preview is complete at 1/8 resolution.
        assert!(
            film(&s.preview())
                .pixels()
                .iter()
                .all(|p| p.rgba[0] == 0.75)
        );
    }

    fn fail(
        s: &mut Scheduler,
        w: &str,
        id: u64,
        kind: FailureKind,
        now: Instant,
    ) -> Option<Counted> {
        s.fail(w, id, kind, &format!("{w} broke"), now).unwrap()
    }

    #[test]
    fn a_failed_unit_goes_to_another_worker_and_three_failures_give_up() {
        let now = Instant::now();
        let units = work_units(16, 16, 8, 4096);
        let mut s = Scheduler::new(units, 16, 16, PixelFormat::Samples, Duration::from_secs(5));
        let (a, b, c) = (
            s.register("a", 1, now),
            s.register("b", 1, now),
            s.register("c", 1, now),
        );
        let (id, unit) = assign(&mut s, &a, now);
        let counted = fail(&mut s, &a, id, FailureKind::Render, now).unwrap();
        assert_eq!(
            (counted.worker.as_str(), counted.index, counted.failures),
            ("a", 0, 1)
        );
        // a is not given the unit it failed while others could take it.
        assert_ne!(assign(&mut s, &a, now).1, unit);
        let (id, again) = assign(&mut s, &b, now);
        assert_eq!(
            again, unit,
            "the failed unit comes back first, to another worker"
        );
        fail(&mut s, &b, id, FailureKind::Assignment, now).unwrap();
        assert!(s.gave_up().is_none());
        let (id, again) = assign(&mut s, &c, now);
        assert_eq!(again, unit);
        fail(&mut s, &c, id, FailureKind::Render, now).unwrap();
        let given_up = s.gave_up().expect("three failures stop the render");
        let message = given_up.to_string();
        assert!(
            matches!(given_up, GiveUp::Unit { index: 0, .. }),
            "{message}"
        );
        for needle in [
            "unit 0",
            "pixel set 0 of 8×8",
            "failed 3 times",
            "worker a (render): w1-",
            "worker b (assignment): w2-",
            "worker c",
        ] {
            assert!(message.contains(needle), "{needle}: {message}");
        }
        assert_eq!(
            s.next(&a, now),
            Ok(Next::Wait),
            "nothing more is handed out"
        );
    }

    #[test]
    fn a_lone_worker_retries_a_failed_unit_up_to_the_limit() {
        let now = Instant::now();
        let units = work_units(8, 8, 8, 4096);
        let mut s = Scheduler::new(units, 8, 8, PixelFormat::Samples, Duration::from_secs(5));
        let a = s.register("a", 1, now);
        let mut ids = Vec::new();
        let mut first = None;
        // The unit is assigned again and again (nobody else could take it).
        for attempt in 1..=MAX_FAILURES {
            let (id, unit) = assign(&mut s, &a, now);
            assert_eq!(*first.get_or_insert(unit), unit);
            ids.push(id);
            assert_eq!(
                fail(&mut s, &a, id, FailureKind::Render, now)
                    .unwrap()
                    .failures,
                attempt
            );
        }
        assert!(matches!(s.gave_up(), Some(GiveUp::Unit { .. })));
        // A report for an assignment no longer held changes nothing; a forged one is refused.
        assert_eq!(
            s.fail(&a, ids[0], FailureKind::Render, "again", now),
            Ok(None)
        );
        assert_eq!(
            s.fail(&a, 999, FailureKind::Render, "forged", now),
            Err(Refusal::NeverAssigned(999))
        );
    }

    #[test]
    fn a_worker_whose_scene_does_not_build_gets_nothing_more() {
        let now = Instant::now();
        let units = work_units(16, 16, 8, 4096);
        let n = units.len();
        let mut s = Scheduler::new(units, 16, 16, PixelFormat::Samples, Duration::from_secs(5));
        let (a, b) = (s.register("a", 1, now), s.register("b", 1, now));
        let (first_id, first) = assign(&mut s, &a, now);
        let (ahead_id, ahead) = assign(&mut s, &a, now);
        fail(&mut s, &a, first_id, FailureKind::Scene, now).unwrap();
        assert_eq!(s.able(), 1);
        assert_eq!(s.next(&a, now), Ok(Next::Wait));
        // Its unit assigned ahead went back with the first: its report changes nothing.
        assert_eq!(fail(&mut s, &a, ahead_id, FailureKind::Scene, now), None);
        assert!(s.gave_up().is_none(), "b can still render");
        let mut got = Vec::new();
        for _ in 0..n {
            let (id, unit) = assign(&mut s, &b, now);
            got.push(unit);
            let wire = convert::unit_to_wire(&unit);
            assert_eq!(
                s.submit(&b, id, Some(&wire), &tile(&unit, 16, 0.5), 1, now),
                Ok(true)
            );
        }
        assert_eq!(
            &got[..2],
            &[first, ahead],
            "given back in order, first in line"
        );
        assert!(s.finished());

        // When no worker present can build the scene, the render stops at once.
        let mut s = Scheduler::new(
            work_units(8, 8, 8, 4096),
            8,
            8,
            PixelFormat::Samples,
            Duration::from_secs(5),
        );
        let a = s.register("a", 1, now);
        let (id, _) = assign(&mut s, &a, now);
        fail(&mut s, &a, id, FailureKind::Scene, now).unwrap();
        let message = s.gave_up().expect("nobody can render").to_string();
        assert!(
            message.contains("can build the scene") && message.contains("worker a (scene): w1-"),
            "{message}"
        );
    }

    fn plan(id: JobId, priority: i32, tags: &[&str]) -> JobPlan {
        JobPlan {
            id,
            priority,
            units: work_units(8, 8, 8, 4096),
            width: 8,
            height: 8,
            format: PixelFormat::Samples,
            frames: Frames::one(0),
            require_tags: tags.iter().map(|t| t.to_string()).collect(),
        }
    }

    fn assign_job(s: &mut Scheduler, w: &str, now: Instant) -> (u64, JobId, WorkUnit) {
        match s.next(w, now).unwrap() {
            Next::Assign {
                assignment_id,
                job,
                unit,
                ..
            } => (assignment_id, job, unit),
            other => panic!("expected an assignment, got {other:?}"),
        }
    }

    #[test]
    fn highest_priority_first_ties_oldest_first_and_a_new_urgent_job_goes_next() {
        let now = Instant::now();
        let mut s = Scheduler::service(Duration::from_secs(5));
        let a = s.register("a", 1, now);
        assert_eq!(s.next(&a, now), Ok(Next::Wait), "a service waits for jobs");
        s.add_job(plan(1, 0, &[]), Resume::default()).unwrap();
        s.add_job(plan(2, 5, &[]), Resume::default()).unwrap();
        s.add_job(plan(3, 5, &[]), Resume::default()).unwrap();
        assert_eq!(assign_job(&mut s, &a, now).1, 2, "priority 5, older");
        s.add_job(plan(4, 9, &[]), Resume::default()).unwrap();
        assert_eq!(
            assign_job(&mut s, &a, now).1,
            4,
            "the urgent job starts on the next unit"
        );
        // When job 4 has nothing left to hand out, the worker goes on with 2.
        let n = s.jobs[&4].plan.units.len();
        for _ in 1..n {
            assert_eq!(assign_job(&mut s, &a, now).1, 4);
        }
        assert_eq!(assign_job(&mut s, &a, now).1, 2);
    }

    #[test]
    fn units_of_two_jobs_interleave_so_no_worker_idles() {
        let now = Instant::now();
        let mut s = Scheduler::service(Duration::from_secs(5));
        let (a, b) = (s.register("a", 1, now), s.register("b", 1, now));
        s.add_job(plan(1, 0, &[]), Resume::default()).unwrap();
        s.add_job(plan(2, 0, &[]), Resume::default()).unwrap();
        let n = work_units(8, 8, 8, 4096).len();
        let mut seen = HashMap::new();
        // Both workers take units until nothing is left: job 1's first, then 2's.
        for i in 0..2 * n {
            let w = if i % 2 == 0 { &a } else { &b };
            let (id, job, unit) = assign_job(&mut s, w, now);
            *seen.entry(job).or_insert(0) += 1;
            let wire = convert::unit_to_wire(&unit);
            assert_eq!(
                s.submit(w, id, Some(&wire), &tile(&unit, 8, 0.5), 1, now),
                Ok(true)
            );
        }
        assert_eq!(seen[&1], n);
        assert_eq!(seen[&2], n);
        let done = s.take_completed();
        assert_eq!(done.iter().map(|f| f.job).collect::<Vec<_>>(), vec![1, 2]);
        assert!(s.finished());
        assert_eq!(s.next(&a, now), Ok(Next::Wait));
    }

    #[test]
    fn tagged_jobs_go_only_to_workers_carrying_every_tag() {
        let now = Instant::now();
        let mut s = Scheduler::service(Duration::from_secs(5));
        let plain = s.register("plain", 1, now);
        let gpu = s.register_tagged("gpu", 1, vec!["gpu".into(), "big".into()], now);
        s.add_job(plan(1, 0, &["gpu", "big"]), Resume::default())
            .unwrap();
        assert_eq!(s.next(&plain, now), Ok(Next::Wait));
        assert_eq!(assign_job(&mut s, &gpu, now).1, 1);
    }

    #[test]
    fn a_worker_failing_three_units_of_a_job_is_blocklisted_for_it_and_other_jobs_go_on() {
        let now = Instant::now();
        let mut s = Scheduler::service(Duration::from_secs(5));
        let (bad, good) = (s.register("bad", 1, now), s.register("good", 1, now));
        s.add_job(plan(1, 1, &[]), Resume::default()).unwrap();
        s.add_job(plan(2, 0, &[]), Resume::default()).unwrap();
        for k in 1..=MAX_FAILURES {
            let (id, job, _) = assign_job(&mut s, &bad, now);
            assert_eq!(job, 1);
            let counted = fail(&mut s, &bad, id, FailureKind::Render, now).unwrap();
            assert_eq!(counted.blocklisted, k == MAX_FAILURES);
        }
        assert_eq!(s.blocklisted(1), vec!["bad".to_string()]);
        assert_eq!(s.blocklisted_for(&bad), vec![1]);
        assert!(
            s.gave_up_jobs().next().is_none(),
            "good can still render job 1"
        );
        // bad now gets job 2's units; good gets job 1's.
        assert_eq!(assign_job(&mut s, &bad, now).1, 2);
        assert_eq!(assign_job(&mut s, &good, now).1, 1);
    }

    #[test]
    fn a_unit_failing_on_three_workers_fails_its_job_only() {
        let now = Instant::now();
        let mut s = Scheduler::service(Duration::from_secs(5));
        let ws: Vec<String> = ["a", "b", "c"]
            .iter()
            .map(|n| s.register(n, 1, now))
            .collect();
        s.add_job(plan(1, 1, &[]), Resume::default()).unwrap();
        s.add_job(plan(2, 0, &[]), Resume::default()).unwrap();
        let mut unit = None;
        for w in &ws {
            let (id, job, u) = assign_job(&mut s, w, now);
            assert_eq!(job, 1);
            assert_eq!(
                *unit.get_or_insert(u),
                u,
                "the failed unit goes to another worker"
            );
            fail(&mut s, w, id, FailureKind::Render, now).unwrap();
        }
        let failed: Vec<JobId> = s.gave_up_jobs().map(|(id, _)| id).collect();
        assert_eq!(failed, vec![1]);
        s.remove_job(1);
        assert_eq!(assign_job(&mut s, &ws[0], now).1, 2, "other jobs go on");
    }

    #[test]
    fn a_resumed_job_hands_out_only_the_units_not_stored_and_late_tiles_of_a_cancelled_job_are_unused()
     {
        let now = Instant::now();
        let units = work_units(8, 8, 8, 4096);
        let n = units.len();
        let stored: Vec<(usize, Vec<u8>)> =
            (0..n / 2).map(|u| (u, tile(&units[u], 8, 0.5))).collect();
        let mut s = Scheduler::service(Duration::from_secs(5));
        let a = s.register("a", 1, now);
        s.add_job(
            plan(7, 0, &[]),
            Resume {
                frames_done: 0,
                tiles: stored,
                redo: Vec::new(),
            },
        )
        .unwrap();
        assert_eq!(s.job_progress(7).unwrap().units_done, (n / 2) as u64);
        let (id, _, unit) = assign_job(&mut s, &a, now);
        assert_eq!(
            unit,
            units[n / 2],
            "the stored units are not rendered again"
        );
        assert!(s.cancel(7));
        let wire = convert::unit_to_wire(&unit);
        assert_eq!(
            s.submit(&a, id, Some(&wire), &tile(&unit, 8, 0.5), 1, now),
            Ok(false)
        );
        // A job whose every tile was stored is complete at once.
        let all: Vec<(usize, Vec<u8>)> = (0..n).map(|u| (u, tile(&units[u], 8, 0.5))).collect();
        s.add_job(
            plan(8, 0, &[]),
            Resume {
                frames_done: 0,
                tiles: all,
                redo: Vec::new(),
            },
        )
        .unwrap();
        let done = s.take_completed();
        assert_eq!(done.len(), 1);
        assert_eq!(done[0].job, 8);
    }
}
