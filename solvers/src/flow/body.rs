//! Bodies in a flow: a shape given by parameters, as a level set `φ`
//! (negative inside), and what it cuts out of the MAC grid: the open
//! fraction (aperture) of every face for the projection, which faces are
//! fluid (their centre outside the body), and for each fluid face the
//! distance fraction to the body along each of its four stencil directions
//! for the no-slip condition. Every quantity depends continuously on the
//! shape's parameters.

use super::Flow2d;

/// A closed body.
#[derive(Clone, Debug, PartialEq)]
pub enum Shape {
    /// A disc.
    Circle {
        /// Centre `(x, y)`.
        center: [f64; 2],
        /// Radius.
        radius: f64,
    },
    /// A star-shaped body about `center` with radius
    /// `r(θ) = r0 + Σₖ cos[k−1]·cos kθ + sin[k−1]·sin kθ`, `k = 1, 2, …`.
    Fourier {
        /// Centre `(x, y)`.
        center: [f64; 2],
        /// Mean radius.
        r0: f64,
        /// Cosine coefficients `a₁, a₂, …`.
        cos: Vec<f64>,
        /// Sine coefficients `b₁, b₂, …`.
        sin: Vec<f64>,
    },
}

impl Shape {
    /// The level set: negative inside, zero on the boundary, positive
    /// outside (the distance for a circle; `|x − c| − r(θ)` for a Fourier
    /// body).
    pub fn level(&self, x: f64, y: f64) -> f64 {
        match self {
            Shape::Circle { center, radius } => (x - center[0]).hypot(y - center[1]) - radius,
            Shape::Fourier { center, r0, cos, sin } => {
                let (dx, dy) = (x - center[0], y - center[1]);
                let theta = dy.atan2(dx);
                let mut r = *r0;
                for (k, a) in cos.iter().enumerate() {
                    r += a * ((k + 1) as f64 * theta).cos();
                }
                for (k, b) in sin.iter().enumerate() {
                    r += b * ((k + 1) as f64 * theta).sin();
                }
                dx.hypot(dy) - r
            }
        }
    }

    /// The exact area.
    pub fn area(&self) -> f64 {
        use std::f64::consts::PI;
        match self {
            Shape::Circle { radius, .. } => PI * radius * radius,
            // ½∫r² dθ over a period.
            Shape::Fourier { r0, cos, sin, .. } => PI * r0 * r0 + 0.5 * PI * cos.iter().chain(sin).map(|c| c * c).sum::<f64>(),
        }
    }
}

/// Where along the segment from `a` to `b` the level set changes sign, as
/// a fraction of its length from `a`: the root of `φ` on the segment (a
/// few secant steps from the linear interpolation of its end values,
/// safeguarded to stay in the bracket).
fn crossing(shape: &Shape, a: [f64; 2], b: [f64; 2], fa: f64, fb: f64) -> f64 {
    let at = |t: f64| shape.level(a[0] + t * (b[0] - a[0]), a[1] + t * (b[1] - a[1]));
    let (mut lo, mut hi, mut flo, mut fhi) = (0.0, 1.0, fa, fb);
    let mut t = fa / (fa - fb);
    for _ in 0..30 {
        let ft = at(t);
        if ft == 0.0 {
            return t;
        }
        if (ft < 0.0) == (flo < 0.0) {
            lo = t;
            flo = ft;
        } else {
            hi = t;
            fhi = ft;
        }
        if hi - lo < 1e-13 {
            break;
        }
        // Regula falsi on the bracket (Illinois would be faster; this is
        // computed once per shape).
        t = lo + flo / (flo - fhi) * (hi - lo);
        if !(t > lo && t < hi) {
            t = 0.5 * (lo + hi);
        }
    }
    t
}

