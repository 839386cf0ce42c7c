//! The workspace's layout (docs/architecture.md): the library pulls in no
//! command-line, plotting or progress-bar crate, and the autodiff flag goes
//! only to the crates that declare differentiated functions and to the
//! final binaries.

fn manifest(path: &str) -> toml::Table {
    std::fs::read_to_string(path).unwrap().parse().unwrap()
}

#[test]
fn the_library_depends_on_no_command_line_crate() {
    let root = manifest("Cargo.toml");
    let deps = root["dependencies"].as_table().unwrap();
    for name in ["clap", "plotters", "indicatif", "ctrlc", "png"] {
        assert!(!deps.contains_key(name), "the library (root Cargo.toml) depends on {name}: it belongs to cli/");
    }
    let cli = manifest("cli/Cargo.toml");
    assert!(cli["dependencies"].as_table().unwrap().contains_key("clap"), "the command line has its parser");
}

#[test]
fn the_autodiff_flag_goes_to_the_library_and_the_binaries_only() {
    let root = manifest("Cargo.toml");
    let packages = root["profile"]["release"]["package"].as_table().unwrap();
    let mut flagged: Vec<&str> = packages
        .iter()
        .filter(|(_, p)| p.get("rustflags").and_then(|f| f.as_array()).is_some_and(|f| f.iter().any(|x| x.as_str() == Some("-Zautodiff=Enable"))))
        .map(|(name, _)| name.as_str())
        .collect();
    flagged.sort();
    assert_eq!(flagged, ["diffsim", "diffsim-bin", "diffsim-python"]);
    // The program is one line over the command line.
    let main = std::fs::read_to_string("bin/main.rs").unwrap();
    let code: Vec<&str> = main.lines().map(str::trim).filter(|l| !l.is_empty() && !l.starts_with("//")).collect();
    assert_eq!(code, ["fn main() {", "diffsim_cli::main()", "}"]);
}
