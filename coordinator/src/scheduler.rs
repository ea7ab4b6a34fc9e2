//! The scheduler: who renders which unit, and what comes back.
//!
//! Pure state, no I/O and no clock of its own (callers pass `now`), so every rule
//! is unit-tested here. Units are handed out in coarse-to-fine order; a unit
//! whose worker stops heartbeating goes back to the front of the queue; when the
//! queue is empty, idle workers get speculative duplicates of units still out
//! (first tile wins — results are identical by construction). A tile is checked
//! completely before it touches the canvas.
//!
//! A sequence of frames is one session: the workers stay, and the tile that
//! completes a frame moves its image to [`Scheduler::take_completed`] and starts
//! the next frame at once (its first unit goes out in that tile's reply).
//! Assignment ids run on across frames; a late tile of an earlier frame is
//! valid and unused.
//!
//! A worker that cannot render a unit reports it ([`Scheduler::fail`]): the unit
//! goes back to the queue, preferably to a worker that has not failed it; a
//! worker whose scene does not build gets no more units; and the render is
//! given up ([`GiveUp`]) when a unit has failed [`MAX_FAILURES`] times or no
//! worker present can build the scene, instead of retrying forever.

use std::collections::{HashMap, VecDeque};
use std::time::{Duration, Instant};

use hypertexture::PixelFormat;
use hypertexture::interleave::WorkUnit;

use crate::canvas::{Canvas, FrameImage};
use hypertexture_proto::convert::{self, WireError};
use hypertexture_proto::{FailureKind, pb};

/// At most this many workers hold the same unit at once.
const MAX_HOLDERS: usize = 2;

/// A unit that fails to render this many times (on different workers when
/// there are any) stops the render.
pub const MAX_FAILURES: usize = 3;

/// What a worker is told when it asks for work.
#[derive(Clone, Debug, PartialEq)]
pub enum Next {
    /// Render this unit of this frame under this assignment id.
    Assign {
        assignment_id: u64,
        unit: WorkUnit,
        frame: u32,
    },
    /// Nothing to hand out now; ask again later.
    Wait,
    /// Every frame is complete.
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

/// Why the render was given up.
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
    /// Every worker present failed to build the scene.
    Scene {
        /// One failure per worker that cannot build it.
        failures: Vec<UnitFailure>,
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
    /// The reporting worker's name.
    pub worker: String,
    /// The unit's index.
    pub index: usize,
    /// The unit given back.
    pub unit: WorkUnit,
    /// The unit's failures so far (scene failures are the worker's, not the unit's).
    pub failures: usize,
}

/// A frame whose every unit is in.
#[derive(Clone, Debug)]
pub struct CompletedFrame {
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
    /// Its name.
    pub name: String,
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
    /// Why the scene does not build on this worker, if it said so: it gets no
    /// more units.
    pub cannot_build: Option<String>,
}

#[derive(Clone, Copy, Debug)]
struct Lease {
    unit: usize,
    worker: u64,
}

/// The state of a render: one frame, or a sequence rendered one after another.
pub struct Scheduler {
    /// The frame numbers, in order, and the index of the one rendering.
    frames: Vec<u32>,
    current: usize,
    /// When the current frame's first unit went out.
    frame_started: Option<Instant>,
    /// Frames complete and not yet taken.
    completed: Vec<CompletedFrame>,
    units: Vec<WorkUnit>,
    pending: VecDeque<usize>,
    done: Vec<bool>,
    remaining: usize,
    /// Outstanding assignments.
    leases: HashMap<u64, Lease>,
    /// The frame (index into `frames`) and unit of every assignment ever issued
    /// (to tell late duplicates from forgeries).
    issued: Vec<(usize, usize)>,
    workers: HashMap<u64, WorkerState>,
    next_worker: u64,
    lease: Duration,
    /// The frame rendering.
    canvas: Canvas,
    /// Per unit: the CPU microseconds the accepted tile cost.
    unit_cpu: Vec<u64>,
    /// Per unit: the async-thread CPU microseconds its last tile reported.
    unit_calls: Vec<u64>,
    /// Per unit: the workers (by id) that failed it, and how.
    failures: Vec<Vec<(u64, UnitFailure)>>,
    /// Set when the render cannot go on.
    gave_up: Option<GiveUp>,
}

impl Scheduler {
    /// A scheduler for `units` of a `width × height` frame whose tiles come in
    /// `format`; a worker silent for `lease` loses its units.
    pub fn new(
        units: Vec<WorkUnit>,
        width: u32,
        height: u32,
        format: PixelFormat,
        lease: Duration,
    ) -> Scheduler {
        let n = units.len();
        Scheduler {
            frames: vec![0],
            current: 0,
            frame_started: None,
            completed: Vec::new(),
            pending: (0..n).collect(),
            done: vec![false; n],
            remaining: n,
            leases: HashMap::new(),
            issued: Vec::new(),
            workers: HashMap::new(),
            next_worker: 1,
            lease,
            canvas: Canvas::new(
                width,
                height,
                units.first().map_or(1, |u| u.set.interleave),
                format,
            ),
            unit_cpu: vec![0; n],
            unit_calls: vec![0; n],
            failures: vec![Vec::new(); n],
            gave_up: None,
            units,
        }
    }

