//! What a worker says to the coordinator outside its work: the known-answer
//! probe it registers with, its registration, its heartbeat and its goodbye.

use std::time::Duration;

use hypertexture_proto::{PROTOCOL_VERSION, pb};
use tokio::sync::oneshot;
use tonic::Status;

use crate::connection::Client;
use crate::cpu::process_cpu_micros;
use crate::render::{RenderPool, panic_message};
use crate::{Fault, WorkerConfig, WorkerError};

/// The probe digest this worker registers with: this build's, or one bit
/// off it under [`Fault::Arithmetic`].
pub(crate) async fn arithmetic_digest(
    pool: &RenderPool,
    fault: Option<Fault>,
) -> Result<u64, WorkerError> {
    match fault {
        Some(Fault::Arithmetic) => Ok(probe(pool).await? ^ 1),
        _ => probe(pool).await,
    }
}

/// This build's known-answer probe digest ([`hypertexture::render::probe`]), computed on
/// the render pool: the coordinator admits a worker only when it matches its own.
async fn probe(pool: &RenderPool) -> Result<u64, WorkerError> {
    let (done, digest) = oneshot::channel();
    pool.threads.spawn(move || {
        let started = std::time::Instant::now();
        let digest = std::panic::catch_unwind(hypertexture::render::probe::arithmetic_digest);
        if let Ok(Ok(d)) = &digest {
            tracing::debug!(
                "known-answer probe: digest {d:016x} in {:?}",
                started.elapsed()
            );
        }
        let _ = done.send(digest);
    });
    match digest.await {
        Ok(Ok(Ok(digest))) => Ok(digest),
        Ok(Ok(Err(e))) => Err(WorkerError::Probe(e.to_string())),
        Ok(Err(payload)) => Err(WorkerError::Probe(format!(
            "it panicked: {}",
            panic_message(&*payload)
        ))),
        Err(_) => Err(WorkerError::Probe("the render pool dropped it".into())),
    }
}

/// Registers this worker (its protocol version, threads, probe digest and
/// tags) with the coordinator `client` reaches.
pub(crate) async fn register(
    client: &mut Client,
    config: &WorkerConfig,
    arithmetic_digest: u64,
) -> Result<pb::RegisterResult, Status> {
    client
        .register(pb::RegisterParams {
            protocol_version: PROTOCOL_VERSION,
            name: config.name.clone(),
            threads: config.threads as u32,
            arithmetic_digest,
            tags: config.tags.clone(),
        })
        .await
        .map(tonic::Response::into_inner)
}

/// Beats every `every` until aborted. Failures are left to the work loop to notice.
pub(crate) async fn heartbeat(mut client: Client, worker_id: String, every: Duration) {
    let mut tick = tokio::time::interval(every);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    loop {
        tick.tick().await;
        let _ = client
            .heartbeat(pb::HeartbeatParams {
                worker_id: worker_id.clone(),
            })
            .await;
    }
}

/// Says goodbye, with the process's CPU time (none when the worker shares its
/// process). The coordinator's answer does not matter: the worker is leaving.
pub(crate) async fn goodbye(client: &mut Client, config: &WorkerConfig, worker_id: &str) {
    let _ = client
        .goodbye(pb::GoodbyeParams {
            worker_id: worker_id.to_string(),
            process_cpu_micros: if config.shares_process {
                0
            } else {
                process_cpu_micros()
            },
        })
        .await;
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test]
    async fn the_digest_is_the_probes_and_an_arithmetic_fault_flips_one_bit() {
        let pool = RenderPool::new(1).unwrap();
        let digest = arithmetic_digest(&pool, None).await.unwrap();
        assert_eq!(
            digest,
            hypertexture::render::probe::arithmetic_digest().unwrap()
        );
        let faulty = arithmetic_digest(&pool, Some(Fault::Arithmetic))
            .await
            .unwrap();
        assert_eq!(faulty, digest ^ 1);
        assert_eq!(
            arithmetic_digest(&pool, Some(Fault::Panic)).await.unwrap(),
            digest
        );
    }
}
