//! The `diffsim` command: see `diffsim --help` and the `diffsim-cli` crate.

fn main() {
    diffsim_cli::main()
}
