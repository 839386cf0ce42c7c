//! Minimisation of functions that are smooth except on kinks: the
//! gradient-sampling method of Burke, Lewis & Overton ("A robust gradient
//! sampling algorithm for nonsmooth, nonconvex optimization", SIAM J.
//! Optim. 15, 2005), and the nearest point of a polytope to the origin
//! (Wolfe, "Finding the nearest point in a polytope", Math. Program. 11,
//! 1976) that it needs.
//!
//! Where a function has a kink, its gradient jumps and a gradient-based
//! method (L-BFGS) stalls: no step along the gradient of one side decreases
//! it. The gradients sampled in a ball of radius `ε` around the point,
//! their convex hull's element nearest to zero `g`, give both a descent
//! direction (`−g`) and a stationarity measure: `‖g‖` small means that some
//! combination of nearby gradients vanishes, the point is (Clarke)
//! stationary up to `ε`. The discrete drag of a cut-cell body is such a
//! function (a kink wherever a grid node or face centre crosses the
//! boundary; [`crate::flow::drag_shape`]). Where a function jumps instead
//! of kinking, no step across the jump decreases it and no combination of
//! gradients need vanish there: the method stops without a measure of
//! stationarity, as it should.

use crate::linalg::pseudo_inverse_power_apply;

/// The element of the convex hull of `points` (each of the same length)
/// nearest to the origin, and its weights (one per point, non-negative,
/// summing to 1). Wolfe's algorithm: exact up to rounding, in finitely
/// many steps.
///
/// # Panics
/// If `points` is empty or the lengths differ.
pub fn min_norm_point(points: &[Vec<f64>]) -> (Vec<f64>, Vec<f64>) {
    assert!(!points.is_empty(), "min_norm_point: no points");
    let n = points[0].len();
    assert!(points.iter().all(|p| p.len() == n), "min_norm_point: points of different lengths");
    let dot = |a: &[f64], b: &[f64]| a.iter().zip(b).map(|(x, y)| x * y).sum::<f64>();
    let scale = points.iter().map(|p| dot(p, p)).fold(0.0, f64::max);
    if scale == 0.0 {
        let mut w = vec![0.0; points.len()];
        w[0] = 1.0;
        return (vec![0.0; n], w);
    }
    let combine = |set: &[usize], w: &[f64]| {
        let mut x = vec![0.0; n];
        for (&i, &wi) in set.iter().zip(w) {
            for (xk, pk) in x.iter_mut().zip(&points[i]) {
                *xk += wi * pk;
            }
        }
        x
    };
    let first = (0..points.len()).min_by(|&a, &b| dot(&points[a], &points[a]).total_cmp(&dot(&points[b], &points[b]))).expect("a point");
    let (mut set, mut w) = (vec![first], vec![1.0]);
    let mut x = points[first].clone();
    let tol = 1e-12 * scale;
    for _ in 0..(10 * points.len() + 10) {
        // The point that most decreases the distance, if any.
        let j = (0..points.len()).min_by(|&a, &b| dot(&x, &points[a]).total_cmp(&dot(&x, &points[b]))).expect("a point");
        if dot(&x, &x) - dot(&x, &points[j]) <= tol || set.contains(&j) {
            break;
        }
        set.push(j);
        w.push(0.0);
        // Minor cycles: the nearest point of the affine hull, kept inside
        // the convex hull by dropping the points whose weight reaches 0.
        loop {
            let v = affine_min_norm(points, &set);
            if v.iter().all(|&vi| vi > 1e-14) {
                w = v;
                break;
            }
            let theta = w.iter().zip(&v).filter(|&(_, &vi)| vi <= 1e-14).map(|(&wi, &vi)| wi / (wi - vi)).fold(1.0, f64::min);
            for (wi, vi) in w.iter_mut().zip(&v) {
                *wi = (1.0 - theta) * *wi + theta * vi;
            }
            // Drop the points whose weight has reached zero (at least one).
            let smallest = (0..w.len()).min_by(|&a, &b| w[a].total_cmp(&w[b])).expect("a weight");
            let keep: Vec<usize> = (0..w.len()).filter(|&k| k != smallest && w[k] > 1e-14).collect();
            set = keep.iter().map(|&k| set[k]).collect();
            w = keep.iter().map(|&k| w[k]).collect();
            let total: f64 = w.iter().sum();
            w.iter_mut().for_each(|wi| *wi /= total);
            if set.len() <= 1 {
                break;
            }
        }
        x = combine(&set, &w);
    }
    let mut weights = vec![0.0; points.len()];
    for (&i, &wi) in set.iter().zip(&w) {
        weights[i] = wi;
    }
    (x, weights)
}

