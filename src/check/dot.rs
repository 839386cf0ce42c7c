//! The dot-product (adjoint) test between a JVP and a VJP, and the VJP's
//! buffer contract.

use std::fmt;

use super::{CheckParams, Verdict, dot, random_vector, rng};
use crate::op::{Jvp, OperatorExt, Vjp};

/// Result of [`dot_product`].
#[derive(Clone, Debug)]
pub struct DotReport {
    /// `⟨J·v, w⟩` from the JVP.
    pub jvp_side: f64,
    /// `⟨v, Jᵀ·w⟩` from the VJP.
    pub vjp_side: f64,
    /// `|a − b| / max(|a|, |b|)`.
    pub rel_error: f64,
    /// Violations of the VJP contract (`vjp` accumulates and consumes the
    /// seed; `vjp_overwrite` overwrites `dx`), empty when it holds.
    pub contract: Vec<String>,
    /// The verdict against the tolerance.
    pub verdict: Verdict,
}

impl fmt::Display for DotReport {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "dot product: ⟨Jv,w⟩ = {:.15e}, ⟨v,Jᵀw⟩ = {:.15e}, rel error {:.2e} → {}", self.jvp_side, self.vjp_side, self.rel_error, self.verdict)?;
        for c in &self.contract {
            write!(f, "\n  contract: {c}")?;
        }
        Ok(())
    }
}

/// Dot-product test of an operator's own JVP against its own VJP, with the
/// tolerance `1e-10` (both sides are exact derivatives up to rounding).
#[track_caller]
pub fn dot_product<O: Vjp + Jvp>(op: &O, x: &[f64], p: &[f64], opts: &CheckParams) -> DotReport {
    crate::op::check_lengths(op, "dot_product", x, p, None);
    dot_product_between(op, op, x, p, &CheckParams { tol: 1e-10, ..opts.clone() })
}

/// Dot-product test between the JVP of `a` and the VJP of `b` (two
/// implementations of the same operator), with tolerance `opts.tol`; also
/// checks `b`'s VJP contract.
#[track_caller]
pub fn dot_product_between<A: Jvp, B: Vjp>(a: &A, b: &B, x: &[f64], p: &[f64], opts: &CheckParams) -> DotReport {
    crate::op::check_lengths(a, "dot_product_between", x, p, None);
    let mut rng = rng(opts, 3);
    let vx = random_vector(&mut rng, a.n_in());
    let vp = random_vector(&mut rng, a.n_params());
    let w = random_vector(&mut rng, a.n_out());
    let jv = a.jvp_new(x, p, &vx, &vp);
    let (gx, gp) = b.vjp_new(x, p, &w);
    let jvp_side = dot(&jv, &w);
    let vjp_side = dot(&vx, &gx) + dot(&vp, &gp);
    // Relative to the Cauchy–Schwarz bounds ‖Jv‖·‖w‖ and ‖v‖·‖Jᵀw‖ (each
    // side's size before cancellation): rounding in either product is a
    // fraction of these, while a wrong adjoint misses by as much.
    let norm = |a: &[f64]| dot(a, a).sqrt();
    let bound = (norm(&jv) * norm(&w)).max(norm(&vx).hypot(norm(&vp)) * norm(&gx).hypot(norm(&gp)));
    let rel_error = (jvp_side - vjp_side).abs() / jvp_side.abs().max(vjp_side.abs()).max(bound).max(f64::MIN_POSITIVE);

    // Contract: starting from dx = r, dp = q the VJP must leave r + Jᵀw, q + Jᵀw,
    // and the seed must come back zero.
    let mut contract = Vec::new();
    let r = random_vector(&mut rng, a.n_in());
    let q = random_vector(&mut rng, a.n_params());
    let (mut seed, mut dx, mut dp) = (w.clone(), r.clone(), q.clone());
    b.vjp(x, p, &mut seed, &mut dx, &mut dp);
    if seed.iter().any(|&s| s != 0.0) {
        contract.push("the seed dy was not consumed (zeroed)".into());
    }
    let off = |acc: &[f64], base: &[f64], g: &[f64]| acc.iter().zip(base).zip(g).map(|((a, b), g)| (a - b - g).abs()).fold(0.0, f64::max);
    let scale = gx.iter().chain(&gp).fold(1.0f64, |m, v| m.max(v.abs()));
    if off(&dx, &r, &gx).max(off(&dp, &q, &gp)) > 1e-12 * scale {
        contract.push("dx/dp were overwritten, not accumulated into".into());
    }
    // vjp_overwrite must give the same product whatever dx held before.
    let (mut seed, mut dxo, mut dpo) = (w.clone(), random_vector(&mut rng, a.n_in()), q.clone());
    b.vjp_overwrite(x, p, &mut seed, &mut dxo, &mut dpo);
    if off(&dxo, &vec![0.0; dxo.len()], &gx).max(off(&dpo, &q, &gp)) > 1e-12 * scale {
        contract.push("vjp_overwrite differs from vjp (dx not overwritten, or dp not accumulated)".into());
    }
    // Inner solves to relative tolerance s leave both products off by about s.
    let tol = opts.tol.max(10.0 * opts.solve_tolerance_of(a).max(opts.solve_tolerance_of(b)));
    let verdict = if rel_error.is_nan() || rel_error > tol {
        Verdict::Fail(format!("relative mismatch {rel_error:.2e} exceeds {tol:.1e}"))
    } else if !contract.is_empty() {
        Verdict::Fail(contract.join("; "))
    } else {
        Verdict::Pass
    };
    DotReport { jvp_side, vjp_side, rel_error, contract, verdict }
}
