//! `coordinator serve` and `coordinator studio`: jobs that survive restarts,
//! the service's limits, a failing store, hostile HTTP, the studio in a
//! browser, and the deployment files checked against the binaries.

#[path = "../support/mod.rs"]
mod support;

mod deploy;
mod hostile_http;
mod limits;
mod service;
mod store_faults;
mod studio;
