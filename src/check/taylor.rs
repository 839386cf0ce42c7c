//! The Taylor remainder test.

use std::fmt;

use super::{CheckParams, Verdict, axpy, dot, functional, max_abs, random_vector, rng};
use crate::op::{OperatorExt, Vjp};

/// Result of [`taylor`].
#[derive(Clone, Debug)]
pub struct TaylorReport {
    /// The steps `h_k = h₀/2^k`.
    pub steps: Vec<f64>,
    /// The remainders `|φ(z + h_k·v) − φ(z) − h_k·⟨∇φ, v⟩|`.
    pub remainders: Vec<f64>,
    /// `log₂(r_k / r_{k+1})` where both remainders stand well above
    /// rounding (`None` elsewhere).
    pub rates: Vec<Option<f64>>,
    /// The smoothness radius along `v` (∞ for smooth operators).
    pub radius: f64,
    /// The noise level of `φ` (its rounding, or the declared solve
    /// tolerance times `|φ|` when larger): remainders at or below `100×`
    /// this carry no rate (printed as "round-off").
    pub rounding: f64,
    /// The verdict: the rates at the smallest usable steps ≥ 1.8.
    pub verdict: Verdict,
    /// Set when larger steps showed lower rates that recover at smaller
    /// ones: a kink (switch) lies within reach of the larger steps.
    pub note: Option<String>,
}

impl fmt::Display for TaylorReport {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        writeln!(f, "taylor remainder (radius {:.2e}) → {}", self.radius, self.verdict)?;
        if let Some(n) = &self.note {
            writeln!(f, "  note: {n}")?;
        }
        for (k, (h, r)) in self.steps.iter().zip(&self.remainders).enumerate() {
            let rate = match self.rates.get(k).copied().flatten() {
                Some(q) => format!("{q:4.2}"),
                None if *r <= 100.0 * self.rounding => "   - (round-off)".to_string(),
                None => "   -".to_string(),
            };
            writeln!(f, "  h {h:9.3e}  remainder {r:9.3e}  rate {rate}")?;
        }
        Ok(())
    }
}

