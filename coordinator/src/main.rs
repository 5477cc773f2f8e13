use std::process::ExitCode;

use clap::{CommandFactory, Parser};
use coordinator::cli::Cli;

/// Every allocation on cache lines of its own: no false sharing between render threads
/// (see [`tracer_core::alloc`]).
#[global_allocator]
static ALLOC: tracer_core::alloc::OwnLines = tracer_core::alloc::OwnLines;

fn main() -> ExitCode {
    let argv = std::env::args_os().collect();
    // `serve --config FILE`: the file's flags join the command line where it has none.
    let argv =
        match worker::config_file::with_file_flags(&Cli::command(), argv, &["serve"], "serve") {
            Ok(argv) => argv,
            Err(e) => {
                eprintln!("coordinator serve: {e}");
                return ExitCode::from(tracer_core::cli_args::exit::USAGE);
            }
        };
    coordinator::cli::main(Cli::parse_from(argv))
}