/// The open (fluid) fraction of the segment from `a` to `b`. Up to two
/// crossings: when both ends lie on the same side, the level set's extreme
/// value along the segment (golden-section search, only when an end is
/// within a segment length of the boundary) says whether the segment dips
/// through the body (or out of it), and the two crossings around that point
/// are found. So the fraction changes continuously as a body moves, even
/// where it grazes a face.
fn open_fraction(shape: &Shape, a: [f64; 2], b: [f64; 2]) -> f64 {
    let (fa, fb) = (shape.level(a[0], a[1]), shape.level(b[0], b[1]));
    let along = |t: f64| [a[0] + t * (b[0] - a[0]), a[1] + t * (b[1] - a[1])];
    match (fa >= 0.0, fb >= 0.0) {
        (true, false) => crossing(shape, a, b, fa, fb),
        (false, true) => 1.0 - crossing(shape, a, b, fa, fb),
        (outside, _) => {
            let length = (b[0] - a[0]).hypot(b[1] - a[1]);
            if fa.abs().min(fb.abs()) > length {
                return if outside { 1.0 } else { 0.0 };
            }
            // The extreme value on the far side: the minimum outside, the maximum inside.
            let sign = if outside { 1.0 } else { -1.0 };
            let g = |t: f64| {
                let p = along(t);
                sign * shape.level(p[0], p[1])
            };
            let t = golden_minimum(g);
            if g(t) >= 0.0 {
                return if outside { 1.0 } else { 0.0 };
            }
            let m = along(t);
            let fm = shape.level(m[0], m[1]);
            // Crossings on [a, m] and [m, b], as fractions of the whole segment.
            let t1 = t * crossing(shape, a, m, fa, fm);
            let t2 = t + (1.0 - t) * crossing(shape, m, b, fm, fb);
            let inner = t2 - t1;
            if outside { 1.0 - inner } else { inner }
        }
    }
}

/// The minimiser of `g` on `[0, 1]` by golden-section search (to 1e-12).
fn golden_minimum(g: impl Fn(f64) -> f64) -> f64 {
    let r = 0.5 * (5f64.sqrt() - 1.0);
    let (mut lo, mut hi) = (0.0f64, 1.0f64);
    let (mut c, mut d) = (hi - r * (hi - lo), lo + r * (hi - lo));
    let (mut gc, mut gd) = (g(c), g(d));
    while hi - lo > 1e-12 {
        if gc < gd {
            hi = d;
            d = c;
            gd = gc;
            c = hi - r * (hi - lo);
            gc = g(c);
        } else {
            lo = c;
            c = d;
            gc = gd;
            d = lo + r * (hi - lo);
            gd = g(d);
        }
    }
    0.5 * (lo + hi)
}

/// What a set of bodies cuts out of a flow's grid.
#[derive(Clone, Debug, PartialEq)]
pub struct Cut {
    /// Open fraction of each x-face (`u` layout).
    pub aperture_u: Vec<f64>,
    /// Open fraction of each y-face (`v` layout).
    pub aperture_v: Vec<f64>,
    /// Per velocity (packed `[u, v]`): 1 where the face centre is in the
    /// fluid, 0 inside a body.
    pub fluid: Vec<f64>,
    /// Per cell: 1 where the cell centre is in the fluid, 0 inside a body.
    pub cell_fluid: Vec<f64>,
    /// Per velocity: `Σ (1/θ − 1)` over the stencil directions whose
    /// neighbour lies inside a body at the distance fraction `θ` (0 where
    /// no neighbour does): the extra no-slip coupling, in units of `1/h²`.
    pub wall: Vec<f64>,
}

impl Cut {
    /// The cut of `shapes` on `cfg`'s grid.
    pub fn new(cfg: &Flow2d, shapes: &[Shape]) -> Self {
        let (nx, ny, h) = (cfg.nx, cfg.ny, cfg.h);
        let level = |x: f64, y: f64| shapes.iter().map(|s| s.level(x, y)).fold(f64::INFINITY, f64::min);
        // The body a point is nearest to the inside of (the one with the smallest level).
        let nearest = |x: f64, y: f64| shapes.iter().min_by(|a, b| a.level(x, y).total_cmp(&b.level(x, y))).expect("at least one shape");
        let segment = |a: [f64; 2], b: [f64; 2]| {
            let s = nearest(0.5 * (a[0] + b[0]), 0.5 * (a[1] + b[1]));
            open_fraction(s, a, b)
        };
        let mut aperture_u = vec![1.0; ny * (nx + 1)];
        for j in 0..ny {
            for i in 0..=nx {
                let x = i as f64 * h;
                aperture_u[j * (nx + 1) + i] = segment([x, j as f64 * h], [x, (j + 1) as f64 * h]);
            }
        }
        let mut aperture_v = vec![1.0; (ny + 1) * nx];
        for j in 0..=ny {
            for i in 0..nx {
                let y = j as f64 * h;
                aperture_v[j * nx + i] = segment([i as f64 * h, y], [(i + 1) as f64 * h, y]);
            }
        }
        // Face centres: u at (i·h, (j+½)·h), v at ((i+½)·h, j·h).
        let n_u = ny * (nx + 1);
        let centre = |k: usize| -> [f64; 2] {
            if k < n_u {
                let (j, i) = (k / (nx + 1), k % (nx + 1));
                [i as f64 * h, (j as f64 + 0.5) * h]
            } else {
                let k = k - n_u;
                let (j, i) = (k / nx, k % nx);
                [(i as f64 + 0.5) * h, j as f64 * h]
            }
        };
        let n = n_u + (ny + 1) * nx;
        let fluid: Vec<f64> = (0..n).map(|k| if level(centre(k)[0], centre(k)[1]) >= 0.0 { 1.0 } else { 0.0 }).collect();
        let mut wall = vec![0.0; n];
        for (k, w) in wall.iter_mut().enumerate() {
            if fluid[k] == 0.0 {
                continue;
            }
            let c = centre(k);
            for d in [[h, 0.0], [-h, 0.0], [0.0, h], [0.0, -h]] {
                let b = [c[0] + d[0], c[1] + d[1]];
                if level(b[0], b[1]) < 0.0 {
                    let s = nearest(b[0], b[1]);
                    let theta = crossing(s, c, b, s.level(c[0], c[1]), s.level(b[0], b[1])).max(1e-12);
                    *w += 1.0 / theta - 1.0;
                }
            }
        }
        let cell_fluid = (0..nx * ny).map(|c| if level(((c % nx) as f64 + 0.5) * h, ((c / nx) as f64 + 0.5) * h) >= 0.0 { 1.0 } else { 0.0 }).collect();
        Cut { aperture_u, aperture_v, fluid, cell_fluid, wall }
    }

