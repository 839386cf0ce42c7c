//! `diffsim new PATH [--name NAME] [--template starter|implicit]`: a crate
//! of your own on diffsim, ready to build. It writes a template,
//! `examples/starter` (an explicit step, its hand and generated adjoints)
//! or `examples/implicit` (an implicit step from its right-hand side), the
//! crates `docs/own-solver.md` walks through, with its names replaced, the pinned
//! toolchain, the Enzyme log guard, this checkout's lock file, and a cargo
//! configuration that stops debug builds at once and (unless
//! `--own-target`) shares this checkout's target folder.

use std::path::{Path, PathBuf};

use super::CliError;

/// Writes each file of the template (names in it: `starter` the program,
/// `starter-solver`, `starter-run`) with its names replaced. One call per
/// file, not a loop over a table of `(path, text)` pairs: this crate is
/// built with the autodiff flag, and arrays of tuples iterated by value
/// abort rustc there (docs/pitfalls.md).
macro_rules! template {
    ($root:expr, $names:expr, $dir:literal, $file:literal) => {
        write($root, $file, &instantiate($file, include_str!(concat!("../../examples/", $dir, "/", $file)), $names))?
    };
}

/// Writes every file of the template in `examples/$dir`.
macro_rules! templates {
    ($root:expr, $names:expr, $dir:literal) => {{
        template!($root, $names, $dir, "Cargo.toml");
        template!($root, $names, $dir, "README.md");
        template!($root, $names, $dir, "src/lib.rs");
        template!($root, $names, $dir, "solver/Cargo.toml");
        template!($root, $names, $dir, "solver/src/lib.rs");
        template!($root, $names, $dir, "run/Cargo.toml");
        template!($root, $names, $dir, "run/src/main.rs");
        template!($root, $names, $dir, "run/tests/checks.rs");
    }};
}

/// The crate to start from.
#[derive(Clone, Copy, Debug, PartialEq, Eq, clap::ValueEnum)]
pub enum Template {
    /// An explicit step (Fisher–KPP): `differentiable!`, `stencil3!`, lent
    /// scratch, a hand adjoint beside Enzyme's, an Adam fit.
    Starter,
    /// An implicit step (backward-Euler heat conduction with a conductivity
    /// per cell) from its right-hand side: `ode_system!` and the
    /// integrator, an L-BFGS fit of the conductivities.
    Implicit,
}

const TOOLCHAIN: &str = include_str!("../../rust-toolchain.toml");
const GUARD: &str = include_str!("../../scripts/cargo-enzyme");
const LOCK: &str = include_str!("../../Cargo.lock");
/// The guard's line that finds the pitfalls page relative to itself; a
/// copy in a new crate gets the checkout's absolute path instead.
const PITFALLS_LINE: &str = r#"pitfalls="$(cd "$(dirname "$0")/.." && pwd)/docs/pitfalls.md""#;

/// Arguments of `diffsim new`.
#[derive(Debug, clap::Args)]
pub struct NewArgs {
    /// Folder to create (must not exist, or be empty).
    path: PathBuf,
    /// Package name (lowercase letters, digits, `-`, `_`); default: the
    /// folder's name.
    #[arg(long)]
    name: Option<String>,
    /// The diffsim checkout to depend on; default: the one this binary was
    /// built from.
    #[arg(long)]
    diffsim: Option<PathBuf>,
    /// Build into the new crate's own `target/` instead of the diffsim
    /// checkout's (whose compiled dependencies make a first build take
    /// seconds instead of minutes).
    #[arg(long)]
    own_target: bool,
    /// The crate to start from.
    #[arg(long, value_enum, default_value_t = Template::Starter)]
    template: Template,
}

fn invalid(arg: &'static str, reason: impl Into<String>) -> CliError {
    CliError::Argument { arg, reason: reason.into() }
}

/// Checks a package name: what cargo accepts, and not one that clashes.
fn check_name(name: &str) -> Result<(), CliError> {
    let ok_chars = name.chars().all(|c| c.is_ascii_lowercase() || c.is_ascii_digit() || c == '-' || c == '_');
    if name.is_empty() || !ok_chars || !name.starts_with(|c: char| c.is_ascii_lowercase()) {
        return Err(invalid(
            "--name",
            format!(
                "`{name}` is not a package name: use lowercase letters, digits, `-` and `_`, starting with a letter (pass --name if the folder's name is not one)"
            ),
        ));
    }
    let snake = name.replace('-', "_");
    if name.ends_with('-') || name.ends_with('_') || name.contains("--") {
        return Err(invalid("--name", format!("`{name}` ends with or doubles a separator")));
    }
    let reserved = ["diffsim", "diffsim_solvers", "test", "std", "core", "alloc", "proc_macro"];
    // Rust's keywords (strict and reserved, 2024 edition): the crate's name
    // is an identifier in its main.rs.
    let keywords = [
        "as", "async", "await", "break", "const", "continue", "crate", "dyn", "else", "enum", "extern", "false", "fn", "for", "gen", "if", "impl", "in", "let",
        "loop", "match", "mod", "move", "mut", "pub", "ref", "return", "self", "static", "struct", "super", "trait", "true", "type", "unsafe", "use", "where",
        "while", "abstract", "become", "box", "do", "final", "macro", "override", "priv", "try", "typeof", "unsized", "virtual", "yield",
    ];
    if keywords.contains(&snake.as_str()) {
        return Err(invalid("--name", format!("`{name}` is a Rust keyword, which cannot name a crate; choose another")));
    }
    if reserved.contains(&snake.as_str()) {
        return Err(invalid("--name", format!("`{name}` clashes with a crate it depends on or a Rust name; choose another")));
    }
    Ok(())
}

