//! The `diffsim` command: see `diffsim --help`.

fn main() {
    diffsim::cli::main()
}
