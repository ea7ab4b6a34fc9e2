//! `--idle-exit`: how long this worker has had nothing to render, whether
//! the coordinator had no unit for it or could not be reached (never, or no
//! longer), and whether that is long enough to leave.

use std::time::{Duration, Instant};

/// The time since this worker last had work, against its limit.
#[derive(Debug)]
pub(crate) struct Idle {
    /// Leave after this long without work (`None`: never).
    limit: Option<Duration>,
    /// Since when there has been nothing to render: the start, or the last
    /// unit assigned or rendered.
    since: Instant,
}

impl Idle {
    /// Idle from now, for at most `limit`.
    pub(crate) fn new(limit: Option<Duration>) -> Idle {
        Idle {
            limit,
            since: Instant::now(),
        }
    }

    /// A unit was assigned, or its render ended: idle from now on.
    pub(crate) fn worked(&mut self) {
        self.since = Instant::now();
    }

    /// Whether the worker has been idle for its whole limit; says so in the
    /// log when it has.
    pub(crate) fn expired(&self) -> bool {
        match self.limit {
            Some(limit) if self.since.elapsed() >= limit => {
                tracing::info!(
                    "no work for {:.0} s (--idle-exit): leaving",
                    self.since.elapsed().as_secs_f64()
                );
                true
            }
            _ => false,
        }
    }

    /// `wait`, cut to the rest of the limit (at least 10 ms), so that an
    /// idle worker leaves on time rather than after its next retry.
    pub(crate) fn cap(&self, wait: Duration) -> Duration {
        match self.limit {
            Some(limit) => wait
                .min(limit.saturating_sub(self.since.elapsed()))
                .max(Duration::from_millis(10)),
            None => wait,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn without_a_limit_a_worker_is_never_idle_enough_to_leave() {
        let idle = Idle::new(None);
        assert!(!idle.expired());
        assert_eq!(idle.cap(Duration::from_secs(5)), Duration::from_secs(5));
    }

    #[test]
    fn a_worker_idle_for_its_limit_leaves_and_work_starts_it_afresh() {
        let mut idle = Idle::new(Some(Duration::ZERO));
        assert!(idle.expired());
        assert_eq!(idle.cap(Duration::from_secs(5)), Duration::from_millis(10));
        idle.limit = Some(Duration::from_secs(3600));
        idle.since = Instant::now() - Duration::from_secs(3599);
        assert!(!idle.expired());
        assert!(idle.cap(Duration::from_secs(5)) <= Duration::from_secs(1));
        idle.worked();
        assert_eq!(idle.cap(Duration::from_secs(5)), Duration::from_secs(5));
    }
}
