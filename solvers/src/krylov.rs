//! BiCGStab (van der Vorst 1992) for a general square system given as a
//! matrix-vector product: the solve of an implicit step whose matrix is
//! not symmetric (advection–diffusion, a transposed solve), where
//! [`crate::cg`] does not apply. Plain ([`bicgstab`]) or preconditioned
//! on the right ([`bicgstab_preconditioned`]: it solves `A·M⁻¹·u = b`,
//! `x = M⁻¹·u`, so its residual is the system's own); convergence is
//! confirmed on the true residual `‖b − A·x‖₂ ≤ tol·‖b‖₂`, restarting from
//! it when the recursive one drifted.

use crate::cg::{NoConvergence, Stop};

fn dot(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}

/// Solves `A·x = b` with `apply(v, out)` computing `out = A·v`, from
/// `x = 0` (or from the `x` given when `warm` and finite); overwrites `x`.
/// Returns the matrix products taken, or the residual reached when
/// `stop.max_iterations` products pass, the iteration breaks down, or a
/// value is not finite.
///
/// # Panics
/// If `b` and `x` differ in length.
pub fn bicgstab(apply: impl FnMut(&[f64], &mut [f64]), stop: Stop, b: &[f64], x: &mut [f64], warm: bool) -> Result<usize, NoConvergence> {
    run(apply, None, stop, b, x, warm)
}

/// [`bicgstab`] preconditioned on the right by `precondition(r, z)`,
/// `z = M⁻¹·r` for a non-singular `M` close to `A` (its diagonal, say):
/// the iteration solves `A·M⁻¹·u = b` and returns `x = M⁻¹·u`, so the
/// residual it measures and stops on is `b − A·x` itself.
///
/// # Panics
/// If `b` and `x` differ in length.
pub fn bicgstab_preconditioned(
    apply: impl FnMut(&[f64], &mut [f64]),
    mut precondition: impl FnMut(&[f64], &mut [f64]),
    stop: Stop,
    b: &[f64],
    x: &mut [f64],
    warm: bool,
) -> Result<usize, NoConvergence> {
    run(apply, Some(&mut precondition), stop, b, x, warm)
}

/// A right preconditioner, `z = M⁻¹·r`.
type Preconditioner<'a> = &'a mut dyn FnMut(&[f64], &mut [f64]);

/// `M⁻¹·v` into `out` and a view of it, or `v` itself without `M`.
fn preconditioned<'a>(precondition: &mut Option<Preconditioner<'_>>, v: &'a [f64], out: &'a mut [f64]) -> &'a [f64] {
    match precondition {
        Some(m) => {
            m(v, out);
            out
        }
        None => v,
    }
}

