//! The `diffsim` command: see `diffsim --help`.

use clap::Parser;

fn main() {
    let cli = diffsim::cli::Cli::parse();
    if let Err(e) = diffsim::cli::run(cli) {
        eprintln!("error: {e}");
        std::process::exit(e.exit_code());
    }
}
