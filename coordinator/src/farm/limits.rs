//! The process's open-file limit: every worker holds one connection (one
//! file descriptor) for as long as it is registered, so a farm of a thousand
//! workers needs more than the 1,024 that many systems give a process by
//! default. The soft limit is raised to the hard one at start, as servers
//! do; a hard limit too low for a large farm is said once, with the fix.

/// Descriptors kept for everything but workers: the listener, the store, the
/// logs, the outputs being written, the local workers' pipes.
pub const RESERVED: u64 = 64;

/// A hard limit under this many descriptors is worth a warning.
pub const WANTED: u64 = 4096;

/// What [`raise_open_files`] did.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct OpenFiles {
    /// The soft limit before.
    pub before: u64,
    /// The soft limit now.
    pub now: u64,
    /// The hard limit (the most the soft one can be raised to without
    /// privilege).
    pub hard: u64,
}

impl OpenFiles {
    /// About how many workers can be connected at once.
    pub fn workers(self) -> u64 {
        self.now.saturating_sub(RESERVED)
    }
}

/// Raises the soft open-file limit to the hard one, logs what it did, and
/// warns when the limit leaves room for fewer than [`WANTED`] connections.
/// `None` where the limit cannot be read.
pub fn raise_open_files() -> Option<OpenFiles> {
    let limits = raise()?;
    if limits.now > limits.before {
        tracing::info!(
            "open-file limit raised from {} to {}: room for about {} workers",
            limits.before,
            limits.now,
            limits.workers()
        );
    }
    if limits.now < WANTED {
        tracing::warn!(
            "the open-file limit is {} (hard limit {}): about {} workers can be connected at once; raise it for a larger farm (`ulimit -n {WANTED}` as root, or `LimitNOFILE={WANTED}` in a systemd unit)",
            limits.now,
            limits.hard,
            limits.workers()
        );
    }
    Some(limits)
}

#[cfg(unix)]
fn raise() -> Option<OpenFiles> {
    // SAFETY: getrlimit and setrlimit read and write only the struct passed.
    unsafe {
        let mut lim: libc::rlimit = std::mem::zeroed();
        if libc::getrlimit(libc::RLIMIT_NOFILE, &mut lim) != 0 {
            return None;
        }
        let before = lim.rlim_cur;
        // An unlimited hard limit is still capped by the kernel's nr_open.
        let target = lim.rlim_max.min(1 << 20);
        if lim.rlim_cur < target {
            let raised = libc::rlimit {
                rlim_cur: target,
                rlim_max: lim.rlim_max,
            };
            if libc::setrlimit(libc::RLIMIT_NOFILE, &raised) == 0 {
                lim.rlim_cur = target;
            }
        }
        Some(OpenFiles {
            before: before as u64,
            now: lim.rlim_cur as u64,
            hard: lim.rlim_max as u64,
        })
    }
}

#[cfg(not(unix))]
fn raise() -> Option<OpenFiles> {
    None
}
