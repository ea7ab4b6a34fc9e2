//! Logging set-up for the binary: human-readable lines on stderr.

use tracing_subscriber::EnvFilter;

/// Installs the global subscriber: `info` by default, `warn` with `--quiet`,
/// `RUST_LOG` overrides both.
pub fn init(quiet: bool) {
    let default = if quiet { "warn" } else { "info" };
    let filter = EnvFilter::try_from_default_env().unwrap_or_else(|_| EnvFilter::new(default));
    let _ = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(Stderr::default)
        .log_internal_errors(false)
        .with_target(false)
        .without_time()
        .try_init();
}

/// Standard error for log lines, whose write errors are ignored: a closed
/// stderr (EPIPE, EBADF) must never stop the work or lose its result.
#[derive(Debug, Default)]
pub struct Stderr;

impl std::io::Write for Stderr {
    fn write(&mut self, buf: &[u8]) -> std::io::Result<usize> {
        let _ = std::io::stderr().write_all(buf);
        Ok(buf.len())
    }

    fn flush(&mut self) -> std::io::Result<()> {
        let _ = std::io::stderr().flush();
        Ok(())
    }
}
