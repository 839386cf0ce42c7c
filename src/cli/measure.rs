//! Wall-clock and memory measurement for the benchmark commands.

use std::time::Instant;

/// Median wall time in seconds of `f` over repeats, after one warm-up call.
/// Repeats until `budget_s` seconds are spent, at least `min` and at most
/// `max` times. Returns the median and the last result.
pub fn median_time<T>(budget_s: f64, min: usize, max: usize, mut f: impl FnMut() -> T) -> (f64, T) {
    let mut out = f();
    let mut times = Vec::new();
    let start = Instant::now();
    while times.len() < min || (times.len() < max && start.elapsed().as_secs_f64() < budget_s) {
        let t = Instant::now();
        out = std::hint::black_box(f());
        times.push(t.elapsed().as_secs_f64());
    }
    times.sort_by(f64::total_cmp);
    (times[times.len() / 2], out)
}

/// Peak resident set size of this process in bytes (`VmHWM` from
/// `/proc/self/status`; 0 where that is not available).
pub fn peak_rss_bytes() -> u64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| s.lines().find(|l| l.starts_with("VmHWM:")).and_then(|l| l.split_whitespace().nth(1)).and_then(|kb| kb.parse::<u64>().ok()))
        .map_or(0, |kb| kb * 1024)
}

/// Resets the peak resident set size to the current one (Linux: writes `5`
/// to `/proc/self/clear_refs`), so that [`peak_rss_bytes`] afterwards
/// measures what runs in between. Returns whether the reset worked.
pub fn reset_peak_rss() -> bool {
    std::fs::write("/proc/self/clear_refs", "5").is_ok()
}
