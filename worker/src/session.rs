//! The work loop over one registration: units pulled, started on the render
//! pool one ahead of the one rendering, and their tiles sent while the next
//! renders.

use std::sync::Arc;
use std::time::Duration;

use hypertexture_proto::pb::{self, GetWorkResult, get_work_result::Outcome};
use hypertexture_proto::{FailureKind, convert};
use tokio::sync::watch;
use tonic::{Code, Status};

use crate::assets::fetch_assets;
use crate::connection::{Client, is_refusal, said, shown, sleep_or_stop};
use crate::cpu::CallsCpu;
use crate::idle::Idle;
use crate::render::{RenderPool, Rendering, start_render};
use crate::tiles::{Sending, TileStream, send_tile};
use crate::withdrawals::Withdrawn;
use crate::{SceneCache, WorkerConfig, WorkerError, WorkerReport};

/// Why the connected loop ended.
pub(crate) enum Leave {
    /// Asked to stop, or the frame is done: return.
    Done,
    /// Lost the coordinator (or it forgot us): connect and register again.
    Reconnect,
}

/// What the work loop got when it asked for work.
enum Asked {
    Assignment(pb::Assignment),
    Wait(Duration),
    Finished,
}

/// Asks for the next unit, saying which scene this worker has built.
async fn ask(client: &mut Client, worker_id: &str, known_scene_hash: u64) -> Result<Asked, Status> {
    let work = client
        .get_work(pb::GetWorkParams {
            worker_id: worker_id.to_string(),
            known_scene_hash,
        })
        .await?
        .into_inner();
    Ok(Asked::from(work))
}

impl From<GetWorkResult> for Asked {
    fn from(work: GetWorkResult) -> Asked {
        match work.outcome {
            Some(Outcome::Assignment(a)) => Asked::Assignment(a),
            Some(Outcome::RetryAfterMs(ms)) => {
                Asked::Wait(Duration::from_millis(u64::from(ms).clamp(10, 5000)))
            }
            Some(Outcome::Finished(_)) => Asked::Finished,
            None => Asked::Wait(Duration::from_millis(500)),
        }
    }
}

/// Pulls and renders units over one connection. One unit is always assigned
/// ahead of the one rendering: it comes in the reply to the previous tile (or,
/// when there is none, from GetWork while the unit renders) and is queued on
/// the pool at once, so the render threads never wait for a round trip, nor
/// for this thread to hear that a unit is done.
pub(crate) async fn serve(
    config: &WorkerConfig,
    client: &mut Client,
    worker_id: &str,
    (pool, withdrawn, idle): (&RenderPool, &Arc<Withdrawn>, &mut Idle),
    scenes: &mut SceneCache,
    report: &mut WorkerReport,
    stop: &mut watch::Receiver<bool>,
) -> Result<Leave, WorkerError> {
    let calls_cpu = CallsCpu::new(pool.async_clock);
    // Opened now, so the first tile does not wait for it (if this fails, the
    // first tile retries).
    let stream = TileStream::open(client).await.ok();
    Session {
        config,
        client,
        worker_id,
        pool,
        withdrawn,
        idle,
        scenes,
        report,
        stop,
        calls_cpu,
        ahead: None,
        queued: None,
        sending: None,
        stream,
    }
    .run()
    .await
}

/// The work loop's state over one connection.
struct Session<'a> {
    config: &'a WorkerConfig,
    client: &'a mut Client,
    worker_id: &'a str,
    pool: &'a RenderPool,
    withdrawn: &'a Arc<Withdrawn>,
    /// How long there has been nothing to render (`--idle-exit`).
    idle: &'a mut Idle,
    scenes: &'a mut SceneCache,
    report: &'a mut WorkerReport,
    stop: &'a mut watch::Receiver<bool>,
    /// The async thread's CPU since the previous tile (statistics).
    calls_cpu: CallsCpu,
    /// Assigned and not started yet.
    ahead: Option<pb::Assignment>,
    /// Assigned and already queued on the pool behind the unit rendering, so
    /// the render threads go straight from one unit to the next.
    queued: Option<(pb::Assignment, Rendering)>,
    /// The previous tile, on its way while the next unit renders.
    sending: Option<Sending>,
    /// The open SubmitTiles stream, while no tile is on it.
    stream: Option<TileStream>,
}

