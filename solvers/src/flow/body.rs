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
    /// A simple polygon through its vertices (either orientation; at least
    /// three, no two edges crossing).
    Polygon {
        /// Vertices `(x, y)` in order around the boundary.
        vertices: Vec<[f64; 2]>,
    },
}

/// Why a shape cannot be put into a flow.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum ShapeError {
    /// A parameter is NaN or infinite.
    NotFinite,
    /// The radius is not positive somewhere (at this angle, in radians).
    Radius {
        /// The angle where `r(θ) ≤ 0`.
        angle: f64,
        /// `r` there.
        radius: f64,
    },
    /// A polygon with fewer than three vertices.
    TooFewVertices(usize),
    /// Two edges of a polygon cross (edges `i → i+1` and `j → j+1`).
    SelfIntersecting {
        /// First edge.
        first: usize,
        /// Second edge.
        second: usize,
    },
    /// The body reaches within one cell of the domain's sides (or beyond).
    LeavesDomain {
        /// The point of the body nearest the offending side.
        point: [f64; 2],
    },
    /// A parameter vector of the wrong length for the shape.
    Parameters {
        /// Expected length.
        expected: usize,
        /// Given length.
        given: usize,
    },
    /// Fourier coefficients too large for the area asked of the body: no
    /// positive `r₀` gives it (`π r₀² = A − (π/2)·Σ(aₖ² + bₖ²)`).
    NoRadiusForArea {
        /// The area asked.
        area: f64,
    },
}

impl std::fmt::Display for ShapeError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            ShapeError::NotFinite => f.write_str("shape: a parameter is not finite"),
            ShapeError::Radius { angle, radius } => write!(f, "shape: the radius is {radius:.4} (not positive) at {angle:.3} rad"),
            ShapeError::TooFewVertices(n) => write!(f, "shape: a polygon needs at least 3 vertices, got {n}"),
            ShapeError::SelfIntersecting { first, second } => write!(f, "shape: the polygon crosses itself (edges {first} and {second})"),
            ShapeError::LeavesDomain { point } => {
                write!(f, "shape: reaches ({:.3}, {:.3}), within a cell of the sides", point[0], point[1])
            }
            ShapeError::Parameters { expected, given } => write!(f, "shape: {given} parameters given, the shape has {expected}"),
            ShapeError::NoRadiusForArea { area } => write!(f, "shape: no r0 > 0 gives the area {area:.4e}"),
        }
    }
}

impl std::error::Error for ShapeError {}

/// Whether the closed segments `a–b` and `c–d` cross (proper crossing or
/// touching).
fn segments_cross(a: [f64; 2], b: [f64; 2], c: [f64; 2], d: [f64; 2]) -> bool {
    let orient = |p: [f64; 2], q: [f64; 2], r: [f64; 2]| (q[0] - p[0]) * (r[1] - p[1]) - (q[1] - p[1]) * (r[0] - p[0]);
    let (d1, d2, d3, d4) = (orient(c, d, a), orient(c, d, b), orient(a, b, c), orient(a, b, d));
    (d1 > 0.0) != (d2 > 0.0) && (d3 > 0.0) != (d4 > 0.0)
        || [d1, d2, d3, d4].contains(&0.0) && {
            let within = |p: [f64; 2], q: [f64; 2], r: [f64; 2]| {
                orient(p, q, r) == 0.0 && r[0] >= p[0].min(q[0]) && r[0] <= p[0].max(q[0]) && r[1] >= p[1].min(q[1]) && r[1] <= p[1].max(q[1])
            };
            within(c, d, a) || within(c, d, b) || within(a, b, c) || within(a, b, d)
        }
}

/// The point of the segment `a–b` nearest `p`, as the fraction along it.
fn nearest_on_segment(a: [f64; 2], b: [f64; 2], p: [f64; 2]) -> f64 {
    let (ex, ey) = (b[0] - a[0], b[1] - a[1]);
    let len2 = ex * ex + ey * ey;
    if len2 == 0.0 { 0.0 } else { (((p[0] - a[0]) * ex + (p[1] - a[1]) * ey) / len2).clamp(0.0, 1.0) }
}

