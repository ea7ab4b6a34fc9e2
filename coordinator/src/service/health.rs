//! Whether the service's store writes: what `status`, `/metrics` and
//! `/readyz` report, and the one WARN line a minute while it does not.
//!
//! Every store write of the service reports its outcome here
//! ([`Health::outcome`]). The first failure is logged at once, later ones are
//! counted and summed up in one line a minute; the service probes the store
//! every [`PROBE_EVERY`] while it fails ([`Health::probe_due`]), and the
//! first success (a probe's or a write's) ends the failure with one INFO
//! line. Nothing here takes another lock: it is called with the farm's state
//! or the store locked.

use std::sync::Mutex;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::{Duration, Instant};

use crate::service::store::StoreError;

/// How often a store that fails is probed.
pub const PROBE_EVERY: Duration = Duration::from_secs(1);

/// At most one WARN line this often while the store fails.
pub const WARN_EVERY: Duration = Duration::from_secs(60);

/// The store's failure in progress.
#[derive(Clone, Debug)]
struct Failing {
    since: Instant,
    reason: String,
    full: bool,
    last_probe: Instant,
}

/// The failure in progress, and the WARN lines' pace (kept across failures,
/// so a store that fails on and off still logs one line a minute).
#[derive(Debug, Default)]
struct State {
    failing: Option<Failing>,
    last_warn: Option<Instant>,
    /// Writes failed since the last WARN line.
    unreported: u64,
}

/// The store's health, shared by the service's threads.
#[derive(Debug, Default)]
pub struct Health {
    state: Mutex<State>,
    /// Stored tiles dropped because their bytes failed their checksum.
    pub tiles_dropped: AtomicU64,
}

impl Health {
    fn lock(&self) -> std::sync::MutexGuard<'_, State> {
        self.state.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// Notes a write's outcome; `what` names the write for the log.
    pub fn outcome<T>(
        &self,
        result: Result<T, StoreError>,
        what: impl FnOnce() -> String,
    ) -> Result<T, StoreError> {
        match &result {
            Ok(_) => self.wrote(),
            Err(e) => self.failed(e, what),
        }
        result
    }

    /// A write succeeded: a failure in progress ends.
    pub fn wrote(&self) {
        let ended = self.lock().failing.take();
        if let Some(f) = ended {
            tracing::info!(
                "the store writes again after {:.0} s: tiles are accepted and jobs taken again",
                f.since.elapsed().as_secs_f64()
            );
        }
    }

    fn failed(&self, e: &StoreError, what: impl FnOnce() -> String) {
        let now = Instant::now();
        let mut state = self.lock();
        let state = &mut *state;
        let since = match &state.failing {
            Some(f) => f.since,
            None => now,
        };
        let started = state.failing.is_none();
        state.failing = Some(Failing {
            since,
            reason: e.to_string(),
            full: e.is_full(),
            last_probe: state.failing.as_ref().map_or(now, |f| f.last_probe),
        });
        let due = state
            .last_warn
            .is_none_or(|t| now.saturating_duration_since(t) >= WARN_EVERY);
        if !due {
            state.unreported += 1;
            return;
        }
        if started && state.unreported == 0 {
            tracing::warn!(
                "the store cannot write ({}: {e}): tiles are refused and handed out again, \
                 submissions refused, until it can (probed every {} s; one line a minute \
                 while it fails)",
                what(),
                PROBE_EVERY.as_secs()
            );
        } else {
            tracing::warn!(
                "the store still cannot write ({} writes failed in the last minute, this one \
                 for {:.0} s): {e}",
                state.unreported + 1,
                now.saturating_duration_since(since).as_secs_f64()
            );
        }
        state.last_warn = Some(now);
        state.unreported = 0;
    }

    /// Whether the store writes (its last write succeeded).
    pub fn writable(&self) -> bool {
        self.lock().failing.is_none()
    }

    /// Why the store does not write, and whether for lack of room.
    pub fn failure(&self) -> Option<(String, bool)> {
        self.lock().failing.as_ref().map(|f| {
            (
                format!(
                    "the store cannot write, for {:.0} s: {}",
                    f.since.elapsed().as_secs_f64(),
                    f.reason
                ),
                f.full,
            )
        })
    }

    /// Whether a failing store is due for a probe (and notes the probe).
    pub fn probe_due(&self, now: Instant) -> bool {
        match &mut self.lock().failing {
            Some(f) if now.saturating_duration_since(f.last_probe) >= PROBE_EVERY => {
                f.last_probe = now;
                true
            }
            _ => false,
        }
    }

    /// Counts tiles dropped for a failed checksum.
    pub fn dropped(&self, n: u64) {
        self.tiles_dropped.fetch_add(n, Ordering::Relaxed);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn full() -> StoreError {
        StoreError::Sqlite {
            file: "farm.sqlite".into(),
            source: rusqlite::Error::SqliteFailure(
                rusqlite::ffi::Error::new(rusqlite::ffi::SQLITE_FULL),
                None,
            ),
        }
    }

    #[test]
    fn a_failure_lasts_until_a_write_succeeds() {
        let h = Health::default();
        assert!(h.writable());
        assert!(h.failure().is_none());
        let r: Result<(), _> = h.outcome(Err(full()), || "a tile".into());
        assert!(r.is_err());
        assert!(!h.writable());
        let (why, is_full) = h.failure().expect("failing");
        assert!(why.contains("farm.sqlite"), "{why}");
        assert!(is_full);
        // Probed at most once a PROBE_EVERY.
        let later = Instant::now() + PROBE_EVERY;
        assert!(h.probe_due(later));
        assert!(!h.probe_due(later));
        assert_eq!(h.outcome(Ok(5), || "a probe".into()).ok(), Some(5));
        assert!(h.writable());
        assert!(!h.probe_due(later + PROBE_EVERY));
    }
}
