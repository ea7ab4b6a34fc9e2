//! `coordinator`: parses arguments, sets up logging, runs. Everything else is in the library.

use std::process::ExitCode;

use clap::Parser;
use coordinator::cli::{Cli, Command};

fn main() -> ExitCode {
    let mut cli = Cli::parse();
    let result: Result<ExitCode, String> = match cli.command.take() {
        Some(Command::Bench(args)) => {
            coordinator::logging::init(true);
            coordinator::bench::run(&args.into_config())
                .map(|()| ExitCode::SUCCESS)
                .map_err(|e| e.to_string())
        }
        Some(Command::Grid(args)) => coordinator::grid::png_to_grid(&args.png, args.side as usize)
            .map(|grid| {
                println!("{grid}");
                ExitCode::SUCCESS
            })
            .map_err(|e| e.to_string()),
        Some(Command::Eval(args)) => coordinator::eval(
            &args.expression,
            args.scene.as_deref(),
            args.at,
            args.frame,
            &args.set,
        )
        .map(|value| {
            println!("{value}");
            ExitCode::SUCCESS
        })
        .map_err(|e| e.to_string()),
        Some(Command::Recolor(args)) => {
            coordinator::logging::init(false);
            coordinator::recolor::run(&args.input, &args.colormap, &args.out)
                .map(|()| ExitCode::SUCCESS)
                .map_err(|e| e.to_string())
        }
        Some(Command::Serve(args)) => coordinator::service::run(args)
            .map(|()| ExitCode::SUCCESS)
            .map_err(|e| e.to_string()),
        Some(Command::Studio(args)) => coordinator::service::run_studio(args)
            .map(|()| ExitCode::SUCCESS)
            .map_err(|e| e.to_string()),
        Some(Command::Submit(args)) => coordinator::client::submit(&args)
            .map(|id| {
                println!("{id}");
                ExitCode::SUCCESS
            })
            .map_err(|e| e.to_string()),
        Some(Command::Status(args)) => coordinator::client::status(&args)
            .map(|table| {
                print!("{table}");
                ExitCode::SUCCESS
            })
            .map_err(|e| e.to_string()),
        Some(Command::Cancel(args)) => coordinator::client::cancel(&args)
            .map(|job| {
                println!("{} {}", job.id, job.state.as_str());
                ExitCode::SUCCESS
            })
            .map_err(|e| e.to_string()),
        Some(Command::Wait(args)) => coordinator::client::wait(&args)
            .map(|job| {
                println!("{} {}", job.id, job.state.as_str());
                if job.state == coordinator::jobs::JobState::Done {
                    ExitCode::SUCCESS
                } else {
                    if let Some(e) = &job.error {
                        eprintln!("error: job {}: {e}", job.id);
                    }
                    ExitCode::FAILURE
                }
            })
            .map_err(|e| e.to_string()),
        None => {
            coordinator::logging::init(cli.quiet);
            coordinator::run_all(cli.into_config())
                .map(|_| ExitCode::SUCCESS)
                .map_err(|e| e.to_string())
        }
    };
    match result {
        Ok(code) => code,
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::FAILURE
        }
    }
}