    /// Renders these frames (in order, at least one) instead of frame 0.
    pub fn with_frames(mut self, frames: Vec<u32>) -> Scheduler {
        assert!(!frames.is_empty(), "a render has at least one frame");
        self.frames = frames;
        self
    }

    /// The frame rendering now.
    pub fn frame(&self) -> u32 {
        self.frames[self.current]
    }

    /// Registers a worker; returns its id.
    pub fn register(&mut self, name: &str, threads: u32, now: Instant) -> String {
        let id = self.next_worker;
        self.next_worker += 1;
        self.workers.insert(
            id,
            WorkerState {
                name: name.to_string(),
                threads,
                last_seen: now,
                joined: now,
                units: 0,
                pixels: 0,
                render_cpu_micros: 0,
                process_cpu_micros: None,
                alive: true,
                cannot_build: None,
            },
        );
        format!("w{id}")
    }

    fn worker_mut(&mut self, worker_id: &str) -> Result<(u64, &mut WorkerState), Refusal> {
        let unknown = || Refusal::UnknownWorker(worker_id.to_string());
        let id: u64 = worker_id
            .strip_prefix('w')
            .and_then(|n| n.parse().ok())
            .ok_or_else(unknown)?;
        match self.workers.get_mut(&id) {
            Some(w) if w.alive => Ok((id, w)),
            _ => Err(unknown()),
        }
    }

    /// Records that the worker is alive.
    pub fn heartbeat(&mut self, worker_id: &str, now: Instant) -> Result<(), Refusal> {
        self.worker_mut(worker_id)?.1.last_seen = now;
        Ok(())
    }

    /// The next thing for this worker to do.
    pub fn next(&mut self, worker_id: &str, now: Instant) -> Result<Next, Refusal> {
        let (wid, w) = self.worker_mut(worker_id)?;
        w.last_seen = now;
        let cannot_build = w.cannot_build.is_some();
        if self.remaining == 0 {
            return Ok(Next::Finished);
        }
        if cannot_build || self.gave_up.is_some() {
            return Ok(Next::Wait);
        }
        let unit = match self.pending_for(wid) {
            Some(u) => Some(u),
            None => self.speculative(wid),
        };
        Ok(match unit {
            Some(unit) => {
                let assignment_id = self.issued.len() as u64 + 1;
                self.issued.push((self.current, unit));
                self.leases
                    .insert(assignment_id, Lease { unit, worker: wid });
                self.frame_started.get_or_insert(now);
                Next::Assign {
                    assignment_id,
                    unit: self.units[unit],
                    frame: self.frame(),
                }
            }
            None => Next::Wait,
        })
    }

    /// Takes the first pending unit this worker has not failed, or that no other
    /// worker could take instead (so a lone worker retries, up to the limit).
    fn pending_for(&mut self, worker: u64) -> Option<usize> {
        let position = self
            .pending
            .iter()
            .position(|&u| !self.failed_by(u, worker) || !self.another_could_take(u, worker))?;
        self.pending.remove(position)
    }

