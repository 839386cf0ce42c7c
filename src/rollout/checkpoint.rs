//! The backward pass of a rollout under each checkpointing mode.

use std::str::FromStr;

use super::{Gradient, Loss, Rollout, RolloutError, RolloutStats};
use crate::op::{Real, Vjp};

/// How the states of a rollout are kept for its backward pass.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Checkpointing {
    /// Every state is stored: least compute, `T` states of memory.
    Store,
    /// Every `every`-th state is stored; each segment is recomputed from its
    /// checkpoint during the backward pass (`⌈T/k⌉ + k` states, about one
    /// extra forward). `every ≈ √T` minimises memory.
    Periodic {
        /// Distance `k ≥ 1` between checkpoints.
        every: usize,
    },
    /// Binomial checkpointing (Griewank's *revolve* schedule) with at most
    /// `snapshots` extra states: memory `s + 2` states, recomputation
    /// `r·T` steps with `r` the smallest integer such that `C(s + r, s) ≥ T`.
    /// With `s ≈ log₂ T` memory grows as `log T`.
    Binomial {
        /// Number `s ≥ 1` of snapshots.
        snapshots: usize,
    },
}

impl Checkpointing {
    /// Periodic checkpoints every `⌈√T⌉` steps.
    pub fn periodic_sqrt(steps: usize) -> Self {
        Checkpointing::Periodic { every: (steps as f64).sqrt().ceil().max(1.0) as usize }
    }

    /// Binomial checkpointing with `⌈log₂ T⌉` snapshots (at least 1).
    pub fn binomial_log(steps: usize) -> Self {
        Checkpointing::Binomial { snapshots: (usize::BITS - steps.max(1).leading_zeros()).max(1) as usize }
    }
}

impl FromStr for Checkpointing {
    type Err = String;

    /// `store`, `periodic` (every ⌈√T⌉, resolved later), `periodic:K`,
    /// `binomial` (⌈log₂ T⌉ snapshots), `binomial:S`. `periodic` and
    /// `binomial` without a number are returned with 0, which
    /// [`Checkpointing::resolve`] replaces by the default for `T`.
    fn from_str(s: &str) -> Result<Self, String> {
        let (name, num) = match s.split_once(':') {
            Some((a, b)) => (a, Some(b)),
            None => (s, None),
        };
        let parse = |default: usize| -> Result<usize, String> {
            match num {
                None => Ok(default),
                Some(v) => match v.parse::<usize>() {
                    Ok(k) if k >= 1 => Ok(k),
                    _ => Err(format!("`{v}` in `{s}` is not a positive integer")),
                },
            }
        };
        match name {
            "store" if num.is_none() => Ok(Checkpointing::Store),
            "periodic" => Ok(Checkpointing::Periodic { every: parse(0)? }),
            "binomial" => Ok(Checkpointing::Binomial { snapshots: parse(0)? }),
            _ => Err(format!("unknown checkpointing `{s}` (expected store, periodic[:K] or binomial[:S])")),
        }
    }
}

impl Checkpointing {
    /// Replaces a zero parameter (from parsing `periodic` or `binomial`
    /// alone) by the default for `steps`.
    pub fn resolve(self, steps: usize) -> Self {
        match self {
            Checkpointing::Periodic { every: 0 } => Checkpointing::periodic_sqrt(steps),
            Checkpointing::Binomial { snapshots: 0 } => Checkpointing::binomial_log(steps),
            m => m,
        }
    }
}

impl std::fmt::Display for Checkpointing {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Checkpointing::Store => write!(f, "store"),
            Checkpointing::Periodic { every } => write!(f, "periodic:{every}"),
            Checkpointing::Binomial { snapshots } => write!(f, "binomial:{snapshots}"),
        }
    }
}

