use std::process::ExitCode;

use clap::Parser;

fn main() -> ExitCode {
    coordinator::cli::main(coordinator::cli::Cli::parse())
}
