//! The MAC grid's rules, each test written once and run for D = 2 and 3:
//! sampling against the multilinear formula written out per corner, its
//! adjoint against central differences, the velocity taps against the
//! faces written out by hand, and the traces' adjoint (with respect to the
//! velocity and the traced field together) against central differences.

use super::advect::{trace, trace_adjoint};
use super::fft::FftProjection;
use super::periodic::Periodic;
use super::*;
use crate::smoke::Scheme;

/// A fixed pseudo-random sequence in [-1, 1) (no dependency, same values
/// on every machine).
fn values(len: usize, seed: u64) -> Vec<f64> {
    let mut s = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
    (0..len)
        .map(|_| {
            s = s.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            ((s >> 11) as f64 / (1u64 << 53) as f64) * 2.0 - 1.0
        })
        .collect()
}

/// Grids of each kind: bounded, wrapping on one axis, wrapping on all.
fn grids<const D: usize>() -> Vec<Mac<D, [bool; D]>> {
    let n: [usize; D] = std::array::from_fn(|a| 4 + a);
    let mut one = [false; D];
    one[0] = true;
    vec![Mac { n, wrap: [false; D] }, Mac { n, wrap: one }, Mac { n, wrap: [true; D] }]
}

/// The lattices of a `D`-dimensional grid.
fn all_at<const D: usize>() -> Vec<At> {
    std::iter::once(At::Centre).chain((0..D).map(At::Face)).collect()
}

/// `Σ_corners f·Π weights`, the corners found by clamping or wrapping each
/// axis on its own: the definition [`sample`] blends axis by axis.
fn sample_by_definition<const D: usize>(wrap: [bool; D], f: &[f64], lat: &Lattice<D>, p: [f64; D]) -> f64 {
    let mut total = 0.0;
    for k in 0..1usize << D {
        let (mut index, mut w) = (0, 1.0);
        for a in 0..D {
            let (i0, i1, t) = position(wrap[a], lat.n[a], p[a] - lat.o[a]);
            let upper = (k >> a) & 1 == 1;
            index += if upper { i1 } else { i0 } * lat.stride[a];
            w *= if upper { t } else { 1.0 - t };
        }
        total += f[index] * w;
    }
    total
}

fn sampling<const D: usize>() {
    for mac in grids::<D>() {
        for at in all_at::<D>() {
            let lat = mac.lattice(at);
            let f = values(lat.len, 7);
            for (m, p) in values(40 * D, 3).chunks(D).enumerate() {
                // Points inside, on the lattice, and outside it.
                let p: [f64; D] = std::array::from_fn(|a| if m % 5 == 0 { (m % 3) as f64 } else { 4.0 * p[a] + 2.5 });
                let (s, want) = (sample(mac.wraps(), &f, &lat, p), sample_by_definition(mac.wraps(), &f, &lat, p));
                assert!((s - want).abs() <= 1e-14, "D = {D}, {at:?} at {p:?}: {s} vs {want}");
                let (lo, hi) = sample_range(mac.wraps(), &f, &lat, p);
                assert!(lo <= s + 1e-15 && s <= hi + 1e-15, "the sample lies outside its corners' range");
            }
        }
    }
}

#[test]
fn sampling_is_the_multilinear_blend_of_the_corners() {
    sampling::<2>();
    sampling::<3>();
}

fn sample_adjoint_matches_differences<const D: usize>() {
    let h = 1e-6;
    for mac in grids::<D>() {
        for at in all_at::<D>() {
            let lat = mac.lattice(at);
            let f = values(lat.len, 11);
            for p in values(20 * D, 5).chunks(D) {
                // Away from lattice planes, where sampling is smooth.
                let p: [f64; D] = std::array::from_fn(|a| 3.0 * p[a] + 2.13);
                let g = 0.7;
                let mut gf = vec![0.0; lat.len];
                let dp = sample_adjoint(mac.wraps(), &f, &mut gf, &lat, p, g);
                for a in 0..D {
                    let (mut lo, mut hi) = (p, p);
                    lo[a] -= h;
                    hi[a] += h;
                    let fd = g * (sample(mac.wraps(), &f, &lat, hi) - sample(mac.wraps(), &f, &lat, lo)) / (2.0 * h);
                    assert!((dp[a] - fd).abs() <= 1e-7, "D = {D}, ∂/∂p{a} at {p:?}: {} vs {fd}", dp[a]);
                }
                // Linear in f: the adjoint is the weights themselves.
                let mut e = vec![0.0; lat.len];
                for c in 0..lat.len {
                    e[c] = 1.0;
                    let want = g * sample(mac.wraps(), &e, &lat, p);
                    assert!((gf[c] - want).abs() <= 1e-15, "D = {D}, ∂/∂f[{c}]: {} vs {want}", gf[c]);
                    e[c] = 0.0;
                }
            }
        }
    }
}

#[test]
fn sample_adjoint_matches_central_differences() {
    sample_adjoint_matches_differences::<2>();
    sample_adjoint_matches_differences::<3>();
}

