//! Tiles coming back: each is checked completely (its worker, assignment,
//! unit and bytes) before it touches a canvas; a second rendering is compared
//! with the tile it checks; an accepted tile is kept first (the service's
//! store), then stored in its frame's canvas and counted for its worker.

use std::time::{Duration, Instant};

use hypertexture::render::interleave::WorkUnit;
use hypertexture_proto::convert::{self, WireError};
use hypertexture_proto::{FailureKind, pb};

use super::state::{Accepted, Check, CheckWhy, JobId, Refusal, Scheduler};

/// What [`Scheduler::accept_kept`] calls to keep a tile before accepting it:
/// `Err` (why) refuses the tile.
pub type Keep<'a> = dyn FnMut(&Accepted, &[u8]) -> Result<(), String> + 'a;

impl Scheduler {
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
        let Some(delivery) = self.delivery(worker_id, assignment_id, unit, values, now)? else {
            return Ok(None);
        };
        if delivery.check && self.second_rendering(&delivery, now) {
            return Ok(None);
        }
        let accepted = self.keep_tile(&delivery, now, keep)?;
        self.store_tile(&delivery, accepted.held, render_cpu_micros, now);
        Ok(Some(accepted))
    }

    /// Checks a tile completely against the assignment it answers: the
    /// worker, the assignment, the unit and the bytes. `Ok(None)` when it is
    /// valid but unused (a late duplicate, or of a job that has ended).
    fn delivery<'a>(
        &mut self,
        worker_id: &str,
        assignment_id: u64,
        unit: Option<&pb::Unit>,
        values: &'a [u8],
        now: Instant,
    ) -> Result<Option<Delivery<'a>>, Refusal> {
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
        Ok(Some(Delivery {
            assignment: assignment_id,
            worker: wid,
            job: job_id,
            index: issued_unit,
            unit: claimed,
            pixels: claimed.pixel_count(width),
            values,
            tile,
            issued: issued_at,
            check,
        }))
    }

    /// Takes a second rendering of a unit whose tile is in into account:
    /// equal bytes confirm the held tile, different bytes go to the
    /// coordinator to decide. False when the held tile was a liar's and is
    /// gone: this tile is the unit's.
    fn second_rendering(&mut self, d: &Delivery<'_>, now: Instant) -> bool {
        self.leases.remove(&d.assignment);
        let job = self.jobs.get_mut(&d.job).expect("checked above");
        if job.held.contains_key(&d.index) {
            self.verified += 1;
        }
        match job.held.get(&d.index) {
            Some((_, first)) if first.as_slice() == d.values => {
                // The two renderings agree: the tile is stored now.
                let (first_worker, bytes) = job.held.remove(&d.index).expect("matched above");
                let frame = job.frame();
                self.confirmed.push((
                    Accepted {
                        job: d.job,
                        frame,
                        unit: d.index,
                        worker: self
                            .workers
                            .get(&first_worker)
                            .map_or_else(String::new, |w| w.name.clone()),
                        latency: Duration::ZERO,
                        held: false,
                    },
                    bytes,
                ));
                self.settle(d.job, now);
                true
            }
            Some(_) => {
                // They differ: the coordinator's own rendering decides.
                let fresh = !job.disputed.contains_key(&d.index);
                job.disputed
                    .entry(d.index)
                    .or_default()
                    .push((d.worker, d.values.to_vec()));
                if fresh {
                    self.urgent.push_back(Check {
                        job: d.job,
                        pass: job.pass,
                        frame: job.frame(),
                        index: d.index,
                        unit: d.unit,
                        why: CheckWhy::Dispute,
                    });
                }
                true
            }
            // Confirmed or decided meanwhile.
            None if job.done[d.index] => true,
            // Its first tile was a liar's: this one is the unit's tile.
            None => false,
        }
    }

    /// Has `keep` keep a tile about to be accepted. When it cannot, the tile
    /// is refused, its unit queued again, and nothing more goes out until
    /// whoever keeps the tiles resumes the scheduler.
    fn keep_tile(
        &mut self,
        d: &Delivery<'_>,
        now: Instant,
        keep: &mut Keep<'_>,
    ) -> Result<Accepted, Refusal> {
        let job = self.jobs.get_mut(&d.job).expect("checked above");
        let held = job.sampled(self.verify_key, d.index);
        let frame = job.frame();
        let accepted = Accepted {
            job: d.job,
            frame,
            unit: d.index,
            worker: self.workers[&d.worker].name.clone(),
            latency: now.saturating_duration_since(d.issued),
            held,
        };
        if let Err(reason) = keep(&accepted, d.values) {
            // Nothing more goes out until whoever keeps the tiles resumes it.
            self.paused = true;
            self.leases.remove(&d.assignment);
            self.requeue(d.job, d.index);
            return Err(Refusal::Unstored {
                id: d.assignment,
                reason,
            });
        }
        Ok(accepted)
    }

    /// Stores an accepted tile in its frame's canvas (held for a second
    /// rendering when `held`), ends every lease of its unit, counts it for
    /// its worker, and completes the frame when it was the last.
    fn store_tile(&mut self, d: &Delivery<'_>, held: bool, render_cpu_micros: u64, now: Instant) {
        let job = self.jobs.get_mut(&d.job).expect("checked above");
        // Checked (the whole tile, above): store it.
        job.canvas.store(&d.unit, d.tile);
        job.done[d.index] = true;
        job.delivered[d.index] = Some(d.worker);
        if held {
            job.held.insert(d.index, (d.worker, d.values.to_vec()));
            job.to_check.push_back(d.index);
        }
        job.remaining -= 1;
        job.unit_cpu[d.index] = render_cpu_micros;
        job.pending.retain(|&u| u != d.index);
        self.leases
            .retain(|_, l| l.job != d.job || l.unit != d.index);
        let w = self.workers.get_mut(&d.worker).expect("checked above");
        w.credit(d.pixels as u64, render_cpu_micros, now);
        self.settle(d.job, now);
    }
}

/// A tile checked against the assignment it answers.
struct Delivery<'a> {
    /// The assignment.
    assignment: u64,
    /// The worker holding it.
    worker: u64,
    /// Its job.
    job: JobId,
    /// The unit's index.
    index: usize,
    /// The unit.
    unit: WorkUnit,
    /// The unit's pixels.
    pixels: usize,
    /// The tile as it came.
    values: &'a [u8],
    /// The tile's pixels, checked.
    tile: &'a [u8],
    /// When the assignment was handed out.
    issued: Instant,
    /// A second rendering of a unit whose tile is in (verified rendering).
    check: bool,
}

#[cfg(test)]
mod tests {
    use super::super::testing::*;

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
}
