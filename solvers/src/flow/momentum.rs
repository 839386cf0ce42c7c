//! The momentum right-hand side `F(u) = −∇·(u⊗u) + ν·Δu` on the MAC grid:
//! the velocity copied into arrays padded with one ring of ghost values that
//! carry the side conditions, then one branch-free stencil per face.

use super::{Convection, Flow2d};
use crate::boundary::Side;

/// The velocity with a ring of ghost values: `u` with columns `−1..=Nx+1`
/// and rows `−1..=Ny`, `v` with columns `−1..=Nx` and rows `−1..=Ny+1`.
#[derive(Clone, Debug)]
pub struct Pads {
    u: Vec<f64>,
    v: Vec<f64>,
}

impl Pads {
    /// Buffers for `cfg`'s grid.
    pub fn new(cfg: &Flow2d) -> Self {
        let (nx, ny) = (cfg.nx, cfg.ny);
        Self { u: vec![0.0; (nx + 3) * (ny + 2)], v: vec![0.0; (nx + 2) * (ny + 3)] }
    }
}

/// The ghost value beyond a side for the velocity component tangential to
/// it: no-slip at the wall's speed, no-slip at rest on inflow, zero normal
/// gradient on outflow.
#[inline(always)]
fn tangential_ghost(side: Side, wall_speed: f64, inside: f64) -> f64 {
    match side {
        Side::Closed | Side::NoSlip => 2.0 * wall_speed - inside,
        Side::Inflow(_) => -inside,
        Side::Outflow | Side::Periodic => inside,
    }
}

/// Fills the padded arrays from the packed velocity `x`: the interior
/// copied, ghosts tangential to a side from [`tangential_ghost`], ghosts
/// normal to a side (read only for outflow faces) copies of the side's face.
pub fn fill_pads(cfg: &Flow2d, x: &[f64], pads: &mut Pads) {
    let (nx, ny) = (cfg.nx, cfg.ny);
    let (u, v) = x.split_at(cfg.n_u());
    let b = &cfg.boundary;
    let w = &cfg.wall_speed;
    // u: padded row J = j + 1, column I = i + 1, width nx + 3.
    let su = nx + 3;
    for j in 0..ny {
        let row = &mut pads.u[(j + 1) * su..(j + 2) * su];
        row[1..nx + 2].copy_from_slice(&u[j * (nx + 1)..(j + 1) * (nx + 1)]);
        row[0] = row[1];
        row[nx + 2] = row[nx + 1];
    }
    for i in 0..su {
        pads.u[i] = tangential_ghost(b.lower(1), w.bottom, pads.u[su + i]);
        pads.u[(ny + 1) * su + i] = tangential_ghost(b.upper(1), w.top, pads.u[ny * su + i]);
    }
    // v: padded row J = j + 1, column I = i + 1, width nx + 2.
    let sv = nx + 2;
    for j in 0..=ny {
        let row = &mut pads.v[(j + 1) * sv..(j + 2) * sv];
        row[1..nx + 1].copy_from_slice(&v[j * nx..(j + 1) * nx]);
        row[0] = tangential_ghost(b.lower(0), w.left, row[1]);
        row[nx + 1] = tangential_ghost(b.upper(0), w.right, row[nx]);
    }
    for i in 0..sv {
        pads.v[i] = pads.v[sv + i];
        pads.v[(ny + 2) * sv + i] = pads.v[(ny + 1) * sv + i];
    }
}

/// The faces whose velocity the momentum equation advances along one
/// axis of `n` cells: the interior faces `1..n`, and the side's face where
/// the side is an outflow.
#[inline]
pub fn advanced_faces(lo: Side, hi: Side, n: usize) -> std::ops::RangeInclusive<usize> {
    let first = if lo == Side::Outflow { 0 } else { 1 };
    let last = if hi == Side::Outflow { n } else { n - 1 };
    first..=last
}