fn velocity_taps<const D: usize>() {
    for mac in grids::<D>() {
        let vel_store: Vec<Vec<f64>> = (0..D).map(|b| values(mac.lattice(At::Face(b)).len, 20 + b as u64)).collect();
        let vel: [&[f64]; D] = std::array::from_fn(|b| vel_store[b].as_slice());
        for at in all_at::<D>() {
            let lat = mac.lattice(at);
            for c in 0..lat.len {
                let q: [usize; D] = std::array::from_fn(|a| (c / lat.stride[a]) % (lat.stride.get(a + 1).copied().unwrap_or(lat.len) / lat.stride[a]));
                if (0..D).any(|a| q[a] >= lat.n[a]) {
                    continue; // a periodic copy
                }
                let v = mac.velocity(at, vel, q);
                for b in 0..D {
                    // Written out: the face at index q of component b's array,
                    // its neighbour along b (wrapped), and along the face's
                    // own axis the faces of the cells on both sides.
                    let face = mac.lattice(At::Face(b));
                    let wrap = |a: usize, k: isize| -> usize {
                        let n = mac.n[a] as isize;
                        if mac.wraps()[a] { k.rem_euclid(n) as usize } else { k.clamp(0, n - 1) as usize }
                    };
                    let want = if at == At::Face(b) {
                        vel[b][face.index(q)]
                    } else {
                        let mut up = q;
                        up[b] = if mac.wraps()[b] { (q[b] + 1) % mac.n[b] } else { q[b] + 1 };
                        match at {
                            At::Centre => 0.5 * (vel[b][face.index(q)] + vel[b][face.index(up)]),
                            At::Face(a) => {
                                let side = |p: [usize; D], k: isize| {
                                    let mut p = p;
                                    p[a] = wrap(a, k);
                                    vel[b][face.index(p)]
                                };
                                let qa = q[a] as isize;
                                0.25 * (side(q, qa - 1) + side(q, qa) + side(up, qa - 1) + side(up, qa))
                            }
                        }
                    };
                    assert!((v[b] - want).abs() <= 1e-15, "D = {D}, {at:?} q = {q:?} component {b}: {} vs {want}", v[b]);
                }
            }
        }
    }
}

#[test]
fn velocity_is_the_mean_of_the_nearest_faces() {
    velocity_taps::<2>();
    velocity_taps::<3>();
}

/// `⟨g, trace(at)⟩` over the points holding their own value, with the
/// velocity and the centres' field moved by `t` along `(dvel, df)` (on a
/// face lattice the traced field is the velocity component itself).
#[allow(clippy::too_many_arguments)]
fn traced_sum<const D: usize>(mac: Mac<D, [bool; D]>, at: At, vel: &[Vec<f64>], f: &[f64], dvel: &[Vec<f64>], df: &[f64], g: &[f64], t: f64) -> f64 {
    let moved: Vec<Vec<f64>> = vel.iter().zip(dvel).map(|(v, d)| v.iter().zip(d).map(|(a, b)| a + t * b).collect()).collect();
    let vv: [&[f64]; D] = std::array::from_fn(|b| moved[b].as_slice());
    let fm: Vec<f64> = f.iter().zip(df).map(|(a, b)| a + t * b).collect();
    let field: &[f64] = if let At::Face(a) = at { vv[a] } else { &fm };
    let lat = mac.lattice(at);
    let mut out = vec![0.0; lat.len];
    trace(mac, at, vv, field, 0.9, 0..mac.n[D - 1], &mut out);
    (0..lat.len).filter(|&c| own(&lat, c)).map(|c| g[c] * out[c]).sum()
}

fn trace_adjoint_matches<const D: usize>() {
    let h = 1e-6;
    for mac in grids::<D>() {
        let vel: Vec<Vec<f64>> = (0..D).map(|b| values(mac.lattice(At::Face(b)).len, 30 + b as u64).iter().map(|x| 0.8 * x).collect()).collect();
        let dvel: Vec<Vec<f64>> = (0..D).map(|b| values(vel[b].len(), 60 + b as u64)).collect();
        let vr: [&[f64]; D] = std::array::from_fn(|b| vel[b].as_slice());
        for at in all_at::<D>() {
            let lat = mac.lattice(at);
            let n_centre = mac.lattice(At::Centre).len;
            let (f, df) = (values(n_centre, 41), values(n_centre, 43));
            let g: Vec<f64> = values(lat.len, 47).iter().enumerate().map(|(c, &x)| if own(&lat, c) { x } else { 0.0 }).collect();
            let mut gvel_store: Vec<Vec<f64>> = (0..D).map(|b| vec![0.0; vel[b].len()]).collect();
            let mut gvel: [&mut [f64]; D] = gvel_store.iter_mut().map(|v| v.as_mut_slice()).collect::<Vec<_>>().try_into().unwrap();
            let mut gs = vec![0.0; n_centre];
            let field: &[f64] = if let At::Face(a) = at { vr[a] } else { &f };
            trace_adjoint(mac, at, vr, field, 0.9, &g, if at == At::Centre { Some(&mut gs) } else { None }, &mut gvel);
            let adjoint: f64 = gvel_store.iter().zip(&dvel).flat_map(|(a, d)| a.iter().zip(d)).map(|(a, d)| a * d).sum::<f64>()
                + gs.iter().zip(&df).map(|(a, d)| a * d).sum::<f64>();
            let fd = (traced_sum(mac, at, &vel, &f, &dvel, &df, &g, h) - traced_sum(mac, at, &vel, &f, &dvel, &df, &g, -h)) / (2.0 * h);
            assert!((fd - adjoint).abs() <= 1e-6 * fd.abs().max(1.0), "D = {D}, {at:?}, wraps {:?}: differences {fd} vs adjoint {adjoint}", mac.wrap);
        }
    }
}

