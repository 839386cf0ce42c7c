//! Buoyancy, external forces on the faces, and inflow regions.

use super::*;

/// Buoyancy, in place: `v += coefficient · (smoke averaged to the y-face)`
/// on the interior y-faces and, when y wraps, on face row `0` (whose copy,
/// row `Ny`, follows).
pub fn add_buoyancy(cfg: &MacGrid<2>, coefficient: f64, s: &[f64], v: &mut [f64]) {
    let (n, ny) = (cfg.n[0], cfg.n[1]);
    for j in 1..ny {
        for i in 0..n {
            v[j * n + i] += coefficient * 0.5 * (s[(j - 1) * n + i] + s[j * n + i]);
        }
    }
    if cfg.boundary.periodic(1) {
        for i in 0..n {
            v[i] += coefficient * 0.5 * (s[(ny - 1) * n + i] + s[i]);
            v[ny * n + i] = v[i];
        }
    }
}

/// [`add_buoyancy`] as a map of packed states: `y = x` with
/// `v += coefficient · (smoke averaged to the y-face)`.
pub fn apply_buoyancy(cfg: &MacGrid<2>, coefficient: f64, x: &[f64], y: &mut [f64]) {
    assert!(x.len() == cfg.n_state() && y.len() == cfg.n_state(), "smoke: state lengths");
    copy(x, y);
    let (s, [_, _]) = cfg.split(x);
    let (_, [_, v2]) = cfg.split_mut(y);
    add_buoyancy(cfg, coefficient, s, v2);
}

/// An external force over a time step `dt`: `[s, u, v] ↦ [s, u + dt·fu,
/// v + dt·fv]`, with the force `f = [fu, fv]` given per face (the velocity
/// layout, [`MacGrid<2>::n_vel`] values), on the interior faces and the faces
/// that wrap across a periodic side (copies refreshed); the faces on other
/// sides keep their velocity.
pub fn apply_force(cfg: &MacGrid<2>, dt: f64, x: &[f64], f: &[f64], y: &mut [f64]) {
    let (n, ny) = (cfg.n[0], cfg.n[1]);
    assert!(x.len() == cfg.n_state() && y.len() == cfg.n_state() && f.len() == cfg.n_vel(), "smoke: force lengths");
    let nu = n + 1;
    copy(x, y);
    let (fu, fv) = f.split_at(cfg.n_face(0));
    let (_, [u2, v2]) = cfg.split_mut(y);
    let (wx, wy) = (cfg.boundary.periodic(0) as usize, cfg.boundary.periodic(1) as usize);
    for j in 0..ny {
        for i in 1 - wx..n {
            u2[j * nu + i] += dt * fu[j * nu + i];
        }
    }
    for j in 1 - wy..ny {
        for i in 0..n {
            v2[j * n + i] += dt * fv[j * n + i];
        }
    }
    for j in 0..ny * wx {
        u2[j * nu + n] = u2[j * nu];
    }
    for i in 0..n * wy {
        v2[ny * n + i] = v2[i];
    }
}

/// Inflow: in the cells `i0..i1 × j0..j1` set the smoke to `p[0]` and the
/// velocity on the faces of those cells (walls excepted) to `(p[1], p[2])`;
/// everything else passes through.
pub fn apply_inflow(cfg: &MacGrid<2>, region: [usize; 4], x: &[f64], p: &[f64], y: &mut [f64]) {
    let (n, ny) = (cfg.n[0], cfg.n[1]);
    let [i0, i1, j0, j1] = region;
    assert!(x.len() == cfg.n_state() && y.len() == cfg.n_state() && p.len() == 3 && i0 < i1 && i1 <= n && j0 < j1 && j1 <= ny, "smoke: inflow");
    let nu = n + 1;
    for (o, &a) in y.iter_mut().zip(x) {
        *o = a;
    }
    let (s2, [u2, v2]) = cfg.split_mut(y);
    for j in j0..j1 {
        for i in i0..i1 {
            s2[j * n + i] = p[0];
        }
        for i in i0.max(1)..=i1.min(n - 1) {
            u2[j * nu + i] = p[1];
        }
    }
    for j in j0.max(1)..=j1.min(ny - 1) {
        for i in i0..i1 {
            v2[j * n + i] = p[2];
        }
    }
}