    fn failed_by(&self, unit: usize, worker: u64) -> bool {
        self.failures[unit].iter().any(|(w, _)| *w == worker)
    }

    /// Whether a worker other than `worker`, able to render, has not failed `unit`.
    fn another_could_take(&self, unit: usize, worker: u64) -> bool {
        self.workers.iter().any(|(&id, w)| {
            id != worker && w.alive && w.cannot_build.is_none() && !self.failed_by(unit, id)
        })
    }

    /// An outstanding unit this worker does not hold and has not failed, held by
    /// fewer than [`MAX_HOLDERS`] workers: first the newest unit a worker holds
    /// queued behind the one it is rendering (workers render their units in the
    /// order given, so that one would be started last, and a copy started now
    /// ends the frame soonest), then the oldest outstanding one (a straggler).
    fn speculative(&self, worker: u64) -> Option<usize> {
        // Each worker's oldest lease: the unit it is rendering.
        let mut rendering: HashMap<u64, u64> = HashMap::new();
        for (&id, lease) in &self.leases {
            let oldest = rendering.entry(lease.worker).or_insert(id);
            *oldest = (*oldest).min(id);
        }
        // Per unit: holders, its oldest and newest lease, whether this worker
        // holds it, whether a holder has it queued rather than rendering.
        let mut holders: HashMap<usize, (usize, u64, u64, bool, bool)> = HashMap::new();
        for (&id, lease) in &self.leases {
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
                !mine && count < MAX_HOLDERS && !self.done[unit] && !self.failed_by(unit, worker)
            })
            .min_by_key(|&(_, (_, oldest, newest, _, queued))| {
                if queued {
                    (0, u64::MAX - newest)
                } else {
                    (1, oldest)
                }
            })
            .map(|(unit, _)| unit)
    }