/// State of one backward pass: adjoints, buffer accounting, counters.
pub(super) struct Backward<'r, 'a, O, L, R> {
    rollout: &'r Rollout<'a, O, R>,
    loss: &'r L,
    n: usize,
    /// Gradient of one loss term.
    term: Vec<R>,
    /// Adjoint of the current state (the seed of the next VJP).
    lam: Vec<R>,
    /// Buffer the next VJP overwrites.
    lam_next: Vec<R>,
    dp: Vec<R>,
    /// The parameters' cotangent in the operator's own form
    /// ([`Vjp::vjp_deferred`]), when the parameters are the same at every
    /// step; turned into `dp` at the end.
    deferred: Option<Vec<R>>,
    /// Recycled state buffers.
    free: Vec<Vec<R>>,
    live: usize,
    stats: RolloutStats,
    /// The first step (in backward order) whose adjoint was found not
    /// finite.
    non_finite: Option<usize>,
    /// Check the adjoint after every `check_every`-th VJP (and the last).
    check_every: usize,
    /// VJPs run so far.
    vjps: usize,
    /// Reverses the segments of a periodic schedule on two threads
    /// ([`reverse_two_threads`]); `None`: on this thread, in turn.
    two_threads: Option<TwoThreads<O, L, R>>,
}

/// [`reverse_two_threads`] for one operator and loss, as a function pointer:
/// it needs both to be `Sync`, which the generic backward pass does not ask
/// of every rollout, so the caller that knows it passes this in.
/// Arguments: the backward pass, the checkpoint store, the distance `k`,
/// the last segment's states (kept by the forward pass) and a spare buffer
/// of `k − 1` states; returns the two buffers.
pub(super) type TwoThreads<O, L, R> = for<'r, 'a, 's> fn(&mut Backward<'r, 'a, O, L, R>, &'s [R], usize, Vec<Vec<R>>, Vec<Vec<R>>) -> [Vec<Vec<R>>; 2];

/// `seg[i] = x_{a+1+i}` from `ckpt = x_a`, by the rollout's steps.
pub(super) fn recompute<R: Real, O: Vjp<R>>(r: &Rollout<'_, O, R>, a: usize, ckpt: &[R], seg: &mut [Vec<R>]) {
    for i in 0..seg.len() {
        let (done, rest) = seg.split_at_mut(i);
        let src: &[R] = if i == 0 { ckpt } else { &done[i - 1] };
        r.op.forward(src, r.p_at(a + i), &mut rest[0]);
    }
}

impl<'r, 'a, R: Real, O: Vjp<R>, L: Loss<R>> Backward<'r, 'a, O, L, R> {
    fn alloc(&mut self) -> Vec<R> {
        self.live += 1;
        self.stats.peak_states = self.stats.peak_states.max(self.live);
        self.free.pop().unwrap_or_else(|| vec![R::zero(); self.n])
    }

    fn release(&mut self, v: Vec<R>) {
        self.live -= 1;
        self.free.push(v);
    }

    /// `y = x_{t+1}` from `x = x_t`.
    fn step(&mut self, t: usize, x: &[R], y: &mut [R]) {
        self.stats.step_evaluations += 1;
        self.rollout.op.forward(x, self.rollout.p_at(t), y);
    }

    /// `ℓ_t(x_t)` if step `t` has a loss term, else 0; with `seed`, its
    /// gradient is also added into `λ`.
    fn loss_term(&mut self, t: usize, x: &[R], seed: bool) -> f64 {
        if !self.loss.has_term(t, self.rollout.steps) {
            return 0.0;
        }
        let value = self.loss.term(t, x, &mut self.term);
        if seed {
            for (l, g) in self.lam.iter_mut().zip(&self.term) {
                *l += *g;
            }
        }
        value
    }

