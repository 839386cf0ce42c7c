//! The VJP against central finite differences, index by index.

use std::fmt;

use super::{CheckParams, Verdict, axpy, functional, max_abs, random_vector, rng};
use crate::op::{OperatorExt, Vjp};

/// The whole gradient of a scalar function by central differences:
/// `∂f/∂x_i ≈ (f(x + h_i·e_i) − f(x − h_i·e_i)) / 2h_i` with `h_i =
/// rel_step · max(1, |x_i|)`, two evaluations per index. For a gradient
/// to compare against where no operator is at hand (a rollout's loss as a
/// function of its initial state, say); operators are checked by
/// [`finite_differences`], which also sweeps the step and avoids kinks.
pub fn central_gradient(f: impl Fn(&[f64]) -> f64, x: &[f64], rel_step: f64) -> Vec<f64> {
    let mut x = x.to_vec();
    (0..x.len())
        .map(|i| {
            let xi = x[i];
            let h = rel_step * xi.abs().max(1.0);
            x[i] = xi + h;
            let up = f(&x);
            x[i] = xi - h;
            let down = f(&x);
            x[i] = xi;
            (up - down) / (2.0 * h)
        })
        .collect()
}

/// One step of the sweep.
#[derive(Clone, Debug)]
pub struct FdStep {
    /// Relative step: the absolute step at index `i` is `rel_step · max(1, |z_i|)`.
    pub rel_step: f64,
    /// Largest `|fd_i − g_i| / ‖g‖∞` over the indices whose step stays on
    /// one smooth piece.
    pub max_error: f64,
    /// The index where it occurs (`x[i]` or `p[j]`).
    pub worst: String,
    /// How many indices were skipped because this step crosses a kink.
    pub crossing_kink: usize,
}

/// Result of [`finite_differences`].
#[derive(Clone, Debug)]
pub struct FdReport {
    /// Number of indices differenced.
    pub indices_checked: usize,
    /// `‖g‖∞`, the scale of the errors.
    pub scale: f64,
    /// The sweep, largest step first; the principled step `ε^{1/3}` is
    /// among them.
    pub sweep: Vec<FdStep>,
    /// `max_i min_h |fd_i(h) − g_i| / ‖g‖∞`: each index at its best step.
    pub error: f64,
    /// The index with the largest such error.
    pub worst: String,
    /// Indices where even the smallest step crosses a kink, or where only
    /// steps below [`RELIABLE_STEP`] fit and miss.
    pub unusable: Vec<String>,
    /// The verdict against `opts.tol` (or `10·s^{2/3}` for a solve
    /// tolerance `s`, when larger).
    pub verdict: Verdict,
}

impl fmt::Display for FdReport {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        writeln!(
            f,
            "finite differences: {} indices, ‖g‖∞ = {:.3e}, error {:.3e} at {} → {}",
            self.indices_checked, self.scale, self.error, self.worst, self.verdict
        )?;
        for s in &self.sweep {
            write!(f, "  step {:9.2e}: max error {:9.3e} at {}", s.rel_step, s.max_error, s.worst)?;
            if s.crossing_kink > 0 {
                write!(f, " ({} indices skipped: step crosses a kink)", s.crossing_kink)?;
            }
            writeln!(f)?;
        }
        if !self.unusable.is_empty() {
            write!(f, "  no step fits between the point and a kink at: {}", self.unusable.join(", "))?;
        }
        Ok(())
    }
}

/// The smallest relative step whose central difference rounding leaves
/// within tolerance for smooth maps; an index that only smaller steps fit
/// before a kink, and that misses there, is reported as at the kink.
pub const RELIABLE_STEP: f64 = 1e-7;

/// The relative steps of the sweep: decades from 1e-2 to 1e-9 and the
/// principled `ε^{1/3}` (≈ 6.06e-6), largest first.
pub fn sweep_steps() -> Vec<f64> {
    let mut s: Vec<f64> = (2..=9).map(|k| 10f64.powi(-k)).collect();
    s.push(f64::EPSILON.cbrt());
    s.sort_by(|a, b| b.total_cmp(a));
    s
}

fn name(i: usize, n: usize) -> String {
    if i < n { format!("x[{i}]") } else { format!("p[{}]", i - n) }
}