    /// Notes what a tile's worker says its calls cost it (statistics only,
    /// whether the tile is accepted or not): for the unit of `assignment_id`,
    /// when that is of the frame rendering.
    pub fn note_calls_cpu(&mut self, assignment_id: u64, calls_cpu_micros: u64) {
        if let Some(&(frame, unit)) = assignment_id
            .checked_sub(1)
            .and_then(|i| self.issued.get(i as usize))
            && frame == self.current
        {
            self.unit_calls[unit] = calls_cpu_micros;
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
        let (wid, w) = self.worker_mut(worker_id)?;
        w.last_seen = now;
        let Some(&(issued_frame, issued_unit)) = assignment_id
            .checked_sub(1)
            .and_then(|i| self.issued.get(i as usize))
        else {
            return Err(Refusal::NeverAssigned(assignment_id));
        };
        if issued_frame != self.current {
            // A duplicate of a unit of a frame that is complete.
            return Ok(false);
        }
        let (width, height) = (self.canvas.width(), self.canvas.height());
        let unit_of = |u: Option<&pb::Unit>| {
            u.ok_or(WireError::Missing("unit"))
                .and_then(|u| convert::unit_from_wire(u, width, height))
        };
        let claimed = unit_of(unit).map_err(|error| Refusal::Malformed {
            id: assignment_id,
            error,
        })?;
        if claimed != self.units[issued_unit] {
            return Err(Refusal::WrongUnit(assignment_id));
        }
        let tile =
            convert::tile_from_wire(values, claimed.pixel_count(width), self.canvas.format())
                .map_err(|error| Refusal::Malformed {
                    id: assignment_id,
                    error,
                })?;
        match self.leases.get(&assignment_id) {
            Some(lease) if lease.worker == wid => {}
            _ if self.done[issued_unit] => return Ok(false),
            _ => return Err(Refusal::NotHeld(assignment_id)),
        }
        // Checked (the whole tile, above): store it.
        self.canvas.store(&claimed, tile);
        self.done[issued_unit] = true;
        self.remaining -= 1;
        self.unit_cpu[issued_unit] = render_cpu_micros;
        self.leases.retain(|_, l| l.unit != issued_unit);
        self.pending.retain(|&u| u != issued_unit);
        let w = self.workers.get_mut(&wid).expect("checked above");
        w.units += 1;
        w.pixels += claimed.pixel_count(width) as u64;
        w.render_cpu_micros += render_cpu_micros;
        if self.remaining == 0 {
            self.complete_frame(now);
        }
        Ok(true)
    }

    /// Moves the complete frame's image out and starts the next frame, if any.
    fn complete_frame(&mut self, now: Instant) {
        let n = self.units.len();
        let last = self.current + 1 == self.frames.len();
        self.completed.push(CompletedFrame {
            frame: self.frame(),
            // A blank canvas of the same size stays: late duplicates are still
            // checked against it.
            image: self.canvas.take(),
            unit_costs: std::mem::replace(&mut self.unit_cpu, vec![0; n]),
            unit_calls: std::mem::replace(&mut self.unit_calls, vec![0; n]),
            render_time: self
                .frame_started
                .take()
                .map_or(Duration::ZERO, |t| now.saturating_duration_since(t)),
        });
        if last {
            return;
        }
        self.current += 1;
        self.pending = (0..n).collect();
        self.done = vec![false; n];
        self.remaining = n;
        // Duplicates still out belong to the frame just completed.
        self.leases.clear();
        self.failures = vec![Vec::new(); n];
    }

    /// Whether a frame is complete and not yet taken.
    pub fn has_completed(&self) -> bool {
        !self.completed.is_empty()
    }

    /// The frames completed since the last call, in order.
    pub fn take_completed(&mut self) -> Vec<CompletedFrame> {
        std::mem::take(&mut self.completed)
    }

    /// A worker gives back an assignment it could not render. The unit goes back
    /// to the front of the queue; a worker whose scene does not build gives back
    /// everything it holds and gets nothing more. `Ok(None)`: the assignment was
    /// no longer this worker's, nothing changed. The render is given up
    /// ([`Scheduler::gave_up`]) when the unit has failed [`MAX_FAILURES`] times,
    /// or no worker present can build the scene.
    pub fn fail(
        &mut self,
        worker_id: &str,
        assignment_id: u64,
        kind: FailureKind,
        reason: &str,
        now: Instant,
    ) -> Result<Option<Counted>, Refusal> {
        let (wid, w) = self.worker_mut(worker_id)?;
        w.last_seen = now;
        let name = w.name.clone();
        let Some(&(frame, unit)) = assignment_id
            .checked_sub(1)
            .and_then(|i| self.issued.get(i as usize))
        else {
            return Err(Refusal::NeverAssigned(assignment_id));
        };
        match self.leases.get(&assignment_id) {
            Some(lease) if lease.worker == wid && frame == self.current => {}
            _ => return Ok(None),
        }
        let failure = UnitFailure {
            worker: name.clone(),
            kind,
            reason: reason.to_string(),
        };
        self.leases.remove(&assignment_id);
        if kind == FailureKind::Scene {
            // Deterministic on this worker: every unit it holds would fail too.
            let w = self.workers.get_mut(&wid).expect("checked above");
            w.cannot_build = Some(reason.to_string());
            self.release(wid);
        } else {
            self.failures[unit].push((wid, failure));
        }
        let held = self.leases.values().any(|l| l.unit == unit);
        if !self.done[unit] && !held && !self.pending.contains(&unit) {
            self.pending.push_front(unit);
        }
        if self.gave_up.is_none() {
            if self.failures[unit].len() >= MAX_FAILURES {
                self.gave_up = Some(GiveUp::Unit {
                    index: unit,
                    unit: self.units[unit],
                    failures: self.failures[unit].iter().map(|(_, f)| f.clone()).collect(),
                });
            } else if kind == FailureKind::Scene && self.able() == 0 {
                let mut failures: Vec<(Instant, UnitFailure)> = self
                    .workers
                    .values()
                    .filter_map(|w| {
                        let reason = w.cannot_build.clone()?;
                        Some((
                            w.joined,
                            UnitFailure {
                                worker: w.name.clone(),
                                kind: FailureKind::Scene,
                                reason,
                            },
                        ))
                    })
                    .collect();
                failures.sort_by_key(|f| f.0);
                self.gave_up = Some(GiveUp::Scene {
                    failures: failures.into_iter().map(|(_, f)| f).collect(),
                });
            }
        }
        Ok(Some(Counted {
            worker: name,
            index: unit,
            unit: self.units[unit],
            failures: self.failures[unit].len(),
        }))
    }

    /// Why the render cannot go on, once it cannot.
    pub fn gave_up(&self) -> Option<&GiveUp> {
        self.gave_up.as_ref()
    }

    /// A worker leaves cleanly; anything it still held goes back to the queue.
    /// Its process's CPU time is kept when it knows it (not 0).
    pub fn goodbye(&mut self, worker_id: &str, process_cpu_micros: u64) -> Result<(), Refusal> {
        let (wid, w) = self.worker_mut(worker_id)?;
        w.process_cpu_micros = (process_cpu_micros > 0).then_some(process_cpu_micros);
        w.alive = false;
        self.release(wid);
        Ok(())
    }

    /// Drops workers silent for longer than the lease; their units go back to the
    /// front of the queue. Returns the names of the workers dropped.
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
            self.release(id);
        }
        names
    }

    fn release(&mut self, worker: u64) {
        let mut freed: Vec<(u64, usize)> = self
            .leases
            .iter()
            .filter(|(_, l)| l.worker == worker)
            .map(|(&id, l)| (id, l.unit))
            .collect();
        freed.sort_unstable();
        for &(id, _) in &freed {
            self.leases.remove(&id);
        }
        // Back to the front, in their original order, unless someone else holds them.
        for &(_, unit) in freed.iter().rev() {
            let held = self.leases.values().any(|l| l.unit == unit);
            if !self.done[unit] && !held && !self.pending.contains(&unit) {
                self.pending.push_front(unit);
            }
        }
    }

    /// Whether every unit of every frame is complete.
    pub fn finished(&self) -> bool {
        self.remaining == 0
    }

    /// Units complete and in all, over every frame.
    pub fn progress(&self) -> (usize, usize) {
        let n = self.units.len();
        (self.current * n + n - self.remaining, self.frames.len() * n)
    }

    /// Workers still in the farm.
    pub fn alive(&self) -> usize {
        self.workers.values().filter(|w| w.alive).count()
    }

    /// Workers still in the farm that can build the scene.
    pub fn able(&self) -> usize {
        self.workers
            .values()
            .filter(|w| w.alive && w.cannot_build.is_none())
            .count()
    }

    /// Every worker that ever joined.
    pub fn workers(&self) -> impl Iterator<Item = &WorkerState> {
        self.workers.values()
    }

    /// The image so far, gaps filled from coarser pixel sets ([`Canvas::preview`]).
    pub fn preview(&self) -> FrameImage {
        self.canvas.preview()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use hypertexture::Sample;
    use hypertexture::interleave::work_units;

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
    fn a_sequence_starts_the_next_frame_with_the_tile_that_completes_one() {
        let now = Instant::now();
        let units = work_units(8, 8, 8, 4096);
        let n = units.len();
        let mut s = Scheduler::new(units, 8, 8, PixelFormat::Samples, Duration::from_secs(5))
            .with_frames(vec![3, 4]);
        let (a, b) = (s.register("a", 1, now), s.register("b", 1, now));
        let mut first_frame = Vec::new();
        for _ in 0..n {
            match s.next(&a, now).unwrap() {
                Next::Assign {
                    assignment_id,
                    unit,
                    frame,
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
        assert!(matches!(
            s.submit(&a, id, None, &good, 0, now),
            Err(Refusal::Malformed { .. })
        ));
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
        assert_eq!(s.submit(&a, id, Some(&wire), &good, 0, now), Ok(true));
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
            "worker a (render): w1 broke",
            "worker b (assignment): w2 broke",
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
            message.contains("can build the scene")
                && message.contains("worker a (scene): w1 broke"),
            "{message}"
        );
    }
}