    /// `λ_t = (∂f/∂x at x_t)ᵀ·λ_{t+1} + ∂ℓ_t/∂x_t`, `dp_t += (∂f/∂p at
    /// x_t)ᵀ·λ_{t+1}`; `next` is `x_{t+1}` where the schedule holds it
    /// (an implicit step's VJP then needs no solve of its own).
    fn vjp(&mut self, t: usize, x: &[R], next: Option<&[R]>) {
        let r = self.rollout;
        if t + 1 == r.steps && self.non_finite.is_none() && !super::all_finite(&self.lam) {
            // The seed itself: the loss gradient at x_T.
            self.non_finite = Some(r.steps);
        }
        let (lam, lam_next, p) = (&mut self.lam, &mut self.lam_next, r.p_at(t));
        match (&mut self.deferred, next) {
            (Some(acc), _) => r.op.vjp_deferred(x, p, next, lam, lam_next, acc),
            (None, Some(y)) => r.op.vjp_overwrite_given(x, p, y, lam, lam_next, &mut self.dp[r.block(t)]),
            (None, None) => r.op.vjp_overwrite(x, p, lam, lam_next, &mut self.dp[r.block(t)]),
        }
        std::mem::swap(&mut self.lam, &mut self.lam_next);
        if t > 0 {
            self.loss_term(t, x, true);
        }
        // Where a NaN or infinity enters the adjoint: checked every
        // `check_every` steps and after the last, since a NaN, once in the
        // adjoint, stays in it through every VJP that multiplies (one that
        // selects, like a clamp's, could drop it between two checks: then
        // it is not reported, and did not reach the gradient). `run` is
        // called again with 1 to name the exact step.
        self.vjps += 1;
        if self.non_finite.is_none() && (t == 0 || self.vjps.is_multiple_of(self.check_every)) && !super::all_finite(&self.lam) {
            self.non_finite = Some(t);
        }
    }

    /// Reverses steps `a..b` of a periodic segment from `x_a = ckpt`,
    /// `seg[i] = x_{a+1+i}` and, where known, `x_b = after`.
    fn reverse(&mut self, a: usize, b: usize, ckpt: &[R], seg: &[Vec<R>], after: Option<&[R]>) {
        for t in (a..b).rev() {
            let x: &[R] = if t == a { ckpt } else { &seg[t - a - 1] };
            let next = if t + 1 < b { Some(&seg[t - a][..]) } else { after };
            self.vjp(t, x, next);
        }
    }

    /// A new buffer holding `x_{t+k}` from `from = x_t`.
    fn advance(&mut self, from: &[R], t: usize, k: usize) -> Vec<R> {
        let mut out = self.alloc();
        out.copy_from_slice(from);
        if k > 0 {
            let mut tmp = self.alloc();
            for s in t..t + k {
                self.step(s, &out, &mut tmp);
                std::mem::swap(&mut out, &mut tmp);
            }
            self.release(tmp);
        }
        out
    }

    /// Reverses steps `a..b`, given `x_a`, with `s` snapshots to spare.
    /// The left part is a loop, not a call: the recursion is at most `s`
    /// deep (with one snapshot and 10⁵ steps a recursive left part
    /// overflowed the stack).
    fn binomial(&mut self, a: usize, mut b: usize, xa: &[R], s: usize) {
        loop {
            let t = b - a;
            if t == 1 {
                self.vjp(a, xa, None);
                return;
            }
            if s == 0 {
                for j in (a..b).rev() {
                    let xj = self.advance(xa, a, j - a);
                    self.vjp(j, &xj, None);
                    self.release(xj);
                }
                return;
            }
            let m = b - split(t, s);
            let xm = self.advance(xa, a, m - a);
            self.binomial(m, b, &xm, s - 1);
            self.release(xm);
            b = m;
        }
    }
}

/// The length of the right part when `t > 1` steps are reversed with
/// `s ≥ 1` snapshots: the right part is reversed with one snapshot fewer,
/// the left with one repetition fewer (`|right| ≤ β(s−1, r)`,
/// `|left| ≤ β(s, r−1)`, `r` the smallest with `C(s + r, s) ≥ t`).
pub(super) fn split(t: usize, s: usize) -> usize {
    // `C(s + r, s)` grows with `r`: double, then bisect (one snapshot
    // needs r = t − 1, too many for a linear search over 10⁵ steps).
    let enough = |r: usize| binom(s + r, s) >= t as u128;
    let mut hi = 1;
    while !enough(hi) {
        hi *= 2;
    }
    let mut lo = hi / 2;
    while lo + 1 < hi {
        let mid = lo + (hi - lo) / 2;
        if enough(mid) { hi = mid } else { lo = mid }
    }
    let r = if enough(lo.max(1)) { lo.max(1) } else { hi };
    (binom(s - 1 + r, s - 1).min(t as u128 - 1)) as usize
}

