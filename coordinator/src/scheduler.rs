//! The scheduler: who renders which unit, and what comes back.
//!
//! Pure state, no I/O and no clock of its own (callers pass `now`), so every rule
//! is unit-tested here. Units are handed out in coarse-to-fine order; a unit
//! whose worker stops heartbeating goes back to the front of the queue; when the
//! queue is empty, idle workers get speculative duplicates of units still out
//! (first tile wins — results are identical by construction). A tile is checked
//! completely before it touches the film.

use std::collections::{HashMap, VecDeque};
use std::time::{Duration, Instant};

use hypertexture::interleave::WorkUnit;
use hypertexture::{Film, Sample};
use hypertexture_proto::convert::{self, WireError};
use hypertexture_proto::pb;

/// At most this many workers hold the same unit at once.
const MAX_HOLDERS: usize = 2;

/// What a worker is told when it asks for work.
#[derive(Clone, Debug, PartialEq)]
pub enum Next {
    /// Render this unit under this assignment id.
    Assign { assignment_id: u64, unit: WorkUnit },
    /// Nothing to hand out now; ask again later.
    Wait,
    /// The frame is complete.
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
    /// The tile itself is malformed.
    #[error("malformed tile for assignment {id}: {error}")]
    Malformed {
        /// The assignment.
        id: u64,
        /// What is wrong.
        error: WireError,
    },
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
}

#[derive(Clone, Copy, Debug)]
struct Lease {
    unit: usize,
    worker: u64,
}

/// The state of one frame's render.
pub struct Scheduler {
    units: Vec<WorkUnit>,
    pending: VecDeque<usize>,
    done: Vec<bool>,
    remaining: usize,
    /// Outstanding assignments.
    leases: HashMap<u64, Lease>,
    /// The unit of every assignment ever issued (to tell late duplicates from forgeries).
    issued: Vec<usize>,
    workers: HashMap<u64, WorkerState>,
    next_worker: u64,
    lease: Duration,
    film: Film,
    /// Per pixel: rendered yet (for previews).
    rendered: Vec<bool>,
    /// Per unit: the CPU microseconds the accepted tile cost.
    unit_cpu: Vec<u64>,
}

impl Scheduler {
    /// A scheduler for `units` of a `width × height` frame; a worker silent for
    /// `lease` loses its units.
    pub fn new(units: Vec<WorkUnit>, width: u32, height: u32, lease: Duration) -> Scheduler {
        let n = units.len();
        Scheduler {
            pending: (0..n).collect(),
            done: vec![false; n],
            remaining: n,
            leases: HashMap::new(),
            issued: Vec::new(),
            workers: HashMap::new(),
            next_worker: 1,
            lease,
            film: Film::new(width, height),
            rendered: vec![false; width as usize * height as usize],
            unit_cpu: vec![0; n],
            units,
        }
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
        if self.remaining == 0 {
            return Ok(Next::Finished);
        }
        let unit = match self.pending.pop_front() {
            Some(u) => Some(u),
            None => self.speculative(wid),
        };
        Ok(match unit {
            Some(unit) => {
                let assignment_id = self.issued.len() as u64 + 1;
                self.issued.push(unit);
                self.leases
                    .insert(assignment_id, Lease { unit, worker: wid });
                Next::Assign {
                    assignment_id,
                    unit: self.units[unit],
                }
            }
            None => Next::Wait,
        })
    }

    /// The oldest outstanding unit this worker does not hold, held by fewer than
    /// [`MAX_HOLDERS`] workers.
    fn speculative(&self, worker: u64) -> Option<usize> {
        let mut holders: HashMap<usize, (usize, u64, bool)> = HashMap::new();
        for (&id, lease) in &self.leases {
            let e = holders.entry(lease.unit).or_insert((0, id, false));
            e.0 += 1;
            e.1 = e.1.min(id);
            e.2 |= lease.worker == worker;
        }
        holders
            .into_iter()
            .filter(|&(unit, (count, _, mine))| !mine && count < MAX_HOLDERS && !self.done[unit])
            .min_by_key(|&(_, (_, oldest, _))| oldest)
            .map(|(unit, _)| unit)
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
        let Some(&issued_unit) = assignment_id
            .checked_sub(1)
            .and_then(|i| self.issued.get(i as usize))
        else {
            return Err(Refusal::NeverAssigned(assignment_id));
        };
        let (width, height) = (self.film.width(), self.film.height());
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
        let samples =
            convert::samples_from_wire(values, claimed.pixel_count(width)).map_err(|error| {
                Refusal::Malformed {
                    id: assignment_id,
                    error,
                }
            })?;
        match self.leases.get(&assignment_id) {
            Some(lease) if lease.worker == wid => {}
            _ if self.done[issued_unit] => return Ok(false),
            _ => return Err(Refusal::NotHeld(assignment_id)),
        }
        // Checked (the samples come out only after the whole tile passed): write it.
        let film = self.film.pixels_mut();
        for ((x, y), sample) in claimed.pixels(width).zip(samples) {
            let i = (y * width + x) as usize;
            film[i] = sample;
            self.rendered[i] = true;
        }
        self.done[issued_unit] = true;
        self.remaining -= 1;
        self.unit_cpu[issued_unit] = render_cpu_micros;
        self.leases.retain(|_, l| l.unit != issued_unit);
        self.pending.retain(|&u| u != issued_unit);
        let w = self.workers.get_mut(&wid).expect("checked above");
        w.units += 1;
        w.pixels += claimed.pixel_count(width) as u64;
        w.render_cpu_micros += render_cpu_micros;
        Ok(true)
    }

