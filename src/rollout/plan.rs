//! Checkpointing chosen by budget: a cost model of the three modes (states
//! held, step evaluations, memory traffic) and [`choose`], the fastest mode
//! whose states fit a memory budget.
//!
//! The model, per gradient of a `T`-step rollout of states of `b` bytes,
//! with `t_f` the time of one forward step:
//!
//! - time = evaluations·t_f + T·t_b + traffic, with `t_b = 2·t_f` (a VJP
//!   step; the same for every mode, so it only shifts the estimate);
//! - traffic: a state written and read back from main memory costs `2b` at
//!   [`BANDWIDTH`]; the states of a mode whose states held exceed
//!   [`CACHE`] all go there (store: all `T`; periodic: the checkpoints, and
//!   the recomputed segments when they too exceed it; binomial: every
//!   evaluation), those of a mode that fits stay in cache;
//! - states held, evaluations: as measured by [`super::RolloutStats`] —
//!   store `T + 2` and `T`; periodic `k` `⌈T/k⌉ + 2k` (two segments live
//!   with the two-thread backward pass) and `2T − ⌈T/k⌉`; binomial `s`
//!   `s + 2` and `T` plus the recomputations of the revolve schedule,
//!   counted exactly.
//!
//! On P1 (N = 2048, T = 1000) the model gives 4.4, 1.6 and 2.6 ms for store,
//! periodic and binomial against 4.5, 1.6 and 3.1 ms measured in one run
//! (docs/memory.md has the T = 10³…10⁵ table).

use std::collections::HashMap;

use super::Checkpointing;
use super::checkpoint::split;
use crate::memory::{MemoryError, human};

/// Main-memory bandwidth assumed for state traffic, bytes per second.
pub const BANDWIDTH: f64 = 10e9;
/// Time per periodic segment beyond its steps (its hand-off between the two
/// backward threads, its buffers): measured about 4-5 µs on P1 (T = 1000,
/// every 8 against every 32 steps).
pub const SEGMENT_S: f64 = 4e-6;

/// What a gradient's checkpointing is chosen for.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Job {
    /// Steps `T` of the rollout.
    pub steps: usize,
    /// Bytes of one state.
    pub state_bytes: u64,
    /// Gradients whose states are held at once (a benchmark keeping the
    /// workspaces of several variants: each holds its own states).
    pub copies: u64,
    /// Seconds of one forward step.
    pub forward_s: f64,
}
/// States held up to this many bytes stay in cache.
pub const CACHE: u64 = 16_000_000;
/// A periodic segment's states up to this many bytes stay in the core's
/// own cache (L2, 2 MiB per core here); beyond it they go through the
/// shared cache at [`SHARED_BANDWIDTH`].
pub const CORE_CACHE: u64 = 2 << 20;
/// Bandwidth of the shared cache, bytes per second (fitted: P1 at T = 1000
/// took 0.4 ms longer with segments of 128 states than of 32).
pub const SHARED_BANDWIDTH: f64 = 80e9;

/// The cost model's estimate for one mode.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Plan {
    /// The mode.
    pub mode: Checkpointing,
    /// States held at once.
    pub states: u64,
    /// Their bytes.
    pub bytes: u64,
    /// Step evaluations (forward and recomputation).
    pub evaluations: u64,
    /// Estimated seconds for one gradient.
    pub seconds: f64,
}

impl std::fmt::Display for Plan {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}: {} states ({}), {} step evaluations, about {:.3} s", self.mode, self.states, human(self.bytes), self.evaluations, self.seconds)
    }
}

