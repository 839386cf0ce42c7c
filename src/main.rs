//! The `diffsim` command: see `diffsim --help`.

use clap::Parser;

fn main() {
    let cli = diffsim::cli::Cli::parse();
    if let Err(e) = diffsim::cli::run(cli) {
        eprintln!("error: {e}");
        // 130: stopped by a signal (the shell's code for SIGINT).
        let code = if matches!(e, diffsim::cli::CliError::Interrupted { .. }) { 130 } else { 1 };
        std::process::exit(code);
    }
}
