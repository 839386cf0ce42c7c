//! Fluid operators: gradient checks (parameters included), stability of
//! implicit diffusion far beyond the explicit limit, refusal of an unstable
//! explicit step; and, written once and run for 2D and 3D, conservation of
//! the upwind scheme, MacCormack's limiter (no new extrema) and accuracy on
//! a smooth translation, inflow regions.

use diffsim::check::{CheckParams, check_all};
use diffsim::fluids::{AdvectUpwind, DiffuseExplicit, DiffuseImplicit};
use diffsim::op::{OpError, OperatorExt};
use diffsim::rollout::{Pass, Rollout, RolloutError};
use diffsim_solvers::smoke::MacGrid;

fn field(n: usize, seed: u64) -> Vec<f64> {
    (0..n).map(|k| (((k as f64 + 1.0) * 0.6180339887 * (seed as f64 + 0.7)).fract() - 0.5) * 2.0).collect()
}

#[test]
fn diffusion_operators_pass_all_checks() {
    for n in [4, 7] {
        let x = field(n * n, n as u64);
        let r = check_all(&DiffuseExplicit::new(n), &x, &[0.15], &CheckParams::default());
        assert!(r.passed(), "explicit n = {n}:\n{r}");
        let r = check_all(&DiffuseImplicit::new(n, 1e-13, 500), &x, &[0.7], &CheckParams::default());
        assert!(r.passed(), "implicit n = {n}:\n{r}");
    }
    // Smoke and velocity of a closed box, in 2D and 3D (other sides:
    // boundaries.rs).
    box_diffusion_passes(MacGrid::new([7, 5]));
    box_diffusion_passes(MacGrid::new([6, 5, 4]));
}

/// Explicit and implicit diffusion of the smoke and the velocity of the
/// box `cfg` under the three checks.
fn box_diffusion_passes<const D: usize>(cfg: MacGrid<D>) {
    use diffsim::fluids::Diffuse;
    let x = crate::boundaries::signed_state(&cfg, 41);
    let r = check_all(&Diffuse::explicit(cfg, true, true), &x, &[0.1], &CheckParams::default());
    assert!(r.passed(), "explicit diffusion {:?}:\n{r}", cfg.n);
    let r = check_all(&Diffuse::implicit(cfg, true, true, 1e-13, 500), &x, &[0.7], &CheckParams::default());
    assert!(r.passed(), "implicit diffusion {:?}:\n{r}", cfg.n);
}
#[test]
fn implicit_diffusion_is_stable_at_100x_the_explicit_limit() {
    let n = 16;
    let op = DiffuseImplicit::new(n, 1e-10, 1000);
    let x0 = field(n * n, 9);
    let kappa = [100.0 * diffsim_solvers::diffusion::EXPLICIT_LIMIT];
    let r = Rollout::new(&op, &kappa, 50).unwrap();
    let x = r.final_state(&x0).unwrap();
    let (max0, max) = (x0.iter().fold(0.0f64, |m, v| m.max(v.abs())), x.iter().fold(0.0f64, |m, v| m.max(v.abs())));
    assert!(max <= max0, "maximum principle: {max} > {max0}");
    // Mass is conserved (closed box) and the field tends to its mean.
    let mean0 = x0.iter().sum::<f64>() / x0.len() as f64;
    let mean = x.iter().sum::<f64>() / x.len() as f64;
    assert!((mean - mean0).abs() < 1e-9, "{mean} vs {mean0}");
    assert!(x.iter().all(|v| (v - mean).abs() < 0.05), "not yet smooth");
}

#[test]
fn an_unstable_explicit_step_is_an_error() {
    let n = 8;
    let op = DiffuseExplicit::new(n);
    let r = Rollout::new(&op, &[0.3], 5).unwrap();
    assert_eq!(
        r.final_state(&field(n * n, 2)).unwrap_err(),
        RolloutError::Operator { pass: Pass::Forward, error: OpError::Unstable { value: 0.3, limit: 0.25 } }
    );
}

