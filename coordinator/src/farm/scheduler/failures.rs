//! Units that cannot be rendered. A worker that cannot render a unit reports
//! it ([`Scheduler::fail`]): the unit goes back to the queue, to a worker that
//! has not failed it when there is one; a worker that has failed
//! [`MAX_FAILURES`] units of a job is blocklisted for that job; a worker whose
//! scene does not build gets no more units of that job; and a job is given up
//! ([`GiveUp`]) when one of its units has failed [`MAX_FAILURES`] times (on
//! different workers when there are any) or, in a one-shot render, when no
//! worker present can render it. Other jobs go on.

use std::collections::BTreeSet;
use std::time::Instant;

use hypertexture::render::interleave::WorkUnit;
use hypertexture_proto::FailureKind;

use super::state::{GiveUp, JobId, MAX_FAILURES, ONE_SHOT_JOB, Refusal, Scheduler, UnitFailure};
use super::workers::number;

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

impl Scheduler {
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

    /// Takes an assignment back from the worker that could not render it:
    /// the unit goes back to the front of the queue (or, for a second
    /// rendering, to the units waiting for one); a worker whose scene does
    /// not build gives back everything of the job. `None` when the
    /// assignment is no longer this worker's.
    #[allow(clippy::type_complexity)]
    pub(super) fn give_back(
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

    /// Counts a failure of a unit of the frame rendering: towards the
    /// worker's blocklist, towards the unit's failures (when `of_unit`), and
    /// gives the job up when the unit has failed [`MAX_FAILURES`] times or,
    /// in a one-shot render, no worker present can render it.
    #[allow(clippy::too_many_arguments)]
    pub(super) fn count_failure(
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
}

#[cfg(test)]
mod tests {
    use super::super::testing::*;

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
}