/// Taylor remainder test of `op` at `(x, p)` along a seeded random direction
/// `v`, for `φ = ⟨w, f⟩` with a seeded random `w`.
///
/// With a correct gradient the remainder falls as `h²` (rate 2 when `h`
/// halves); a wrong one leaves a first-order term (rate 1). Steps start at
/// `h₀ = min(0.1, radius/2)` so that they stay on one smooth piece; rates are
/// only taken where the remainder stands 100× above the rounding level of
/// `φ`, and the verdict is taken on the last two (the asymptotic regime);
/// lower rates at larger steps are reported in [`TaylorReport::note`] as an
/// undeclared kink within their reach. Where the signed remainder changes
/// sign between usable steps (its second-order term small along `v`) and
/// the plain rates fail, `4R(h) − R(2h)` is judged instead (no
/// second-order term: rate 3 for a right gradient, 1 for a wrong one),
/// with a note. A remainder at rounding level for every step (a linear operator with
/// an exact gradient) passes, and the report's note says so; a radius too
/// small for any usable step, or one that leaves fewer than three
/// remainders above rounding, gives [`Verdict::Kink`]. Where the operator
/// gives NaN at the larger steps only (the perturbed input leaves its
/// domain), the smaller steps are judged, with a note.
#[track_caller]
pub fn taylor<O: Vjp>(op: &O, x: &[f64], p: &[f64], opts: &CheckParams) -> TaylorReport {
    crate::op::check_lengths(op, "taylor", x, p, None);
    let mut rng = rng(opts, 2);
    let w = random_vector(&mut rng, op.n_out());
    let vx = random_vector(&mut rng, op.n_in());
    let vp = random_vector(&mut rng, op.n_params());
    let (gx, gp) = op.vjp_new(x, p, &w);
    let slope = dot(&gx, &vx) + dot(&gp, &vp);
    let mut y = vec![0.0; op.n_out()];
    let phi0 = functional(op, x, p, &w, &mut y);
    // Rounding level of φ: ε times the sum of magnitudes, with room for the
    // error that the operator's own arithmetic accumulates.
    let magnitude: f64 = w.iter().zip(&y).map(|(a, b)| (a * b).abs()).sum::<f64>() + phi0.abs();
    let rounding = 1e3 * f64::EPSILON * magnitude.max(f64::MIN_POSITIVE);

    let radius = op.smooth_radius(x, p, &vx, &vp);
    let zscale = max_abs(x).max(max_abs(p)).max(1.0);
    let h0 = (0.1 * zscale).min(0.5 * radius);
    let steps: Vec<f64> = (0..16).map(|k| h0 / 2f64.powi(k)).collect();
    let signed: Vec<f64> = steps.iter().map(|&h| functional(op, &axpy(x, h, &vx), &axpy(p, h, &vp), &w, &mut y) - phi0 - h * slope).collect();
    let remainders: Vec<f64> = signed.iter().map(|r| r.abs()).collect();
    // The perturbed point may leave the operator's domain at the larger
    // steps (a concentration turned negative, a solve without a root): its
    // output there is NaN. If every smaller step gives a number, judge on
    // those; a NaN below a number is a failure.
    let skip = remainders.iter().rposition(|r| r.is_nan()).map_or(0, |k| k + 1);
    let skip = if skip < steps.len() && slope.is_finite() { skip } else { 0 };
    let mut judged = judge(&steps[skip..], &remainders[skip..], slope, rounding, h0, radius, zscale);
    if matches!(judged.verdict, Verdict::Fail(_))
        && skip == 0
        && let Some(again) = across_a_sign_change(&steps, &signed, rounding)
    {
        judged = Judged { rates: judged.rates, ..again };
    }
    if skip > 0 {
        judged.rates.splice(0..0, std::iter::repeat_n(None, skip));
        judged.note.get_or_insert(format!(
            "the operator gives no finite value at steps ≥ {:.2e} (its input leaves the domain there, or its solve fails): judged on the smaller steps",
            steps[skip - 1]
        ));
    }
    // An inner solve to relative tolerance s leaves errors of up to about
    // s·|φ|. Where the rates at rounding level fail and the operator
    // declares its solves' tolerance, judge again above the solver's level:
    // a pass there is the gradient's, and nothing left to judge is the
    // tolerance's limit, not the gradient's fault.
    let solve = opts.solve_tolerance_of(op);
    let level = solve * magnitude;
    if level > rounding && matches!(judged.verdict, Verdict::Fail(_)) && !(remainders[skip..].iter().any(|r| r.is_nan()) || slope.is_nan()) {
        let mut again = judge(&steps[skip..], &remainders[skip..], slope, level, h0, radius, zscale);
        again.rates.splice(0..0, std::iter::repeat_n(None, skip));
        judged = if again.judged_rates {
            let note = again.verdict.passed().then(|| {
                format!("the remainders below {:.1e} (100× the solver's level, solve tolerance {solve:.1e}) carry no rate: at rounding level the solves' errors showed", 100.0 * level)
            });
            Judged { note: note.or(again.note), ..again }
        } else {
            let left = again.rates.iter().flatten().count();
            Judged {
                verdict: Verdict::Tolerance(format!(
                    "{left} rate(s) left above 100× the solver's level {level:.1e} (solve tolerance {solve:.1e}); tighten the solves to test the gradient"
                )),
                ..again
            }
        };
    }
    let Judged { rates, verdict, note, noise, .. } = judged;
    TaylorReport { steps, remainders, rates, radius, rounding: noise, verdict, note }
}

/// A verdict on the remainders with noise level `noise`.
struct Judged {
    rates: Vec<Option<f64>>,
    verdict: Verdict,
    note: Option<String>,
    noise: f64,
    /// Two rates at the smallest usable steps were there to judge.
    judged_rates: bool,
}

