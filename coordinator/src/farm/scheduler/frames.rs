//! A job's frames, rendered one after another: the tile that completes a
//! frame moves its image to [`Scheduler::take_completed`] and starts the job's
//! next frame at once. Assignment ids are unique over the scheduler's life; a
//! late tile of a frame that is complete (or of a job that has ended) is valid
//! and unused.

use std::time::{Duration, Instant};

use super::state::{CompletedFrame, JobId, Scheduler};

impl Scheduler {
    /// Completes the job's frame when every unit is in and confirmed.
    pub(super) fn settle(&mut self, job_id: JobId, now: Instant) {
        if self
            .jobs
            .get(&job_id)
            .is_some_and(|j| j.current < j.plan.frames.len() && j.frame_settled())
        {
            self.complete_frame(job_id, now);
        }
    }

    /// Moves the job's complete frame's image out and starts its next frame,
    /// if any: a complete frame to render again first, then the plan's next.
    pub(super) fn complete_frame(&mut self, job_id: JobId, now: Instant) {
        let Some(job) = self.jobs.get_mut(&job_id) else {
            return;
        };
        let n = job.plan.units.len();
        self.completed.push(CompletedFrame {
            job: job_id,
            frame: job.frame(),
            // A blank canvas of the same size stays: late duplicates are still
            // checked against it.
            image: job.canvas.take(),
            unit_costs: std::mem::replace(&mut job.unit_cpu, vec![0; n]),
            unit_calls: std::mem::replace(&mut job.unit_calls, vec![0; n]),
            render_time: job
                .frame_started
                .take()
                .map_or(Duration::ZERO, |t| now.saturating_duration_since(t)),
        });
        // Duplicates still out belong to the frame just completed.
        self.leases.retain(|_, l| l.job != job_id);
        let index = job.current;
        // A frame rendered again holds only the tiles of this rendering.
        for frames in job.frames_delivered.values_mut() {
            frames.remove(&index);
        }
        for w in std::mem::replace(&mut job.delivered, vec![None; n])
            .into_iter()
            .flatten()
        {
            job.frames_delivered.entry(w).or_default().insert(index);
        }
        job.held.clear();
        job.to_check.clear();
        job.disputed.clear();
        job.pass += 1;
        if let Some(again) = job.redo.pop_first() {
            job.resume_at.get_or_insert(index + 1);
            job.current = again;
        } else if let Some(next) = job.resume_at.take() {
            job.current = next;
        } else {
            job.current += 1;
        }
        if job.current >= job.plan.frames.len() {
            // Past the last frame, the job is finished: late tiles are unused.
            job.remaining = 0;
            job.pending.clear();
            return;
        }
        job.pending = (0..n).collect();
        job.done = vec![false; n];
        job.remaining = n;
        job.failures = vec![Vec::new(); n];
    }

    /// Whether a frame is complete and not yet taken.
    pub fn has_completed(&self) -> bool {
        !self.completed.is_empty()
    }

    /// The frames completed since the last call, in order.
    pub fn take_completed(&mut self) -> Vec<CompletedFrame> {
        std::mem::take(&mut self.completed)
    }
}

#[cfg(test)]
mod tests {
    use super::super::testing::*;

    #[test]
    fn a_sequence_starts_the_next_frame_with_the_tile_that_completes_one() {
        let now = Instant::now();
        let units = work_units(8, 8, 8, 4096);
        let n = units.len();
        let mut s = Scheduler::new(units, 8, 8, PixelFormat::Samples, Duration::from_secs(5))
            .with_frames(FrameRange::new(3, 4));
        let (a, b) = (s.register("a", 1, now), s.register("b", 1, now));
        let mut first_frame = Vec::new();
        for _ in 0..n {
            match s.next(&a, now).unwrap() {
                Next::Assign {
                    assignment_id,
                    unit,
                    frame,
                    ..
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
}
