//! The lid-driven cavity: the unit box, the top wall sliding at speed 1,
//! `ν = 1/Re`; its centreline profiles and their extrema, and the reference
//! values of Ghia, Ghia & Shin, J. Comput. Phys. 48 (1982) 387–411, Tables I
//! and II (a 129 × 129 grid; their tabulated points, as printed).

use super::{Convection, Flow2d, WallSpeed};
use crate::boundary::Boundary;

impl Flow2d {
    /// The lid-driven cavity of `n × n` cells at Reynolds number `re`.
    pub fn cavity(n: usize, re: f64) -> Self {
        Flow2d {
            nx: n,
            ny: n,
            h: 1.0 / n as f64,
            nu: 1.0 / re,
            boundary: Boundary::CLOSED,
            wall_speed: WallSpeed { top: 1.0, ..WallSpeed::default() },
            convection: Convection::default(),
        }
    }
}

/// A tabulated profile: positions and values, positions ascending.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Profile17 {
    /// Positions (y for u, x for v).
    pub at: [f64; 17],
    /// Velocities.
    pub value: [f64; 17],
}

/// Ghia et al.'s two centreline profiles at one Reynolds number.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct GhiaTable {
    /// Reynolds number.
    pub re: u32,
    /// `u` on the vertical centreline `x = ½` (Table I).
    pub u: Profile17,
    /// `v` on the horizontal centreline `y = ½` (Table II).
    pub v: Profile17,
}

const GHIA_Y: [f64; 17] = [0.0, 0.0547, 0.0625, 0.0703, 0.1016, 0.1719, 0.2813, 0.4531, 0.5, 0.6172, 0.7344, 0.8516, 0.9531, 0.9609, 0.9688, 0.9766, 1.0];
const GHIA_X: [f64; 17] = [0.0, 0.0625, 0.0703, 0.0781, 0.0938, 0.1563, 0.2266, 0.2344, 0.5, 0.8047, 0.8594, 0.9063, 0.9453, 0.9531, 0.9609, 0.9688, 1.0];

/// Ghia, Ghia & Shin's tables for Re 100, 400 and 1000. The Re 400 value
/// `v = −0.23827` at `x = 0.9063` breaks the profile's monotone run (it is
/// printed so; its neighbours suggest about −0.43); it is not an extremum.
pub const GHIA: [GhiaTable; 3] = [
    GhiaTable {
        re: 100,
        u: Profile17 {
            at: GHIA_Y,
            value: [
                0.0, -0.03717, -0.04192, -0.04775, -0.06434, -0.10150, -0.15662, -0.21090, -0.20581, -0.13641, 0.00332, 0.23151, 0.68717, 0.73722, 0.78871,
                0.84123, 1.0,
            ],
        },
        v: Profile17 {
            at: GHIA_X,
            value: [
                0.0, 0.09233, 0.10091, 0.10890, 0.12317, 0.16077, 0.17507, 0.17527, 0.05454, -0.24533, -0.22445, -0.16914, -0.10313, -0.08864, -0.07391,
                -0.05906, 0.0,
            ],
        },
    },
    GhiaTable {
        re: 400,
        u: Profile17 {
            at: GHIA_Y,
            value: [
                0.0, -0.08186, -0.09266, -0.10338, -0.14612, -0.24299, -0.32726, -0.17119, -0.11477, 0.02135, 0.16256, 0.29093, 0.55892, 0.61756, 0.68439,
                0.75837, 1.0,
            ],
        },
        v: Profile17 {
            at: GHIA_X,
            value: [
                0.0, 0.18360, 0.19713, 0.20920, 0.22965, 0.28124, 0.30203, 0.30174, 0.05186, -0.38598, -0.44993, -0.23827, -0.22847, -0.19254, -0.15663,
                -0.12146, 0.0,
            ],
        },
    },
    GhiaTable {
        re: 1000,
        u: Profile17 {
            at: GHIA_Y,
            value: [
                0.0, -0.18109, -0.20196, -0.22220, -0.29730, -0.38289, -0.27805, -0.10648, -0.06080, 0.05702, 0.18719, 0.33304, 0.46604, 0.51117, 0.57492,
                0.65928, 1.0,
            ],
        },
        v: Profile17 {
            at: GHIA_X,
            value: [
                0.0, 0.27485, 0.29012, 0.30353, 0.32627, 0.37095, 0.33075, 0.32235, 0.02526, -0.31966, -0.42665, -0.51550, -0.39188, -0.33714, -0.27669,
                -0.21388, 0.0,
            ],
        },
    },
];

/// Ghia et al.'s table at this Reynolds number, if they give one.
pub fn ghia(re: f64) -> Option<&'static GhiaTable> {
    GHIA.iter().find(|t| t.re as f64 == re)
}

