//! The momentum equation's right-hand side on a box periodic on every axis
//! by central differences: `−∇·(u⊗u) + ν·∇²u` on each component's faces, in
//! 2D and 3D from one code.
//!
//! The flux is in divergence form on the staggered grid (Harlow and Welch
//! 1965): `u_a²` at the cell centres from the mean of the two faces beside
//! each, `u_a·u_b` at the edges from the means of the two faces of each
//! component beside the edge. For a velocity whose discrete divergence is
//! zero this form conserves momentum and kinetic energy exactly in space
//! (Morinishi et al. 1998): `Σ u·∇·(u⊗u) = 0` over the box (tested). A
//! smooth map — a quadratic and a linear term, no interpolation with a
//! kink — that a Runge–Kutta step keeps stable without a limiter
//! (`diffsim::navier_stokes::CentralNavierStokes`).

use super::axes_of;

/// The right-hand side `−∇·(u⊗u) + ν·∇²u` of the momentum equation at every
/// face of the packed velocity `x` of a periodic box of `n` cells of size
/// `h` (each component on its faces, a periodic axis's copy face `n`
/// included) into `y` (the copies written as copies; never read).
///
/// # Panics
/// If `x` or `y` is not the packed velocity's length.
pub fn momentum_rhs<const D: usize>(n: &[usize; D], h: f64, nu: f64, x: &[f64], y: &mut [f64]) {
    let n = axes_of(n);
    // Each component's first face and strides (its array has one more face
    // along its own axis: the copy).
    let mut start = [0usize; D];
    let mut stride = [[1usize; D]; D];
    let mut total = 0;
    let mut cells = 1;
    each_axis!(D, c => {
        start[c] = total;
        let mut s = 1;
        each_axis!(D, b => {
            stride[c][b] = s;
            s *= if b == c { n[b] + 1 } else { n[b] };
        });
        total += s;
        cells *= n[c];
    });
    assert!(x.len() == total && y.len() == total, "momentum_rhs: lengths of the packed velocity");
    let (inv_h, inv_h2) = (1.0 / h, 1.0 / (h * h));
    let mut q = [0usize; D];
    for _ in 0..cells {
        // Each component's face at `q` and its neighbours' offsets along
        // every axis, wrapping (never onto the copy face).
        let mut base = [0isize; D];
        let mut plus = [[0isize; D]; D];
        let mut minus = [[0isize; D]; D];
        each_axis!(D, c => {
            let mut at = start[c];
            each_axis!(D, b => {
                let s = stride[c][b] as isize;
                at += q[b] * stride[c][b];
                plus[c][b] = if q[b] + 1 == n[b] { -((n[b] - 1) as isize) * s } else { s };
                minus[c][b] = if q[b] == 0 { (n[b] - 1) as isize * s } else { -s };
            });
            base[c] = at as isize;
        });
        each_axis!(D, a => {
            let ua = |o: isize| x[(base[a] + o) as usize];
            let own = ua(0);
            // ∂(u_a²)/∂x_a from the cell centres on either side.
            let (right, left) = (0.5 * (own + ua(plus[a][a])), 0.5 * (ua(minus[a][a]) + own));
            let mut flux = right * right - left * left;
            let mut lap = 0.0;
            each_axis!(D, b => {
                lap += ua(plus[a][b]) + ua(minus[a][b]) - 2.0 * own;
                if b != a {
                    // ∂(u_a·u_b)/∂x_b from the edges above and below.
                    let ub = |o: isize| x[(base[b] + o) as usize];
                    let above = 0.5 * (own + ua(plus[a][b])) * 0.5 * (ub(plus[b][b] + minus[b][a]) + ub(plus[b][b]));
                    let below = 0.5 * (ua(minus[a][b]) + own) * 0.5 * (ub(minus[b][a]) + ub(0));
                    flux += above - below;
                }
            });
            let value = nu * lap * inv_h2 - flux * inv_h;
            let i = base[a] as usize;
            y[i] = value;
            if q[a] == 0 {
                // The copy face `n` along the component's own axis.
                y[i + n[a] * stride[a][a]] = value;
            }
        });
        // The next cell, x fastest.
        let mut carry = true;
        each_axis!(D, b => {
            if carry {
                q[b] += 1;
                if q[b] == n[b] {
                    q[b] = 0;
                } else {
                    carry = false;
                }
            }
        });
    }
}
