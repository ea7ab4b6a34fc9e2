//! Logging set-up for the binary: lines on stderr, plain or JSON.

use std::io::IsTerminal;

use tracing_subscriber::EnvFilter;

/// Installs the global subscriber: `info` by default, `warn` with `--quiet`,
/// `RUST_LOG` overrides both. Plain text, coloured only when stderr is a
/// terminal.
pub fn init(quiet: bool) {
    init_with(quiet, false);
}

/// [`init`], or one JSON object per event (`--log-format json`): time, level,
/// message and fields, for a log collector.
pub fn init_with(quiet: bool, json: bool) {
    let default = if quiet { "warn" } else { "info" };
    let filter = EnvFilter::try_from_default_env().unwrap_or_else(|_| EnvFilter::new(default));
    // A second initialisation (tests) is harmless: keep the first.
    if json {
        let _ = tracing_subscriber::fmt()
            .json()
            .with_env_filter(filter)
            .with_writer(worker::logging::Stderr::default)
            .log_internal_errors(false)
            .with_target(false)
            .with_current_span(false)
            .try_init();
    } else {
        let _ = tracing_subscriber::fmt()
            .with_env_filter(filter)
            .with_writer(worker::logging::Stderr::default)
            .log_internal_errors(false)
            .with_ansi(std::io::stderr().is_terminal())
            .with_target(false)
            .without_time()
            .try_init();
    }
}
