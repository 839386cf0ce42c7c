//! Wall-clock and memory measurement for the studies and the benchmark
//! commands.

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

/// Wall times of several computations measured in interleaved rounds (one
/// call of each per round, after one warm-up call of each), so that all of
/// them see the same machine state; on a shared, noisy machine this keeps
/// their ratios stable where back-to-back medians drift apart. Repeats
/// rounds until `budget_s` seconds are spent, at least `min` and at most
/// `max` rounds. Returns, per computation, the median time, and, per
/// computation, the median over rounds of its time divided by the first
/// computation's time in the same round.
pub fn interleaved_times(budget_s: f64, min: usize, max: usize, fs: &mut [&mut dyn FnMut()]) -> (Vec<f64>, Vec<f64>) {
    for f in fs.iter_mut() {
        f();
    }
    let k = fs.len();
    let mut times: Vec<Vec<f64>> = vec![Vec::new(); k];
    let start = Instant::now();
    while times[0].len() < min || (times[0].len() < max && start.elapsed().as_secs_f64() < budget_s) {
        for (f, t) in fs.iter_mut().zip(times.iter_mut()) {
            let s = Instant::now();
            f();
            t.push(s.elapsed().as_secs_f64());
        }
    }
    let median = |mut v: Vec<f64>| {
        v.sort_by(f64::total_cmp);
        v[v.len() / 2]
    };
    let ratios = (0..k).map(|j| median(times[j].iter().zip(&times[0]).map(|(t, t0)| t / t0).collect())).collect();
    (times.into_iter().map(median).collect(), ratios)
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