/// What a step of the work loop came to.
enum Step<T> {
    /// Go on with this.
    Go(T),
    /// Start the loop over.
    Again,
    /// End the loop.
    Leave(Leave),
}

impl Session<'_> {
    /// The loop: start a unit (or take the one queued), look ahead while it
    /// renders, queue the next, and send the tile.
    async fn run(&mut self) -> Result<Leave, WorkerError> {
        loop {
            if self.stopping() {
                // Deliver the last tile; a unit assigned ahead (queued or not) goes
                // back with the goodbye.
                return self.deliver().await.map(|_| Leave::Done);
            }
            let (assignment, rendering) = match self.queued.take() {
                Some(started) => started,
                None => match self.start_next().await? {
                    Step::Go(started) => started,
                    Step::Again => continue,
                    Step::Leave(leave) => return Ok(leave),
                },
            };
            let lost_while_rendering = self.look_ahead().await?;
            if lost_while_rendering.is_none() && !self.stopping() {
                self.queue_ahead().await;
            }
            if let Some(leave) = self
                .finish(assignment, rendering, lost_while_rendering)
                .await?
            {
                return Ok(leave);
            }
        }
    }

    /// Whether the worker is asked to stop.
    fn stopping(&self) -> bool {
        *self.stop.borrow()
    }

    /// Waits for the tile in flight, if any ([`delivered`]).
    async fn deliver(&mut self) -> Result<Delivered, WorkerError> {
        delivered(
            self.config,
            self.sending.take(),
            self.report,
            &mut self.stream,
        )
        .await
    }

    /// Starts the unit assigned ahead, or one asked for. A unit that cannot
    /// be started is given back at once, with the reason: holding it would
    /// hang the frame (the heartbeat keeps the lease alive).
    async fn start_next(&mut self) -> Result<Step<(pb::Assignment, Rendering)>, WorkerError> {
        let assignment = match self.ahead.take() {
            Some(a) => a,
            None => match self.next_assignment().await? {
                Step::Go(a) => a,
                Step::Again => return Ok(Step::Again),
                Step::Leave(leave) => return Ok(Step::Leave(leave)),
            },
        };
        match self.start(&assignment).await {
            Ok(rendering) => {
                if self.report.first_unit_after.is_none() {
                    let after = self.report.started.map(|t| t.elapsed()).unwrap_or_default();
                    self.report.first_unit_after = Some(after);
                    tracing::info!("first unit started {} ms after start", after.as_millis());
                }
                Ok(Step::Go((assignment, rendering)))
            }
            Err((kind, reason)) => {
                if let Err(status) =
                    report_failure(self.client, self.worker_id, &assignment, kind, &reason).await
                {
                    let _ = self.deliver().await;
                    return lost(self.config, status).map(Step::Leave);
                }
                Ok(Step::Again)
            }
        }
    }

    /// Nothing ahead: the reply to the tile in flight may bring the next
    /// unit, or say that the frame is done; otherwise ask. A wait is waited
    /// out here.
    async fn next_assignment(&mut self) -> Result<Step<pb::Assignment>, WorkerError> {
        let asked = match self.deliver().await? {
            Delivered::Next(asked) => Ok(asked),
            Delivered::Lost(status) => Err(status),
            Delivered::Nothing => ask(self.client, self.worker_id, self.scenes.known()).await,
        };
        match asked {
            Ok(Asked::Assignment(a)) => {
                self.idle.worked();
                Ok(Step::Go(a))
            }
            Ok(Asked::Wait(d)) => Ok(
                if self.idle.expired() || sleep_or_stop(self.idle.cap(d), self.stop).await {
                    Step::Leave(Leave::Done)
                } else {
                    Step::Again
                },
            ),
            Ok(Asked::Finished) => Ok(
                if self.config.exit_when_done
                    || self.idle.expired()
                    || sleep_or_stop(self.idle.cap(Duration::from_secs(1)), self.stop).await
                {
                    Step::Leave(Leave::Done)
                } else {
                    Step::Again
                },
            ),
            Err(status) => lost(self.config, status).map(Step::Leave),
        }
    }

    /// Fetches the files of an assignment's scene this worker lacks and
    /// starts its render on the pool ([`start_render`]).
    async fn start(
        &mut self,
        assignment: &pb::Assignment,
    ) -> Result<Rendering, (FailureKind, String)> {
        let fetched = fetch_assets(self.client, self.worker_id, self.scenes, assignment).await?;
        start_render(
            assignment,
            (self.pool, self.withdrawn),
            (self.scenes, &fetched),
            self.config.fault,
        )
    }

    /// While a unit renders: the previous tile's reply brings the unit after
    /// this one; without one (the first unit, or a refused tile), ask. The
    /// status of a connection lost meanwhile is returned, to leave on once
    /// the unit is done.
    async fn look_ahead(&mut self) -> Result<Option<Status>, WorkerError> {
        let mut lost_while_rendering = None;
        match self.deliver().await? {
            Delivered::Next(Asked::Assignment(a)) => self.ahead = Some(a),
            Delivered::Next(Asked::Wait(_) | Asked::Finished) => {}
            Delivered::Lost(status) => lost_while_rendering = Some(status),
            Delivered::Nothing if !self.stopping() => {
                match ask(self.client, self.worker_id, self.scenes.known()).await {
                    Ok(Asked::Assignment(a)) => self.ahead = Some(a),
                    Ok(Asked::Wait(_) | Asked::Finished) => {}
                    Err(status) => lost_while_rendering = Some(status),
                }
            }
            Delivered::Nothing => {}
        }
        Ok(lost_while_rendering)
    }

    /// Queues the unit ahead on the pool behind the one rendering: the render
    /// threads take it up the moment they are free, without waiting for this
    /// thread to hear that the current unit is done. A new scene's files are
    /// fetched while the current unit renders. One that cannot be started
    /// (or whose files fail to arrive) stays ahead, and is tried again, or
    /// given back with the reason, when its turn comes.
    async fn queue_ahead(&mut self) {
        if let Some(a) = self.ahead.take() {
            match self.start(&a).await {
                Ok(rendering) => self.queued = Some((a, rendering)),
                Err(_) => self.ahead = Some(a),
            }
        }
    }

    /// Waits for the unit's render and sends its tile. A unit taken back
    /// while it rendered is counted and dropped; one whose render failed is
    /// given back with the reason. Returns how to leave when the connection
    /// was lost.
    async fn finish(
        &mut self,
        assignment: pb::Assignment,
        rendering: Rendering,
        lost_while_rendering: Option<Status>,
    ) -> Result<Option<Leave>, WorkerError> {
        let rendered = rendering
            .await
            .unwrap_or_else(|_| Err("the render task ended without a result".into()));
        self.idle.worked();
        let (unit, pixels, cpu) = match rendered {
            Ok(Some(tile)) => tile,
            Ok(None) => {
                // Taken back while it rendered (or before it started): no
                // tile, the next unit.
                self.report.withdrawn += 1;
                tracing::debug!(
                    "dropped assignment {}: the coordinator took it back",
                    assignment.assignment_id
                );
                return self.leave_if_lost(lost_while_rendering);
            }
            Err(reason) => {
                if lost_while_rendering.is_some() {
                    return self.leave_if_lost(lost_while_rendering);
                }
                let failed = report_failure(
                    self.client,
                    self.worker_id,
                    &assignment,
                    FailureKind::Render,
                    &reason,
                )
                .await;
                return self.leave_if_lost(failed.err());
            }
        };
        let tile = pb::SubmitTileParams {
            worker_id: self.worker_id.to_string(),
            assignment_id: assignment.assignment_id,
            unit: Some(convert::unit_to_wire(&unit)),
            pixels,
            render_cpu_micros: cpu,
            calls_cpu_micros: self.calls_cpu.since_last(),
            // The unit after the one ahead, to render while the next tile travels.
            want_next: !self.stopping() && lost_while_rendering.is_none(),
            known_scene_hash: self.scenes.known(),
        };
        self.sending = Some(send_tile(self.client, self.stream.take(), tile));
        if lost_while_rendering.is_some() {
            let _ = self.deliver().await;
        }
        self.leave_if_lost(lost_while_rendering)
    }

    /// How to leave after `status`, a failed call ([`lost`]); nothing to do
    /// without one.
    fn leave_if_lost(&self, status: Option<Status>) -> Result<Option<Leave>, WorkerError> {
        status.map(|status| lost(self.config, status)).transpose()
    }
}