/// The remainder `R(h) = a·h² + b·h³ + …` of a right gradient changes sign
/// where its second-order term is small along the direction (`a` and `b·h`
/// of opposite signs): its rates dip near the crossing and climb back to 2
/// only a few halvings later, perhaps below rounding, which fails the
/// plain judgement on a right gradient. Where the signed remainders
/// `signed` change sign between usable steps, judge instead the Richardson
/// combination `E(h) = 4R(h) − R(2h) = 2εh − 4b·h³ + …`: `a` cancels
/// exactly, so a right gradient (`ε = 0`) leaves `E` falling at rate 3, a
/// first-order error `ε` at rate 1. Pass on its last two usable rates ≥
/// 2.5 (with a note), fail below 1.8; `None` (keep the plain verdict)
/// without a sign change or with too few usable values.
fn across_a_sign_change(steps: &[f64], signed: &[f64], noise: f64) -> Option<Judged> {
    let usable = |r: f64| r.abs() > 100.0 * noise;
    let crossing = signed.windows(2).position(|r| usable(r[0]) && usable(r[1]) && r[0] * r[1] < 0.0)?;
    // E at each step h_{k+1} = h_k / 2, its noise 5× the remainders'.
    let e: Vec<f64> = signed.windows(2).map(|r| 4.0 * r[1] - r[0]).collect();
    let rates: Vec<f64> = e.windows(2).filter(|e| e[0].abs() > 500.0 * noise && e[1].abs() > 500.0 * noise).map(|e| (e[0] / e[1]).abs().log2()).collect();
    if rates.len() < 2 {
        return None;
    }
    let low = rates[rates.len() - 2..].iter().copied().fold(f64::INFINITY, f64::min);
    let at = steps[crossing + 1];
    let verdict = if low >= 2.5 {
        Verdict::Pass
    } else if low < 1.8 {
        Verdict::Fail(format!(
            "the remainder changes sign near h = {at:.2e}, and 4R(h) − R(2h) falls at rate {low:.2} < 1.8: the gradient leaves a first-order error"
        ))
    } else {
        return None;
    };
    let note = verdict.passed().then(|| {
        format!(
            "the remainder changes sign near h = {at:.2e} (its second-order term is small along this direction), so its rates dip there; judged instead by 4R(h) − R(2h), which has no second-order term: rates {} (3 for a right gradient, 1 for a wrong one)",
            rates.iter().map(|r| format!("{r:.2}")).collect::<Vec<_>>().join(", ")
        )
    });
    Some(Judged { rates: Vec::new(), verdict, note, noise, judged_rates: true })
}

/// The rates where both remainders stand 100× above `noise`, and the
/// verdict on the last two (the asymptotic regime).
fn judge(steps: &[f64], remainders: &[f64], slope: f64, noise: f64, h0: f64, radius: f64, zscale: f64) -> Judged {
    let usable = |r: f64| r > 100.0 * noise;
    let rates: Vec<Option<f64>> = remainders.windows(2).map(|r| (usable(r[0]) && usable(r[1])).then(|| (r[0] / r[1]).log2())).collect();
    let valid: Vec<f64> = rates.iter().flatten().copied().collect();
    // The asymptotic regime is at the smallest steps: judge the last two
    // usable rates; lower rates before them mean the larger steps crossed a
    // kink the operator did not declare.
    let tail = &valid[valid.len().saturating_sub(2)..];
    let mut note = None;

    let verdict = if remainders.iter().any(|r| r.is_nan()) || slope.is_nan() {
        Verdict::Fail("NaN in remainder or gradient".into())
    } else if tail.len() == 2 {
        let low = tail.iter().copied().fold(f64::INFINITY, f64::min);
        if low < 1.8 {
            Verdict::Fail(format!("remainder rate {low:.2} < 1.8 at the smallest steps: the gradient leaves a first-order error"))
        } else {
            if let Some((k, r)) = rates.iter().enumerate().filter_map(|(k, r)| r.map(|r| (k, r))).find(|(_, r)| *r < 1.8) {
                note = Some(format!("rate {r:.2} at h = {:.2e} recovers to ≥ 1.8 at smaller steps: a kink lies within reach of the larger steps", steps[k]));
            }
            Verdict::Pass
        }
    } else if h0 < 1e-6 * zscale {
        Verdict::Kink(format!("a kink lies {radius:.2e} from the point along the test direction; no usable step fits"))
    } else if remainders.iter().all(|&r| r <= 100.0 * noise) {
        // Locally linear (or curvature below rounding) and the gradient
        // exact to rounding: nothing to measure a rate on, and nothing wrong.
        note = Some(format!(
            "every remainder is at round-off (≤ {:.1e}, 100× the rounding level of φ): the map is linear along the test direction (or its curvature is below rounding) and the gradient is exact to rounding, so there is no rate to measure; a wrong gradient would leave a remainder growing like h",
            100.0 * noise
        ));
        Verdict::Pass
    } else if 0.5 * radius < 0.1 * zscale {
        // The steps were shortened to stay short of a declared kink, and
        // those that fit fall to rounding too soon: nothing to judge.
        Verdict::Kink(format!("a kink lies {radius:.2e} from the point along the test direction; the steps that fit leave too few remainders above rounding"))
    } else {
        Verdict::Fail("too few remainders above rounding to measure a rate".into())
    };
    Judged { rates, verdict, note, noise, judged_rates: tail.len() == 2 }
}
