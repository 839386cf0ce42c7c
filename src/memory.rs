//! Memory chosen, not guessed. Every command that allocates in proportion
//! to its input (a scene's grid, a rollout's stored states, a training
//! run's data) estimates what it needs before it allocates, and refuses up
//! front, with the estimate and the smallest budget that would fit, what
//! exceeds the **memory budget**: `--memory-budget BYTES`, by default half
//! of the machine's memory. A rollout's gradient picks its checkpointing
//! (store, periodic or binomial) within the budget from a cost model
//! ([`crate::rollout::plan`]).
//!
//! The budget is a process-wide setting, like the thread count: the
//! command line sets it once ([`set_budget`]) and every estimate is
//! checked against [`budget`].

use std::sync::atomic::{AtomicU64, Ordering};

/// Bytes a process holds before any estimate counts (code, the allocator,
/// thread stacks, buffers of the output files): `bench p1` with a few
/// hundred kB of states peaks at 7-8 MB here; counted once in every check.
pub const BASE: u64 = 8_000_000;

/// Keeps freed memory in the process instead of returning each large block
/// to the system (glibc's allocator; elsewhere nothing happens). Generated
/// adjoints allocate their tapes afresh on every call, several megabytes
/// each for P4's step; returned to the system and mapped again each time,
/// they cost a page fault per page, which measured 40 % of the time of
/// P4's slab adjoint at 32³ (docs/p4.md). Call once at start-up, before any
/// thread exists; the command line and the benchmarks do.
pub fn keep_freed_memory() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: `mallopt` only sets the allocator's thresholds; called at
    // start-up it races with no allocation on another thread.
    unsafe {
        // Blocks up to 1 GiB from the heap, and the heap's top kept.
        libc::mallopt(libc::M_MMAP_THRESHOLD, 1 << 30);
        libc::mallopt(libc::M_TRIM_THRESHOLD, 1 << 30);
    }
}

/// A request that does not fit.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum MemoryError {
    /// The estimate exceeds the budget.
    #[error(
        "{what} needs about {} ({detail}), more than the memory budget of {}; \
         it would fit in --memory-budget {}{}",
        human(*need), human(*budget), human_up(*need), hint.as_deref().map(|h| format!(", or {h}")).unwrap_or_default()
    )]
    OverBudget {
        /// What was estimated ("the scene's grid", "the gradient's states").
        what: String,
        /// How the estimate is made up.
        detail: String,
        /// The estimate, in bytes (the base included).
        need: u64,
        /// The budget, in bytes.
        budget: u64,
        /// Another way to make it fit.
        hint: Option<String>,
    },
    /// The sizes overflow any memory (their product does not fit 64 bits).
    #[error("{what}: the sizes ({detail}) overflow: no machine has that much memory")]
    Overflow {
        /// What was estimated.
        what: String,
        /// The sizes.
        detail: String,
    },
    /// A malformed `--memory-budget`.
    #[error("--memory-budget: {0}")]
    Parse(String),
}

/// 0: not set (the default applies).
static BUDGET: AtomicU64 = AtomicU64::new(0);

/// Sets the process's memory budget in bytes.
pub fn set_budget(bytes: u64) {
    BUDGET.store(bytes.max(1), Ordering::Relaxed);
}

thread_local! {
    /// 0: no budget of this thread's own ([`with_budget`]).
    static LOCAL: std::cell::Cell<u64> = const { std::cell::Cell::new(0) };
}

/// The memory budget: this thread's own while [`with_budget`] runs, else the
/// process's as set, else [`default_budget`].
pub fn budget() -> u64 {
    match (LOCAL.with(std::cell::Cell::get), BUDGET.load(Ordering::Relaxed)) {
        (0, 0) => default_budget(),
        (0, b) | (b, _) => b,
    }
}

/// Runs `f` with a budget of `bytes` for the checks made on this thread
/// (a host running many scenes with a budget each, the fuzz targets), then
/// restores the previous one, also when `f` panics.
pub fn with_budget<R>(bytes: u64, f: impl FnOnce() -> R) -> R {
    struct Restore(u64);
    impl Drop for Restore {
        fn drop(&mut self) {
            LOCAL.with(|l| l.set(self.0));
        }
    }
    let _restore = Restore(LOCAL.with(|l| l.replace(bytes.max(1))));
    f()
}

/// Half of the machine's memory (`MemTotal` of `/proc/meminfo`; 4 GB where
/// it cannot be read).
pub fn default_budget() -> u64 {
    machine_memory().map_or(4_000_000_000, |m| m / 2)
}