impl Shape {
    /// The level set: negative inside, zero on the boundary, positive
    /// outside (the distance for a circle; `|x − c| − r(θ)` for a Fourier
    /// body).
    pub fn level(&self, x: f64, y: f64) -> f64 {
        match self {
            Shape::Circle { center, radius } => (x - center[0]).hypot(y - center[1]) - radius,
            Shape::Fourier { center, .. } => {
                let (dx, dy) = (x - center[0], y - center[1]);
                dx.hypot(dy) - self.radius_at(dy.atan2(dx)).expect("a Fourier body has a radius")
            }
            Shape::Polygon { vertices } => polygon_level(vertices, [x, y], None),
        }
    }

    /// The radius `r(θ)` of a circle or Fourier body about its centre
    /// (`None` for a polygon).
    pub fn radius_at(&self, theta: f64) -> Option<f64> {
        match self {
            Shape::Circle { radius, .. } => Some(*radius),
            Shape::Fourier { r0, cos, sin, .. } => {
                let mut r = *r0;
                for (k, a) in cos.iter().enumerate() {
                    r += a * ((k + 1) as f64 * theta).cos();
                }
                for (k, b) in sin.iter().enumerate() {
                    r += b * ((k + 1) as f64 * theta).sin();
                }
                Some(r)
            }
            Shape::Polygon { .. } => None,
        }
    }

    /// Points along the boundary: `n` equally spaced angles for a circle or
    /// Fourier body (at the radius [`Shape::radius_at`], even where it is not
    /// positive), the vertices of a polygon.
    pub fn outline(&self, n: usize) -> Vec<[f64; 2]> {
        match self {
            Shape::Circle { center, .. } | Shape::Fourier { center, .. } => (0..n)
                .map(|k| {
                    let theta = 2.0 * std::f64::consts::PI * k as f64 / n as f64;
                    let r = self.radius_at(theta).expect("a round body has a radius");
                    [center[0] + r * theta.cos(), center[1] + r * theta.sin()]
                })
                .collect(),
            Shape::Polygon { vertices } => vertices.clone(),
        }
    }

    /// The shape's parameters as one vector: circle `[cx, cy, r]`;
    /// Fourier `[cx, cy, r0, a₁…, b₁…]`; polygon `[x₀, y₀, x₁, y₁, …]`.
    pub fn params(&self) -> Vec<f64> {
        match self {
            Shape::Circle { center, radius } => vec![center[0], center[1], *radius],
            Shape::Fourier { center, r0, cos, sin } => [center[0], center[1], *r0].iter().chain(cos).chain(sin).copied().collect(),
            Shape::Polygon { vertices } => vertices.iter().flatten().copied().collect(),
        }
    }

    /// The number of parameters ([`Shape::params`]).
    pub fn n_params(&self) -> usize {
        match self {
            Shape::Circle { .. } => 3,
            Shape::Fourier { cos, sin, .. } => 3 + cos.len() + sin.len(),
            Shape::Polygon { vertices } => 2 * vertices.len(),
        }
    }

    /// The same kind of shape with parameters `p` (laid out as
    /// [`Shape::params`]).
    pub fn with_params(&self, p: &[f64]) -> Result<Shape, ShapeError> {
        if p.len() != self.n_params() {
            return Err(ShapeError::Parameters { expected: self.n_params(), given: p.len() });
        }
        Ok(match self {
            Shape::Circle { .. } => Shape::Circle { center: [p[0], p[1]], radius: p[2] },
            Shape::Fourier { cos, .. } => {
                let n = cos.len();
                Shape::Fourier { center: [p[0], p[1]], r0: p[2], cos: p[3..3 + n].to_vec(), sin: p[3 + n..].to_vec() }
            }
            Shape::Polygon { .. } => Shape::Polygon { vertices: p.chunks(2).map(|c| [c[0], c[1]]).collect() },
        })
    }

