//! The workers the scheduler knows: registration, the ids they present
//! (a number and a secret drawn for it), heartbeats, departures, and the
//! pixels per second each delivers.

use std::collections::{HashSet, VecDeque};
use std::time::Instant;

use super::state::{JobId, ONE_SHOT_JOB, RATE_WINDOW, Refusal, Scheduler, WorkerState};

/// The number of a worker's id as views show it (`w7`), or as it was handed
/// to the worker (`w7-…`).
pub(super) fn number(worker_id: &str) -> Option<u64> {
    let rest = worker_id.strip_prefix('w')?;
    rest.split_once('-').map_or(rest, |(n, _)| n).parse().ok()
}

impl Scheduler {
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

    pub(super) fn worker_mut(
        &mut self,
        worker_id: &str,
    ) -> Result<(u64, &mut WorkerState), Refusal> {
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
    pub(super) fn able_for(&self, job: JobId) -> usize {
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

    /// Workers whose tags let them render `tags`, alive now.
    pub fn tagged(&self, tags: &[String]) -> usize {
        let set: HashSet<&String> = tags.iter().collect();
        self.workers
            .values()
            .filter(|w| w.alive && set.iter().all(|t| w.tags.contains(t)))
            .count()
    }
}

#[cfg(test)]
mod tests {
    use super::super::testing::*;

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
}
