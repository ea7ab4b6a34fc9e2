//! The queue: jobs added, cancelled and removed, their order (highest
//! priority first, ties oldest first), and which unit goes to a worker asking
//! for work: a pending unit, a second rendering to check, or a speculative
//! duplicate of a unit still out.

use std::collections::HashMap;
use std::time::Instant;

use hypertexture::render::interleave::WorkUnit;
use hypertexture_proto::convert::WireError;

use super::state::{Job, JobId, JobPlan, Lease, Refusal, Resume, Scheduler};

/// At most this many workers hold the same unit at once.
const MAX_HOLDERS: usize = 2;

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

impl Scheduler {
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

    /// The jobs in the queue's order: highest priority first, ties oldest first.
    pub(super) fn queue_order(&self) -> Vec<JobId> {
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
    pub(super) fn pending_for(&mut self, job_id: JobId, worker: u64) -> Option<usize> {
        let job = &self.jobs[&job_id];
        let position = job.pending.iter().position(|&u| {
            !job.failed_by(u, worker) || (self.one_shot && !self.another_could_take(job, u, worker))
        })?;
        self.jobs.get_mut(&job_id)?.pending.remove(position)
    }

    /// Whether a worker other than `worker`, able to render the job, has not
    /// failed `unit`.
    pub(super) fn another_could_take(&self, job: &Job, unit: usize, worker: u64) -> bool {
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
    pub(super) fn speculative(&self, job_id: JobId, worker: u64) -> Option<usize> {
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
}

#[cfg(test)]
mod tests {
    use super::super::testing::*;

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
