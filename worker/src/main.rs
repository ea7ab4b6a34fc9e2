//! `worker`: parses arguments, sets up logging and signals, runs the work loop.

use std::io::Write as _;
use std::process::ExitCode;

use clap::Parser;
use worker::cli::Cli;

fn main() -> ExitCode {
    let cli = Cli::parse();
    worker::logging::init(cli.quiet);
    let parent = cli.parent_pid;
    let config = match cli.into_config() {
        Ok(c) => c,
        Err(e) => {
            complain(format_args!("error: {e}\n"));
            return ExitCode::FAILURE;
        }
    };
    // One async thread is plenty for a heartbeat and a tile in flight, and it
    // leaves the cores to the render threads.
    let runtime = match tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
    {
        Ok(r) => r,
        Err(e) => {
            complain(format_args!("error: cannot start the async runtime: {e}\n"));
            return ExitCode::FAILURE;
        }
    };
    let result = runtime.block_on(async {
        let (stop, stopped) = tokio::sync::watch::channel(false);
        if let Some(parent) = parent {
            tokio::spawn(worker::exit_when_orphaned(parent));
        }
        tokio::spawn(async move {
            worker::shutdown_signal().await;
            tracing::info!("shutting down: finishing the current unit");
            let _ = stop.send(true);
        });
        worker::run(config, stopped).await
    });
    match result {
        Ok(_) => ExitCode::SUCCESS,
        Err(e) => {
            complain(format_args!("error: {e}\n"));
            ExitCode::FAILURE
        }
    }
}

/// Writes to stderr; a closed stderr is ignored.
fn complain(text: std::fmt::Arguments) {
    let _ = std::io::stderr().write_fmt(text);
}