/// Gives an assignment back to the coordinator with the reason it could not be
/// rendered (logged here too). Errors are the call's own (connection lost, or
/// the coordinator forgot this worker).
async fn report_failure(
    client: &mut Client,
    worker_id: &str,
    assignment: &pb::Assignment,
    kind: FailureKind,
    reason: &str,
) -> Result<(), Status> {
    tracing::error!(
        "cannot render assignment {} ({kind}): {}",
        assignment.assignment_id,
        shown(reason)
    );
    client
        .report_failure(pb::ReportFailureParams {
            worker_id: worker_id.to_string(),
            assignment_id: assignment.assignment_id,
            kind: convert::failure_kind_to_wire(kind) as i32,
            reason: reason.to_string(),
        })
        .await
        .map(|_| ())
}

/// What became of a tile in flight.
enum Delivered {
    /// No tile was in flight, it was refused, or the reply carried no next unit.
    Nothing,
    /// Delivered; the reply's next unit (or wait, or finished).
    Next(Asked),
    /// The connection failed, or the coordinator forgot this worker: reconnect.
    Lost(Status),
}

/// Waits for a tile in flight. A refused tile is logged (the unit was taken back
/// or is malformed: not fatal); only refusals of the worker itself are errors.
async fn delivered(
    config: &WorkerConfig,
    sending: Option<Sending>,
    report: &mut WorkerReport,
    stream: &mut Option<TileStream>,
) -> Result<Delivered, WorkerError> {
    let Some(task) = sending else {
        return Ok(Delivered::Nothing);
    };
    let outcome = task.await.map(|(back, result)| {
        *stream = back;
        result
    });
    Ok(match outcome {
        Ok(Ok(result)) => {
            if result.accepted {
                report.units += 1;
            }
            result
                .next
                .map_or(Delivered::Nothing, |next| Delivered::Next(next.into()))
        }
        Ok(Err(status))
            if status.code() == Code::InvalidArgument
                || status.code() == Code::FailedPrecondition =>
        {
            tracing::warn!("tile refused: {}", said(&status));
            Delivered::Nothing
        }
        Ok(Err(status)) => {
            if is_refusal(&status) {
                return Err(WorkerError::Refused(said(&status)));
            }
            tracing::warn!(
                "a tile was not delivered to {}: {}",
                config.coordinator,
                said(&status)
            );
            Delivered::Lost(status)
        }
        Err(e) => {
            tracing::error!("the tile sender failed: {e}");
            Delivered::Nothing
        }
    })
}