/// Whether entry `c` of the lattice's array holds its own value (not a
/// periodic copy).
fn own<const D: usize>(lat: &Lattice<D>, c: usize) -> bool {
    (0..D).all(|a| {
        let extent = lat.stride.get(a + 1).copied().unwrap_or(lat.len) / lat.stride[a];
        (c / lat.stride[a]) % extent < lat.n[a]
    })
}

#[test]
fn trace_adjoint_matches_central_differences() {
    trace_adjoint_matches::<2>();
    trace_adjoint_matches::<3>();
}

/// The periodic divergence of a MAC velocity (cells `x` fastest): `Σ_a
/// (u_a[c + e_a] − u_a[c])`, face `n_a` read as face 0.
fn periodic_divergence<const D: usize>(n: [usize; D], vel: &[Vec<f64>]) -> Vec<f64> {
    let cells: usize = n.iter().product();
    (0..cells)
        .map(|c| {
            let q: [usize; D] = std::array::from_fn(|a| (c / n[..a].iter().product::<usize>()) % n[a]);
            (0..D)
                .map(|a| {
                    let index = |q: [usize; D]| (0..D).map(|b| q[b] * (0..b).map(|e| n[e] + (e == a) as usize).product::<usize>()).sum::<usize>();
                    let mut up = q;
                    up[a] = (q[a] + 1) % n[a];
                    vel[a][index(up)] - vel[a][index(q)]
                })
                .sum()
        })
        .collect()
}

/// A random velocity on the faces of a periodic box, copies equal to
/// their faces when `copies`, else random too (never read).
fn periodic_velocity<const D: usize>(n: [usize; D], seed: u64, copies: bool) -> Vec<Vec<f64>> {
    let fft = FftProjection::new(n);
    (0..D)
        .map(|a| {
            let mut v = values(fft.face_len(a), seed + a as u64);
            if copies {
                let mut pairs = Vec::new();
                fft.for_copies(a, |face, copy| pairs.push((face, copy)));
                for (face, copy) in pairs {
                    v[copy] = v[face];
                }
            }
            v
        })
        .collect()
}

fn fft_projection<const D: usize>(n: [usize; D]) {
    let mut fft = FftProjection::new(n);
    let x = periodic_velocity(n, 70, false);
    let mut y = x.clone();
    fft.project(y.iter_mut().map(|v| v.as_mut_slice()).collect::<Vec<_>>().try_into().unwrap());
    let div = periodic_divergence(n, &y);
    let worst = div.iter().fold(0.0f64, |m, d| m.max(d.abs()));
    assert!(worst < 1e-12, "D = {D}, {n:?}: divergence {worst:e} after the projection");
    // The mean of each component stays; a projection twice is the projection.
    let mut z = y.clone();
    fft.project(z.iter_mut().map(|v| v.as_mut_slice()).collect::<Vec<_>>().try_into().unwrap());
    let moved = y.iter().flatten().zip(z.iter().flatten()).fold(0.0f64, |m, (a, b)| m.max((a - b).abs()));
    assert!(moved < 1e-13, "D = {D}: projecting twice moved the field by {moved:e}");
    // Adjoint: ⟨P x, w⟩ = ⟨x, Pᵀ w⟩ over whole arrays, copies included.
    let w = periodic_velocity(n, 90, false);
    let mut pw = w.clone();
    fft.project_adjoint(pw.iter_mut().map(|v| v.as_mut_slice()).collect::<Vec<_>>().try_into().unwrap());
    let dot = |a: &[Vec<f64>], b: &[Vec<f64>]| a.iter().flatten().zip(b.iter().flatten()).map(|(p, q)| p * q).sum::<f64>();
    let (lhs, rhs) = (dot(&y, &w), dot(&x, &pw));
    assert!((lhs - rhs).abs() <= 1e-12 * lhs.abs().max(1.0), "D = {D}: ⟨Px, w⟩ = {lhs} but ⟨x, Pᵀw⟩ = {rhs}");
}

#[test]
fn fft_projection_is_divergence_free_idempotent_and_its_own_adjoint() {
    fft_projection([8, 6]);
    fft_projection([16, 16]);
    fft_projection([5, 4, 6]);
    fft_projection([8, 8, 8]);
}

