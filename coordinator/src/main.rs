//! `coordinator`: parses arguments, sets up logging, runs. Everything else is in the library.

use std::io::Write as _;
use std::process::ExitCode;

use clap::Parser;
use coordinator::cli::{Cli, Command};

fn main() -> ExitCode {
    let mut cli = Cli::parse();
    coordinator::farm::panics::install();
    let result: Result<ExitCode, String> = match cli.command.take() {
        Some(Command::Bench(args)) => {
            coordinator::logging::init(true);
            coordinator::pipeline::bench::run(&args.into_config())
                .map(|()| ExitCode::SUCCESS)
                .map_err(|e| e.to_string())
        }
        Some(Command::Grid(args)) => {
            coordinator::pipeline::grid::png_to_grid(&args.png, args.side as usize)
                .map(|grid| {
                    say(format_args!("{grid}\n"));
                    ExitCode::SUCCESS
                })
                .map_err(|e| e.to_string())
        }
        Some(Command::Eval(args)) => coordinator::eval(
            &args.expression,
            args.scene.as_deref(),
            args.at,
            args.frame,
            &args.set,
        )
        .map(|value| {
            say(format_args!("{value}\n"));
            ExitCode::SUCCESS
        })
        .map_err(|e| e.to_string()),
        Some(Command::Bake(args)) => {
            coordinator::logging::init(args.quiet);
            coordinator::pipeline::bake::run(&args.into_config())
                .map(|_| ExitCode::SUCCESS)
                .map_err(|e| e.to_string())
        }
        Some(Command::Recolor(args)) => {
            coordinator::logging::init(false);
            coordinator::pipeline::recolor::run(&args.input, &args.colormap, &args.out)
                .map(|()| ExitCode::SUCCESS)
                .map_err(|e| e.to_string())
        }
        Some(Command::Serve(args)) => coordinator::service::run(args)
            .map(|()| ExitCode::SUCCESS)
            .map_err(|e| e.to_string()),
        Some(Command::Studio(args)) => coordinator::service::run_studio(args)
            .map(|()| ExitCode::SUCCESS)
            .map_err(|e| e.to_string()),
        Some(Command::Submit(args)) => coordinator::service::client::submit(&args)
            .map(|id| {
                say(format_args!("{id}\n"));
                ExitCode::SUCCESS
            })
            .map_err(|e| e.to_string()),
        Some(Command::Status(args)) => coordinator::service::client::status(&args)
            .map(|table| {
                say(format_args!("{table}"));
                ExitCode::SUCCESS
            })
            .map_err(|e| e.to_string()),
        Some(Command::Cancel(args)) => coordinator::service::client::cancel(&args)
            .map(|job| {
                say(format_args!("{} {}\n", job.id, job.state.as_str()));
                ExitCode::SUCCESS
            })
            .map_err(|e| e.to_string()),
        Some(Command::Wait(args)) => coordinator::service::client::wait(&args)
            .map(|job| {
                say(format_args!("{} {}\n", job.id, job.state.as_str()));
                if job.state == coordinator::service::jobs::JobState::Done {
                    ExitCode::SUCCESS
                } else {
                    if let Some(e) = &job.error {
                        complain(format_args!("error: job {}: {e}\n", job.id));
                    }
                    ExitCode::FAILURE
                }
            })
            .map_err(|e| e.to_string()),
        Some(Command::Store(command)) => store_command(command),
        Some(Command::Cert(args)) => coordinator::farm::cert::make(&args.out, &args.name)
            .map(|files| {
                for f in &files {
                    say(format_args!("{}\n", f.display()));
                }
                ExitCode::SUCCESS
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
            complain(format_args!("error: {e}\n"));
            ExitCode::FAILURE
        }
    }
}

/// `coordinator store check|backup`.
fn store_command(command: coordinator::cli::StoreCommand) -> Result<ExitCode, String> {
    use coordinator::cli::StoreCommand;
    match command {
        StoreCommand::Check { data } => {
            let report = coordinator::service::store::check(&data).map_err(|e| e.to_string())?;
            for problem in &report.problems {
                complain(format_args!("{}: {problem}\n", report.file.display()));
            }
            if report.problems.is_empty() {
                say(format_args!(
                    "{}: ok ({} jobs, {} tiles checked)\n",
                    report.file.display(),
                    report.jobs,
                    report.tiles
                ));
                Ok(ExitCode::SUCCESS)
            } else {
                complain(format_args!(
                    "{}: {} problems found; restore it from a backup, or let the service drop \
                     the tiles that fail (they are rendered again)\n",
                    report.file.display(),
                    report.problems.len()
                ));
                Ok(ExitCode::FAILURE)
            }
        }
        StoreCommand::Backup { data, file } => {
            let generation =
                coordinator::service::store::backup(&data, &file).map_err(|e| e.to_string())?;
            say(format_args!(
                "{}: a copy of {} (job ids up to {generation})\n",
                file.display(),
                data.join(coordinator::service::store::DB_FILE).display()
            ));
            Ok(ExitCode::SUCCESS)
        }
    }
}

/// Writes to stdout; a closed stdout is ignored (the work is done: a full
/// disk or a reader gone must not turn success into a panic).
fn say(text: std::fmt::Arguments) {
    let _ = std::io::stdout().write_fmt(text);
}

/// Writes to stderr; a closed stderr is ignored.
fn complain(text: std::fmt::Arguments) {
    let _ = std::io::stderr().write_fmt(text);
}
