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
//! The modules, in the order they may import one another (each only from
//! those above it); this module itself only declares them and re-exports
//! their public items:
//!
//! - `state`: [`Scheduler`], the state it keeps per job, worker and
//!   assignment, job plans and frames, checks asked for, what it reports
//!   (progress, previews), [`Refusal`], and the limits;
//! - `frames`: a job's frames, rendered one after another;
//! - `workers`: registration, the ids workers present, heartbeats, rates;
//! - `leases`: assignments outstanding, taken back, and their units queued again;
//! - `queue`: jobs in the queue's order, and which unit goes to which worker;
//! - `failures`: units that cannot be rendered, blocklists, jobs given up;
//! - `verify`: verified rendering, and the coordinator's checks of claims;
//! - `tiles`: a tile checked and accepted into its frame's canvas.

mod failures;
mod frames;
mod leases;
mod queue;
mod state;
mod tiles;
mod verify;
mod workers;

pub use failures::Counted;
pub use queue::Next;
pub use state::{
    Accepted, Check, CheckWhy, CompletedFrame, GiveUp, JobId, JobPlan, JobProgress, MAX_FAILURES,
    ONE_SHOT_JOB, Refusal, Resume, Scheduler, UnitFailure, WorkerState, describe,
};
pub use tiles::Keep;
pub use verify::{CheckOutcome, Liar, Verdict};

#[cfg(test)]
mod testing;
