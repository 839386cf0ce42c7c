//! What a data-parallel iteration costs over K ranks, as a model whose
//! inputs are measured here (`diffsim bench scaling`, `diffsim bench
//! exchange`), to say how far past this machine's two cores a workload
//! scales.
//!
//! One iteration over `K` ranks of a batch of `B` samples:
//!
//! `T(K) = ⌈B/K⌉·t_s + t_0 + T_x(K)`,
//! `T_x(K) = ⌈log₂K⌉·α + (K−1)/K · B·V·8 / β` (for `K > 1`),
//!
//! with `t_s` the gradient of one sample on one thread, `t_0` the work
//! every rank repeats (the optimizer, drawing the batch), `V` the values
//! sent per sample (the parameters and the loss: [`super::World`] gathers
//! every sample's gradient so that the sum runs in sample order for any
//! K) and `α`, `β` the all-gather's latency and bandwidth (a recursive
//! doubling or ring all-gather). The efficiency is `T(1)/(K·T(K))`.
//!
//! Because every sample's gradient is exchanged, `T_x` grows with `B`: a
//! larger batch does not hide it. As `B → ∞` the efficiency tends to
//! `t_s / (t_s + (K−1)·V·8/β)`, so past `K ≈ t_s·β/(8V)` no batch reaches
//! half efficiency.

/// The model's inputs (see the module's formulas).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct ScalingModel {
    /// `t_s`: seconds for one sample's gradient on one thread.
    pub sample_s: f64,
    /// `t_0`: seconds of the work every rank repeats per iteration.
    pub fixed_s: f64,
    /// `V`: values exchanged per sample (parameters + 1).
    pub values_per_sample: usize,
    /// `α`: the latency of an all-gather step, seconds.
    pub latency_s: f64,
    /// `β`: the all-gather's bandwidth, bytes per second.
    pub bandwidth: f64,
}

impl ScalingModel {
    /// `T(K)` for a batch of `batch`, seconds.
    pub fn iteration_s(&self, ranks: usize, batch: usize) -> f64 {
        let k = ranks.max(1);
        let compute = batch.div_ceil(k) as f64 * self.sample_s + self.fixed_s;
        if k == 1 {
            return compute;
        }
        let steps = (usize::BITS - (k - 1).leading_zeros()) as f64;
        let bytes = batch as f64 * self.values_per_sample as f64 * 8.0;
        compute + steps * self.latency_s + (k - 1) as f64 / k as f64 * bytes / self.bandwidth
    }

    /// The parallel efficiency `T(1)/(K·T(K))` at `ranks` for `batch`.
    pub fn efficiency(&self, ranks: usize, batch: usize) -> f64 {
        self.iteration_s(1, batch) / (ranks.max(1) as f64 * self.iteration_s(ranks, batch))
    }

    /// The smallest batch (a multiple of `ranks`, up to 2²⁰) at which
    /// `ranks` reach `efficiency`; `None` when no batch does (the exchange
    /// outgrows the compute).
    pub fn batch_for(&self, ranks: usize, efficiency: f64) -> Option<usize> {
        let k = ranks.max(1);
        (1..=(1usize << 20) / k).map(|m| m * k).find(|&b| self.efficiency(k, b) >= efficiency)
    }

    /// The most ranks at which a large batch still reaches half efficiency:
    /// `t_s·β/(8V) + 1`.
    pub fn rank_limit(&self) -> f64 {
        self.sample_s * self.bandwidth / (8.0 * self.values_per_sample as f64) + 1.0
    }
}

#[cfg(test)]
mod tests {
    use super::ScalingModel;

    /// Compute only: perfect scaling while every rank has a sample; the
    /// exchange caps it as the formula says.
    #[test]
    fn the_model_follows_its_formula() {
        let free = ScalingModel { sample_s: 1e-3, fixed_s: 0.0, values_per_sample: 100, latency_s: 0.0, bandwidth: f64::INFINITY };
        assert_eq!(free.efficiency(8, 64), 1.0);
        assert_eq!(free.efficiency(64, 32), 0.5);
        let m = ScalingModel { latency_s: 1e-6, bandwidth: 1e9, ..free };
        // T(4) for B = 64: 16 ms + 2 µs + 3/4 · 51 200 B / 1 GB/s.
        let t = 16e-3 + 2e-6 + 0.75 * 64.0 * 100.0 * 8.0 / 1e9;
        assert!((m.iteration_s(4, 64) - t).abs() < 1e-15);
        // Past t_s·β/(8V) + 1 = 1251 ranks no batch reaches one half.
        assert!((m.rank_limit() - 1251.0).abs() < 1e-9);
        assert!(m.batch_for(1024, 0.5).is_some() && m.batch_for(2048, 0.5).is_none());
    }
}