/// The weights (summing to 1) of the point of the affine hull of
/// `points[set]` nearest to the origin, by least squares on the
/// differences to the first point (the pseudo-inverse, so that points that
/// are affinely dependent do no harm).
fn affine_min_norm(points: &[Vec<f64>], set: &[usize]) -> Vec<f64> {
    if set.len() == 1 {
        return vec![1.0];
    }
    let n = points[0].len();
    let k = set.len() - 1;
    let p0 = &points[set[0]];
    // Row-major n × k: column c is points[set[c + 1]] − p0.
    let mut d = vec![0.0; n * k];
    for r in 0..n {
        for c in 0..k {
            d[r * k + c] = points[set[c + 1]][r] - p0[r];
        }
    }
    let b: Vec<f64> = p0.iter().map(|v| -v).collect();
    let alpha = pseudo_inverse_power_apply(n, k, &d, &b, 1.0, 1e-12).unwrap_or_else(|_| vec![0.0; k]);
    let mut v = Vec::with_capacity(k + 1);
    v.push(1.0 - alpha.iter().sum::<f64>());
    v.extend(alpha);
    v
}

/// Settings of [`gradient_sampling`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct SamplingParams {
    /// The sampling ball's first radius `ε` (in the parameters' units).
    pub radius: f64,
    /// The smallest radius: stationarity is claimed only at or below it,
    /// and the run ends when `ε` has to shrink below it.
    pub min_radius: f64,
    /// Gradients sampled per iteration (besides the point's own); at
    /// least the number of parameters + 1 for the method's guarantees.
    pub samples: usize,
    /// Iterations at most.
    pub max_iterations: usize,
    /// Stationary when the sampled hull's smallest gradient is at most this.
    pub tolerance: f64,
    /// Seed of the sampling's random numbers (runs are reproducible).
    pub seed: u64,
}

/// The former name of [`SamplingParams`].
#[deprecated(note = "renamed SamplingParams")]
pub type SamplingOptions = SamplingParams;

/// What [`gradient_sampling`] reached.
#[derive(Clone, Debug, PartialEq)]
pub struct SamplingOutcome {
    /// The final point, its value and gradient.
    pub x: Vec<f64>,
    /// See `x`.
    pub value: f64,
    /// See `x`.
    pub gradient: Vec<f64>,
    /// The norm of the smallest element of the hull of the gradients
    /// sampled around the final point, at radius `radius`.
    pub min_norm: f64,
    /// The radius of that last sample.
    pub radius: f64,
    /// Iterations run.
    pub iterations: usize,
    /// Every accepted point: `(x, value, gradient)`.
    pub accepted: Vec<(Vec<f64>, f64, Vec<f64>)>,
    /// Function evaluations (samples and line-search trials).
    pub evaluations: usize,
    /// `min_norm ≤ tolerance` at a radius at most `min_radius`.
    pub converged: bool,
}

