//! What the service and the studio see of a running farm, and all they may
//! change in it: each call takes the farm's lock once and hands back plain
//! values, so the scheduler and the farm's state stay private to `farm/`.

use std::time::Instant;

use hypertexture::render::interleave::WorkUnit;
use hypertexture::{FrameRange, PixelFormat};
use hypertexture_proto::convert::WireError;

use super::scheduler::{JobId, JobPlan, JobProgress, Resume};
use super::{FarmStats, Shared, WireJob};

/// The studio's live frames' priority: above every other job.
pub const LIVE_PRIORITY: i32 = i32::MAX;

/// A worker in the farm, as the service lists it.
#[derive(Clone, Debug, PartialEq)]
pub struct WorkerSummary {
    /// Its id as views and logs show it (`w7`).
    pub id: String,
    /// Its name.
    pub name: String,
    /// Its tags.
    pub tags: Vec<String>,
    /// Render threads it announced.
    pub threads: u32,
    /// Pixels per second over the last minute.
    pub pixels_per_second: f64,
    /// The job it is rendering, if any.
    pub current_job: Option<JobId>,
    /// Units accepted from it.
    pub units: u64,
    /// The jobs it is blocklisted for.
    pub blocklisted_for: Vec<JobId>,
    /// When it registered.
    pub joined: Instant,
}

/// The farm's queue and counters at one moment (a metrics scrape).
#[derive(Clone, Debug, Default)]
pub struct QueueView {
    /// The farm's counters.
    pub stats: FarmStats,
    /// Units waiting to be handed out, over every job.
    pub queued_all: u64,
    /// Per job a unit of which has been handed out: (job, units waiting,
    /// units held by workers).
    pub started: Vec<(JobId, u64, u64)>,
}

impl Shared {
    /// A job's progress; `None` when it is not in the farm.
    pub fn job_progress(&self, job: JobId) -> Option<JobProgress> {
        self.lock().scheduler.job_progress(job)
    }

    /// The names of the workers blocklisted for a job.
    pub fn blocklisted(&self, job: JobId) -> Vec<String> {
        self.lock().scheduler.blocklisted(job)
    }

    /// A job's progress and the workers blocklisted for it, at one moment.
    pub fn job_standing(&self, job: JobId) -> (Option<JobProgress>, Vec<String>) {
        let state = self.lock();
        (
            state.scheduler.job_progress(job),
            state.scheduler.blocklisted(job),
        )
    }

    /// Whether a job has nothing left to render (true when it is not in the
    /// farm).
    pub fn job_finished(&self, job: JobId) -> bool {
        self.lock().scheduler.job_finished(job)
    }

    /// Holds units back while the tiles cannot be kept (`writable` false),
    /// and hands them out again once they can.
    pub fn set_writable(&self, writable: bool) {
        let mut state = self.lock();
        if state.scheduler.paused() == writable {
            state.scheduler.pause(!writable);
        }
    }

    /// Stops handing out units (a draining service).
    pub fn drain(&self) {
        self.lock().scheduler.drain();
    }

    /// Units held by workers now.
    pub fn in_flight(&self) -> usize {
        self.lock().scheduler.in_flight()
    }

    /// The workers still in the farm, in no particular order.
    pub fn workers(&self, now: Instant) -> Vec<WorkerSummary> {
        let state = self.lock();
        let s = &state.scheduler;
        s.workers()
            .filter(|w| w.alive)
            .map(|w| WorkerSummary {
                id: w.id.clone(),
                name: w.name.clone(),
                tags: w.tags.clone(),
                threads: w.threads,
                pixels_per_second: w.pixels_per_second(now),
                current_job: s.current_job(&w.id),
                units: w.units,
                blocklisted_for: s.blocklisted_for(&w.id),
                joined: w.joined,
            })
            .collect()
    }

    /// The queue and the counters, at one moment.
    pub fn queue(&self) -> QueueView {
        let state = self.lock();
        let mut view = QueueView {
            stats: state.stats.clone(),
            ..QueueView::default()
        };
        for id in state.scheduler.job_ids() {
            let Some(p) = state.scheduler.job_progress(id) else {
                continue;
            };
            view.queued_all += p.units_queued;
            if p.started {
                view.started.push((id, p.units_queued, p.units_in_flight));
            }
        }
        view
    }

    /// Adds a job of one frame, `frame`, of `units` at `priority` whose
    /// units are not rendered twice (the studio's live frames, at
    /// [`LIVE_PRIORITY`]: their first coarse image waits for nothing).
    pub fn add_live_frame(
        &self,
        (id, frame, priority): (JobId, u32, i32),
        units: Vec<WorkUnit>,
        (width, height): (u32, u32),
        format: PixelFormat,
        wire: WireJob,
    ) -> Result<(), WireError> {
        let plan = JobPlan {
            frames: FrameRange::one(frame),
            ..JobPlan::one_frame(id, priority, units, (width, height), format)
        };
        self.add_job(plan, Resume::default(), wire)
    }
}