/// `C(n, k)`, saturating.
pub(super) fn binom(n: usize, k: usize) -> u128 {
    let mut c: u128 = 1;
    for i in 0..k as u128 {
        c = c.saturating_mul(n as u128 - i) / (i + 1);
    }
    c
}

/// Buffers a rollout's backward pass reuses from one call to the next: the
/// checkpoint store and the state buffers. Reusing them (as a training loop
/// does) saves the allocation and first-touch page faults of every call,
/// which for a stored trajectory can cost as much as the arithmetic.
#[derive(Debug)]
pub struct Workspace<R = f64> {
    store: Vec<R>,
    free: Vec<Vec<R>>,
}

impl<R> Default for Workspace<R> {
    fn default() -> Self {
        Self { store: Vec::new(), free: Vec::new() }
    }
}

impl<R> Workspace<R> {
    /// An empty workspace; it grows to what the rollouts run in it need.
    pub fn new() -> Self {
        Self::default()
    }
}

/// How often the backward pass checks its adjoint for NaN and infinity:
/// every this many steps. A check reads the whole adjoint (about a quarter
/// of a P1 step at 16384 cells); once a NaN is found, the backward pass is
/// run again checking every step to name the step where it entered.
pub(super) const CHECK_EVERY: usize = 16;

/// The loss and gradient of `r` from `x0`, checking the adjoint every
/// `check_every` steps (see [`CHECK_EVERY`]).
pub(super) fn run<R: Real, O: Vjp<R>, L: Loss<R>>(
    r: &Rollout<'_, O, R>,
    ws: &mut Workspace<R>,
    x0: &[R],
    loss: &L,
    mode: Checkpointing,
    check_every: usize,
    two_threads: Option<TwoThreads<O, L, R>>,
) -> Result<Gradient<R>, RolloutError> {
    let n = x0.len();
    let steps = r.steps;
    let mut free = std::mem::take(&mut ws.free);
    free.retain(|v| v.len() == n);
    let mut bw = Backward {
        rollout: r,
        loss,
        n,
        term: vec![R::zero(); n],
        lam: vec![R::zero(); n],
        lam_next: vec![R::zero(); n],
        dp: vec![R::zero(); r.p.len()],
        deferred: (!r.per_step).then(|| vec![R::zero(); r.op.n_deferred()]),
        free,
        live: 0,
        stats: RolloutStats { steps, ..Default::default() },
        non_finite: None,
        check_every: check_every.max(1),
        vjps: 0,
        two_threads,
    };
    // With no steps the loss is on x_0 itself.
    let value = if steps == 0 {
        bw.loss_term(0, x0, true)
    } else {
        match mode.resolve(steps) {
            Checkpointing::Store => periodic(&mut bw, &mut ws.store, x0, 1),
            Checkpointing::Periodic { every } => periodic(&mut bw, &mut ws.store, x0, every),
            Checkpointing::Binomial { snapshots } => {
                // Forward once for the loss (two buffers), then reverse.
                let mut x = bw.advance(x0, 0, 0);
                let mut tmp = bw.alloc();
                let mut value = 0.0;
                for t in 0..steps {
                    bw.step(t, &x, &mut tmp);
                    std::mem::swap(&mut x, &mut tmp);
                    value += bw.loss_term(t + 1, &x, t + 1 == steps);
                }
                bw.release(tmp);
                bw.release(x);
                if steps > 0 {
                    let x0v = bw.advance(x0, 0, 0);
                    bw.binomial(0, steps, &x0v, snapshots);
                    bw.release(x0v);
                }
                value
            }
        }
    };
    if let Some(mut acc) = bw.deferred.take() {
        r.op.finish_deferred(r.p, &mut acc, &mut bw.dp);
    }
    bw.stats.peak_state_bytes = bw.stats.peak_states * n * std::mem::size_of::<R>();
    ws.free = std::mem::take(&mut bw.free);
    if let Some(step) = bw.non_finite {
        return Err(RolloutError::NonFinite { pass: super::Pass::Backward, step, operator: crate::op::Forward::<R>::name(r.op) });
    }
    Ok(Gradient { loss: value, dx0: bw.lam, dp: bw.dp, stats: bw.stats })
}