/// In the closed box `cfg` with the state `x`: upwind advection conserves
/// the smoke; MacCormack's limiter creates no extrema; a field not advected
/// passes through unchanged.
fn advection_keeps_its_promises<const D: usize>(cfg: MacGrid<D>, x: &[f64])
where
    AdvectUpwind<D>: diffsim::op::Forward,
    diffsim::fluids::Advect<D>: diffsim::op::Forward,
{
    use diffsim::fluids::Advect;
    use diffsim_solvers::smoke::Scheme;
    let ns = cfg.n_s();
    let mass = |v: &[f64]| v[..ns].iter().sum::<f64>();
    let up = AdvectUpwind { cfg, dt: 0.4 }.eval(x, &[]);
    assert!((mass(&up) - mass(x)).abs() < 1e-12 * mass(x), "{:?}: upwind mass {} → {}", cfg.n, mass(x), mass(&up));
    let y = Advect { velocity: false, ..Advect::new(cfg, Scheme::MacCormack { limiter: true }) }.eval(x, &[]);
    let (lo, hi) = x[..ns].iter().fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), &v| (a.min(v), b.max(v)));
    assert!(y[..ns].iter().all(|&v| v >= lo - 1e-12 && v <= hi + 1e-12), "{:?}: the limiter let a new extremum through", cfg.n);
    assert_eq!(&y[ns..], &x[ns..], "{:?}: the velocity not advected changed", cfg.n);
}

#[test]
fn advection_keeps_its_promises_in_2d_and_3d() {
    for n in [5, 8] {
        let cfg = MacGrid::p2(n);
        let x: Vec<f64> = field(cfg.n_state(), 11 + n as u64).iter().enumerate().map(|(k, v)| if k < cfg.n_s() { 1.0 + v } else { 0.3 * v }).collect();
        advection_keeps_its_promises(cfg, &x);
    }
    let cfg = MacGrid::new([6, 6, 5]).with_dt(0.8);
    advection_keeps_its_promises(cfg, &crate::boundaries::signed_state(&cfg, 51));
}

/// A smooth bump in an `n`-cube translated by the constant velocity `v`
/// for `steps` steps: the largest error of the semi-Lagrangian,
/// MacCormack and limited MacCormack schemes against the exactly
/// translated bump.
fn translation_errors<const D: usize>(n: usize, v: [f64; D], steps: usize, width: f64) -> [f64; 3]
where
    diffsim::fluids::Advect<D>: diffsim::op::Forward,
{
    use diffsim::fluids::Advect;
    use diffsim_solvers::mac::{At, Mac};
    use diffsim_solvers::smoke::Scheme;
    let cfg = MacGrid::new([n; D]);
    let cells = Mac::bounded([n; D]).lattice(At::Centre);
    let start = 0.4 * n as f64;
    let bump = |p: [f64; D]| (-(0..D).map(|a| (p[a] - start).powi(2)).sum::<f64>() / width).exp();
    let centre = |q: [usize; D]| q.map(|k| k as f64 + 0.5);
    let mut x = vec![0.0; cfg.n_state()];
    for q in cells.points() {
        x[cells.index(q)] = bump(centre(q));
    }
    // Every velocity sample the traces read (the walls' faces included:
    // the translation runs in the interior, far from them).
    for (a, &va) in v.iter().enumerate() {
        let r = cfg.face_range(a);
        x[cfg.n_s() + r.start..cfg.n_s() + r.end].fill(va);
    }
    let run = |scheme: Scheme| -> f64 {
        let op = Advect { velocity: false, ..Advect::new(cfg, scheme) };
        let mut s = x.clone();
        for _ in 0..steps {
            s = op.eval(&s, &[]);
        }
        cells.points().map(|q| (s[cells.index(q)] - bump(std::array::from_fn(|a| centre(q)[a] - steps as f64 * v[a]))).abs()).fold(0.0, f64::max)
    };
    [run(Scheme::SemiLagrangian), run(Scheme::MacCormack { limiter: false }), run(Scheme::MacCormack { limiter: true })]
}

#[test]
fn maccormack_is_more_accurate_than_semi_lagrangian_on_a_smooth_translation() {
    // One call per dimension (an array of tuples iterated by value trips
    // Enzyme's type trees in this flagged crate, docs/pitfalls.md).
    compare_with_semi_lagrangian(2, translation_errors(32, [0.3, 0.2], 10, 18.0));
    compare_with_semi_lagrangian(3, translation_errors(20, [0.3, 0.2, 0.25], 8, 8.0));
}

fn compare_with_semi_lagrangian(d: usize, [sl, mc, mcl]: [f64; 3]) {
    eprintln!("{d}D, max error: semi-Lagrangian {sl:.3e}, MacCormack {mc:.3e}, limited {mcl:.3e}");
    assert!(mc < 0.5 * sl, "{d}D: MacCormack {mc} vs semi-Lagrangian {sl}");
    assert!(mcl <= sl, "{d}D: limited MacCormack {mcl} vs semi-Lagrangian {sl}");
}