/// The names that replace the template's.
struct Names<'a> {
    /// The package name (`-` between words).
    kebab: &'a str,
    /// The crate name in Rust code (`_` between words).
    snake: &'a str,
    /// The diffsim checkout, an absolute path.
    diffsim: &'a str,
}

/// The template's text with its names replaced: `starter` becomes the
/// package name in manifests and prose, the crate name in Rust code; the
/// relative path to diffsim becomes the checkout's absolute path.
fn instantiate(file: &str, text: &str, names: &Names) -> String {
    let diffsim = format!("path = \"{}\"", names.diffsim);
    let text = text.replace("path = \"../../..\"", &diffsim).replace("path = \"../..\"", &diffsim);
    text.replace("starter", if file.ends_with(".rs") { names.snake } else { names.kebab })
}

fn write(root: &Path, rel: &str, text: &str) -> Result<(), CliError> {
    let path = root.join(rel);
    let io = |source| CliError::Io { path: path.clone(), source };
    if let Some(dir) = path.parent() {
        std::fs::create_dir_all(dir).map_err(io)?;
    }
    diffsim::files::write(&path, text).map_err(io)
}

/// Writes the crate.
pub fn new(a: NewArgs) -> Result<(), CliError> {
    let name = match &a.name {
        Some(n) => n.clone(),
        None => a
            .path
            .file_name()
            .and_then(|s| s.to_str())
            .map(str::to_string)
            .ok_or_else(|| invalid("PATH", format!("{} has no folder name to take the package name from; pass --name", a.path.display())))?,
    };
    check_name(&name)?;
    let (kebab, snake) = (name.replace('_', "-"), name.replace('-', "_"));
    if a.path.exists() {
        let empty = std::fs::read_dir(&a.path).map(|mut d| d.next().is_none()).unwrap_or(false);
        if !empty {
            return Err(invalid("PATH", format!("{} exists and is not an empty folder", a.path.display())));
        }
    }
    // (This crate lives in cli/ of the checkout.)
    let diffsim = std::fs::canonicalize(a.diffsim.as_deref().unwrap_or(Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/.."))))
        .map_err(|e| invalid("--diffsim", format!("cannot find the diffsim checkout: {e}")))?;
    // The checkout's manifest names the package `diffsim` (and its
    // solvers crate is beside it): any other crate would fail to build.
    let manifest = diffsim::files::read_text(&diffsim.join("Cargo.toml"), 1 << 20, "Cargo.toml").ok();
    let package = manifest.as_deref().and_then(|t| t.parse::<toml::Table>().ok()).and_then(|t| t.get("package")?.get("name")?.as_str().map(String::from));
    if package.as_deref() != Some("diffsim") || !diffsim.join("src/lib.rs").is_file() || !diffsim.join("solvers/Cargo.toml").is_file() {
        return Err(invalid(
            "--diffsim",
            format!(
                "{} is not a diffsim checkout (its Cargo.toml {}, and it needs src/lib.rs and solvers/Cargo.toml)",
                diffsim.display(),
                match &package {
                    Some(name) => format!("names the package `{}`", diffsim::files::shorten(name, 40)),
                    None => "is missing or names no package".to_string(),
                }
            ),
        ));
    }
    let diffsim_str = diffsim.to_str().ok_or_else(|| invalid("--diffsim", "the path is not valid UTF-8"))?.replace('\\', "/");

    let root = &a.path;
    let names = Names { kebab: &kebab, snake: &snake, diffsim: &diffsim_str };
    match a.template {
        Template::Starter => templates!(root, &names, "starter"),
        Template::Implicit => templates!(root, &names, "implicit"),
    }
    write(root, "rust-toolchain.toml", TOOLCHAIN)?;
    write(root, "Cargo.lock", LOCK)?;
    write(root, ".gitignore", "/target\n*.log\n")?;
    let guard = GUARD.replace(PITFALLS_LINE, &format!("pitfalls=\"{diffsim_str}/docs/pitfalls.md\""));
    write(root, "cargo-enzyme", &guard)?;
    make_executable(&root.join("cargo-enzyme"))?;
    let mut config = format!(
        "[build]\n\
         # Stops a debug build at its first crate, with what to run instead\n\
         # (Enzyme needs a release build); `cargo check` passes.\n\
         rustc-wrapper = \"{diffsim_str}/scripts/rustc-guard\"\n"
    );
    if !a.own_target {
        config += &format!(
            "# Builds into the diffsim checkout's target folder, so that the dependencies\n\
             # it has compiled already are reused (a first build takes seconds instead of\n\
             # minutes). Delete this line to build into ./target instead.\n\
             target-dir = \"{diffsim_str}/target\"\n"
        );
    }
    write(root, ".cargo/config.toml", &config)?;
    println!("created {} (package {kebab}) on diffsim at {diffsim_str}", root.display());
    println!("next:\n  cd {}\n  cargo run --release            # builds, checks the gradients, fits the parameters", root.display());
    println!("  ./cargo-enzyme run --release   # the same under the Enzyme log guard");
    println!("the walk-through: {diffsim_str}/docs/own-solver.md");
    Ok(())
}

#[cfg(unix)]
fn make_executable(path: &Path) -> Result<(), CliError> {
    use std::os::unix::fs::PermissionsExt;
    std::fs::set_permissions(path, std::fs::Permissions::from_mode(0o755)).map_err(|source| CliError::Io { path: path.to_path_buf(), source })
}

#[cfg(not(unix))]
fn make_executable(_: &Path) -> Result<(), CliError> {
    Ok(())
}
