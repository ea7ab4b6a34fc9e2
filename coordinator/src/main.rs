//! `coordinator`: parses arguments, sets up logging, runs. Everything else is in the library.

use std::process::ExitCode;

use clap::Parser;
use coordinator::cli::Cli;

fn main() -> ExitCode {
    let cli = Cli::parse();
    coordinator::logging::init(cli.quiet);
    match coordinator::run(cli.into_config()) {
        Ok(_) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::FAILURE
        }
    }
}
