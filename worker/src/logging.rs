//! Logging set-up for the binary: human-readable lines on stderr.

use tracing_subscriber::EnvFilter;

/// Installs the global subscriber: `info` by default, `warn` with `--quiet`,
/// `RUST_LOG` overrides both.
pub fn init(quiet: bool) {
    let default = if quiet { "warn" } else { "info" };
    let filter = EnvFilter::try_from_default_env().unwrap_or_else(|_| EnvFilter::new(default));
    let _ = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        .with_target(false)
        .without_time()
        .try_init();
}