/// Stores `x_0, x_k, x_2k, …` in one flat buffer during the forward pass and
/// recomputes each segment from its checkpoint in the backward pass. The
/// forward pass writes each checkpoint in place (no copy) and keeps the
/// states of the last segment, which is therefore not recomputed. With
/// `k = 1` nothing is recomputed and each step writes straight into its
/// slot.
fn periodic<R: Real, O: Vjp<R>, L: Loss<R>>(bw: &mut Backward<'_, '_, O, L, R>, store: &mut Vec<R>, x0: &[R], k: usize) -> f64 {
    let (n, steps) = (bw.n, bw.rollout.steps);
    let n_ckpt = steps.div_ceil(k).max(1);
    if store.len() < n_ckpt * n {
        store.resize(n_ckpt * n, R::zero());
    }
    let store = &mut store[..n_ckpt * n];
    bw.live += n_ckpt;
    store[..n].copy_from_slice(x0);
    // seg[i] holds x_{a+1+i} for the segment a..b being reversed.
    let mut seg: Vec<Vec<R>> = (0..k.min(steps) - 1).map(|_| bw.alloc()).collect();
    let (mut x, mut y) = (bw.alloc(), bw.alloc());
    let a_last = (n_ckpt - 1) * k;
    let mut value = 0.0;
    // Forward up to the last checkpoint: x_t lives in its checkpoint slot
    // (t a multiple of k) or in `x`.
    for t in 0..a_last {
        let next = (t + 1).is_multiple_of(k);
        if t.is_multiple_of(k) && next {
            // k = 1: slot to slot.
            let (done, rest) = store.split_at_mut((t + 1) * n);
            bw.step(t, &done[t * n..], &mut rest[..n]);
            value += bw.loss_term(t + 1, &rest[..n], false);
        } else if next {
            let c = (t + 1) / k;
            bw.step(t, &x, &mut store[c * n..(c + 1) * n]);
            value += bw.loss_term(t + 1, &store[c * n..(c + 1) * n], false);
        } else {
            let c = t / k;
            let src: &[R] = if t.is_multiple_of(k) { &store[c * n..(c + 1) * n] } else { &x };
            bw.step(t, src, &mut y);
            std::mem::swap(&mut x, &mut y);
            value += bw.loss_term(t + 1, &x, false);
        }
    }
    // The last segment: its states go straight into `seg`, x_T into `y`.
    for t in a_last..steps {
        let i = t - a_last;
        let (done, rest) = seg.split_at_mut(i);
        let src: &[R] = if i == 0 { &store[(n_ckpt - 1) * n..] } else { &done[i - 1] };
        if t + 1 < steps {
            bw.step(t, src, &mut rest[0]);
            value += bw.loss_term(t + 1, &rest[0], false);
        } else {
            bw.step(t, src, &mut y);
            value += bw.loss_term(t + 1, &y, true);
        }
    }
    bw.release(x);
    // Backward, segment by segment from the last: on two threads, or here,
    // each segment recomputed from its checkpoint in turn.
    if let Some(two) = bw.two_threads.filter(|_| n_ckpt > 1 && k > 1) {
        bw.release(y);
        let spare = (0..k - 1).map(|_| bw.alloc()).collect();
        for s in two(bw, store, k, seg, spare).into_iter().flatten() {
            bw.release(s);
        }
        bw.live -= n_ckpt;
        return value;
    }
    for c in (0..n_ckpt).rev() {
        let (a, b) = (c * k, ((c + 1) * k).min(steps));
        let ckpt = &store[c * n..(c + 1) * n];
        if c + 1 < n_ckpt {
            recompute(bw.rollout, a, ckpt, &mut seg[..b - a - 1]);
            bw.stats.step_evaluations += b - a - 1;
        }
        // x_b: the next checkpoint, or x_T after the last segment.
        let after: &[R] = if c + 1 < n_ckpt { &store[(c + 1) * n..(c + 2) * n] } else { &y };
        bw.reverse(a, b, ckpt, &seg, Some(after));
    }
    bw.release(y);
    for s in seg {
        bw.release(s);
    }
    bw.live -= n_ckpt;
    value
}

