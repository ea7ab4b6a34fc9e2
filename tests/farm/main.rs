//! The farm with real processes on loopback: exact images from any number of
//! workers, hostile workers and environments, TLS certificates, bakes on the
//! farm.

#[path = "../support/mod.rs"]
mod support;

mod adversarial;
mod bake_farm;
mod farm;
mod tls;
