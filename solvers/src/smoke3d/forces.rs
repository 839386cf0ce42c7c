//! Forces on the 3D grid as maps of packed states `[s, u, v, w]`: buoyancy
//! along any axis and inflow regions. Plain loops indexing the packed
//! state, so that Enzyme differentiates them (with respect to the state and
//! the coefficients).

use super::MacGrid;
use crate::smoke::copy;

/// Where the faces normal to `axis` start in the packed state, and their
/// extents `[x, y, z]`.
#[inline(always)]
fn faces(cfg: &MacGrid<3>, axis: usize) -> (usize, [usize; 3]) {
    (cfg.slab_starts(0).1[axis], cfg.face_dims(axis))
}

/// Buoyancy along `axis` (0 x, 1 y, 2 z; a negative coefficient pushes the
/// other way): `y = x` with the velocity component of `axis` on its faces
/// between two cells (interior, and across a periodic side: the last cell
/// and the first, the copy refreshed) raised by `coefficient · (smoke
/// averaged to the face)`.
///
/// # Panics
/// If `x` or `y` is not a packed state or `axis > 2`.
pub fn apply_buoyancy3(cfg: &MacGrid<3>, axis: usize, coefficient: f64, x: &[f64], y: &mut [f64]) {
    assert!(x.len() == cfg.n_state() && y.len() == cfg.n_state() && axis < 3, "smoke3d: buoyancy lengths");
    copy(x, y);
    let [nx, ny, _] = cfg.n;
    let (start, e) = faces(cfg, axis);
    // Cells one step down `axis` from cell c are at c − stride.
    let stride = [1, nx, nx * ny][axis];
    let n = cfg.n[axis];
    let wrap = cfg.boundary.wraps()[axis];
    for k in 0..e[2] {
        for j in 0..e[1] {
            for i in 0..e[0] {
                let along = [i, j, k][axis];
                let c = (k * ny + j) * nx + i;
                if along > 0 && along < n {
                    y[start + (k * e[1] + j) * e[0] + i] += coefficient * 0.5 * (x[c - stride] + x[c]);
                } else if wrap && along == 0 {
                    y[start + (k * e[1] + j) * e[0] + i] += coefficient * 0.5 * (x[c + (n - 1) * stride] + x[c]);
                }
            }
        }
    }
    refresh_copies(cfg, axis, y);
}

/// On a periodic `axis`, each last face of the packed state `y` set to the
/// copy of its face `0`.
#[inline(always)]
fn refresh_copies(cfg: &MacGrid<3>, axis: usize, y: &mut [f64]) {
    if !cfg.boundary.wraps()[axis] {
        return;
    }
    let (start, e) = faces(cfg, axis);
    let n = cfg.n[axis];
    let step = [1, e[0], e[0] * e[1]][axis];
    for k in 0..e[2] {
        for j in 0..e[1] {
            for i in 0..e[0] {
                if [i, j, k][axis] == 0 {
                    let face = start + (k * e[1] + j) * e[0] + i;
                    y[face + n * step] = y[face];
                }
            }
        }
    }
}

/// Inflow: in the cells `i0..i1 × j0..j1 × k0..k1` (`region = [i0, i1, j0,
/// j1, k0, k1]`) the smoke set to `p[0]` and the velocity on the faces of
/// those cells (the box's sides excepted) to `(p[1], p[2], p[3])`;
/// everything else passes through.
///
/// # Panics
/// If the lengths are wrong or the region is empty or leaves the box.
pub fn apply_inflow3(cfg: &MacGrid<3>, region: [usize; 6], x: &[f64], p: &[f64], y: &mut [f64]) {
    let [nx, ny, nz] = cfg.n;
    let [i0, i1, j0, j1, k0, k1] = region;
    assert!(
        x.len() == cfg.n_state() && y.len() == cfg.n_state() && p.len() == 4 && i0 < i1 && i1 <= nx && j0 < j1 && j1 <= ny && k0 < k1 && k1 <= nz,
        "smoke3d: inflow"
    );
    copy(x, y);
    for k in k0..k1 {
        for j in j0..j1 {
            for i in i0..i1 {
                y[(k * ny + j) * nx + i] = p[0];
            }
        }
    }
    let lo = [i0, j0, k0];
    let hi = [i1, j1, k1];
    let n = [nx, ny, nz];
    for axis in 0..3 {
        let (start, e) = faces(cfg, axis);
        // Faces of the region's cells along `axis`, those on the box's sides left out.
        let from = |b: usize| if b == axis { lo[b].max(1) } else { lo[b] };
        let to = |b: usize| if b == axis { hi[b].min(n[b] - 1) + 1 } else { hi[b] };
        for k in from(2)..to(2) {
            for j in from(1)..to(1) {
                for i in from(0)..to(0) {
                    y[start + (k * e[1] + j) * e[0] + i] = p[1 + axis];
                }
            }
        }
    }
}

/// An external force over a time step `dt`: `[s, u, v, w] ↦ [s, u + dt·fu,
/// v + dt·fv, w + dt·fw]` on the interior faces and those that wrap across
/// a periodic side (copies refreshed), with the force `f` given per face
/// (the velocity layout, [`MacGrid<3>::n_vel`] values); the faces on the
/// other sides keep their velocity.
///
/// # Panics
/// If the lengths are wrong.
pub fn apply_force3(cfg: &MacGrid<3>, dt: f64, x: &[f64], f: &[f64], y: &mut [f64]) {
    assert!(x.len() == cfg.n_state() && y.len() == cfg.n_state() && f.len() == cfg.n_vel(), "smoke3d: force lengths");
    copy(x, y);
    let n = cfg.n;
    let ns = cfg.n_s();
    let wraps = cfg.boundary.wraps();
    for axis in 0..3 {
        let (start, e) = faces(cfg, axis);
        let first = 1 - wraps[axis] as usize;
        for k in 0..e[2] {
            for j in 0..e[1] {
                for i in 0..e[0] {
                    let along = [i, j, k][axis];
                    if along >= first && along < n[axis] {
                        let face = start + (k * e[1] + j) * e[0] + i;
                        y[face] += dt * f[face - ns];
                    }
                }
            }
        }
        refresh_copies(cfg, axis, y);
    }
}