/// The backward pass of a periodic schedule on two threads of the current
/// rayon pool. Each thread in turn claims the next segment (from the last
/// down), recomputes its states from the checkpoint into its own buffer,
/// waits until the segment after it has been reversed, then reverses it:
/// the states are read by the core that wrote them (from its own cache),
/// and one thread's recomputation overlaps the other's reversal. The
/// adjoint passes from thread to thread once per segment. The steps run in
/// the same order on the same states as on one thread, so the result is the
/// same bit for bit. While waiting, a thread runs other jobs of the pool
/// (the halves of split steps, see `op::stencil`).
///
/// If the second thread never starts, the first does every segment in
/// order (it then never waits); a panic in either thread stops the other.
pub(super) fn reverse_two_threads<R: Real, O: Vjp<R> + Sync, L: Loss<R> + Sync>(
    bw: &mut Backward<'_, '_, O, L, R>,
    store: &[R],
    k: usize,
    last: Vec<Vec<R>>,
    spare: Vec<Vec<R>>,
) -> [Vec<Vec<R>>; 2] {
    use std::sync::Mutex;
    use std::sync::atomic::{AtomicBool, AtomicIsize, AtomicUsize, Ordering};
    let (n, steps, rollout) = (bw.n, bw.rollout.steps, bw.rollout);
    let n_ckpt = steps.div_ceil(k);
    // Segments c < next_claim + 1 are not yet claimed; segments ≥ reversed
    // are reversed.
    let next_claim = AtomicIsize::new(n_ckpt as isize - 2);
    let reversed = AtomicUsize::new(n_ckpt);
    let stop = AtomicBool::new(false);
    let shared = Mutex::new(bw);
    /// Sets `stop` when its thread unwinds.
    struct StopOnPanic<'s>(&'s AtomicBool);
    impl Drop for StopOnPanic<'_> {
        fn drop(&mut self) {
            if std::thread::panicking() {
                self.0.store(true, Ordering::Release);
            }
        }
    }
    let work = |mut seg: Vec<Vec<R>>, mut first: Option<usize>| -> Vec<Vec<R>> {
        let _guard = StopOnPanic(&stop);
        loop {
            // The last segment's states come from the forward pass; any
            // other segment is claimed and recomputed.
            let (c, recomputed) = match first.take() {
                Some(c) => (c, false),
                None => match usize::try_from(next_claim.fetch_sub(1, Ordering::Relaxed)) {
                    Ok(c) => (c, true),
                    Err(_) => return seg,
                },
            };
            let (a, b) = (c * k, ((c + 1) * k).min(steps));
            let ckpt = &store[c * n..(c + 1) * n];
            if recomputed {
                recompute(rollout, a, ckpt, &mut seg[..b - a - 1]);
            }
            while reversed.load(Ordering::Acquire) != c + 1 {
                if stop.load(Ordering::Acquire) {
                    return seg;
                }
                if rayon::yield_now() != Some(rayon::Yield::Executed) {
                    std::hint::spin_loop();
                }
            }
            let Ok(mut bw) = shared.lock() else { return seg };
            if recomputed {
                bw.stats.step_evaluations += b - a - 1;
            }
            let after = (c + 1 < n_ckpt).then(|| &store[(c + 1) * n..(c + 2) * n]);
            bw.reverse(a, b, ckpt, &seg, after);
            drop(bw);
            reversed.store(c, Ordering::Release);
        }
    };
    let (x, y) = rayon::join(|| work(last, Some(n_ckpt - 1)), || work(spare, None));
    [x, y]
}
