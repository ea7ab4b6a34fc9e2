//! The process's stop signals: SIGTERM or Ctrl-C, and the death of the
//! coordinator that started this worker.

use std::time::Duration;

/// Resolves when the process is asked to stop (SIGTERM or Ctrl-C).
pub async fn shutdown_signal() {
    #[cfg(unix)]
    {
        use tokio::signal::unix::{SignalKind, signal};
        match signal(SignalKind::terminate()) {
            Ok(mut term) => {
                tokio::select! {
                    _ = term.recv() => {}
                    _ = tokio::signal::ctrl_c() => {}
                }
            }
            Err(_) => {
                let _ = tokio::signal::ctrl_c().await;
            }
        }
    }
    #[cfg(not(unix))]
    {
        let _ = tokio::signal::ctrl_c().await;
    }
}

/// Exits the process (status 1) once `parent` is no longer its parent: the
/// coordinator that started this worker has died, however it died. (The
/// coordinator also asks the kernel to kill it then, `PR_SET_PDEATHSIG`; this
/// covers the rest, such as another platform.)
pub async fn exit_when_orphaned(parent: u32) {
    let mut tick = tokio::time::interval(Duration::from_millis(250));
    loop {
        tick.tick().await;
        if std::os::unix::process::parent_id() != parent {
            eprintln!("error: the coordinator that started this worker (pid {parent}) has gone");
            std::process::exit(1);
        }
    }
}