    /// A worker leaves cleanly; anything it still held goes back to the queue.
    pub fn goodbye(&mut self, worker_id: &str, process_cpu_micros: u64) -> Result<(), Refusal> {
        let (wid, w) = self.worker_mut(worker_id)?;
        w.process_cpu_micros = Some(process_cpu_micros);
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

    /// Whether every unit is complete.
    pub fn finished(&self) -> bool {
        self.remaining == 0
    }

    /// Units complete and in all.
    pub fn progress(&self) -> (usize, usize) {
        (self.units.len() - self.remaining, self.units.len())
    }

    /// Workers still in the farm.
    pub fn alive(&self) -> usize {
        self.workers.values().filter(|w| w.alive).count()
    }

    /// Every worker that ever joined.
    pub fn workers(&self) -> impl Iterator<Item = &WorkerState> {
        self.workers.values()
    }

    /// The CPU cost of each unit's accepted tile, in microseconds.
    pub fn unit_costs(&self) -> &[u64] {
        &self.unit_cpu
    }

    /// The image so far.
    pub fn film(&self) -> &Film {
        &self.film
    }

    /// Takes the image (the frame is over: no copy of 36 bytes a pixel), leaving
    /// an empty one.
    pub fn take_film(&mut self) -> Film {
        std::mem::replace(&mut self.film, Film::new(0, 0))
    }

    /// The image so far with each missing pixel filled from the nearest rendered
    /// pixel of a coarser lattice (units arrive coarse to fine, so after the first
    /// pixel set the whole picture is there at low resolution).
    pub fn preview(&self) -> Film {
        let mut film = self.film.clone();
        let (w, h) = (film.width(), film.height());
        for y in 0..h {
            for x in 0..w {
                if self.rendered[(y * w + x) as usize] {
                    continue;
                }
                let mut spacing = 2;
                while spacing <= 64 {
                    let (px, py) = (x - x % spacing, y - y % spacing);
                    if self.rendered[(py * w + px) as usize] {
                        film.set(x, y, self.film.get(px, py));
                        break;
                    }
                    spacing *= 2;
                }
                if spacing > 64 {
                    film.set(x, y, Sample::default());
                }
            }
        }
        film
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use hypertexture::interleave::work_units;

    fn tile(unit: &WorkUnit, width: u32, value: f32) -> Vec<u8> {
        let samples = vec![Sample::from_array([value; Sample::CHANNELS]); unit.pixel_count(width)];
        convert::samples_to_wire(&samples).to_vec()
    }

    fn assign(s: &mut Scheduler, w: &str, now: Instant) -> (u64, WorkUnit) {
        match s.next(w, now).unwrap() {
            Next::Assign {
                assignment_id,
                unit,
            } => (assignment_id, unit),
            other => panic!("expected an assignment, got {other:?}"),
        }
    }

    #[test]
    fn hands_out_every_unit_once_then_finishes() {
        let now = Instant::now();
        let units = work_units(16, 16, 8, 4096);
        let mut s = Scheduler::new(units.clone(), 16, 16, Duration::from_secs(5));
        let w = s.register("a", 1, now);
        for expected in &units {
            let (id, unit) = assign(&mut s, &w, now);
            assert_eq!(&unit, expected);
            let wire = convert::unit_to_wire(&unit);
            assert_eq!(
                s.submit(&w, id, Some(&wire), &tile(&unit, 16, 0.5), 10, now),
                Ok(true)
            );
        }
        assert!(s.finished());
        assert_eq!(s.next(&w, now), Ok(Next::Finished));
        assert!(s.film().pixels().iter().all(|p| p.rgba[0] == 0.5));
    }

    #[test]
    fn a_silent_worker_loses_its_units_to_others() {
        let t0 = Instant::now();
        let units = work_units(8, 8, 8, 4096);
        let mut s = Scheduler::new(units, 8, 8, Duration::from_secs(5));
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
        let mut s = Scheduler::new(units, 8, 8, Duration::from_secs(5));
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
            s.film().pixels().iter().all(|p| *p == Sample::default()),
            "nothing written"
        );
        assert_eq!(s.submit(&a, id, Some(&wire), &good, 0, now), Ok(true));
    }

    #[test]
    fn idle_workers_get_speculative_duplicates_and_first_tile_wins() {
        let now = Instant::now();
        let units = work_units(8, 8, 8, 4096);
        let n = units.len();
        let mut s = Scheduler::new(units, 8, 8, Duration::from_secs(5));
        let (a, b) = (s.register("a", 1, now), s.register("b", 1, now));
        let mut held = Vec::new();
        for _ in 0..n {
            held.push(assign(&mut s, &a, now));
        }
        // The queue is empty: b gets a duplicate of a's oldest unit.
        let (dup_id, dup_unit) = assign(&mut s, &b, now);
        assert_eq!(dup_unit, held[0].1);
        let wire = convert::unit_to_wire(&dup_unit);
        assert_eq!(
            s.submit(&b, dup_id, Some(&wire), &tile(&dup_unit, 8, 1.0), 0, now),
            Ok(true)
        );
        // a's copy arrives later: valid, ignored.
        assert_eq!(
            s.submit(&a, held[0].0, Some(&wire), &tile(&dup_unit, 8, 1.0), 0, now),
            Ok(false)
        );
    }

    #[test]
    fn goodbye_returns_units_and_preview_fills_from_coarse_sets() {
        let now = Instant::now();
        let units = work_units(16, 16, 8, 4096);
        let mut s = Scheduler::new(units, 16, 16, Duration::from_secs(5));
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
        assert!(s.preview().pixels().iter().all(|p| p.rgba[0] == 0.75));
    }
}
