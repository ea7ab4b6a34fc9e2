//! `coordinator`: parses arguments, sets up logging, runs. Everything else is in the library.

use std::process::ExitCode;

use clap::Parser;
use coordinator::cli::{Cli, Command};

fn main() -> ExitCode {
    let mut cli = Cli::parse();
    let result = match cli.command.take() {
        Some(Command::Bench(args)) => {
            coordinator::logging::init(true);
            coordinator::bench::run(&args.into_config())
        }
        Some(Command::Grid(args)) => coordinator::grid::png_to_grid(&args.png, args.side as usize)
            .map(|grid| {
                println!("{grid}");
            }),
        Some(Command::Eval(args)) => coordinator::eval(
            &args.expression,
            args.scene.as_deref(),
            args.at,
            args.frame,
            &args.set,
        )
        .map(|value| println!("{value}")),
        Some(Command::Recolor(args)) => {
            coordinator::logging::init(false);
            coordinator::recolor::run(&args.input, &args.colormap, &args.out)
        }
        None => {
            coordinator::logging::init(cli.quiet);
            coordinator::run_all(cli.into_config()).map(|_| ())
        }
    };
    match result {
        Ok(_) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e}");
            ExitCode::FAILURE
        }
    }
}