/// Checks the VJP of `op` at `(x, p)` against central differences of
/// `φ(z) = ⟨w, f(z)⟩` for a seeded random weight `w`, index by index, over
/// the steps of [`sweep_steps`].
///
/// Each index is judged at its best step inside the operator's
/// [`smooth_radius`](crate::op::Forward::smooth_radius) along that index:
/// the verdict fails when `max_i min_h |fd_i − g_i| > tol·‖g‖∞`.
#[track_caller]
pub fn finite_differences<O: Vjp>(op: &O, x: &[f64], p: &[f64], opts: &CheckParams) -> FdReport {
    crate::op::check_lengths(op, "finite_differences", x, p, None);
    let (n, m) = (op.n_in(), op.n_params());
    let mut rng = rng(opts, 1);
    let w = random_vector(&mut rng, op.n_out());
    let (gx, gp) = op.vjp_new(x, p, &w);
    let g: Vec<f64> = gx.iter().chain(&gp).copied().collect();
    let scale = max_abs(&g).max(f64::MIN_POSITIVE);

    let mut indices: Vec<usize> = (0..n + m).collect();
    if indices.len() > opts.max_indices.max(2) {
        use rand::seq::SliceRandom;
        let last = n + m - 1;
        let mut middle: Vec<usize> = (1..last).collect();
        middle.shuffle(&mut rng);
        indices = [0, last].into_iter().chain(middle.into_iter().take(opts.max_indices.max(2) - 2)).collect();
        indices.sort_unstable();
    }

    // With inner solves to relative tolerance s, the best central
    // difference is good to about s^{2/3}.
    let solve = opts.solve_tolerance_of(op);
    let tol = opts.tol.max(10.0 * solve.powf(2.0 / 3.0));
    let steps = sweep_steps();
    let mut sweep: Vec<FdStep> = steps.iter().map(|&rel_step| FdStep { rel_step, max_error: 0.0, worst: "-".into(), crossing_kink: 0 }).collect();
    let (mut error, mut worst, mut unusable) = (0.0f64, "-".to_string(), Vec::new());
    let mut y = vec![0.0; op.n_out()];
    let (mut ex, mut ep) = (vec![0.0; n], vec![0.0; m]);
    for &i in &indices {
        let zi = if i < n { x[i] } else { p[i - n] };
        if i < n {
            ex[i] = 1.0
        } else {
            ep[i - n] = 1.0
        }
        let radius = op.smooth_radius(x, p, &ex, &ep);
        let (mut best, mut reliable) = (f64::INFINITY, false);
        for (s, &rel) in sweep.iter_mut().zip(&steps) {
            let h = rel * zi.abs().max(1.0);
            if h >= radius {
                s.crossing_kink += 1;
                continue;
            }
            reliable |= rel >= RELIABLE_STEP;
            let plus = functional(op, &axpy(x, h, &ex), &axpy(p, h, &ep), &w, &mut y);
            let minus = functional(op, &axpy(x, -h, &ex), &axpy(p, -h, &ep), &w, &mut y);
            let err = ((plus - minus) / (2.0 * h) - g[i]).abs() / scale;
            if err > s.max_error || s.worst == "-" {
                s.max_error = s.max_error.max(err);
                s.worst = name(i, n);
            }
            best = best.min(err);
        }
        if i < n {
            ex[i] = 0.0
        } else {
            ep[i - n] = 0.0
        }
        // Only steps below the reliable ones fit before a kink, and they
        // miss: rounding (and a solver's tolerance) swamps them, so the
        // index is as good as on the kink.
        if best.is_infinite() || (!reliable && best > tol) {
            unusable.push(name(i, n));
        } else if best > error || worst == "-" {
            error = error.max(best);
            worst = name(i, n);
        }
    }
    let verdict = if error > tol || error.is_nan() {
        let why = if tol > opts.tol { format!(" (10·s^(2/3) for the solve tolerance s = {solve:.1e})") } else { String::new() };
        Verdict::Fail(format!("relative error {error:.3e} at {worst} exceeds {tol:.1e}{why}"))
    } else if !unusable.is_empty() {
        Verdict::Kink(format!("{} of {} indices sit within the smallest step of a kink: {}", unusable.len(), indices.len(), unusable.join(", ")))
    } else {
        Verdict::Pass
    };
    FdReport { indices_checked: indices.len(), scale, sweep, error, worst, unusable, verdict }
}