/// What to do after a failed call: give up on refusal, otherwise reconnect.
fn lost(config: &WorkerConfig, status: Status) -> Result<Leave, WorkerError> {
    if is_refusal(&status) {
        return Err(WorkerError::Refused(said(&status)));
    }
    if status.code() == Code::NotFound {
        tracing::info!("the coordinator does not know this worker any more: registering again");
    } else {
        tracing::warn!("lost {}: {}", config.coordinator, said(&status));
    }
    Ok(Leave::Reconnect)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn config() -> WorkerConfig {
        crate::testing::config("http://127.0.0.1:1")
    }

    fn work(outcome: Option<Outcome>) -> Asked {
        Asked::from(GetWorkResult { outcome })
    }

    fn wait_of(asked: Asked) -> Duration {
        match asked {
            Asked::Wait(d) => d,
            _ => panic!("expected a wait"),
        }
    }

    #[test]
    fn a_wait_asked_for_is_kept_between_10_ms_and_5_s() {
        let after = |ms| wait_of(work(Some(Outcome::RetryAfterMs(ms))));
        assert_eq!(after(0), Duration::from_millis(10));
        assert_eq!(after(250), Duration::from_millis(250));
        assert_eq!(after(u32::MAX), Duration::from_secs(5));
        assert_eq!(wait_of(work(None)), Duration::from_millis(500));
        assert!(matches!(
            work(Some(Outcome::Finished(Default::default()))),
            Asked::Finished
        ));
        let a = pb::Assignment {
            assignment_id: 9,
            ..Default::default()
        };
        assert!(matches!(
            work(Some(Outcome::Assignment(a))),
            Asked::Assignment(pb::Assignment {
                assignment_id: 9,
                ..
            })
        ));
    }

    #[test]
    fn a_lost_call_reconnects_unless_the_worker_is_refused() {
        let config = config();
        for code in [Code::Unavailable, Code::NotFound, Code::Internal] {
            assert!(
                matches!(lost(&config, Status::new(code, "")), Ok(Leave::Reconnect)),
                "{code:?}"
            );
        }
        match lost(&config, Status::unauthenticated("bad\ntoken")) {
            Err(WorkerError::Refused(message)) => assert_eq!(message, "bad\\ntoken"),
            _ => panic!("expected a refusal"),
        }
    }

    /// A tile in flight whose reply is `reply`.
    fn sending(reply: Result<pb::SubmitTileResult, Status>) -> Option<Sending> {
        Some(tokio::spawn(async move { (None, reply) }))
    }

    #[tokio::test]
    async fn a_delivered_tile_is_counted_and_brings_the_next_unit() {
        let config = config();
        let mut report = WorkerReport::default();
        let mut stream = None;
        let none = delivered(&config, None, &mut report, &mut stream).await;
        assert!(matches!(none, Ok(Delivered::Nothing)));

        let next = pb::SubmitTileResult {
            accepted: true,
            next: Some(GetWorkResult {
                outcome: Some(Outcome::Finished(Default::default())),
            }),
        };
        let got = delivered(&config, sending(Ok(next)), &mut report, &mut stream).await;
        assert!(matches!(got, Ok(Delivered::Next(Asked::Finished))));
        assert_eq!(report.units, 1);

        let duplicate = pb::SubmitTileResult {
            accepted: false,
            next: None,
        };
        let got = delivered(&config, sending(Ok(duplicate)), &mut report, &mut stream).await;
        assert!(matches!(got, Ok(Delivered::Nothing)));
        assert_eq!(report.units, 1, "a duplicate is not counted");
    }

    #[tokio::test]
    async fn a_refused_tile_is_not_fatal_but_a_refused_worker_is() {
        let config = config();
        let mut report = WorkerReport::default();
        let mut stream = None;
        let refused = sending(Err(Status::invalid_argument("not this worker's unit")));
        let got = delivered(&config, refused, &mut report, &mut stream).await;
        assert!(matches!(got, Ok(Delivered::Nothing)));

        let gone = sending(Err(Status::unavailable("connection reset")));
        let got = delivered(&config, gone, &mut report, &mut stream).await;
        assert!(matches!(got, Ok(Delivered::Lost(s)) if s.code() == Code::Unavailable));

        let denied = sending(Err(Status::permission_denied("wrong token")));
        let got = delivered(&config, denied, &mut report, &mut stream).await;
        assert!(matches!(got, Err(WorkerError::Refused(m)) if m == "wrong token"));
        assert_eq!(report.units, 0);
    }
}