/// `out = F(x)`: advection in divergence form, `−∂(uu)/∂x − ∂(uv)/∂y` for
/// `u` and `−∂(uv)/∂x − ∂(vv)/∂y` for `v` (central flux differences, the
/// velocities interpolated to the flux points as `cfg.convection` says:
/// two-point averages, or four-point where the points fit), plus `ν·Δ`
/// with the five-point Laplacian, on every advanced face
/// ([`advanced_faces`]); zero on faces the boundary sets.
pub fn momentum(cfg: &Flow2d, x: &[f64], pads: &mut Pads, out: &mut [f64]) {
    fill_pads(cfg, x, pads);
    let (nx, ny) = (cfg.nx, cfg.ny);
    let (inv_h, nu_h2) = (1.0 / cfg.h, cfg.nu / (cfg.h * cfg.h));
    let b = &cfg.boundary;
    out.fill(0.0);
    let (ou, ov) = out.split_at_mut(cfg.n_u());
    let (pu, pv) = (&pads.u, &pads.v);
    let (su, sv) = (nx + 3, nx + 2);
    // u at x-face (i, j): padded U(i, j) = pu[(j+1)·su + i+1], V(i, j) = pv[(j+1)·sv + i+1].
    let faces = advanced_faces(b.lower(0), b.upper(0), nx);
    // Fourth order: four-point interpolation wherever its points lie in
    // the padded arrays (two-point averages next to the sides).
    let high = cfg.convection == Convection::Fourth;
    let i4 = |a: f64, b: f64, c: f64, d: f64| (9.0 * (b + c) - (a + d)) / 16.0;
    for j in 0..ny {
        let (r, rd, rn) = ((j + 1) * su, j * su, (j + 2) * su);
        let (vr, vn) = ((j + 1) * sv, (j + 2) * sv);
        for i in faces.clone() {
            let c = r + i + 1;
            let uc = pu[c];
            let mut ue = 0.5 * (uc + pu[c + 1]);
            let mut uw = 0.5 * (pu[c - 1] + uc);
            let mut un = 0.5 * (uc + pu[rn + i + 1]);
            let mut us = 0.5 * (pu[rd + i + 1] + uc);
            // Four points along x fit from face 2 to face nx − 2.
            let wide_x = high && i >= 2 && i + 2 <= nx;
            if wide_x {
                ue = i4(pu[c - 1], uc, pu[c + 1], pu[c + 2]);
                uw = i4(pu[c - 2], pu[c - 1], uc, pu[c + 1]);
            }
            if high && j >= 1 && j + 3 <= ny + 1 {
                un = i4(pu[rd + i + 1], uc, pu[rn + i + 1], pu[rn + su + i + 1]);
                us = i4(pu[rd - su + i + 1], pu[rd + i + 1], uc, pu[rn + i + 1]);
            }
            // Corners above and below the face: v averaged over the face's two columns.
            let mut vn_ = 0.5 * (pv[vn + i] + pv[vn + i + 1]);
            let mut vs = 0.5 * (pv[vr + i] + pv[vr + i + 1]);
            if wide_x {
                vn_ = i4(pv[vn + i - 1], pv[vn + i], pv[vn + i + 1], pv[vn + i + 2]);
                vs = i4(pv[vr + i - 1], pv[vr + i], pv[vr + i + 1], pv[vr + i + 2]);
            }
            let adv = (ue * ue - uw * uw + un * vn_ - us * vs) * inv_h;
            let lap = pu[c + 1] + pu[c - 1] + pu[rn + i + 1] + pu[rd + i + 1] - 4.0 * uc;
            ou[j * (nx + 1) + i] = nu_h2 * lap - adv;
        }
    }
    // v at y-face (i, j).
    for j in advanced_faces(b.lower(1), b.upper(1), ny) {
        let (r, rd, rn) = ((j + 1) * sv, j * sv, (j + 2) * sv);
        let (ur, ud) = ((j + 1) * su, j * su);
        for i in 0..nx {
            let c = r + i + 1;
            let vc = pv[c];
            let mut vn_ = 0.5 * (vc + pv[rn + i + 1]);
            let mut vs = 0.5 * (pv[rd + i + 1] + vc);
            let mut ve = 0.5 * (vc + pv[c + 1]);
            let mut vw = 0.5 * (pv[c - 1] + vc);
            // Four points along y fit from face 2 to face ny − 2.
            let wide_y = high && j >= 2 && j + 2 <= ny;
            if wide_y {
                vn_ = i4(pv[rd + i + 1], vc, pv[rn + i + 1], pv[rn + sv + i + 1]);
                vs = i4(pv[rd - sv + i + 1], pv[rd + i + 1], vc, pv[rn + i + 1]);
            }
            if high && i >= 1 && i + 2 <= nx {
                ve = i4(pv[c - 1], vc, pv[c + 1], pv[c + 2]);
                vw = i4(pv[c - 2], pv[c - 1], vc, pv[c + 1]);
            }
            // Corners right and left of the face: u averaged over the face's two rows.
            let mut ue = 0.5 * (pu[ud + i + 2] + pu[ur + i + 2]);
            let mut uw = 0.5 * (pu[ud + i + 1] + pu[ur + i + 1]);
            if wide_y {
                ue = i4(pu[ud - su + i + 2], pu[ud + i + 2], pu[ur + i + 2], pu[ur + su + i + 2]);
                uw = i4(pu[ud - su + i + 1], pu[ud + i + 1], pu[ur + i + 1], pu[ur + su + i + 1]);
            }
            let adv = (ue * ve - uw * vw + vn_ * vn_ - vs * vs) * inv_h;
            let lap = pv[c + 1] + pv[c - 1] + pv[rn + i + 1] + pv[rd + i + 1] - 4.0 * vc;
            ov[j * nx + i] = nu_h2 * lap - adv;
        }
    }
}
