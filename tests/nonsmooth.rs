//! Nonsmooth minimisation (`diffsim_solvers::nonsmooth`): the nearest
//! point of a polytope, checked by its optimality conditions, and gradient
//! sampling on functions with kinks whose minimisers are known.

use diffsim_solvers::nonsmooth::{SamplingParams, gradient_sampling, min_norm_point};

fn dot(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| x * y).sum()
}

/// Checks that `(x, w)` is the nearest point of the hull of `points` to
/// the origin, by its certificate: `x = Σ wᵢ pᵢ` with `w` on the simplex,
/// and no point of the hull closer (`x·pᵢ ≥ x·x` for every point, the
/// condition of a separating plane through `x`).
fn assert_nearest(points: &[Vec<f64>], x: &[f64], w: &[f64]) {
    let scale = points.iter().map(|p| dot(p, p)).fold(0.0, f64::max);
    assert!(w.iter().all(|&wi| wi >= 0.0), "negative weight in {w:?}");
    assert!((w.iter().sum::<f64>() - 1.0).abs() < 1e-12, "weights {w:?} do not sum to 1");
    for (k, xk) in x.iter().enumerate() {
        let combined: f64 = points.iter().zip(w).map(|(p, wi)| wi * p[k]).sum();
        assert!((combined - xk).abs() < 1e-10 * scale.sqrt().max(1.0), "x is not Σ wᵢ pᵢ");
    }
    for p in points {
        assert!(dot(x, p) >= dot(x, x) - 1e-10 * scale, "a point of the hull is nearer: x·p {} < x·x {}", dot(x, p), dot(x, x));
    }
}

#[test]
fn the_nearest_point_of_a_polytope_meets_its_optimality_conditions() {
    // Known answers: one point; the middle of a segment; the origin inside
    // a triangle; an edge's foot.
    let one = vec![vec![3.0, -4.0]];
    let (x, w) = min_norm_point(&one);
    assert_eq!((x, w), (vec![3.0, -4.0], vec![1.0]));
    let seg = vec![vec![1.0, 1.0], vec![-1.0, 1.0]];
    let (x, w) = min_norm_point(&seg);
    assert!(x[0].abs() < 1e-14 && (x[1] - 1.0).abs() < 1e-14 && (w[0] - 0.5).abs() < 1e-14, "{x:?} {w:?}");
    let tri = vec![vec![1.0, 0.0], vec![-1.0, 1.0], vec![-1.0, -1.0]];
    let (x, w) = min_norm_point(&tri);
    assert!(dot(&x, &x).sqrt() < 1e-12, "{x:?}");
    assert_nearest(&tri, &x, &w);
    // The foot on the edge from (2, −1) to (2, 3), a far point beside.
    let edge = vec![vec![2.0, -1.0], vec![2.0, 3.0], vec![5.0, 5.0]];
    let (x, w) = min_norm_point(&edge);
    assert!((x[0] - 2.0).abs() < 1e-12 && x[1].abs() < 1e-12 && w[2] == 0.0, "{x:?} {w:?}");
    // Pseudo-random sets, some holding the origin, some not, some with
    // repeated and affinely dependent points (more points than dimensions + 1).
    let mut seed = 12345u64;
    let mut next = || {
        seed = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        ((seed >> 11) as f64 / (1u64 << 53) as f64) * 2.0 - 1.0
    };
    for case in 0..200 {
        let (n, m) = (1 + case % 6, 1 + (case / 6) % 12);
        let shift: Vec<f64> = (0..n).map(|_| if case % 3 == 0 { 0.0 } else { 2.0 * next() }).collect();
        let mut points: Vec<Vec<f64>> = (0..m).map(|_| (0..n).map(|k| next() + shift[k]).collect()).collect();
        if case % 5 == 0 {
            points.push(points[0].clone());
        }
        let (x, w) = min_norm_point(&points);
        assert_nearest(&points, &x, &w);
    }
}

