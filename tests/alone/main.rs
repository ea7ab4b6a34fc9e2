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