    /// The level set at `(x, y)`, its gradient in `(x, y)` (returned) and
    /// its derivatives with respect to the parameters (written to `dp`,
    /// [`Shape::n_params`] long). Piecewise smooth for a polygon (the
    /// nearest edge).
    pub fn level_grad(&self, x: f64, y: f64, dp: &mut [f64]) -> (f64, [f64; 2]) {
        assert_eq!(dp.len(), self.n_params(), "level_grad: parameter derivative length");
        match self {
            Shape::Circle { center, radius } => {
                let (dx, dy) = (x - center[0], y - center[1]);
                let rho = dx.hypot(dy).max(1e-300);
                let g = [dx / rho, dy / rho];
                dp.copy_from_slice(&[-g[0], -g[1], -1.0]);
                (rho - radius, g)
            }
            Shape::Fourier { center, r0, cos, sin } => {
                let (dx, dy) = (x - center[0], y - center[1]);
                let rho = dx.hypot(dy).max(1e-300);
                let theta = dy.atan2(dx);
                let (mut r, mut dr) = (*r0, 0.0);
                let n = cos.len();
                dp[2] = -1.0;
                for (k, a) in cos.iter().enumerate() {
                    let kf = (k + 1) as f64;
                    let (s, c) = (kf * theta).sin_cos();
                    r += a * c;
                    dr -= kf * a * s;
                    dp[3 + k] = -c;
                }
                for (k, b) in sin.iter().enumerate() {
                    let kf = (k + 1) as f64;
                    let (s, c) = (kf * theta).sin_cos();
                    r += b * s;
                    dr += kf * b * c;
                    dp[3 + n + k] = -s;
                }
                // ∂θ/∂(x, y) = (−dy, dx)/ρ².
                let g = [dx / rho + dr * dy / (rho * rho), dy / rho - dr * dx / (rho * rho)];
                dp[0] = -g[0];
                dp[1] = -g[1];
                (rho - r, g)
            }
            Shape::Polygon { vertices } => {
                let mut g = [0.0; 2];
                let phi = polygon_level(vertices, [x, y], Some((dp, &mut g)));
                (phi, g)
            }
        }
    }

    /// Checks that the shape is a proper body inside the flow's domain, at
    /// least one cell `h` from every side: [`Shape::check`], and the extent.
    pub fn validate(&self, cfg: &Flow2d) -> Result<(), ShapeError> {
        let (w, hgt, h) = (cfg.nx as f64 * cfg.h, cfg.ny as f64 * cfg.h, cfg.h);
        for p in self.boundary_points()? {
            if p[0] < h || p[0] > w - h || p[1] < h || p[1] > hgt - h {
                return Err(ShapeError::LeavesDomain { point: p });
            }
        }
        Ok(())
    }

    /// Checks that the shape is a proper body wherever it lies: finite
    /// parameters, a positive radius at every angle, a simple polygon.
    pub fn check(&self) -> Result<(), ShapeError> {
        self.boundary_points().map(|_| ())
    }

    /// The bounding box `[x_min, x_max, y_min, y_max]` of a checked shape
    /// (a round body's sampled at 720 angles).
    pub fn bounds(&self) -> Result<[f64; 4], ShapeError> {
        let points = self.boundary_points()?;
        Ok(points.iter().fold([f64::INFINITY, f64::NEG_INFINITY, f64::INFINITY, f64::NEG_INFINITY], |b, p| {
            [b[0].min(p[0]), b[1].max(p[0]), b[2].min(p[1]), b[3].max(p[1])]
        }))
    }

    /// Boundary points of a proper body (720 angles of a round body, a
    /// polygon's vertices), or why it is not one.
    fn boundary_points(&self) -> Result<Vec<[f64; 2]>, ShapeError> {
        if self.params().iter().any(|v| !v.is_finite()) {
            return Err(ShapeError::NotFinite);
        }
        match self {
            Shape::Circle { center, .. } | Shape::Fourier { center, .. } => {
                let m = 720;
                (0..m)
                    .map(|k| {
                        let theta = 2.0 * std::f64::consts::PI * k as f64 / m as f64;
                        match self.radius_at(theta).expect("a round body has a radius") {
                            r if r > 0.0 => Ok([center[0] + r * theta.cos(), center[1] + r * theta.sin()]),
                            r => Err(ShapeError::Radius { angle: theta, radius: r }),
                        }
                    })
                    .collect()
            }
            Shape::Polygon { vertices } => {
                let n = vertices.len();
                if n < 3 {
                    return Err(ShapeError::TooFewVertices(n));
                }
                for i in 0..n {
                    for j in i + 1..n {
                        // Adjacent edges share a vertex: only non-adjacent pairs.
                        if j == i + 1 || (i == 0 && j == n - 1) {
                            continue;
                        }
                        if segments_cross(vertices[i], vertices[(i + 1) % n], vertices[j], vertices[(j + 1) % n]) {
                            return Err(ShapeError::SelfIntersecting { first: i, second: j });
                        }
                    }
                }
                if Shape::polygon_area(vertices).abs() == 0.0 {
                    return Err(ShapeError::SelfIntersecting { first: 0, second: 1 });
                }
                Ok(vertices.clone())
            }
        }
    }

