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

use std::time::{Duration, Instant};

use hypertexture_proto::FailureKind;
use hypertexture_proto::convert;

use super::failures::Counted;
use super::state::{Accepted, Check, CheckWhy, JobId, ONE_SHOT_JOB, Refusal, Scheduler};

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

impl Scheduler {
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

    /// Takes a held unit of the job for its second rendering by `worker`,
    /// which did not deliver it.
    pub(super) fn check_for(&mut self, job_id: JobId, worker: u64) -> Option<usize> {
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

    /// Sampled units whose two renderings have been compared so far.
    pub fn verified(&self) -> u64 {
        self.verified
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
                if check.why == CheckWhy::Sample {
                    self.verified += 1;
                }
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
    pub(super) fn decide(
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
    pub(super) fn convict(&mut self, job_id: JobId, worker: u64) -> Option<Liar> {
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
    pub(super) fn store_trusted(
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
}

#[cfg(test)]
mod tests {
    use super::super::testing::*;

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
        assert_eq!(s.verified(), n as u64, "every unit compared once");
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
            .with_frames(FrameRange::new(0, 2));
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
            frames: FrameRange::new(4, 6),
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
}
