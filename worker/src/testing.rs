//! What the unit tests share.

use std::time::Duration;

use crate::WorkerConfig;

/// A worker of one thread for `coordinator`, without token, TLS, tags or
/// faults, that stays (not `exit_when_done`) with a lease of 1 s.
pub(crate) fn config(coordinator: &str) -> WorkerConfig {
    WorkerConfig {
        coordinator: coordinator.into(),
        threads: 1,
        token: None,
        name: "test".into(),
        ca: None,
        exit_when_done: false,
        lease: Duration::from_secs(1),
        fault: None,
        shares_process: false,
        tags: Vec::new(),
        asset_cache_bytes: 0,
        idle_exit: None,
    }
}