/// The FFT projection of a velocity on a periodic box of `dims` cells
/// against the smoke solver's CG projection.
fn fft_against_cg<const D: usize>(dims: [usize; D], precond: crate::smoke::Preconditioner) {
    use crate::boundary::{Boundary, Side};
    let cfg = crate::smoke::MacGrid::new(dims).with_boundary(Boundary::all(Side::Periodic));
    let mut solver = crate::smoke::PressureSolver::new(&cfg, 1e-13, 2000, precond);
    let mut scratch = crate::smoke::ProjectScratch::new(cfg.n_s());
    let vel = periodic_velocity(dims, 5 * D as u64, true);
    let mut state = vec![0.0; cfg.n_s()];
    state.extend_from_slice(&vel.concat());
    crate::smoke::project(&cfg, &mut state, &mut solver, &mut scratch).unwrap();
    let mut y = vel.clone();
    FftProjection::new(dims).project(y.iter_mut().map(|v| v.as_mut_slice()).collect::<Vec<_>>().try_into().unwrap());
    let diff = max_diff(&state[cfg.n_s()..], &y.concat());
    assert!(diff < 1e-10, "{dims:?} with {precond}: FFT and CG projections differ by {diff:e}");
}

#[test]
fn fft_projection_matches_the_conjugate_gradient_projection() {
    use crate::smoke::Preconditioner::*;
    for precond in [None, Mic0, Multigrid, Cholesky] {
        fft_against_cg([12, 10], precond);
        fft_against_cg([5, 6, 4], precond);
    }
}

/// The 2D Taylor–Green vortex on `[0, 2π]²`: `u = sin x cos y·F`, `v = −cos
/// x sin y·F`, `F = e^{−2νt}`, sampled on the faces of `n²` cells.
fn taylor_green(n: usize, f: f64) -> Vec<f64> {
    let h = 2.0 * std::f64::consts::PI / n as f64;
    crate::exact::on_faces([n, n], h, |a, [x, y]| if a == 0 { x.sin() * y.cos() * f } else { -x.cos() * y.sin() * f })
}

/// The largest error of a 2D Taylor–Green run against the exact decay at
/// `t = 1`, `ν = 0.05`, time step `courant·h`.
fn taylor_green_error(n: usize, scheme: Scheme, courant: f64) -> f64 {
    let (nu, t) = (0.05, 1.0);
    let flow = Periodic::new([n, n], 2.0 * std::f64::consts::PI / n as f64, nu, scheme);
    let mut vel = taylor_green(n, 1.0);
    flow.run(t, courant * flow.h, &mut vel);
    max_diff(&vel, &taylor_green(n, (-2.0 * nu * t).exp()))
}

/// The largest difference between two arrays.
fn max_diff(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).fold(0.0f64, |m, (a, b)| m.max((a - b).abs()))
}

#[test]
fn taylor_green_decays_as_the_exact_solution_with_the_schemes_orders() {
    // Semi-Lagrangian: first order (time step ∝ h). MacCormack: its
    // advection is second order, the splitting and the explicit viscosity
    // first order in time; measured 16 → 64, docs/navier-stokes.md.
    let rates = |e: &[f64]| -> Vec<f64> { e.windows(2).map(|w| (w[0] / w[1]).log2()).collect() };
    let sl: Vec<f64> = [16, 32, 64].iter().map(|&n| taylor_green_error(n, Scheme::SemiLagrangian, 0.5)).collect();
    assert!(rates(&sl).iter().all(|&r| r > 0.85), "semi-Lagrangian: errors {sl:?}, observed orders {:?}", rates(&sl));
    let mc: Vec<f64> = [16, 32, 64].iter().map(|&n| taylor_green_error(n, Scheme::MacCormack { limiter: false }, 0.5)).collect();
    let overall = (mc[0] / mc[2]).log2() / 2.0;
    assert!(overall > 1.1 && mc[2] < sl[2] / 4.0, "MacCormack: errors {mc:?} (order {overall:.2} from 16² to 64²) against semi-Lagrangian {sl:?}");
}

#[test]
fn a_large_step_is_split_into_stable_substeps() {
    // ν·dt/h² = 2.6 and a Courant number of 2.9 in one call: split, stable,
    // and the same as the sub-steps taken one by one.
    let n = 16;
    let h = 2.0 * std::f64::consts::PI / n as f64;
    let flow = Periodic::new([n, n], h, 2.6 * h * h / (3.0 * h), Scheme::MacCormack { limiter: true });
    let dt = 3.0 * h;
    let mut vel = taylor_green(n, 1.0);
    let mut work = flow.work();
    let k = flow.substeps(flow.viscosity, dt, &vel);
    assert!(k >= 6, "{k} sub-steps for κ = 2.6 in 2D");
    let mut by_hand = vel.clone();
    assert_eq!(flow.step(dt, &mut vel, &mut work), k);
    for _ in 0..k {
        flow.substep(dt / k as f64, &mut by_hand, &mut work);
    }
    assert_eq!(vel, by_hand);
    let peak = vel.iter().fold(0.0f64, |m, u| m.max(u.abs()));
    assert!(peak.is_finite() && peak < 1.0, "the split step grew the velocity to {peak}");
}

/// The Arnold–Beltrami–Childress flow with `A = B = C = 1` on `[0, 2π]³`
/// at time `t`, sampled on the faces of `n³` cells (copies included).
fn abc(n: usize, nu: f64, t: f64) -> Vec<f64> {
    let flow = crate::exact::Abc { coefficients: [1.0; 3], nu };
    crate::exact::on_faces([n, n, n], 2.0 * std::f64::consts::PI / n as f64, |a, p| flow.velocity(p, t)[a])
}