/// Minimises `f` from `x0` (where `f` is `value0` with gradient `grad0`)
/// by gradient sampling: each iteration samples gradients at
/// `opts.samples` points drawn uniformly from the ball of radius `ε`
/// around the point, takes the smallest element `g` of their hull (the
/// point's own gradient and every gradient evaluated earlier within the
/// ball included), and steps along `−g` by a backtracking
/// (Armijo) line search; `ε` halves when the search fails or when `‖g‖`
/// falls to the tolerance above the smallest radius.
///
/// `f(x)` returns `Ok(Some((value, gradient)))`, `Ok(None)` for a point
/// outside the function's domain (a sample there is drawn again, up to
/// ten times; a line-search trial there counts as no decrease), or an
/// error, which ends the run.
pub fn gradient_sampling<E>(
    mut f: impl FnMut(&[f64]) -> Result<Option<(f64, Vec<f64>)>, E>,
    x0: &[f64],
    value0: f64,
    grad0: &[f64],
    opts: &SamplingParams,
) -> Result<SamplingOutcome, E> {
    let norm = |v: &[f64]| v.iter().map(|a| a * a).sum::<f64>().sqrt();
    let mut rng = SplitMix(opts.seed);
    let (mut x, mut value, mut grad) = (x0.to_vec(), value0, grad0.to_vec());
    let mut eps = opts.radius;
    let mut out = SamplingOutcome {
        x: x.clone(),
        value,
        gradient: grad.clone(),
        min_norm: norm(grad0),
        radius: 0.0,
        iterations: 0,
        accepted: Vec::new(),
        evaluations: 0,
        converged: false,
    };
    // Every gradient evaluated so far, with its point: those within the
    // ball of a later iteration join its sample at no cost.
    let mut pool: Vec<(Vec<f64>, Vec<f64>)> = Vec::new();
    let mut moved = false;
    for it in 0..opts.max_iterations {
        out.iterations = it + 1;
        moved = false;
        let g = sampled_hull(&mut f, &mut rng, (&x, &grad), eps, opts.samples, &mut pool, &mut out.evaluations)?;
        let g_norm = norm(&g);
        (out.min_norm, out.radius) = (g_norm, eps);
        if g_norm <= opts.tolerance {
            if eps <= opts.min_radius {
                out.converged = true;
                break;
            }
            eps = (0.5 * eps).max(opts.min_radius);
            continue;
        }
        // Armijo backtracking along −g/‖g‖, from a step of twice the radius.
        let d: Vec<f64> = g.iter().map(|v| -v / g_norm).collect();
        let mut t = 2.0 * eps;
        for _ in 0..12 {
            let y: Vec<f64> = x.iter().zip(&d).map(|(a, b)| a + t * b).collect();
            out.evaluations += 1;
            if let Some((fy, gy)) = f(&y)? {
                if fy <= value - 1e-6 * t * g_norm {
                    pool.push((x.clone(), grad.clone()));
                    (x, value, grad) = (y, fy, gy);
                    out.accepted.push((x.clone(), value, grad.clone()));
                    moved = true;
                    break;
                }
                pool.push((y, gy));
            }
            t *= 0.5;
        }
        if !moved {
            if eps <= opts.min_radius {
                break;
            }
            eps = (0.5 * eps).max(opts.min_radius);
        }
    }
    // A run that ran out of iterations right after a step measures the
    // point it ended at.
    if moved && out.iterations == opts.max_iterations {
        let g = sampled_hull(&mut f, &mut rng, (&x, &grad), eps, opts.samples, &mut pool, &mut out.evaluations)?;
        (out.min_norm, out.radius) = (norm(&g), eps);
        out.converged = out.min_norm <= opts.tolerance && eps <= opts.min_radius;
    }
    (out.x, out.value, out.gradient) = (x, value, grad);
    Ok(out)
}

/// The smallest element of the hull of the gradients within `eps` of the
/// point `x` (gradient `grad`): its own, the pool's, and `samples` new ones
/// drawn from the ball (added to the pool).
fn sampled_hull<E>(
    f: &mut impl FnMut(&[f64]) -> Result<Option<(f64, Vec<f64>)>, E>,
    rng: &mut SplitMix,
    (x, grad): (&[f64], &[f64]),
    eps: f64,
    samples: usize,
    pool: &mut Vec<(Vec<f64>, Vec<f64>)>,
    evaluations: &mut usize,
) -> Result<Vec<f64>, E> {
    let distance = |a: &[f64], b: &[f64]| a.iter().zip(b).map(|(p, q)| (p - q) * (p - q)).sum::<f64>().sqrt();
    let mut grads = vec![grad.to_vec()];
    grads.extend(pool.iter().filter(|(y, _)| distance(y, x) <= eps).map(|(_, g)| g.clone()));
    for _ in 0..samples {
        for _attempt in 0..10 {
            let y: Vec<f64> = x.iter().zip(rng.in_ball(x.len(), eps)).map(|(a, b)| a + b).collect();
            *evaluations += 1;
            if let Some((_, g)) = f(&y)? {
                grads.push(g.clone());
                pool.push((y, g));
                break;
            }
        }
    }
    Ok(min_norm_point(&grads).0)
}

/// SplitMix64 (Steele, Lea & Flood 2014): a small, seeded generator of
/// the sampling's points.
struct SplitMix(u64);

impl SplitMix {
    fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    /// Uniform in (0, 1].
    fn uniform(&mut self) -> f64 {
        ((self.next_u64() >> 11) as f64 + 1.0) / (1u64 << 53) as f64
    }

    /// A point drawn uniformly from the ball of radius `r` in `n`
    /// dimensions (a Gaussian direction, the radius `r·u^(1/n)`).
    fn in_ball(&mut self, n: usize, r: f64) -> Vec<f64> {
        let mut v: Vec<f64> = (0..n)
            .map(|_| {
                let (u1, u2) = (self.uniform(), self.uniform());
                (-2.0 * u1.ln()).sqrt() * (std::f64::consts::TAU * u2).cos()
            })
            .collect();
        let len = v.iter().map(|a| a * a).sum::<f64>().sqrt().max(1e-300);
        let radius = r * self.uniform().powf(1.0 / n.max(1) as f64);
        v.iter_mut().for_each(|a| *a *= radius / len);
        v
    }
}
