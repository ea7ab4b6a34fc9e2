//! The worker's life: connect, register, serve until the registration ends,
//! and reconnect with backoff, until asked to stop or, for an
//! `exit_when_done` worker, until the coordinator has been gone a lease.

use std::sync::Arc;
use std::time::{Duration, Instant};

use hypertexture_proto::pb;
use tokio::sync::watch;
use tonic::transport::Endpoint;

use crate::connection::{
    self, Auth, Backoff, Client, endpoint, error_chain, is_refusal, said, shown, sleep_or_stop,
};
use crate::idle::Idle;
use crate::register::{arithmetic_digest, goodbye, heartbeat, register};
use crate::render::RenderPool;
use crate::session::{Leave, serve};
use crate::withdrawals::{Withdrawn, listen_for_withdrawals};
use crate::{SceneCache, WorkerConfig, WorkerError, WorkerReport};

/// The worker: connect, register, pull and render units until told to stop.
pub async fn run(
    config: WorkerConfig,
    mut stop: watch::Receiver<bool>,
) -> Result<WorkerReport, WorkerError> {
    let started = std::time::Instant::now();
    let endpoint = endpoint(&config)?;
    let auth = Auth::bearer(&config)?;
    let pool = RenderPool::new(config.threads)?;
    let coordinator = Coordinator {
        config: &config,
        endpoint,
        auth,
        arithmetic_digest: arithmetic_digest(&pool, config.fault).await?,
    };
    let mut report = WorkerReport {
        started: Some(started),
        ..WorkerReport::default()
    };
    let mut scenes = SceneCache::new(config.asset_cache_bytes);
    let mut unreachable = Unreachable::new(&config);
    let mut idle = Idle::new(config.idle_exit);
    loop {
        if *stop.borrow() || idle.expired() {
            return Ok(report);
        }
        if let Some(e) = unreachable.gone() {
            return Err(e);
        }
        let (mut client, registered) = match coordinator.register(&mut unreachable).await? {
            Registered::Yes(registered) => *registered,
            Registered::RetryIn(wait) => {
                if sleep_or_stop(idle.cap(wait), &mut stop).await {
                    return Ok(report);
                }
                continue;
            }
        };
        let registration = Registration {
            config: &config,
            pool: &pool,
            worker_id: &registered.worker_id,
            heartbeat: Duration::from_millis(u64::from(registered.heartbeat_ms.max(50))),
        };
        let left = registration
            .serve(
                &mut client,
                (&mut scenes, &mut idle),
                &mut report,
                &mut stop,
            )
            .await?;
        match left {
            Leave::Done => return Ok(report),
            Leave::Reconnect => {
                if sleep_or_stop(idle.cap(unreachable.lost()), &mut stop).await {
                    return Ok(report);
                }
            }
        }
    }
}

/// The coordinator as this worker dials it, and what it registers with.
struct Coordinator<'a> {
    config: &'a WorkerConfig,
    endpoint: Endpoint,
    auth: Auth,
    /// This worker's known-answer probe digest.
    arithmetic_digest: u64,
}

/// What came of an attempt to register.
enum Registered {
    /// Registered: the client, and what the coordinator answered.
    Yes(Box<(Client, pb::RegisterResult)>),
    /// Not reached, or no answer: try again after this wait.
    RetryIn(Duration),
}

impl Coordinator<'_> {
    /// Connects and registers. A coordinator out of reach is retried after
    /// the backoff; a refusal of this worker is an error.
    async fn register(&self, unreachable: &mut Unreachable<'_>) -> Result<Registered, WorkerError> {
        let config = self.config;
        let channel = match self.endpoint.connect().await {
            Ok(c) => c,
            Err(e) => {
                let wait = unreachable.not_connected();
                tracing::warn!(
                    "cannot reach {}: {}; retrying in {wait:?}",
                    config.coordinator,
                    error_chain(&e)
                );
                return Ok(Registered::RetryIn(wait));
            }
        };
        unreachable.reached = true;
        let mut client = connection::client(channel, self.auth.clone());
        match register(&mut client, config, self.arithmetic_digest).await {
            Ok(registered) => {
                unreachable.registered();
                tracing::info!(
                    "registered with {} as {} ({} threads)",
                    config.coordinator,
                    shown(&registered.worker_id),
                    config.threads
                );
                Ok(Registered::Yes(Box::new((client, registered))))
            }
            Err(status) if is_refusal(&status) => Err(WorkerError::Refused(said(&status))),
            Err(status) => {
                // It took the connection, so it was reached: a coordinator
                // gone before it answered counts against the lease.
                let wait = unreachable.lost();
                tracing::warn!(
                    "cannot register with {}: {}; retrying in {wait:?}",
                    config.coordinator,
                    said(&status)
                );
                Ok(Registered::RetryIn(wait))
            }
        }
    }
}

/// One registration with the coordinator: what the work loop runs under.
struct Registration<'a> {
    config: &'a WorkerConfig,
    pool: &'a RenderPool,
    /// The id the coordinator gave this worker.
    worker_id: &'a str,
    /// How often to heartbeat.
    heartbeat: Duration,
}