/// The largest error of a 3D ABC run against its exact decay at `t = 1`,
/// `ν = 0.05`, time step `courant·h` (at unit speed).
fn abc_error(n: usize, scheme: Scheme, courant: f64) -> f64 {
    let (nu, t) = (0.05, 1.0);
    let flow = Periodic::new([n, n, n], 2.0 * std::f64::consts::PI / n as f64, nu, scheme);
    let mut vel = abc(n, nu, 0.0);
    flow.run(t, courant * flow.h, &mut vel);
    max_diff(&vel, &abc(n, nu, t))
}

#[test]
fn the_abc_flow_decays_as_the_exact_solution_in_3d() {
    let rates = |e: &[f64]| -> Vec<f64> { e.windows(2).map(|w| (w[0] / w[1]).log2()).collect() };
    let sl: Vec<f64> = [8, 16, 32].iter().map(|&n| abc_error(n, Scheme::SemiLagrangian, 0.5)).collect();
    let mc: Vec<f64> = [8, 16, 32].iter().map(|&n| abc_error(n, Scheme::MacCormack { limiter: false }, 0.5)).collect();
    // First order in time for both (time step ∝ h; the splitting and the
    // explicit viscosity), MacCormack's error well below semi-Lagrangian's;
    // measured 8³ → 32³ (docs/navier-stokes.md): SL 0.80, 0.87; MC 0.79, 1.16.
    assert!(rates(&sl).iter().all(|&r| r > 0.75), "semi-Lagrangian: errors {sl:?}, observed orders {:?}", rates(&sl));
    let overall = (mc[0] / mc[2]).log2() / 2.0;
    assert!(overall > 0.9 && mc[2] < sl[2] / 3.0, "MacCormack: errors {mc:?} (order {overall:.2} from 8³ to 32³) against semi-Lagrangian {sl:?}");
}

#[test]
fn centred_values_survive_the_round_trip_spectrally() {
    // A smooth periodic field (modes up to 3 at N = 16): faces → centres →
    // faces returns it to rounding, and the centred values are the field
    // sampled at the centres; a linear average would damp mode k by
    // cos²(πk/N) (docs/navier-stokes.md).
    let n = 16;
    let h = 2.0 * std::f64::consts::PI / n as f64;
    let field = |a: usize, p: [f64; 3]| (p[0] + 2.0 * p[1] + a as f64).sin() + 0.5 * (3.0 * p[2] - p[0]).cos();
    let flow = Periodic::new([n, n, n], h, 0.0, Scheme::SemiLagrangian);
    let vel = crate::exact::on_faces([n, n, n], h, field);
    let centred = flow.faces_to_centres(&vel);
    let mut exact = Vec::new();
    for a in 0..3 {
        for c in 0..n * n * n {
            let q = [c % n, c / n % n, c / (n * n)];
            exact.push(field(a, q.map(|k| (k as f64 + 0.5) * h)));
        }
    }
    let at_centres = max_diff(&centred, &exact);
    assert!(at_centres < 1e-12, "centred values off by {at_centres:e}");
    let back = flow.centres_to_faces(&centred);
    let round_trip = max_diff(&back, &vel);
    assert!(round_trip < 1e-12, "round trip off by {round_trip:e}");
    // The transposes: ⟨F·f, c⟩ = ⟨f, Fᵀ·c⟩ and ⟨C·c, g⟩ = ⟨c, Cᵀ·g⟩ (F
    // faces → centres, C back), at values with no pattern.
    let dot = |a: &[f64], b: &[f64]| a.iter().zip(b).map(|(x, y)| x * y).sum::<f64>();
    let (f, c, g) = (values(vel.len(), 3), values(centred.len(), 4), values(vel.len(), 5));
    let (lhs, rhs) = (dot(&flow.faces_to_centres(&f), &c), dot(&f, &flow.faces_to_centres_transpose(&c)));
    assert!((lhs - rhs).abs() < 1e-10 * lhs.abs().max(1.0), "faces → centres transpose: {lhs} against {rhs}");
    let (lhs, rhs) = (dot(&flow.centres_to_faces(&c), &g), dot(&c, &flow.centres_to_faces_transpose(&g)));
    assert!((lhs - rhs).abs() < 1e-10 * lhs.abs().max(1.0), "centres → faces transpose: {lhs} against {rhs}");
}