/// The model's estimate for `mode` on `job`: the states of all its copies,
/// the time of one gradient.
pub fn estimate(mode: Checkpointing, job: &Job) -> Plan {
    let Job { steps, state_bytes, copies, forward_s } = *job;
    let t = steps.max(1) as u64;
    let (mut segments, mut shared) = (0, 0.0);
    let (states, evaluations, written_out) = match mode.resolve(steps) {
        Checkpointing::Store => (t + 2, t, t),
        Checkpointing::Periodic { every } => {
            let k = every.max(1) as u64;
            let checkpoints = t.div_ceil(k);
            let states = checkpoints + 2 * k;
            let segments_out = 2 * k * state_bytes > CACHE;
            segments = checkpoints;
            if !segments_out && k * state_bytes >= CORE_CACHE {
                shared = t as f64 * 2.0 * state_bytes as f64 / SHARED_BANDWIDTH;
            }
            (states, 2 * t - checkpoints, checkpoints + if segments_out { t } else { 0 })
        }
        Checkpointing::Binomial { snapshots } => {
            let s = snapshots.max(1);
            let evals = t + revolve_recomputations(steps.max(1), s, &mut HashMap::new());
            (s as u64 + 2, evals, evals)
        }
    };
    let one = states.saturating_mul(state_bytes);
    let traffic = if one > CACHE { written_out as f64 * 2.0 * state_bytes as f64 / BANDWIDTH } else { 0.0 };
    let seconds = evaluations as f64 * forward_s + t as f64 * 2.0 * forward_s + traffic + shared + segments as f64 * SEGMENT_S;
    Plan { mode, states, bytes: one.saturating_mul(copies.max(1)), evaluations, seconds }
}

/// Step evaluations the binomial backward pass of [`super::checkpoint`]
/// spends recomputing `t` steps from their first state with `s` snapshots
/// (the same recursion, counted instead of run).
fn revolve_recomputations(t: usize, s: usize, memo: &mut HashMap<(usize, usize), u64>) -> u64 {
    if s == 0 {
        return (t as u64) * (t as u64).saturating_sub(1) / 2;
    }
    if let Some(&c) = memo.get(&(t, s)) {
        return c;
    }
    // The left parts in a loop, as the rollout does.
    let (mut b, mut c) = (t, 0);
    while b > 1 {
        let right = split(b, s);
        c += (b - right) as u64 + revolve_recomputations(right, s - 1, memo);
        b -= right;
    }
    memo.insert((t, s), c);
    c
}

/// Every mode the chooser considers: store, periodic every `k` for `k`
/// around `√T` (¼ to 4×, and the memory-least `k`), binomial with 1 to
/// `⌈log₂ T⌉ + 8` snapshots.
pub fn candidates(steps: usize) -> Vec<Checkpointing> {
    let t = steps.max(1);
    let root = (t as f64).sqrt().ceil() as usize;
    let mut modes = vec![Checkpointing::Store];
    let mut ks: Vec<usize> = [root / 4, root / 2, root, 2 * root, 4 * root].into_iter().map(|k| k.clamp(1, t)).collect();
    ks.dedup();
    modes.extend(ks.into_iter().map(|every| Checkpointing::Periodic { every }));
    let most = (usize::BITS - t.leading_zeros()) as usize + 8;
    modes.extend((1..=most.min(t)).map(|snapshots| Checkpointing::Binomial { snapshots }));
    modes
}

/// The fastest mode by the model whose states and `other` bytes (and
/// [`crate::memory::BASE`]) fit `budget` bytes, with its estimate; refused
/// with the smallest budget that would fit when none does.
pub fn choose(job: &Job, other: u64, budget: u64, what: &str) -> Result<Plan, MemoryError> {
    let plans: Vec<Plan> = candidates(job.steps).into_iter().map(|m| estimate(m, job)).collect();
    let fits = |p: &Plan| p.bytes.saturating_add(other).saturating_add(crate::memory::BASE) <= budget;
    if let Some(best) = plans.iter().filter(|p| fits(p)).min_by(|a, b| a.seconds.total_cmp(&b.seconds)) {
        return Ok(*best);
    }
    let least = plans.iter().min_by_key(|p| p.bytes).copied().expect("store is always a candidate");
    // None fits: refused with the smallest.
    crate::memory::check_within(budget, what, describe(&least, job, other), Some(least.bytes.saturating_add(other)), None)?;
    Ok(least)
}

/// "N states of B with MODE over T steps (×C), and O besides".
pub fn describe(plan: &Plan, job: &Job, other: u64) -> String {
    let copies = if job.copies > 1 { format!(" (×{} gradients)", job.copies) } else { String::new() };
    format!("{} states of {} with {} over {} steps{copies}, and {} besides", plan.states, human(job.state_bytes), plan.mode, job.steps, human(other))
}
