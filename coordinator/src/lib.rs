//! The coordinator: renders scenes on a farm of workers, once
//! ([`pipeline::run`]) or as a service with a job queue ([`service`]).
//!
//! The binary (`main.rs`) only parses arguments ([`cli`]) and calls the
//! library.

pub mod cli;
pub mod farm;
pub mod files;
pub mod guard;
pub mod image;
pub mod logging;
pub mod pipeline;
pub mod service;

pub use pipeline::run::CoordinatorError;