/// The sides of a box on a MAC grid: the faces an inflow side sets, as
/// listed for a profile given as parameters, are those `enforce_boundary`
/// sets, with its values; the viscosity's lattices of a no-slip box are
/// symmetric, with the wall's ghost value the negative of the one inside.
fn sides_of_a_box<const D: usize>() {
    use crate::boundary::{Boundary, Profile, Side};
    use crate::diffusion::{Grid, laplacian};
    use crate::smoke::{MacGrid, enforce_boundary, inflow_faces};
    let n: [usize; D] = std::array::from_fn(|a| 3 + a);
    let mut sides = [[Side::NoSlip; 2]; D];
    sides[0] = [Side::Inflow(Profile::Parabolic(0.7)), Side::Outflow];
    sides[D - 1] = [Side::NoSlip, Side::Inflow(Profile::Uniform(0.4))];
    let cfg = MacGrid::new(n).with_boundary(Boundary { sides });
    let faces = inflow_faces(&cfg);
    let across = |a: usize| (0..D).filter(|&b| b != a).map(|b| n[b]).product::<usize>();
    assert_eq!(faces.len(), across(0) + across(D - 1));
    let mut v = vec![f64::NAN; cfg.n_vel()];
    enforce_boundary(&cfg, &mut v);
    for f in &faces {
        assert_eq!(v[f.index], f.sign * f.speed, "face {}", f.index);
        v[f.index] = f64::NAN;
    }
    // No other face holds a profile value (walls hold 0, the rest NaN).
    assert!(v.iter().all(|x| x.is_nan() || *x == 0.0));
    // The tangential components' lattices: fixed on the no-slip sides.
    for (l, g) in Grid::of_state(&cfg).iter().enumerate().skip(1) {
        let (x, y) = (values(g.len(), 3 + l as u64), values(g.len(), 7 + l as u64));
        let (mut ax, mut ay) = (vec![0.0; g.len()], vec![0.0; g.len()]);
        laplacian(g, &x, &mut ax);
        laplacian(g, &y, &mut ay);
        let dot = |a: &[f64], b: &[f64]| a.iter().zip(b).map(|(a, b)| a * b).sum::<f64>();
        assert!((dot(&ax, &y) - dot(&x, &ay)).abs() < 1e-12, "lattice {l}: not symmetric");
        // Component l − 1 is fixed on the no-slip sides of the other axes:
        // both sides of the middle axis (3D), the lower side of the last.
        let expected: u32 = (1..D).filter(|&a| a != l - 1).map(|a| if a == D - 1 { 1 << (2 * a) } else { 3 << (2 * a) }).sum();
        assert_eq!(g.fixed, expected, "lattice {l}");
    }
    // On a constant field the Laplacian is 2 per fixed edge a sample
    // touches: the u faces of the first row touch the lowest side of the
    // last axis (and in 3D of the middle one, as the next row does).
    let g = Grid::of_state(&cfg)[1];
    let (ones, mut out) = (vec![1.0; g.len()], vec![0.0; g.len()]);
    laplacian(&g, &ones, &mut out);
    let middle = if D == 3 { 2.0 } else { 0.0 };
    assert_eq!((out[0], out[g.stride]), (2.0 + middle, middle));
}

#[test]
fn the_sides_of_a_box_set_their_faces_and_fix_the_tangential_velocity() {
    sides_of_a_box::<2>();
    sides_of_a_box::<3>();
}

/// The kinetic energy `½·Σ u²·h³` of the 3D Taylor–Green vortex `u = sin x
/// cos y cos z`, `v = −cos x sin y cos z`, `w = 0` after `t` (steps of
/// `dt`), relative to its start, at `n³`.
fn taylor_green_3d_energy(n: usize, scheme: Scheme, nu: f64, t: f64, dt: f64) -> f64 {
    let h = 2.0 * std::f64::consts::PI / n as f64;
    let flow = Periodic::new([n, n, n], h, nu, scheme);
    let mut vel = crate::exact::on_faces([n, n, n], h, |a, [x, y, z]| match a {
        0 => x.sin() * y.cos() * z.cos(),
        1 => -x.cos() * y.sin() * z.cos(),
        _ => 0.0,
    });
    // Own faces only (the copies along each component's axis left out).
    let energy =
        |v: &[f64]| (0..3).map(|a| super::periodic::own_faces([n, n, n], a, &v[flow.grid.face_range(a)]).iter().map(|u| u * u).sum::<f64>()).sum::<f64>();
    let e0 = energy(&vel);
    flow.run(t, dt, &mut vel);
    energy(&vel) / e0
}

#[test]
fn the_3d_taylor_green_vortex_loses_energy_at_the_exact_early_rate() {
    // At t = 0 the advection moves no energy (it conserves it) and Δu = −3u,
    // so dE/dt = ν∫u·Δu = −6νE: E(t)/E₀ = e^{−6νt} to first order in t (the
    // vortex stretching that speeds the decay later starts at second
    // order). The observed rate −ln(E/E₀)/t over a short time against 6ν.
    let (nu, t, dt) = (0.05, 0.1, 0.01);
    let off = |scheme: Scheme, n: usize| (-taylor_green_3d_energy(n, scheme, nu, t, dt).ln() / t / (6.0 * nu) - 1.0).abs();
    // Measured (docs/navier-stokes.md): MacCormack 0.44% and 0.74% off at
    // 16³ and 32³; semi-Lagrangian's own dissipation (its interpolation at
    // every step) makes it 95% and 49% too fast, halving per doubling.
    let mc: Vec<f64> = [16, 32].iter().map(|&n| off(Scheme::MacCormack { limiter: false }, n)).collect();
    assert!(mc.iter().all(|&o| o < 0.02), "MacCormack: the rate off by {mc:?} at 16³ and 32³");
    let sl: Vec<f64> = [16, 32].iter().map(|&n| off(Scheme::SemiLagrangian, n)).collect();
    assert!(sl[1] < sl[0] / 1.8, "semi-Lagrangian: the rate off by {sl:?} at 16³ and 32³");
}