impl Registration<'_> {
    /// Serves units until asked to stop, the frame is done (then says
    /// goodbye) or the coordinator is lost; the heartbeat and the listener
    /// for withdrawals run meanwhile, and end with it.
    async fn serve(
        &self,
        client: &mut Client,
        (scenes, idle): (&mut SceneCache, &mut Idle),
        report: &mut WorkerReport,
        stop: &mut watch::Receiver<bool>,
    ) -> Result<Leave, WorkerError> {
        let heartbeat = tokio::spawn(heartbeat(
            client.clone(),
            self.worker_id.to_string(),
            self.heartbeat,
        ));
        let withdrawn = Arc::new(Withdrawn::default());
        let listening = tokio::spawn(listen_for_withdrawals(
            client.clone(),
            self.worker_id.to_string(),
            Arc::clone(&withdrawn),
        ));
        let left = serve(
            self.config,
            client,
            self.worker_id,
            (self.pool, &withdrawn, idle),
            scenes,
            report,
            stop,
        )
        .await;
        heartbeat.abort();
        listening.abort();
        if let Ok(Leave::Done) = left {
            goodbye(client, self.config, self.worker_id).await;
            tracing::info!("leaving after {} units", report.units);
        }
        left
    }
}

/// How long the coordinator has been out of reach, and how long to wait
/// before the next attempt: an exponential backoff that an `exit_when_done`
/// worker cuts to the rest of its lease.
struct Unreachable<'a> {
    config: &'a WorkerConfig,
    backoff: Backoff,
    /// Since when the coordinator this worker had reached has been
    /// unreachable.
    since: Option<Instant>,
    /// Whether a connection to the coordinator was ever made.
    reached: bool,
}

impl<'a> Unreachable<'a> {
    fn new(config: &'a WorkerConfig) -> Unreachable<'a> {
        Unreachable {
            config,
            backoff: Backoff::new(),
            since: None,
            reached: false,
        }
    }

    /// Why an `exit_when_done` worker gives up: its coordinator has been
    /// unreachable for the whole lease.
    fn gone(&self) -> Option<WorkerError> {
        match self.since {
            Some(t) if self.config.exit_when_done && t.elapsed() >= self.config.lease => {
                Some(WorkerError::CoordinatorGone {
                    url: self.config.coordinator.clone(),
                    secs: t.elapsed().as_secs_f64(),
                })
            }
            _ => None,
        }
    }

    /// The wait after a connection failed. It counts against the lease only
    /// once the coordinator was reached: one not up yet is waited for.
    fn not_connected(&mut self) -> Duration {
        if self.reached {
            self.since.get_or_insert_with(Instant::now);
        }
        self.retry()
    }

    /// The wait after the coordinator was lost (or never answered a
    /// connection it took): counted against the lease.
    fn lost(&mut self) -> Duration {
        self.since.get_or_insert_with(Instant::now);
        self.retry()
    }

    /// The coordinator answered: backoff and lease start afresh.
    fn registered(&mut self) {
        self.backoff.reset();
        self.since = None;
    }

    /// The next backoff; an `exit_when_done` worker waits no longer than
    /// the rest of its lease.
    fn retry(&mut self) -> Duration {
        let wait = self.backoff.next();
        match self.since {
            Some(t) if self.config.exit_when_done => wait
                .min(self.config.lease.saturating_sub(t.elapsed()))
                .max(Duration::from_millis(10)),
            _ => wait,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn config(exit_when_done: bool, lease: Duration) -> WorkerConfig {
        WorkerConfig {
            exit_when_done,
            lease,
            ..crate::testing::config("http://127.0.0.1:1")
        }
    }

    #[test]
    fn a_coordinator_never_reached_is_waited_for_without_end() {
        let config = config(true, Duration::ZERO);
        let mut unreachable = Unreachable::new(&config);
        assert_eq!(unreachable.not_connected(), Duration::from_millis(100));
        assert_eq!(unreachable.not_connected(), Duration::from_millis(200));
        assert!(unreachable.since.is_none());
        assert!(unreachable.gone().is_none());
    }

    #[test]
    fn a_coordinator_reached_then_lost_for_the_lease_is_gone() {
        let config = config(true, Duration::ZERO);
        let mut unreachable = Unreachable::new(&config);
        unreachable.reached = true;
        // The rest of a lease of zero: the shortest wait.
        assert_eq!(unreachable.not_connected(), Duration::from_millis(10));
        match unreachable.gone() {
            Some(WorkerError::CoordinatorGone { url, .. }) => assert_eq!(url, config.coordinator),
            other => panic!("expected CoordinatorGone, got {other:?}"),
        }
        unreachable.registered();
        assert!(unreachable.gone().is_none());
        assert_eq!(unreachable.lost(), Duration::from_millis(10));
    }

    #[test]
    fn a_worker_that_stays_waits_the_whole_backoff() {
        let config = config(false, Duration::ZERO);
        let mut unreachable = Unreachable::new(&config);
        let waits: Vec<u128> = (0..8).map(|_| unreachable.lost().as_millis()).collect();
        assert_eq!(waits, [100, 200, 400, 800, 1600, 3200, 5000, 5000]);
        assert!(unreachable.gone().is_none(), "only exit_when_done leaves");
        unreachable.registered();
        assert_eq!(unreachable.lost(), Duration::from_millis(100));
    }

    #[test]
    fn an_exit_when_done_worker_waits_no_longer_than_its_lease() {
        let config = config(true, Duration::from_secs(3600));
        let mut unreachable = Unreachable::new(&config);
        assert_eq!(unreachable.lost(), Duration::from_millis(100));
        assert!(unreachable.gone().is_none(), "within the lease");
    }
}
