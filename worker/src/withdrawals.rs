//! The units the coordinator takes back from this worker while it holds
//! them: a withdrawn unit stops before its next pixel, and one not started
//! yet never starts.

use std::collections::{HashMap, VecDeque};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};

use hypertexture_proto::pb;

use crate::connection::Client;

/// The assignments the coordinator has taken back from this worker, and the
/// stop flags of those rendering: a withdrawn unit stops before its next
/// pixel, and one not started yet never starts.
#[derive(Default)]
pub(crate) struct Withdrawn(Mutex<WithdrawnState>);

#[derive(Default)]
pub(crate) struct WithdrawnState {
    rendering: HashMap<u64, Arc<AtomicBool>>,
    /// Withdrawn before this worker started them (the newest few).
    before_start: VecDeque<u64>,
}

/// How many withdrawn assignments not started yet are remembered.
const WITHDRAWN_REMEMBERED: usize = 1024;

impl Withdrawn {
    fn lock(&self) -> std::sync::MutexGuard<'_, WithdrawnState> {
        self.0.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// The stop flag of an assignment about to render; `None` when it has
    /// been withdrawn already.
    pub(crate) fn start(&self, assignment_id: u64) -> Option<Arc<AtomicBool>> {
        let mut s = self.lock();
        if s.before_start.contains(&assignment_id) {
            return None;
        }
        let flag = Arc::new(AtomicBool::new(false));
        s.rendering.insert(assignment_id, Arc::clone(&flag));
        Some(flag)
    }

    pub(crate) fn finish(&self, assignment_id: u64) {
        self.lock().rendering.remove(&assignment_id);
    }

    pub(crate) fn withdraw(&self, assignment_ids: &[u64]) {
        let mut s = self.lock();
        for id in assignment_ids {
            match s.rendering.get(id) {
                Some(flag) => flag.store(true, Ordering::Relaxed),
                None => {
                    if s.before_start.len() == WITHDRAWN_REMEMBERED {
                        s.before_start.pop_front();
                    }
                    s.before_start.push_back(*id);
                }
            }
        }
    }
}

/// Listens for the assignments the coordinator takes back, for as long as
/// this registration lasts. A coordinator without the call (UNIMPLEMENTED)
/// or a broken stream leaves withdrawn units to render to the end, as their
/// tiles are ignored.
pub(crate) async fn listen_for_withdrawals(
    mut client: Client,
    worker_id: String,
    withdrawn: Arc<Withdrawn>,
) {
    let Ok(response) = client
        .withdrawals(pb::WithdrawalsParams { worker_id })
        .await
    else {
        return;
    };
    let mut stream = response.into_inner();
    while let Ok(Some(w)) = stream.message().await {
        withdrawn.withdraw(&w.assignment_ids);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_unit_withdrawn_while_it_renders_is_told_to_stop() {
        let withdrawn = Withdrawn::default();
        let flag = withdrawn.start(1).unwrap();
        let other = withdrawn.start(2).unwrap();
        withdrawn.withdraw(&[1]);
        assert!(flag.load(Ordering::Relaxed));
        assert!(!other.load(Ordering::Relaxed));
        withdrawn.finish(1);
        withdrawn.finish(2);
        assert!(withdrawn.lock().rendering.is_empty());
    }

    #[test]
    fn a_unit_withdrawn_before_it_starts_never_starts() {
        let withdrawn = Withdrawn::default();
        withdrawn.withdraw(&[5, 6]);
        assert!(withdrawn.start(5).is_none());
        assert!(withdrawn.start(6).is_none());
        assert!(withdrawn.start(7).is_some());
    }

    #[test]
    fn only_the_newest_withdrawals_before_start_are_remembered() {
        let withdrawn = Withdrawn::default();
        let ids: Vec<u64> = (0..WITHDRAWN_REMEMBERED as u64 + 1).collect();
        withdrawn.withdraw(&ids);
        assert_eq!(withdrawn.lock().before_start.len(), WITHDRAWN_REMEMBERED);
        assert!(withdrawn.start(0).is_some(), "the oldest is forgotten");
        assert!(withdrawn.start(1).is_none());
        assert!(withdrawn.start(WITHDRAWN_REMEMBERED as u64).is_none());
    }
}
