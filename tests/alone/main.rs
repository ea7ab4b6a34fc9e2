//! The tests that must not run beside any other: each holds
//! [`support::alone`] for its whole run. The farm across network namespaces
//! stops a worker past its lease, the CPU comparison counts every child this
//! process waits for (`RUSAGE_CHILDREN`), and the Slurm cluster's tasks are
//! timed against deadlines, so none shares the machine with another test of
//! this binary; the other binaries run before or after this one, never
//! beside it.

#[path = "../support/mod.rs"]
mod support;

mod netns;
mod slurm;
mod speedup;
mod thousand;

/// CPU seconds (user + system) of all waited-for children so far.
pub fn children_cpu() -> f64 {
    // SAFETY: getrusage writes only into the zeroed struct we pass.
    let mut usage: libc::rusage = unsafe { std::mem::zeroed() };
    assert_eq!(
        unsafe { libc::getrusage(libc::RUSAGE_CHILDREN, &mut usage) },
        0
    );
    let secs = |t: libc::timeval| t.tv_sec as f64 + t.tv_usec as f64 / 1e6;
    secs(usage.ru_utime) + secs(usage.ru_stime)
}