/// The traces shorter than a cell ([`super::near`]) give the general
/// traces' values to rounding, semi-Lagrangian and MacCormack, on boxes of
/// unequal sides, with displacements of either sign up to 0.95 cells and
/// exact zeros (the periodic copies refreshed in both); it does not apply
/// at a cell or more, with the limiter, or on a box not periodic.
fn near_traces_are_the_traces<const D: usize>(n: [usize; D]) {
    use crate::boundary::{Boundary, Side};
    use crate::smoke::{MacGrid, advect_velocity, advect_velocity_near, advect_velocity_near_scratch_len, advect_velocity_scratch_len, near_applies};
    let cfg = MacGrid::<D> { n, buoyancy: 0.0, dt: 1.0, boundary: Boundary::all(Side::Periodic) };
    let mut vel: Vec<f64> = periodic_velocity(n, 7, true).concat();
    vel[3] = 0.0;
    let dt = 0.95;
    for scheme in [Scheme::SemiLagrangian, Scheme::MacCormack { limiter: false }] {
        assert!(near_applies(&cfg, scheme, dt, &vel) && !near_applies(&cfg, scheme, 1.2, &vel));
        let mut scratch = vec![0.0; advect_velocity_scratch_len(&cfg, scheme).max(advect_velocity_near_scratch_len(&cfg))];
        let (mut near, mut traced) = (vec![f64::NAN; vel.len()], vec![f64::NAN; vel.len()]);
        advect_velocity_near(&cfg, scheme, dt, &vel, &mut near, &mut scratch);
        advect_velocity(&cfg, scheme, dt, &vel, &mut traced, &mut scratch);
        super::periodic::refresh_periodic_copies(&cfg, &mut traced);
        let diff = max_diff(&near, &traced);
        assert!(diff <= 1e-14, "{n:?} {scheme:?}: {diff:e}");
        // Compiled for the widest vectors: the same bits.
        let mut widest = vec![f64::NAN; vel.len()];
        crate::smoke::advect_velocity_near_widest(&cfg, scheme, dt, &vel, &mut widest, &mut scratch);
        assert!(widest.iter().zip(&near).all(|(a, b)| a.to_bits() == b.to_bits()), "{n:?} {scheme:?}: the widest copy differs");
    }
    assert!(!near_applies(&cfg, Scheme::MacCormack { limiter: true }, dt, &vel));
    let mut bad = vel.clone();
    bad[vel.len() - 2] = f64::NAN;
    assert!(!near_applies(&cfg, Scheme::SemiLagrangian, dt, &bad));
    let mut closed = cfg;
    closed.boundary = Boundary::CLOSED;
    assert!(!near_applies(&closed, Scheme::SemiLagrangian, dt, &vel));
}

#[test]
fn traces_shorter_than_a_cell_are_the_traces() {
    near_traces_are_the_traces([5, 4]);
    near_traces_are_the_traces([8, 8]);
    near_traces_are_the_traces([4, 5, 3]);
    near_traces_are_the_traces([6, 6, 6]);
}

/// The hand-written adjoint of the near path against central differences of the forward, with respect to every
/// face (copies included: they get nothing) and the time step.
fn near_adjoint_matches<const D: usize>(n: [usize; D]) {
    use crate::boundary::{Boundary, Side};
    use crate::smoke::{MacGrid, advect_velocity_near, advect_velocity_near_adjoint, advect_velocity_near_scratch_len};
    let cfg = MacGrid::<D> { n, buoyancy: 0.0, dt: 1.0, boundary: Boundary::all(Side::Periodic) };
    let vel: Vec<f64> = periodic_velocity(n, 11, true).concat();
    let (dt, len) = (0.8, vel.len());
    let w = values(len, 5);
    for scheme in [Scheme::SemiLagrangian, Scheme::MacCormack { limiter: false }] {
        let mut scratch = vec![0.0; advect_velocity_near_scratch_len(&cfg)];
        let mut phi = |v: &[f64], dt: f64| {
            let mut y = vec![0.0; len];
            advect_velocity_near(&cfg, scheme, dt, v, &mut y, &mut scratch);
            y.iter().zip(&w).map(|(a, b)| a * b).sum::<f64>()
        };
        let mut g = vec![0.0; len];
        let gdt = advect_velocity_near_adjoint(&cfg, scheme, dt, &vel, &w, &mut g);
        let e = 1e-6;
        for k in 0..len {
            let (mut up, mut down) = (vel.clone(), vel.clone());
            up[k] += e;
            down[k] -= e;
            let fd = (phi(&up, dt) - phi(&down, dt)) / (2.0 * e);
            assert!((fd - g[k]).abs() <= 1e-7 * (1.0 + fd.abs()), "{n:?} {scheme:?} face {k}: {fd} against {}", g[k]);
        }
        let fd = (phi(&vel, dt + e) - phi(&vel, dt - e)) / (2.0 * e);
        assert!((fd - gdt).abs() <= 1e-7 * (1.0 + fd.abs()), "{n:?} {scheme:?} dt: {fd} against {gdt}");
    }
}