/// `f(x) = Σ wᵢ |xᵢ − cᵢ| + ½ μ ‖x‖²`, kinks on every plane `xᵢ = cᵢ`;
/// with `μ·|cᵢ| < wᵢ` its minimiser is `c` (the subgradient `wᵢ·[−1, 1] +
/// μ·cᵢ` holds 0 there), where every gradient jumps.
fn kinked(c: &[f64], w: &[f64], mu: f64) -> impl Fn(&[f64]) -> (f64, Vec<f64>) {
    let (c, w) = (c.to_vec(), w.to_vec());
    move |x: &[f64]| {
        let value = x.iter().zip(&c).zip(&w).map(|((x, c), w)| w * (x - c).abs()).sum::<f64>() + 0.5 * mu * dot(x, x);
        let grad = x.iter().zip(&c).zip(&w).map(|((x, c), w)| w * (x - c).signum() + mu * x).collect();
        (value, grad)
    }
}

#[test]
fn gradient_sampling_reaches_a_minimiser_on_kinks_where_the_gradient_never_vanishes() {
    let c = [0.3, -0.7, 1.1, 0.05, -0.2];
    let w = [1.0, 2.0, 0.5, 1.5, 3.0];
    let f = kinked(&c, &w, 0.1);
    let x0 = vec![0.0; 5];
    let (f0, g0) = f(&x0);
    let g0_norm = dot(&g0, &g0).sqrt();
    let opts = SamplingParams { radius: 0.1, min_radius: 1e-4, samples: 6, max_iterations: 300, tolerance: g0_norm / 100.0, seed: 7 };
    let mut evaluations = 0;
    let out = gradient_sampling(
        |x: &[f64]| -> Result<Option<(f64, Vec<f64>)>, ()> {
            evaluations += 1;
            Ok(Some(f(x)))
        },
        &x0,
        f0,
        &g0,
        &opts,
    )
    .unwrap();
    assert!(out.converged, "not stationary after {} iterations: sampled min-norm {} at radius {}", out.iterations, out.min_norm, out.radius);
    assert_eq!(out.evaluations, evaluations);
    let err = out.x.iter().zip(&c).map(|(x, c)| (x - c).abs()).fold(0.0, f64::max);
    assert!(err < 1e-3, "x {:?} against the minimiser {c:?}", out.x);
    // The gradient at the final point is still of the kinks' size: only the
    // sampled hull shows stationarity.
    assert!(dot(&out.gradient, &out.gradient).sqrt() > 0.3, "gradient {:?}", out.gradient);
    assert!(out.min_norm <= opts.tolerance && out.radius <= opts.min_radius);
    // Accepted points only ever decrease the value.
    let mut last = f0;
    for (x, v, _) in &out.accepted {
        assert!(*v < last, "value rose to {v} from {last}");
        assert_eq!(*v, f(x).0);
        last = *v;
    }
    assert_eq!(out.value, last);
}

#[test]
fn gradient_sampling_keeps_to_the_domain_and_passes_errors_on() {
    // The same function, defined only for x₀ ≥ 0.25 (the minimiser c₀ =
    // 0.3 inside): samples outside are drawn again, trials outside count
    // as no decrease.
    let c = [0.3, -0.4];
    let f = kinked(&c, &[1.0, 1.0], 0.1);
    let domain = |x: &[f64]| -> Result<Option<(f64, Vec<f64>)>, String> { Ok((x[0] >= 0.25).then(|| f(x))) };
    let x0 = vec![1.0, 0.5];
    let (f0, g0) = f(&x0);
    let opts = SamplingParams { radius: 0.05, min_radius: 1e-4, samples: 3, max_iterations: 300, tolerance: 1e-3, seed: 3 };
    let out = gradient_sampling(domain, &x0, f0, &g0, &opts).unwrap();
    assert!(out.accepted.iter().all(|(x, _, _)| x[0] >= 0.25));
    assert!((out.x[0] - 0.3).abs() < 1e-3 && (out.x[1] + 0.4).abs() < 1e-3, "{:?}", out.x);
    // An error from the function ends the run with that error.
    let failing = |x: &[f64]| -> Result<Option<(f64, Vec<f64>)>, String> { if x[0] < 0.9 { Err(format!("no solve at {x:?}")) } else { Ok(Some(f(x))) } };
    let err = gradient_sampling(failing, &x0, f0, &g0, &opts).unwrap_err();
    assert!(err.starts_with("no solve at"), "{err}");
}
