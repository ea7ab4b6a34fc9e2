//! Assignments outstanding: which worker holds which unit since when, the
//! units a worker gives back (or loses when its lease runs out) queued again,
//! and the assignments of a removed job taken back from their workers.

use super::state::{JobId, Scheduler};
use super::workers::number;

impl Scheduler {
    /// The job, frame index and unit of an assignment of a job still in the
    /// scheduler; `Err(true)` when the id was issued for a job that has
    /// ended, `Err(false)` when it never was.
    pub(super) fn issued(&self, assignment_id: u64) -> Result<(JobId, u64, usize), bool> {
        match self.issued.get(&assignment_id) {
            Some(&i) => Ok(i),
            None => Err(assignment_id > 0 && assignment_id < self.next_assignment),
        }
    }

    /// Gives back the units `worker` holds (of `job`, or of every job).
    pub(super) fn release(&mut self, worker: u64, job: Option<JobId>) {
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

    /// Puts a unit no longer held by anyone back in its job's queue: to be
    /// rendered (at the front), or, when its tile is in and held for a
    /// second rendering, with the units waiting for one.
    pub(super) fn requeue(&mut self, job_id: JobId, unit: usize) {
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

    /// The assignments [`Scheduler::remove_job`] took back since the last
    /// call, to tell their workers: (worker id, assignment id).
    pub fn take_withdrawn(&mut self) -> Vec<(String, u64)> {
        std::mem::take(&mut self.withdrawn)
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
}

#[cfg(test)]
mod tests {
    use super::super::testing::*;

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
}