fn run(
    mut apply: impl FnMut(&[f64], &mut [f64]),
    mut precondition: Option<Preconditioner<'_>>,
    stop: Stop,
    b: &[f64],
    x: &mut [f64],
    warm: bool,
) -> Result<usize, NoConvergence> {
    let n = b.len();
    assert_eq!(x.len(), n, "bicgstab: b and x differ in length");
    let fail = |iterations: usize, residual: f64| NoConvergence { iterations, relative_residual: residual, tolerance: stop.tolerance };
    let bnorm = dot(b, b).sqrt();
    if !bnorm.is_finite() {
        return Err(fail(0, f64::NAN));
    }
    if bnorm == 0.0 {
        x.fill(0.0);
        return Ok(0);
    }
    if !(warm && x.iter().all(|v| v.is_finite())) {
        x.fill(0.0);
    }
    let target = stop.tolerance * bnorm;
    let (mut r, mut t) = (vec![0.0; n], vec![0.0; n]);
    let true_residual = |apply: &mut dyn FnMut(&[f64], &mut [f64]), x: &[f64], r: &mut [f64], t: &mut [f64]| {
        apply(x, t);
        for ((r, b), t) in r.iter_mut().zip(b).zip(t.iter()) {
            *r = b - t;
        }
        dot(r, r).sqrt()
    };
    let mut products = 1;
    let mut rnorm = true_residual(&mut apply, x, &mut r, &mut t);
    let (mut p, mut v, mut s, mut r0) = (vec![0.0; n], vec![0.0; n], vec![0.0; n], r.clone());
    // M⁻¹·p and M⁻¹·s (unused without M).
    let (mut mp, mut ms) = if precondition.is_some() { (vec![0.0; n], vec![0.0; n]) } else { (Vec::new(), Vec::new()) };
    let (mut rho, mut alpha, mut omega) = (1.0, 1.0, 1.0);
    loop {
        if rnorm <= target {
            // Confirm on the true residual; restart from it if needed.
            rnorm = true_residual(&mut apply, x, &mut r, &mut t);
            products += 1;
            if rnorm <= target {
                return Ok(products);
            }
            r0.copy_from_slice(&r);
            (rho, alpha, omega) = (1.0, 1.0, 1.0);
            p.fill(0.0);
            v.fill(0.0);
        }
        if products >= stop.max_iterations || !rnorm.is_finite() {
            return Err(fail(products, rnorm / bnorm));
        }
        let rho_new = dot(&r0, &r);
        if rho_new == 0.0 || omega == 0.0 {
            // Breakdown: restart from the current residual.
            r0.copy_from_slice(&r);
            (rho, alpha, omega) = (1.0, 1.0, 1.0);
            p.fill(0.0);
            v.fill(0.0);
            if dot(&r0, &r) == 0.0 {
                return Err(fail(products, rnorm / bnorm));
            }
            continue;
        }
        let beta = (rho_new / rho) * (alpha / omega);
        rho = rho_new;
        for ((p, r), v) in p.iter_mut().zip(&r).zip(&v) {
            *p = r + beta * (*p - omega * v);
        }
        let ph = preconditioned(&mut precondition, &p, &mut mp);
        apply(ph, &mut v);
        products += 1;
        alpha = rho / dot(&r0, &v);
        for ((s, r), v) in s.iter_mut().zip(&r).zip(&v) {
            *s = r - alpha * v;
        }
        let snorm = dot(&s, &s).sqrt();
        if snorm <= target {
            for (x, p) in x.iter_mut().zip(ph) {
                *x += alpha * p;
            }
            r.copy_from_slice(&s);
            rnorm = snorm;
            continue;
        }
        let sh = preconditioned(&mut precondition, &s, &mut ms);
        apply(sh, &mut t);
        products += 1;
        omega = dot(&t, &s) / dot(&t, &t);
        for ((x, p), s) in x.iter_mut().zip(ph).zip(sh) {
            *x += alpha * p + omega * s;
        }
        for ((r, s), t) in r.iter_mut().zip(&s).zip(&t) {
            *r = s - omega * t;
        }
        rnorm = dot(&r, &r).sqrt();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Advection–diffusion on a line: `(2 + c)·x_i − (1 + c)·x_{i−1} −
    /// x_{i+1}`, not symmetric.
    fn apply(c: f64) -> impl FnMut(&[f64], &mut [f64]) {
        move |v, out| {
            let n = v.len();
            for i in 0..n {
                let left = if i > 0 { v[i - 1] } else { 0.0 };
                let right = if i + 1 < n { v[i + 1] } else { 0.0 };
                out[i] = (2.0 + c) * v[i] - (1.0 + c) * left - right;
            }
        }
    }

    #[test]
    fn bicgstab_solves_a_nonsymmetric_system_to_its_tolerance() {
        let n = 60;
        let b: Vec<f64> = (0..n).map(|i| (0.2 * i as f64).sin() + 0.1).collect();
        let mut x = vec![0.0; n];
        let stop = Stop { tolerance: 1e-10, max_iterations: 1000 };
        let products = bicgstab(apply(0.7), stop, &b, &mut x, false).unwrap();
        assert!(products > 2 && products < 1000);
        let mut ax = vec![0.0; n];
        apply(0.7)(&x, &mut ax);
        let res: f64 = ax.iter().zip(&b).map(|(a, b)| (a - b) * (a - b)).sum::<f64>().sqrt();
        assert!(res <= 1e-10 * dot(&b, &b).sqrt(), "residual {res}");
        // Too few products: an error with the residual reached.
        let e = bicgstab(apply(0.7), Stop { tolerance: 1e-14, max_iterations: 4 }, &b, &mut x, false).unwrap_err();
        assert!(e.iterations >= 4 && e.relative_residual > 1e-14, "{e:?}");
        // A right-hand side that is not finite is refused before any product.
        let mut bad = b.clone();
        bad[3] = f64::NAN;
        assert!(bicgstab(apply(0.7), stop, &bad, &mut x, false).unwrap_err().relative_residual.is_nan());
    }

    /// The same system with its rows scaled over four orders of magnitude:
    /// plain BiCGStab slows down, the diagonal on the right brings it back,
    /// and both reach the tolerance on the true residual.
    #[test]
    fn a_diagonal_preconditioner_on_the_right_undoes_a_bad_row_scaling() {
        let n = 80;
        let scale: Vec<f64> = (0..n).map(|i| 10f64.powf(4.0 * ((i * 37) % n) as f64 / n as f64)).collect();
        let scaled = |v: &[f64], out: &mut [f64]| {
            apply(0.7)(v, out);
            out.iter_mut().zip(&scale).for_each(|(o, s)| *o *= s);
        };
        let diagonal: Vec<f64> = scale.iter().map(|s| (2.0 + 0.7) * s).collect();
        let jacobi = |r: &[f64], z: &mut [f64]| z.iter_mut().zip(r).zip(&diagonal).for_each(|((z, r), d)| *z = r / d);
        let b: Vec<f64> = (0..n).map(|i| scale[i] * ((0.3 * i as f64).cos() + 0.2)).collect();
        let stop = Stop { tolerance: 1e-10, max_iterations: 10_000 };
        let residual = |x: &[f64]| {
            let mut ax = vec![0.0; n];
            scaled(x, &mut ax);
            ax.iter().zip(&b).map(|(a, b)| (a - b) * (a - b)).sum::<f64>().sqrt() / dot(&b, &b).sqrt()
        };
        let (mut plain, mut right) = (vec![0.0; n], vec![0.0; n]);
        let k_plain = bicgstab(scaled, stop, &b, &mut plain, false).unwrap();
        let k_right = bicgstab_preconditioned(scaled, jacobi, stop, &b, &mut right, false).unwrap();
        assert!(residual(&plain) <= 1e-10 && residual(&right) <= 1e-10, "{} {}", residual(&plain), residual(&right));
        assert!(2 * k_right < k_plain, "preconditioned {k_right} products, plain {k_plain}");
        for (a, b) in plain.iter().zip(&right) {
            assert!((a - b).abs() <= 1e-7 * (1.0 + a.abs()), "{a} {b}");
        }
    }
}