/// The machine's memory in bytes, when the system says.
pub fn machine_memory() -> Option<u64> {
    let info = std::fs::read_to_string("/proc/meminfo").ok()?;
    let line = info.lines().find(|l| l.starts_with("MemTotal:"))?;
    let kb: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    kb.checked_mul(1024)
}

/// Parses a size: `50MB`, `2GiB`, `1.5G`, `500k`, `123456` (bytes). `k`,
/// `M`, `G`, `T` with or without `B` are powers of 1000; `KiB`, `MiB`,
/// `GiB`, `TiB` powers of 1024.
pub fn parse_bytes(text: &str) -> Result<u64, MemoryError> {
    let t = text.trim();
    let split = t.find(|c: char| !(c.is_ascii_digit() || c == '.' || c == 'e' || c == 'E' || c == '_')).unwrap_or(t.len());
    let (number, unit) = t.split_at(split);
    let value: f64 =
        number.replace('_', "").parse().map_err(|_| MemoryError::Parse(format!("`{}` is not a size (e.g. 50MB, 2GiB)", crate::files::shorten(t, 40))))?;
    let scale = match unit.trim().to_ascii_lowercase().as_str() {
        "" | "b" => 1.0,
        "k" | "kb" => 1e3,
        "m" | "mb" => 1e6,
        "g" | "gb" => 1e9,
        "t" | "tb" => 1e12,
        "kib" => 1024.0,
        "mib" => 1024f64.powi(2),
        "gib" => 1024f64.powi(3),
        "tib" => 1024f64.powi(4),
        u => return Err(MemoryError::Parse(format!("unknown unit `{}` (B, kB, MB, GB, TB, KiB, MiB, GiB, TiB)", crate::files::shorten(u, 20)))),
    };
    let bytes = value * scale;
    if !(1.0..1.8e19).contains(&bytes) {
        return Err(MemoryError::Parse(format!("`{}` is not a size between 1 byte and 18 EB", crate::files::shorten(t, 40))));
    }
    Ok(bytes as u64)
}

/// A size for people: `48.3 MB`, `2.10 GB`.
pub fn human(bytes: u64) -> String {
    let b = bytes as f64;
    match b {
        _ if b < 1e3 => format!("{bytes} B"),
        _ if b < 1e6 => format!("{:.1} kB", b / 1e3),
        _ if b < 1e9 => format!("{:.1} MB", b / 1e6),
        _ if b < 1e12 => format!("{:.2} GB", b / 1e9),
        _ => format!("{:.2} TB", b / 1e12),
    }
}

/// A budget to suggest: `bytes` rounded up to two significant digits, in
/// the units [`parse_bytes`] reads (`57MB`).
pub fn human_up(bytes: u64) -> String {
    let b = bytes.max(1) as f64;
    let (scale, unit) = match b {
        _ if b >= 1e12 => (1e12, "TB"),
        _ if b >= 1e9 => (1e9, "GB"),
        _ if b >= 1e6 => (1e6, "MB"),
        _ if b >= 1e3 => (1e3, "kB"),
        _ => (1.0, "B"),
    };
    let v = b / scale;
    let digits = if v >= 10.0 { 1.0 } else { 10.0 };
    format!("{}{unit}", (v * digits).ceil() / digits)
}

/// `a × b × …` as bytes of `f64`s, or `None` on overflow.
pub fn f64s(counts: &[u64]) -> Option<u64> {
    counts.iter().try_fold(8u64, |acc, &c| acc.checked_mul(c))
}

/// Checks an estimate (`None`: it overflowed) of `need` bytes beyond the
/// [`BASE`] against the process's [`budget`].
pub fn check(what: &str, detail: impl Into<String>, need: Option<u64>, hint: Option<String>) -> Result<(), MemoryError> {
    check_within(budget(), what, detail, need, hint)
}

/// [`check`] against `budget` bytes.
pub fn check_within(budget: u64, what: &str, detail: impl Into<String>, need: Option<u64>, hint: Option<String>) -> Result<(), MemoryError> {
    let detail = detail.into();
    let Some(need) = need.and_then(|n| n.checked_add(BASE)) else {
        return Err(MemoryError::Overflow { what: what.into(), detail });
    };
    if need > budget {
        return Err(MemoryError::OverBudget { what: what.into(), detail, need, budget, hint });
    }
    Ok(())
}
