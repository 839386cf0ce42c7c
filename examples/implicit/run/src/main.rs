fn main() -> std::process::ExitCode {
    starter::main()
}
