//! The `diffsim` command line: argument parsing and the subcommands.

mod bench;
mod demo;
mod measure;

use clap::{Parser, Subcommand};
use thiserror::Error;

pub use measure::{median_time, peak_rss_bytes};

/// Errors reported by the command line: printed as one message, exit code 1.
#[derive(Debug, Error)]
pub enum CliError {
    /// An argument is out of its range.
    #[error("invalid argument {arg}: {reason}")]
    Argument {
        /// The flag.
        arg: &'static str,
        /// What is wrong with it.
        reason: String,
    },
    /// A rollout failed.
    #[error(transparent)]
    Rollout(#[from] crate::rollout::RolloutError),
    /// A file could not be written.
    #[error("cannot write {path}: {source}")]
    Io {
        /// The file or directory.
        path: std::path::PathBuf,
        /// The cause.
        source: std::io::Error,
    },
    /// The thread pool could not be built.
    #[error("cannot start {threads} threads: {source}")]
    Threads {
        /// Requested thread count.
        threads: usize,
        /// The cause.
        source: rayon::ThreadPoolBuildError,
    },
}

/// diffsim: differentiable physics with Enzyme-generated adjoints.
#[derive(Debug, Parser)]
#[command(name = "diffsim", version, about)]
pub struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Debug, Subcommand)]
enum Command {
    /// Benchmark problems of ../shared/benchmarks.md.
    #[command(subcommand)]
    Bench(bench::BenchCommand),
    /// Demonstrations.
    #[command(subcommand)]
    Demo(DemoCommand),
}

#[derive(Debug, Subcommand)]
enum DemoCommand {
    /// A smoke plume rising around an obstacle, written as PNG.
    Plume(demo::PlumeArgs),
}

/// Runs the command line.
pub fn run(cli: Cli) -> Result<(), CliError> {
    match cli.command {
        Command::Bench(b) => bench::run(b),
        Command::Demo(DemoCommand::Plume(a)) => demo::plume(a),
    }
}
