//! The `glasscan` binary: a thin shell over the library's CLI.

#![deny(unsafe_code)]

use std::process::ExitCode;

fn main() -> ExitCode {
    match glasscan::cli::run() {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) if glasscan::cli::is_broken_pipe(&e) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("error: {e:#}");
            ExitCode::FAILURE
        }
    }
}