/// Inflow in the box `cfg` over `region` with the values `p`: the checks
/// pass, the region's cells and faces off the box's sides hold the values,
/// the rest passes through.
fn inflow_sets_its_region<const D: usize>(cfg: MacGrid<D>, region: [[usize; 2]; D], p: &[f64], seed: u64)
where
    diffsim::fluids::Inflow<D>: diffsim::op::Vjp + diffsim::op::Jvp,
{
    use diffsim::fluids::Inflow;
    use diffsim_solvers::mac::{At, Mac};
    let op = Inflow { cfg, region };
    let x = field(cfg.n_state(), seed);
    let r = check_all(&op, &x, p, &CheckParams::default());
    assert!(r.passed(), "inflow {:?}:\n{r}", cfg.n);
    let y = op.eval(&x, p);
    let mac = Mac::bounded(cfg.n);
    let inside = |q: [usize; D], a: Option<usize>| {
        (0..D).all(|b| {
            if Some(b) == a { q[b] >= region[b][0].max(1) && q[b] <= region[b][1].min(cfg.n[b] - 1) } else { q[b] >= region[b][0] && q[b] < region[b][1] }
        })
    };
    let cells = mac.lattice(At::Centre);
    for q in cells.points() {
        let c = cells.index(q);
        assert_eq!(y[c], if inside(q, None) { p[0] } else { x[c] }, "cell {q:?}");
    }
    for a in 0..D {
        let faces = mac.lattice(At::Face(a));
        let start = cfg.n_s() + cfg.face_range(a).start;
        for q in faces.points() {
            let f = start + faces.index(q);
            assert_eq!(y[f], if inside(q, Some(a)) { p[1 + a] } else { x[f] }, "face {q:?} normal to {a}");
        }
    }
}

#[test]
fn inflow_sets_its_region_in_2d_and_3d() {
    for n in [4, 7] {
        inflow_sets_its_region(MacGrid::p2(n), [[1, 3], [0, 2]], &[1.0, 0.2, 0.7], 21 + n as u64);
    }
    inflow_sets_its_region(MacGrid::new([6, 7, 5]), [[0, 2], [1, 3], [2, 5]], &[0.8, 0.1, 0.4, -0.2], 31);
}

#[test]
fn diffusion_in_3d_decays_a_mode_at_the_exact_rate() {
    use diffsim_solvers::diffusion::{Grid, ImplicitSolver, explicit, laplacian};
    // The cell lattice's Laplacian is the closed box's pressure matrix,
    // written apart (the multigrid's slab-by-slab product).
    let n = 8;
    let g = Grid::of_state(&MacGrid::p4(n))[0];
    let s = field(n * n * n, 3);
    let (mut a, mut b) = (vec![0.0; s.len()], vec![0.0; s.len()]);
    laplacian(&g, &s, &mut a);
    diffsim_solvers::multigrid::apply_box_matrix(n, n, &s, &mut b);
    let diff = a.iter().zip(&b).map(|(a, b)| (a - b).abs()).fold(0.0, f64::max);
    assert!(diff < 1e-12, "3D Laplacian against the box matrix: {diff:e}");
    // cos(π(k+½)/n) along z (constant in x, y) is an eigenvector of the
    // closed lattice's matrix with eigenvalue λ = 2 − 2cos(π/n): explicit
    // diffusion scales it by 1 − κλ, implicit by 1/(1 + κλ).
    let mode: Vec<f64> = (0..n * n * n).map(|c| (std::f64::consts::PI * ((c / (n * n)) as f64 + 0.5) / n as f64).cos()).collect();
    let lambda = 2.0 - 2.0 * (std::f64::consts::PI / n as f64).cos();
    let kappa = 0.15;
    let mut y = vec![0.0; mode.len()];
    explicit(&g, kappa, &mode, &mut y);
    let worst = y.iter().zip(&mode).map(|(y, m)| (y - (1.0 - kappa * lambda) * m).abs()).fold(0.0, f64::max);
    assert!(worst < 1e-13, "explicit: {worst:e}");
    let mut solver = ImplicitSolver::new(g, 1e-13, 500);
    solver.solve(kappa, &mode, &mut y).unwrap();
    let worst = y.iter().zip(&mode).map(|(y, m)| (y - m / (1.0 + kappa * lambda)).abs()).fold(0.0, f64::max);
    assert!(worst < 1e-11, "implicit: {worst:e}");
}
