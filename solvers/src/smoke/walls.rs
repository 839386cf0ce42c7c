//! Velocity boundary conditions on the box's sides, and obstacles (solid
//! cells whose faces are held at zero).

use super::*;

/// The velocity boundary conditions, in place: closed sides' faces 0,
/// inflow sides' faces the profile (inward), outflow faces as they are,
/// and on periodic axes face `N` the copy of face `0`.
pub fn enforce_boundary(cfg: &MacGrid<2>, u: &mut [f64], v: &mut [f64]) {
    let (nx, ny) = (cfg.n[0], cfg.n[1]);
    let nu = nx + 1;
    let b = &cfg.boundary;
    // Position along the side, 0..1: a profile spans the whole side.
    let t = |k: usize, n: usize| (k as f64 + 0.5) / n as f64;
    for j in 0..ny {
        match b.lower(0) {
            Side::Closed => u[j * nu] = 0.0,
            Side::Inflow(p) => u[j * nu] = p.at(t(j, ny)),
            Side::Periodic | Side::Outflow => {}
        }
        match b.upper(0) {
            Side::Closed => u[j * nu + nx] = 0.0,
            Side::Inflow(p) => u[j * nu + nx] = -p.at(t(j, ny)),
            Side::Periodic => u[j * nu + nx] = u[j * nu],
            Side::Outflow => {}
        }
    }
    let top = ny * nx;
    for i in 0..nx {
        match b.lower(1) {
            Side::Closed => v[i] = 0.0,
            Side::Inflow(p) => v[i] = p.at(t(i, nx)),
            Side::Periodic | Side::Outflow => {}
        }
        match b.upper(1) {
            Side::Closed => v[top + i] = 0.0,
            Side::Inflow(p) => v[top + i] = -p.at(t(i, nx)),
            Side::Periodic => v[top + i] = v[i],
            Side::Outflow => {}
        }
    }
}

/// The linear part of [`enforce_boundary`] (inflow faces set to 0, not to
/// the profile), for tangents: closed and inflow faces 0, periodic copies.
pub fn enforce_boundary_linear(cfg: &MacGrid<2>, u: &mut [f64], v: &mut [f64]) {
    enforce_boundary(&cfg.with_boundary(cfg.boundary.homogeneous()), u, v);
}

/// Adjoint of [`enforce_boundary`] (of its linear part) on the velocity
/// adjoint, in place: set faces pass nothing back, copies pass theirs to the
/// original.
pub fn enforce_boundary_adjoint(cfg: &MacGrid<2>, gu: &mut [f64], gv: &mut [f64]) {
    let (nx, ny) = (cfg.n[0], cfg.n[1]);
    let nu = nx + 1;
    let b = &cfg.boundary;
    for j in 0..ny {
        if let Side::Periodic = b.upper(0) {
            gu[j * nu] += gu[j * nu + nx];
            gu[j * nu + nx] = 0.0;
        }
        if b.lower(0).sets_faces() {
            gu[j * nu] = 0.0;
        }
        if b.upper(0).sets_faces() {
            gu[j * nu + nx] = 0.0;
        }
    }
    let top = ny * nx;
    for i in 0..nx {
        if let Side::Periodic = b.upper(1) {
            gv[i] += gv[top + i];
            gv[top + i] = 0.0;
        }
        if b.lower(1).sets_faces() {
            gv[i] = 0.0;
        }
        if b.upper(1).sets_faces() {
            gv[top + i] = 0.0;
        }
    }
}

/// Zeroes the smoke in solid cells and the velocity on every face that
/// touches a solid cell, in place on a packed state: the obstacle boundary
/// condition. Linear and self-adjoint (a diagonal 0/1 mask), so the same
/// call is its own VJP.
pub fn apply_obstacle_mask(cfg: &MacGrid<2>, fluid: &[f64], x: &mut [f64]) {
    let (s, [u, v]) = cfg.split_mut(x);
    for (sv, &w) in s.iter_mut().zip(fluid) {
        *sv *= w;
    }
    for (axis, vel) in [u, v].into_iter().enumerate() {
        for_each_face(cfg.n[0], cfg.n[1], &cfg.boundary, axis, |f| {
            let o = open(Some(fluid), &f);
            vel[f.index] *= o;
            if let Some(k) = f.copy {
                vel[k] *= o;
            }
        });
    }
}

/// Solid cells of an axis-aligned box `[lower, upper)` in cell units (x
/// first), for the fluid operators and, complemented, as the fluid mask of
/// [`PressureSolver::general`]: a cell is solid when its centre lies inside. The box is clipped to the
/// domain; `None` when no cell centre lies inside (a box wholly outside).
pub fn obstacle_box(cfg: &MacGrid<2>, lower: [f64; 2], upper: [f64; 2]) -> Option<Vec<bool>> {
    obstacle(cfg, |x, y| x >= lower[0] && x < upper[0] && y >= lower[1] && y < upper[1])
}

/// Solid cells of a disc (centre in cell units, x first): a cell is solid
/// when its centre lies within `radius`. `None` when no cell is covered.
pub fn obstacle_disc(cfg: &MacGrid<2>, center: [f64; 2], radius: f64) -> Option<Vec<bool>> {
    obstacle(cfg, |x, y| (x - center[0]).powi(2) + (y - center[1]).powi(2) <= radius * radius)
}

fn obstacle(cfg: &MacGrid<2>, inside: impl Fn(f64, f64) -> bool) -> Option<Vec<bool>> {
    let n = cfg.n[0];
    let solid: Vec<bool> = (0..cfg.n_s()).map(|c| inside((c % n) as f64 + 0.5, (c / n) as f64 + 0.5)).collect();
    solid.iter().any(|&s| s).then_some(solid)
}