/// An extremum of a profile: its value and position.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Extremum {
    /// The extreme value.
    pub value: f64,
    /// Where it is.
    pub at: f64,
}

/// The three extrema the cavity is compared on.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CavityExtrema {
    /// Minimum of `u` on the vertical centreline (position: y).
    pub u_min: Extremum,
    /// Maximum of `v` on the horizontal centreline (position: x).
    pub v_max: Extremum,
    /// Minimum of `v` on the horizontal centreline (position: x).
    pub v_min: Extremum,
}

impl GhiaTable {
    /// The extrema of the tabulated points (no interpolation), as the
    /// comparisons in the literature quote them.
    pub fn extrema(&self) -> CavityExtrema {
        let pick = |p: &Profile17, sign: f64| {
            let k = (0..17).max_by(|&a, &b| (sign * p.value[a]).total_cmp(&(sign * p.value[b]))).expect("17 points");
            Extremum { value: p.value[k], at: p.at[k] }
        };
        CavityExtrema { u_min: pick(&self.u, -1.0), v_max: pick(&self.v, 1.0), v_min: pick(&self.v, -1.0) }
    }
}

/// A profile sampled on a grid line: positions ascending, walls included.
#[derive(Clone, Debug, PartialEq)]
pub struct Line {
    /// Positions.
    pub at: Vec<f64>,
    /// Velocities.
    pub value: Vec<f64>,
}

impl Line {
    /// The extremum (`sign` +1: maximum, −1: minimum) of the parabola
    /// through the extreme sample and its two neighbours (second-order
    /// accurate, like the profile); the sample itself at an end.
    pub fn extremum(&self, sign: f64) -> Extremum {
        let (a, f) = (&self.at, &self.value);
        let k = (0..f.len()).max_by(|&i, &j| (sign * f[i]).total_cmp(&(sign * f[j]))).expect("a non-empty line");
        if k == 0 || k + 1 == f.len() {
            return Extremum { value: f[k], at: a[k] };
        }
        let (x0, x1, x2) = (a[k - 1], a[k], a[k + 1]);
        let (f0, f1, f2) = (f[k - 1], f[k], f[k + 1]);
        // Newton form: f = f0 + d0·(x − x0) + c·(x − x0)·(x − x1).
        let d0 = (f1 - f0) / (x1 - x0);
        let d1 = (f2 - f1) / (x2 - x1);
        let c = (d1 - d0) / (x2 - x0);
        if c == 0.0 {
            return Extremum { value: f1, at: x1 };
        }
        // f'(x) = d0 + c·(2x − x0 − x1) (the parabola through the three points).
        let xs = (0.5 * (x0 + x1) - 0.5 * d0 / c).clamp(x0, x2);
        let value = f0 + d0 * (xs - x0) + c * (xs - x0) * (xs - x1);
        Extremum { value, at: xs }
    }
}

/// `u` on the vertical line `x = Lx/2` and `v` on the horizontal line
/// `y = Ly/2` of a flow, with the wall values at the ends (the walls'
/// sliding speeds). On an odd number of cells the two face columns (rows)
/// beside the line are averaged.
pub fn centrelines(cfg: &Flow2d, x: &[f64]) -> (Line, Line) {
    let (nx, ny, h) = (cfg.nx, cfg.ny, cfg.h);
    let (u, v) = x.split_at(cfg.n_u());
    let w = &cfg.wall_speed;
    let (ia, ib) = (nx / 2, nx.div_ceil(2));
    let mut ul = Line { at: vec![0.0], value: vec![w.bottom] };
    for j in 0..ny {
        ul.at.push((j as f64 + 0.5) * h);
        ul.value.push(0.5 * (u[j * (nx + 1) + ia] + u[j * (nx + 1) + ib]));
    }
    ul.at.push(ny as f64 * h);
    ul.value.push(w.top);
    let (ja, jb) = (ny / 2, ny.div_ceil(2));
    let mut vl = Line { at: vec![0.0], value: vec![w.left] };
    for i in 0..nx {
        vl.at.push((i as f64 + 0.5) * h);
        vl.value.push(0.5 * (v[ja * nx + i] + v[jb * nx + i]));
    }
    vl.at.push(nx as f64 * h);
    vl.value.push(w.right);
    (ul, vl)
}

/// The cavity's three extrema from its centrelines.
pub fn cavity_extrema(cfg: &Flow2d, x: &[f64]) -> CavityExtrema {
    let (ul, vl) = centrelines(cfg, x);
    CavityExtrema { u_min: ul.extremum(-1.0), v_max: vl.extremum(1.0), v_min: vl.extremum(-1.0) }
}
