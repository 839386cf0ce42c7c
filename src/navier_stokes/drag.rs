//! [`SurfaceDrag`]: the force along x on a box's obstacles, as the surface
//! sums of Mosaic's `ns-grid` benchmark define it, carried by
//! [`super::NavierStokes::with_drag`] as two sums in the state.
//!
//! Mosaic's drag (`mosaic_shared/problems/navier_stokes_grid/drag.py`) is
//!
//! ```text
//! F = Σ_c σ_c · p_c · h^{D−1}  −  ν · Σ_c σ_c · ū_c · h^{D−2}
//! ```
//!
//! over the fluid cells `c` beside a solid one along x: `σ_c = +1` when the
//! solid is on the cell's +x side, `−1` on its −x side (both: the two
//! cancel); `p` the pressure, `ū` the cell's x-velocity (the mean of its two
//! x-faces). Nothing here needs the pressure itself: the projection changes
//! the velocity of every face between two fluid cells by `Δu = −s·(p_upper −
//! p_lower)/h` (the pressure's gradient over a sub-step `s`, density 1), so
//! the pressure at every fluid cell is, up to one constant per connected
//! region of fluid, a sum of `Δu` along a path of such faces, and the
//! constant drops out of `F` where the `σ` of a region sum to zero (an
//! obstacle that does not touch a closed side). Along a spanning tree of
//! the fluid cells the pressure term of a sub-step times `s` is a fixed
//! linear function of the velocity change, `s·F_p = w·Δu`
//! ([`SurfaceDrag::impulse`]): exact for any tolerance of the solve,
//! without a second solve in the adjoint, and the time integral of the
//! pressure force summed over the sub-steps.

use diffsim_solvers::boundary::faces;
use diffsim_solvers::smoke::MacGrid;

use super::NavierStokesError;

/// The weights of Mosaic's drag on a box's obstacles ([module
/// docs](self)): one per face of the packed velocity each.
#[derive(Clone, Debug, PartialEq)]
pub struct SurfaceDrag {
    /// `w`: the time integral of the pressure force along x over a
    /// sub-step is `w·Δu`, `Δu` the projection's change of the velocity.
    pub impulse: Vec<f64>,
    /// `v`: `v·u = Σ_c σ_c · ū_c · h^{D−2}`, the sum the viscous term
    /// multiplies by `−ν`.
    pub shear: Vec<f64>,
}

impl SurfaceDrag {
    /// The weights on the box `grid` of cells of size `h` with the solid
    /// cells `solid` (one flag per cell, x fastest).
    ///
    /// # Errors
    /// If `solid` does not have one flag per cell, every cell is solid, or
    /// in a connected region of fluid the `σ` do not sum to zero (an
    /// obstacle against a closed side along x: the force would need the
    /// pressure's level, which the velocity does not give).
    pub fn new<const D: usize>(grid: &MacGrid<D>, h: f64, solid: &[bool]) -> Result<Self, NavierStokesError> {
        let cells = grid.n_s();
        if solid.len() != cells {
            return Err(NavierStokesError::SolidFlags { given: solid.len(), cells });
        }
        if solid.iter().all(|&s| s) {
            return Err(NavierStokesError::AllSolid);
        }
        // Each fluid cell's σ and its two x-faces (the mean ū); each pair
        // of fluid cells the projection couples, with the face between.
        let mut sigma = vec![0.0; cells];
        let (mut lower_face, mut upper_face) = (vec![usize::MAX; cells], vec![usize::MAX; cells]);
        let mut links: Vec<Vec<(usize, usize, f64)>> = vec![Vec::new(); cells];
        for axis in 0..D {
            let start = grid.face_range(axis).start;
            for f in faces(grid.n, &grid.boundary, axis) {
                if axis == 0 {
                    if let Some(c) = f.upper {
                        lower_face[c] = start + f.index;
                    }
                    if let Some(c) = f.lower {
                        upper_face[c] = start + f.index;
                    }
                }
                let (Some(l), Some(u)) = (f.lower, f.upper) else { continue };
                if axis == 0 && solid[l] != solid[u] {
                    // The fluid cell's σ: +1 with the solid on its +x side.
                    if solid[u] {
                        sigma[l] += 1.0;
                    } else {
                        sigma[u] -= 1.0;
                    }
                }
                if f.projected && !solid[l] && !solid[u] {
                    // From the lower cell to the upper: s·p_u = s·p_l − h·Δu.
                    links[l].push((u, start + f.index, -h));
                    links[u].push((l, start + f.index, h));
                }
            }
        }
        // A spanning tree of each region by breadth-first search: the order
        // of the visits and each cell's link to its parent.
        let mut parent: Vec<Option<(usize, usize, f64)>> = vec![None; cells];
        let mut seen = solid.to_vec();
        let mut order = Vec::with_capacity(cells);
        let mut roots = Vec::new();
        for root in 0..cells {
            if seen[root] {
                continue;
            }
            seen[root] = true;
            roots.push(root);
            let first = order.len();
            order.push(root);
            let mut next = first;
            while next < order.len() {
                let c = order[next];
                next += 1;
                for &(m, face, coef) in &links[c] {
                    if !seen[m] {
                        seen[m] = true;
                        parent[m] = Some((c, face, coef));
                        order.push(m);
                    }
                }
            }
        }
        // The σ below each cell, leaves first: each tree link carries the
        // σ of the cells beyond it.
        let area = h.powi(D as i32 - 1);
        let mut below = sigma.clone();
        let mut impulse = vec![0.0; grid.n_vel()];
        for &c in order.iter().rev() {
            if let Some((up, face, coef)) = parent[c] {
                impulse[face] += area * coef * below[c];
                below[up] += below[c];
            }
        }
        if let Some(&root) = roots.iter().find(|&&r| below[r] != 0.0) {
            return Err(NavierStokesError::DragLevel { cell: root });
        }
        let mut shear = vec![0.0; grid.n_vel()];
        let scale = 0.5 * h.powi(D as i32 - 2);
        for c in (0..cells).filter(|&c| sigma[c] != 0.0) {
            shear[lower_face[c]] += scale * sigma[c];
            shear[upper_face[c]] += scale * sigma[c];
        }
        Ok(Self { impulse, shear })
    }
}

/// `v += c·w`.
pub(super) fn add(c: f64, w: &[f64], v: &mut [f64]) {
    for (v, w) in v.iter_mut().zip(w) {
        *v += c * w;
    }
}
