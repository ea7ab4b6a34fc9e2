//! `coordinator`: parses arguments, sets up logging, runs. Everything else is in the library.

use std::io::Write as _;
use std::process::ExitCode;

use clap::Parser;
use coordinator::cli::{Cli, Command};

fn main() -> ExitCode {
    let mut cli = Cli::parse();
    coordinator::farm::panics::install();
    let result = match cli.command.take() {
        Some(command) => subcommand(command),
        None => render(cli),
    };
    match result {
        Ok(code) => code,
        Err(e) => {
            complain(format_args!("error: {e}\n"));
            ExitCode::FAILURE
        }
    }
}

/// `coordinator --scene …`: a one-shot render.
fn render(cli: Cli) -> Result<ExitCode, String> {
    coordinator::logging::init(cli.quiet);
    cli.into_config()
        .and_then(coordinator::pipeline::run::run_all)
        .map(|_| ExitCode::SUCCESS)
        .map_err(|e| e.to_string())
}

/// A subcommand: the one-shot tools, the service, or a client of it.
fn subcommand(command: Command) -> Result<ExitCode, String> {
    match command {
        Command::Serve(args) => coordinator::service::run(args.into_config())
            .map(|()| ExitCode::SUCCESS)
            .map_err(|e| e.to_string()),
        Command::Studio(args) => coordinator::service::run_studio(args.into_config())
            .map(|()| ExitCode::SUCCESS)
            .map_err(|e| e.to_string()),
        Command::Submit(_) | Command::Status(_) | Command::Cancel(_) | Command::Wait(_) => {
            client_command(command)
        }
        Command::Store(command) => store_command(command),
        Command::Cert(args) => coordinator::farm::cert::make(&args.out, &args.name)
            .map(|files| {
                for f in &files {
                    say(format_args!("{}\n", f.display()));
                }
                ExitCode::SUCCESS
            })
            .map_err(|e| e.to_string()),
        tool => pipeline_command(tool),
    }
}

/// `coordinator bench|grid|eval|bake|recolor`.
fn pipeline_command(command: Command) -> Result<ExitCode, String> {
    let done = |r: Result<(), coordinator::CoordinatorError>| {
        r.map(|()| ExitCode::SUCCESS).map_err(|e| e.to_string())
    };
    let print = |r: Result<String, coordinator::CoordinatorError>| {
        done(r.map(|text| say(format_args!("{text}\n"))))
    };
    match command {
        Command::Bench(args) => {
            coordinator::logging::init(true);
            done(coordinator::pipeline::bench::run(&args.into_config()))
        }
        Command::Grid(args) => print(coordinator::pipeline::grid::png_to_grid(
            &args.png,
            args.side as usize,
        )),
        Command::Eval(args) => print(coordinator::pipeline::run::eval(
            &args.expression,
            args.scene.as_deref(),
            args.at,
            args.frame,
            &args.knobs.set,
        )),
        Command::Bake(args) => {
            coordinator::logging::init(args.quiet);
            done(coordinator::pipeline::bake::run(&args.into_config()).map(|_| ()))
        }
        Command::Recolor(args) => {
            coordinator::logging::init(false);
            done(coordinator::pipeline::recolor::run(
                &args.input,
                &args.colormap,
                &args.out,
            ))
        }
        other => Err(format!("not a pipeline command: {other:?}")),
    }
}

/// `coordinator submit|status|cancel|wait`: a client of a running service.
fn client_command(command: Command) -> Result<ExitCode, String> {
    use coordinator::service::client;
    let said = |job: &coordinator::service::jobs::JobView| {
        say(format_args!("{} {}\n", job.id, job.state.as_str()));
    };
    let answer = match command {
        Command::Submit(args) => {
            let server = args.server.endpoint();
            args.job()
                .and_then(|job| client::submit(&server, &job))
                .map(|id| say(format_args!("{id}\n")))
        }
        Command::Status(args) => client::status(&args.server.endpoint(), args.job)
            .map(|table| say(format_args!("{table}"))),
        Command::Cancel(args) => {
            client::cancel(&args.server.endpoint(), args.job).map(|job| said(&job))
        }
        Command::Wait(args) => {
            let job = client::wait(&args.server.endpoint(), args.job).map_err(|e| e.to_string())?;
            said(&job);
            if job.state == coordinator::service::jobs::JobState::Done {
                return Ok(ExitCode::SUCCESS);
            }
            if let Some(e) = &job.error {
                complain(format_args!("error: job {}: {e}\n", job.id));
            }
            return Ok(ExitCode::FAILURE);
        }
        other => return Err(format!("not a client command: {other:?}")),
    };
    answer
        .map(|()| ExitCode::SUCCESS)
        .map_err(|e| e.to_string())
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