    /// The area the apertures enclose as solid: `h² · Σ` over cells of the
    /// solid fraction estimated as one minus the mean aperture of the
    /// cell's four faces (exact for a straight boundary through a cell in
    /// the limit; for checks).
    pub fn solid_area(&self, cfg: &Flow2d) -> f64 {
        let (nx, ny, h) = (cfg.nx, cfg.ny, cfg.h);
        let mut a = 0.0;
        for j in 0..ny {
            for i in 0..nx {
                let open =
                    self.aperture_u[j * (nx + 1) + i] + self.aperture_u[j * (nx + 1) + i + 1] + self.aperture_v[j * nx + i] + self.aperture_v[(j + 1) * nx + i];
                a += 1.0 - 0.25 * open;
            }
        }
        a * h * h
    }
}

/// A cell-centred field (the pressure) at the point `(x, y)`, from fluid
/// cells only: the value at the point of the least-squares plane through
/// the fluid cells whose centres lie within `2.5·h` of it (second order;
/// usable on a body's boundary, where bilinear interpolation would mix in
/// cells inside the body). `None` when fewer than three fluid cells, or
/// only collinear ones, are near.
pub fn fluid_value_at(cfg: &Flow2d, cut: Option<&Cut>, field: &[f64], x: f64, y: f64) -> Option<f64> {
    let (nx, ny, h) = (cfg.nx, cfg.ny, cfg.h);
    let reach = 2.5 * h;
    let (i0, i1) = (((x - reach) / h - 0.5).floor().max(0.0) as usize, (((x + reach) / h - 0.5).ceil().max(0.0) as usize).min(nx - 1));
    let (j0, j1) = (((y - reach) / h - 0.5).floor().max(0.0) as usize, (((y + reach) / h - 0.5).ceil().max(0.0) as usize).min(ny - 1));
    // Normal equations of the plane a + b·dx + c·dy, in units of h.
    let mut m = [[0.0f64; 3]; 3];
    let mut r = [0.0f64; 3];
    let mut count = 0;
    for j in j0..=j1 {
        for i in i0..=i1 {
            let c = j * nx + i;
            if cut.is_some_and(|k| k.cell_fluid[c] == 0.0) {
                continue;
            }
            let (dx, dy) = ((((i as f64) + 0.5) * h - x) / h, (((j as f64) + 0.5) * h - y) / h);
            if dx.hypot(dy) > 2.5 {
                continue;
            }
            let basis = [1.0, dx, dy];
            for a in 0..3 {
                for b in 0..3 {
                    m[a][b] += basis[a] * basis[b];
                }
                r[a] += basis[a] * field[c];
            }
            count += 1;
        }
    }
    if count < 3 {
        return None;
    }
    // Cramer's rule for the intercept.
    let det3 = |m: [[f64; 3]; 3]| {
        m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1]) - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
            + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0])
    };
    let d = det3(m);
    if d.abs() < 1e-9 * (count as f64).powi(3) {
        return None;
    }
    let mut mr = m;
    for (row, &rv) in mr.iter_mut().zip(&r) {
        row[0] = rv;
    }
    Some(det3(mr) / d)
}