#[test]
fn near_adjoint_matches_central_differences() {
    near_adjoint_matches([5, 4]);
    near_adjoint_matches([4, 3, 5]);
}

/// A discretely divergence-free velocity on a periodic box of `n` cells
/// (random values projected by FFT), packed with its copies.
fn solenoidal<const D: usize>(n: [usize; D], seed: u64) -> Vec<f64> {
    let flow = Periodic::new(n, 1.0, 0.0, Scheme::SemiLagrangian);
    let mut vel = values(flow.n_vel(), seed);
    let mut fft = FftProjection::new(n);
    fft.project(flow.grid.components_mut(&mut vel));
    vel
}

/// The faces of the packed velocity that are not periodic copies.
fn own_faces_of<const D: usize>(n: [usize; D]) -> Vec<bool> {
    let grid = Periodic::new(n, 1.0, 0.0, Scheme::SemiLagrangian).grid;
    let mut own = vec![true; grid.n_vel()];
    for a in 0..D {
        let start = grid.face_range(a).start;
        for f in crate::boundary::faces(n, &grid.boundary, a) {
            if let Some(c) = f.copy {
                own[start + c] = false;
            }
        }
    }
    own
}

fn central_conserves<const D: usize>(n: [usize; D]) {
    let h = 0.3;
    let u = solenoidal(n, 5);
    let own = own_faces_of(n);
    let mut rhs = vec![0.0; u.len()];
    central::momentum_rhs(&n, h, 0.0, &u, &mut rhs);
    // Kinetic energy: Σ u·∇·(u⊗u) = 0 for a divergence-free u.
    let scale: f64 = u.iter().zip(&rhs).zip(&own).filter(|(_, o)| **o).map(|((u, r), _)| (u * r).abs()).sum();
    let energy: f64 = u.iter().zip(&rhs).zip(&own).filter(|(_, o)| **o).map(|((u, r), _)| u * r).sum();
    assert!(energy.abs() < 1e-12 * scale, "D = {D}: Σ u·rhs = {energy:e} (scale {scale:e})");
    // Momentum, each component, with the viscous term as well.
    central::momentum_rhs(&n, h, 0.7, &u, &mut rhs);
    let grid = Periodic::new(n, h, 0.0, Scheme::SemiLagrangian).grid;
    for a in 0..D {
        let r = grid.face_range(a);
        let total: f64 = rhs[r.clone()].iter().zip(&own[r.clone()]).filter(|(_, o)| **o).map(|(v, _)| v).sum();
        let size: f64 = rhs[r.clone()].iter().map(|v| v.abs()).sum();
        assert!(total.abs() < 1e-12 * size, "D = {D}, component {a}: momentum {total:e}");
        // The copies are the copies.
        for f in crate::boundary::faces(n, &grid.boundary, a) {
            if let Some(c) = f.copy {
                assert_eq!(rhs[r.start + c], rhs[r.start + f.index]);
            }
        }
    }
}

#[test]
fn central_momentum_flux_conserves_energy_and_momentum() {
    central_conserves([6, 5]);
    central_conserves([4, 6, 5]);
}

#[test]
fn central_momentum_flux_converges_at_second_order() {
    // A two-mode flow from ψ = sin x·sin y + ½·cos(2x + y): the discrete
    // right-hand side against −(u·∇)u + ν∇²u written out, at the faces.
    let err = |m: usize, nu: f64| {
        let n = [m, m];
        let h = std::f64::consts::TAU / m as f64;
        let vel = |a: usize, x: f64, y: f64| {
            let (s, c) = ((2.0 * x + y).sin(), (2.0 * x + y).cos());
            if a == 0 {
                let (u, ux, uy) = (x.sin() * y.cos() - 0.5 * s, x.cos() * y.cos() - c, -x.sin() * y.sin() - 0.5 * c);
                (u, ux, uy, -2.0 * x.sin() * y.cos() + 2.5 * s)
            } else {
                let (v, vx, vy) = (-x.cos() * y.sin() + s, x.sin() * y.sin() + 2.0 * c, -x.cos() * y.cos() + c);
                (v, vx, vy, 2.0 * x.cos() * y.sin() - 5.0 * s)
            }
        };
        let u = crate::exact::on_faces(n, h, |a, p| vel(a, p[0], p[1]).0);
        let exact = crate::exact::on_faces(n, h, |a, p| {
            let (u, v) = (vel(0, p[0], p[1]).0, vel(1, p[0], p[1]).0);
            let (_, dx, dy, lap) = vel(a, p[0], p[1]);
            -(u * dx + v * dy) + nu * lap
        });
        let mut rhs = vec![0.0; u.len()];
        central::momentum_rhs(&n, h, nu, &u, &mut rhs);
        rhs.iter().zip(&exact).fold(0.0f64, |m, (r, e)| m.max((r - e).abs()))
    };
    for nu in [0.0, 0.5] {
        let (coarse, fine) = (err(16, nu), err(32, nu));
        let order = (coarse / fine).log2();
        assert!((1.8..2.3).contains(&order), "ν = {nu}: {coarse:e} at 16, {fine:e} at 32, order {order:.2}");
    }
}