    /// The signed area of a polygon (positive counter-clockwise).
    fn polygon_area(vertices: &[[f64; 2]]) -> f64 {
        let n = vertices.len();
        0.5 * (0..n).map(|i| vertices[i][0] * vertices[(i + 1) % n][1] - vertices[(i + 1) % n][0] * vertices[i][1]).sum::<f64>()
    }

    /// The area's derivatives with respect to the parameters.
    pub fn area_grad(&self) -> Vec<f64> {
        use std::f64::consts::PI;
        match self {
            Shape::Circle { radius, .. } => vec![0.0, 0.0, 2.0 * PI * radius],
            Shape::Fourier { r0, cos, sin, .. } => [0.0, 0.0, 2.0 * PI * r0].into_iter().chain(cos.iter().chain(sin).map(|c| PI * c)).collect(),
            Shape::Polygon { vertices } => {
                let n = vertices.len();
                let sign = Shape::polygon_area(vertices).signum();
                let mut g = vec![0.0; 2 * n];
                for i in 0..n {
                    let (prev, next) = (vertices[(i + n - 1) % n], vertices[(i + 1) % n]);
                    g[2 * i] = sign * 0.5 * (next[1] - prev[1]);
                    g[2 * i + 1] = sign * 0.5 * (prev[0] - next[0]);
                }
                g
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
            Shape::Polygon { vertices } => Shape::polygon_area(vertices).abs(),
        }
    }
}

/// The signed distance from `p` to a polygon (negative inside), and with
/// `grads` its derivatives with respect to the vertices (flat `[x₀, y₀,
/// …]`) and to `p`. Where the nearest point lies inside an edge, the signed
/// distance to that edge's line `n·(p − a)` (`n` the outward normal), which
/// stays smooth across the boundary; where it is a vertex, the distance to
/// it with the sign of the even–odd rule.
fn polygon_level(vertices: &[[f64; 2]], p: [f64; 2], grads: Option<(&mut [f64], &mut [f64; 2])>) -> f64 {
    let n = vertices.len();
    let (mut best, mut edge, mut at) = (f64::INFINITY, 0, 0.0);
    let mut inside = false;
    for i in 0..n {
        let (a, b) = (vertices[i], vertices[(i + 1) % n]);
        let t = nearest_on_segment(a, b, p);
        let q = [a[0] + t * (b[0] - a[0]), a[1] + t * (b[1] - a[1])];
        let d = (p[0] - q[0]).hypot(p[1] - q[1]);
        if d < best {
            (best, edge, at) = (d, i, t);
        }
        if (a[1] > p[1]) != (b[1] > p[1]) && p[0] < a[0] + (p[1] - a[1]) / (b[1] - a[1]) * (b[0] - a[0]) {
            inside = !inside;
        }
    }
    let (ia, ib) = (edge, (edge + 1) % n);
    let (a, b) = (vertices[ia], vertices[ib]);
    if at > 0.0 && at < 1.0 {
        // φ = σ·(e_y·w_x − e_x·w_y)/L with e = b − a, w = p − a, L = |e|,
        // σ = +1 for a counter-clockwise polygon.
        let sigma = Shape::polygon_area(vertices).signum();
        let (e, w) = ([b[0] - a[0], b[1] - a[1]], [p[0] - a[0], p[1] - a[1]]);
        let l = e[0].hypot(e[1]);
        let cross = e[1] * w[0] - e[0] * w[1];
        let phi = sigma * cross / l;
        if let Some((dp, g)) = grads {
            let normal = [sigma * e[1] / l, -sigma * e[0] / l];
            *g = normal;
            // ∂φ/∂e (w fixed), then ∂φ/∂b = ∂φ/∂e and ∂φ/∂a = −∂φ/∂e − n.
            let de = [sigma * (-w[1] / l - cross * e[0] / (l * l * l)), sigma * (w[0] / l - cross * e[1] / (l * l * l))];
            dp.fill(0.0);
            for c in 0..2 {
                dp[2 * ib + c] += de[c];
                dp[2 * ia + c] -= de[c] + normal[c];
            }
        }
        return phi;
    }
    let sign = if inside { -1.0 } else { 1.0 };
    if let Some((dp, g)) = grads {
        let v = if at >= 1.0 { ib } else { ia };
        let q = vertices[v];
        let d = best.max(1e-300);
        let unit = [sign * (p[0] - q[0]) / d, sign * (p[1] - q[1]) / d];
        *g = unit;
        dp.fill(0.0);
        dp[2 * v] = -unit[0];
        dp[2 * v + 1] = -unit[1];
    }
    sign * best
}

/// Where along the segment from `a` to `b` the level set changes sign, as
/// a fraction of its length from `a`: the root of `φ` on the segment by the
/// Illinois variant of regula falsi (superlinear, always bracketed), to
/// machine precision, so that the derivatives of the cut by implicit
/// differentiation hold to round-off.
fn crossing(shape: &Shape, a: [f64; 2], b: [f64; 2], fa: f64, fb: f64) -> f64 {
    let at = |t: f64| shape.level(a[0] + t * (b[0] - a[0]), a[1] + t * (b[1] - a[1]));
    let (mut lo, mut hi, mut flo, mut fhi) = (0.0, 1.0, fa, fb);
    let mut last_side = 0i8;
    let mut t = fa / (fa - fb);
    for _ in 0..100 {
        if !(t > lo && t < hi) {
            t = 0.5 * (lo + hi);
        }
        let ft = at(t);
        if ft == 0.0 {
            return t;
        }
        if (ft < 0.0) == (flo < 0.0) {
            lo = t;
            flo = ft;
            if last_side == -1 {
                fhi *= 0.5;
            }
            last_side = -1;
        } else {
            hi = t;
            fhi = ft;
            if last_side == 1 {
                flo *= 0.5;
            }
            last_side = 1;
        }
        if hi - lo <= 4.0 * f64::EPSILON {
            break;
        }
        t = lo + flo / (flo - fhi) * (hi - lo);
    }
    if flo.abs() < fhi.abs() { lo } else { hi }
}

/// The crossing nearest to `a` on the segment from `a` (outside the body)
/// to `b` (inside), as a fraction of the segment: the first of 16 equal
/// pieces whose end lies inside, refined by [`crossing`]. Where the segment
/// crosses the boundary once (a body resolved by the grid) this is
/// `crossing` on the whole segment; where a feature of the body's own
/// scale below a cell makes it cross three times, it is the wall nearest
/// the face, and it does not jump from one root to another as the body
/// moves (regula falsi on the whole segment may converge to any of them).
fn first_crossing(shape: &Shape, a: [f64; 2], b: [f64; 2]) -> f64 {
    const PIECES: usize = 16;
    let along = |t: f64| [a[0] + t * (b[0] - a[0]), a[1] + t * (b[1] - a[1])];
    let (mut t0, mut f0) = (0.0, shape.level(a[0], a[1]));
    for k in 1..=PIECES {
        let t1 = k as f64 / PIECES as f64;
        let p1 = along(t1);
        let f1 = shape.level(p1[0], p1[1]);
        if f1 < 0.0 {
            return t0 + (t1 - t0) * crossing(shape, along(t0), p1, f0, f1);
        }
        (t0, f0) = (t1, f1);
    }
    // `b` is inside: its level is negative, so the loop has returned
    // (reached only through rounding at `b` itself).
    1.0
}

/// The open (fluid) fraction of the segment from `a` to `b`, and the
/// crossings it is made of: the fraction is a constant plus `Σ sign·t` over
/// the returned `(sign, t)` pairs (`t` the crossing's position along the
/// whole segment), so its derivative is `Σ sign·∂t`. Up to two crossings:
/// when both ends lie on the same side, the level set's extreme value along
/// the segment (golden-section search, only when an end is within a
/// segment length of the boundary) says whether the segment dips through
/// the body (or out of it), and the two crossings around that point are
/// found. So the fraction changes continuously as a body moves, even where
/// it grazes a face.
fn open_fraction(shape: &Shape, a: [f64; 2], b: [f64; 2]) -> (f64, Vec<(f64, f64)>) {
    let (fa, fb) = (shape.level(a[0], a[1]), shape.level(b[0], b[1]));
    let along = |t: f64| [a[0] + t * (b[0] - a[0]), a[1] + t * (b[1] - a[1])];
    match (fa >= 0.0, fb >= 0.0) {
        (true, false) => {
            let t = crossing(shape, a, b, fa, fb);
            (t, vec![(1.0, t)])
        }
        (false, true) => {
            let t = crossing(shape, a, b, fa, fb);
            (1.0 - t, vec![(-1.0, t)])
        }
        (outside, _) => {
            let whole = if outside { 1.0 } else { 0.0 };
            let length = (b[0] - a[0]).hypot(b[1] - a[1]);
            if fa.abs().min(fb.abs()) > length {
                return (whole, Vec::new());
            }
            // The extreme value on the far side: the minimum outside, the maximum inside.
            let sign = if outside { 1.0 } else { -1.0 };
            let g = |t: f64| {
                let p = along(t);
                sign * shape.level(p[0], p[1])
            };
            let t = golden_minimum(g);
            if g(t) >= 0.0 {
                return (whole, Vec::new());
            }
            let m = along(t);
            let fm = shape.level(m[0], m[1]);
            // Crossings on [a, m] and [m, b], as fractions of the whole segment.
            let t1 = t * crossing(shape, a, m, fa, fm);
            let t2 = t + (1.0 - t) * crossing(shape, m, b, fm, fb);
            let inner = t2 - t1;
            if outside { (1.0 - inner, vec![(-1.0, t2), (1.0, t1)]) } else { (inner, vec![(1.0, t2), (-1.0, t1)]) }
        }
    }
}

/// Adds `scale · ∂t/∂params` to `out` for the crossing at fraction `t` of
/// the segment `a → b` (`φ(a + t·(b − a)) = 0`, so `∂t = −∂φ/∂params /
/// (∇φ·(b − a))`); `work` is a buffer of the shape's parameter count.
fn add_crossing_derivative(shape: &Shape, a: [f64; 2], b: [f64; 2], t: f64, scale: f64, work: &mut [f64], out: &mut [f64]) {
    let (e0, e1) = (b[0] - a[0], b[1] - a[1]);
    let (_, g) = shape.level_grad(a[0] + t * e0, a[1] + t * e1, work);
    let slope = g[0] * e0 + g[1] * e1;
    if slope == 0.0 {
        return;
    }
    for (o, &d) in out.iter_mut().zip(work.iter()) {
        *o -= scale * d / slope;
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

/// How a [`Cut`] changes with the shapes' parameters (all shapes'
/// [`Shape::params`] concatenated): the derivatives of every aperture and
/// no-slip coupling that a boundary crossing determines (the others are
/// locally constant). The fluid masks are piecewise constant; where a face
/// centre crosses a boundary its coupling and its weight in the projection
/// go continuously to their limits, so the flow is continuous there too.
#[derive(Clone, Debug, PartialEq)]
pub struct CutSensitivity {
    /// Number of parameters.
    pub n_params: usize,
    /// `(face, ∂aperture/∂params)`, the face packed `[u-faces, v-faces]`.
    pub aperture: Vec<(usize, Vec<f64>)>,
    /// `(velocity, ∂wall/∂params)` for [`Cut::wall`].
    pub wall: Vec<(usize, Vec<f64>)>,
}

impl Cut {
    /// The cut of `shapes` on `cfg`'s grid.
    pub fn new(cfg: &Flow2d, shapes: &[Shape]) -> Self {
        Self::build(cfg, shapes, false).0
    }

    /// The cut and its derivatives with respect to the shapes' parameters
    /// (implicit differentiation of every boundary crossing).
    pub fn with_sensitivity(cfg: &Flow2d, shapes: &[Shape]) -> (Self, CutSensitivity) {
        let (cut, sens) = Self::build(cfg, shapes, true);
        (cut, sens.expect("sensitivities asked for"))
    }

    fn build(cfg: &Flow2d, shapes: &[Shape], sensitivity: bool) -> (Self, Option<CutSensitivity>) {
        let (nx, ny, h) = (cfg.nx, cfg.ny, cfg.h);
        let offsets: Vec<usize> = shapes.iter().scan(0, |o, s| Some(std::mem::replace(o, *o + s.n_params()))).collect();
        let n_params: usize = shapes.iter().map(Shape::n_params).sum();
        let level = |x: f64, y: f64| shapes.iter().map(|s| s.level(x, y)).fold(f64::INFINITY, f64::min);
        // The body a point is nearest to the inside of (the one with the smallest level).
        let nearest = |x: f64, y: f64| (0..shapes.len()).min_by(|&a, &b| shapes[a].level(x, y).total_cmp(&shapes[b].level(x, y))).expect("at least one shape");
        let mut d_aperture = Vec::new();
        // The aperture of a segment, and its derivative when it has crossings.
        let mut segment = |face: usize, a: [f64; 2], b: [f64; 2]| {
            let k = nearest(0.5 * (a[0] + b[0]), 0.5 * (a[1] + b[1]));
            let (fraction, crossings) = open_fraction(&shapes[k], a, b);
            if sensitivity && !crossings.is_empty() {
                let mut row = vec![0.0; n_params];
                let mut work = vec![0.0; shapes[k].n_params()];
                let part = &mut row[offsets[k]..offsets[k] + shapes[k].n_params()];
                for (sign, t) in crossings {
                    add_crossing_derivative(&shapes[k], a, b, t, sign, &mut work, part);
                }
                d_aperture.push((face, row));
            }
            fraction
        };
        let n_u = ny * (nx + 1);
        let mut aperture_u = vec![1.0; n_u];
        for j in 0..ny {
            for i in 0..=nx {
                let x = i as f64 * h;
                let f = j * (nx + 1) + i;
                aperture_u[f] = segment(f, [x, j as f64 * h], [x, (j + 1) as f64 * h]);
            }
        }
        let mut aperture_v = vec![1.0; (ny + 1) * nx];
        for j in 0..=ny {
            for i in 0..nx {
                let y = j as f64 * h;
                let f = j * nx + i;
                aperture_v[f] = segment(n_u + f, [i as f64 * h, y], [(i + 1) as f64 * h, y]);
            }
        }
        // Face centres: u at (i·h, (j+½)·h), v at ((i+½)·h, j·h).
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
        let mut d_wall = Vec::new();
        for (k, w) in wall.iter_mut().enumerate() {
            if fluid[k] == 0.0 {
                continue;
            }
            let c = centre(k);
            let mut row = sensitivity.then(|| vec![0.0; n_params]);
            for d in [[h, 0.0], [-h, 0.0], [0.0, h], [0.0, -h]] {
                let b = [c[0] + d[0], c[1] + d[1]];
                if level(b[0], b[1]) < 0.0 {
                    let m = nearest(b[0], b[1]);
                    let s = &shapes[m];
                    let theta = first_crossing(s, c, b);
                    *w += 1.0 / theta.max(1e-12) - 1.0;
                    if let Some(row) = row.as_mut() {
                        // ∂(1/θ) = −∂θ/θ².
                        let mut work = vec![0.0; s.n_params()];
                        let part = &mut row[offsets[m]..offsets[m] + s.n_params()];
                        add_crossing_derivative(s, c, b, theta, -1.0 / (theta.max(1e-12) * theta.max(1e-12)), &mut work, part);
                    }
                }
            }
            if let Some(row) = row.filter(|r| r.iter().any(|&v| v != 0.0)) {
                d_wall.push((k, row));
            }
        }
        let cell_fluid = (0..nx * ny).map(|c| if level(((c % nx) as f64 + 0.5) * h, ((c / nx) as f64 + 0.5) * h) >= 0.0 { 1.0 } else { 0.0 }).collect();
        let sens = sensitivity.then_some(CutSensitivity { n_params, aperture: d_aperture, wall: d_wall });
        (Cut { aperture_u, aperture_v, fluid, cell_fluid, wall }, sens)
    }

    /// How far the parameters of `shape` can move along `ds` before the
    /// cut stops being smooth (a grid node or a face centre changes side of
    /// the boundary): half the smallest first-order estimate `|φ| / |∂φ/∂s·ds|`
    /// over the nodes and face centres within three cells of the boundary.
    pub fn smooth_radius(cfg: &Flow2d, shape: &Shape, ds: &[f64]) -> f64 {
        let (nx, ny, h) = (cfg.nx, cfg.ny, cfg.h);
        let mut work = vec![0.0; shape.n_params()];
        let mut radius = f64::INFINITY;
        let mut visit = |x: f64, y: f64| {
            if shape.level(x, y).abs() > 3.0 * h {
                return;
            }
            let (phi, _) = shape.level_grad(x, y, &mut work);
            let rate: f64 = work.iter().zip(ds).map(|(a, b)| a * b).sum();
            if rate != 0.0 {
                radius = radius.min(0.5 * phi.abs() / rate.abs());
            }
        };
        for j in 0..=2 * ny {
            for i in 0..=2 * nx {
                // Nodes (even, even), u-face centres (even, odd), v-face centres (odd, even).
                if i % 2 == 1 && j % 2 == 1 {
                    continue;
                }
                visit(0.5 * i as f64 * h, 0.5 * j as f64 * h);
            }
        }
        radius
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
/// cells only: the value at the point of the least-squares quadratic
/// `a + b·dx + c·dy + d·dx² + e·dx·dy + f·dy²` through the fluid cells
/// whose centres lie within `3.5·h` of it (third order for a smooth field;
/// usable on a body's boundary, where bilinear interpolation would mix in
/// cells inside the body, and exact at an extremum such as a stagnation
/// point, where a plane's fit is biased by the curvature). `None` when the
/// near fluid cells do not determine the quadratic.
pub fn fluid_value_at(cfg: &Flow2d, cut: Option<&Cut>, field: &[f64], x: f64, y: f64) -> Option<f64> {
    const TERMS: usize = 6;
    const RADIUS: f64 = 3.5;
    let (nx, ny, h) = (cfg.nx, cfg.ny, cfg.h);
    let reach = RADIUS * h;
    let (i0, i1) = (((x - reach) / h - 0.5).floor().max(0.0) as usize, (((x + reach) / h - 0.5).ceil().max(0.0) as usize).min(nx - 1));
    let (j0, j1) = (((y - reach) / h - 0.5).floor().max(0.0) as usize, (((y + reach) / h - 0.5).ceil().max(0.0) as usize).min(ny - 1));
    // Normal equations in units of h.
    let mut m = [[0.0f64; TERMS + 1]; TERMS];
    let mut count = 0;
    for j in j0..=j1 {
        for i in i0..=i1 {
            let c = j * nx + i;
            if cut.is_some_and(|k| k.cell_fluid[c] == 0.0) {
                continue;
            }
            let (dx, dy) = ((((i as f64) + 0.5) * h - x) / h, (((j as f64) + 0.5) * h - y) / h);
            if dx.hypot(dy) > RADIUS {
                continue;
            }
            let basis = [1.0, dx, dy, dx * dx, dx * dy, dy * dy];
            for a in 0..TERMS {
                for b in 0..TERMS {
                    m[a][b] += basis[a] * basis[b];
                }
                m[a][TERMS] += basis[a] * field[c];
            }
            count += 1;
        }
    }
    if count < TERMS {
        return None;
    }
    // Gaussian elimination with partial pivoting; the intercept is the value.
    let scale = m[0][0];
    for k in 0..TERMS {
        let pivot = (k..TERMS).max_by(|&a, &b| m[a][k].abs().total_cmp(&m[b][k].abs()))?;
        if m[pivot][k].abs() < 1e-10 * scale {
            return None;
        }
        m.swap(k, pivot);
        for r in k + 1..TERMS {
            let f = m[r][k] / m[k][k];
            for c in k..=TERMS {
                m[r][c] -= f * m[k][c];
            }
        }
    }
    let mut sol = [0.0f64; TERMS];
    for k in (0..TERMS).rev() {
        let mut v = m[k][TERMS];
        for c in k + 1..TERMS {
            v -= m[k][c] * sol[c];
        }
        sol[k] = v / m[k][k];
    }
    Some(sol[0])
}

#[cfg(test)]
mod tests {
    use super::ShapeError;

    /// Every message fits an operator's error (`OpMessage`, 63 bytes), so
    /// none is cut when a shape operator reports it.
    #[test]
    fn shape_messages_fit_63_bytes() {
        let all = [
            ShapeError::NotFinite,
            ShapeError::Radius { angle: std::f64::consts::TAU, radius: -123.456 },
            ShapeError::TooFewVertices(2),
            ShapeError::SelfIntersecting { first: 99_999, second: 100_000 },
            ShapeError::LeavesDomain { point: [-123.456, -234.567] },
            ShapeError::Parameters { expected: 99_999, given: 100_000 },
            ShapeError::NoRadiusForArea { area: -1.0e-300 },
        ];
        for e in all {
            assert!(e.to_string().len() <= 63, "{e} ({} bytes)", e.to_string().len());
        }
    }
}
