//! Boundary conditions of the 2D and 3D box, per side: closed walls,
//! periodic wrap, inflow with a prescribed velocity profile, and free
//! outflow. [`Boundary<D>`](Boundary) holds the sides of a box of `D` axes
//! (four in 2D, six in 3D); the rules below act on one axis at a time
//! ([`axis_face`], [`validate_axes`]) and are shared by both.
//!
//! What each kind means for the MAC grids of [`crate::smoke`] (2D and 3D):
//!
//! | kind | normal velocity on the side's faces | pressure | advection |
//! |---|---|---|---|
//! | closed (free slip) | 0 | no flux (Neumann) | samples clamped to the box |
//! | no-slip | 0, and the tangential velocity 0 at the wall (viscosity) | no flux (Neumann) | clamped |
//! | periodic | face `N` is a copy of face `0` (never read) | wraps | samples wrap |
//! | inflow | the profile, inward | no flux (Neumann: the face is given) | clamped |
//! | outflow | free (advected, then projected) | `p = 0` outside (Dirichlet) | clamped |
//!
//! A periodic side needs its opposite side periodic too; inflow needs an
//! outflow side somewhere (what flows in must leave), checked by
//! [`Boundary::validate`]. Without an outflow side the pressure matrix is
//! singular (constants) and the solve works in the space of zero mean; with
//! one it is definite.

use std::fmt;

/// Velocity profile of an inflow side, as the inward normal speed at the
/// position `t ∈ (0, 1)` along the side (from its lower-left end), or in
/// 3D at `(t₁, t₂)` across the side ([`Profile::across`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Profile {
    /// The same speed everywhere.
    Uniform(f64),
    /// `4·peak·t·(1 − t)`: zero at the corners, `peak` in the middle (a
    /// channel's Poiseuille profile).
    Parabolic(f64),
}

impl Profile {
    /// The inward speed at `t ∈ (0, 1)`.
    pub fn at(&self, t: f64) -> f64 {
        match *self {
            Profile::Uniform(s) => s,
            Profile::Parabolic(peak) => 4.0 * peak * t * (1.0 - t),
        }
    }

    /// The inward speed at `(t₁, t₂) ∈ (0, 1)²` on a side of a 3D box (the
    /// side's two axes in x, y, z order): the parabolic profile is the
    /// product `16·peak·t₁(1 − t₁)·t₂(1 − t₂)`, zero on the side's edges
    /// and `peak` in its middle (a square duct's profile to leading order).
    pub fn across(&self, t1: f64, t2: f64) -> f64 {
        match *self {
            Profile::Uniform(s) => s,
            Profile::Parabolic(peak) => 16.0 * peak * t1 * (1.0 - t1) * t2 * (1.0 - t2),
        }
    }
}

impl Profile {
    /// The inward speed at the face of a `D`-dimensional box whose position
    /// across the side is `t` (each axis's position in `(0, 1)`, the entry of
    /// the side's own axis `axis` ignored): [`Profile::at`] in 2D,
    /// [`Profile::across`] in 3D.
    #[inline(always)]
    pub fn on_side<const D: usize>(&self, axis: usize, t: [f64; D]) -> f64 {
        if D == 2 {
            self.at(t[1 - axis])
        } else {
            let (b, c) = match axis {
                0 => (1, 2),
                1 => (0, 2),
                _ => (0, 1),
            };
            self.across(t[b], t[c])
        }
    }
}

/// The condition on one side of the box.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Side {
    /// No flow through (free slip along it: the viscosity sees no
    /// gradient of the tangential velocity across it).
    Closed,
    /// No flow through and no slip along it: the tangential velocity is 0
    /// on the wall (the viscosity's ghost value beyond it is the negative
    /// of the value inside, [`crate::diffusion::Grid`]). Otherwise as
    /// [`Side::Closed`].
    NoSlip,
    /// Wraps to the opposite side.
    Periodic,
    /// Fluid enters with this inward normal speed profile.
    Inflow(Profile),
    /// Fluid leaves freely; the pressure outside is zero.
    Outflow,
}

impl Side {
    /// Whether fluid (and what it carries) passes through the side: inflow
    /// and outflow.
    #[inline(always)]
    pub fn lets_through(self) -> bool {
        matches!(self, Side::Inflow(_) | Side::Outflow)
    }

    /// Whether the side sets its faces' normal velocity (closed: 0, inflow:
    /// the profile), so that nothing computed there before survives.
    pub fn sets_faces(self) -> bool {
        matches!(self, Side::Closed | Side::NoSlip | Side::Inflow(_))
    }

    /// Whether the side is a wall (closed or no-slip): no flow through.
    #[inline(always)]
    pub fn is_wall(self) -> bool {
        matches!(self, Side::Closed | Side::NoSlip)
    }

    /// The side with its inhomogeneous part dropped (an inflow closed): the
    /// condition a tangent obeys.
    pub fn homogeneous(self) -> Side {
        if let Side::Inflow(_) = self { Side::Closed } else { self }
    }
}

/// The sides of a box of `D` axes (2 or 3): `sides[a] = [lower, upper]`
/// along axis `a`, that is `[left, right]` along x, `[bottom, top]` along y
/// (up) and `[back, front]` along z (towards the viewer).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Boundary<const D: usize = 2> {
    /// `[lower, upper]` side of each axis.
    pub sides: [[Side; 2]; D],
}

/// A boundary that cannot be simulated.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum BoundaryError {
    /// One side of an axis is periodic and the other is not.
    HalfPeriodic {
        /// `"x"`, `"y"` or `"z"`.
        axis: &'static str,
    },
    /// Fluid flows in but no side lets it out.
    InflowWithoutOutflow,
}

impl fmt::Display for BoundaryError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            BoundaryError::HalfPeriodic { axis } => write!(f, "boundary: the {axis} axis is periodic on one side only; make both sides periodic or neither"),
            BoundaryError::InflowWithoutOutflow => {
                f.write_str("boundary: an inflow side needs an outflow side for the fluid to leave (the pressure solve has no solution otherwise)")
            }
        }
    }
}

impl std::error::Error for BoundaryError {}

impl<const D: usize> Boundary<D> {
    /// Closed walls all round (P2, P4).
    pub const CLOSED: Self = Self::all(Side::Closed);

    /// Every side the same kind.
    pub const fn all(side: Side) -> Self {
        Self { sides: [[side; 2]; D] }
    }

    /// Both sides of each axis `a` of kind `sides[a]`.
    pub const fn axes(sides: [Side; D]) -> Self {
        let mut b = Self::all(Side::Closed);
        let mut a = 0;
        while a < D {
            b.sides[a] = [sides[a], sides[a]];
            a += 1;
        }
        b
    }

    /// The same box with the lower side of `axis` of kind `side`.
    pub const fn with_lower(mut self, axis: usize, side: Side) -> Self {
        self.sides[axis][0] = side;
        self
    }

    /// The same box with the upper side of `axis` of kind `side`.
    pub const fn with_upper(mut self, axis: usize, side: Side) -> Self {
        self.sides[axis][1] = side;
        self
    }

    /// The sides `[lower, upper]` of `axis` (0 x, 1 y, 2 z).
    pub fn axis(&self, axis: usize) -> [Side; 2] {
        self.sides[axis]
    }

    /// The lower side of `axis` (left, bottom, back).
    pub fn lower(&self, axis: usize) -> Side {
        self.sides[axis][0]
    }

    /// The upper side of `axis` (right, top, front).
    pub fn upper(&self, axis: usize) -> Side {
        self.sides[axis][1]
    }

    /// Whether `axis` wraps.
    pub fn periodic(&self, axis: usize) -> bool {
        self.sides[axis][0] == Side::Periodic
    }

    /// Which axes wrap.
    pub fn wraps(&self) -> [bool; D] {
        self.sides.map(|[lo, _]| lo == Side::Periodic)
    }

    /// Whether some side is an outflow (the pressure matrix is then definite).
    pub fn has_outflow(&self) -> bool {
        self.sides.iter().flatten().any(|&s| s == Side::Outflow)
    }

    /// Every side [`Side::homogeneous`].
    pub fn homogeneous(&self) -> Self {
        Self { sides: self.sides.map(|pair| pair.map(Side::homogeneous)) }
    }

    /// Checks that the sides can be simulated together ([`validate_axes`]).
    pub fn validate(&self) -> Result<(), BoundaryError> {
        validate_axes(&self.sides)
    }
}

impl<const D: usize> Default for Boundary<D> {
    fn default() -> Self {
        Self::CLOSED
    }
}

/// Checks that the sides of a box, `[lower, upper]` per axis (x, y, z),
/// can be simulated together: a periodic side's opposite side is periodic,
/// and fluid that flows in has an outflow side to leave by.
pub fn validate_axes(axes: &[[Side; 2]]) -> Result<(), BoundaryError> {
    for (a, [lo, hi]) in axes.iter().enumerate() {
        if (*lo == Side::Periodic) != (*hi == Side::Periodic) {
            return Err(BoundaryError::HalfPeriodic { axis: ["x", "y", "z"][a] });
        }
    }
    let sides = || axes.iter().flatten();
    if sides().any(|s| matches!(s, Side::Inflow(_))) && !sides().any(|s| *s == Side::Outflow) {
        return Err(BoundaryError::InflowWithoutOutflow);
    }
    Ok(())
}

/// Face `k` (of `0..=n`) of an axis of `n` cells whose sides are `lo` and
/// `hi`, along that axis alone: the rule [`for_each_face`] applies per axis. `None` for the
/// duplicate last face of a periodic axis (a copy of face `0`).
#[inline(always)]
pub fn axis_face(k: usize, n: usize, lo: Side, hi: Side) -> Option<AxisFace> {
    if k > 0 && k < n {
        Some(AxisFace { lower: Some(k - 1), upper: Some(k), projected: true, side: None, copy: None })
    } else if k == 0 {
        let wrap = lo == Side::Periodic;
        Some(AxisFace { lower: wrap.then_some(n - 1), upper: Some(0), projected: wrap || lo == Side::Outflow, side: Some(lo), copy: wrap.then_some(n) })
    } else if hi != Side::Periodic {
        Some(AxisFace { lower: Some(n - 1), upper: None, projected: hi == Side::Outflow, side: Some(hi), copy: None })
    } else {
        None
    }
}

/// One face along one axis ([`axis_face`]): positions along the axis.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct AxisFace {
    /// The cell below the face, `None` outside the box.
    pub lower: Option<usize>,
    /// The cell above it.
    pub upper: Option<usize>,
    /// Whether the projection changes the face's velocity.
    pub projected: bool,
    /// The side the face lies on; `None` inside the box.
    pub side: Option<Side>,
    /// On a periodic axis, face `0`'s duplicate (`n`).
    pub copy: Option<usize>,
}

/// A fluid region that an inflow side feeds and no outflow side drains
/// ([`sealed_region`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct SealedRegion<const D: usize = 2> {
    /// Its fluid cells.
    pub cells: usize,
    /// One of its cells touching the inflow side, `(i, j)` in 2D, `[i, j,
    /// k]` in 3D.
    pub at: [usize; D],
}

/// The first fluid region (cells joined through faces, across periodic
/// sides) of a box of `dims` cells with solid cells `solid` (x fastest)
/// that fluid enters through an inflow side and cannot leave, touching no
/// outflow side: obstacles have cut it off. No divergence-free velocity
/// exists there, so a pressure solve cannot converge; `None` when every
/// fed region drains.
pub fn sealed_region<const D: usize>(dims: [usize; D], b: &Boundary<D>, solid: &[bool]) -> Option<SealedRegion<D>> {
    sealed_in(dims, b.sides, solid)
}

/// [`sealed_region`] on the sides `[lower, upper]` of each axis.
fn sealed_in<const D: usize>(dims: [usize; D], sides: [[Side; 2]; D], solid: &[bool]) -> Option<SealedRegion<D>> {
    let n: usize = dims.iter().product();
    assert_eq!(solid.len(), n, "sealed_region: mask length");
    let strides: [usize; D] = std::array::from_fn(|a| dims[..a].iter().product());
    // Whether an inflow side feeds the cell at `q` (its position across the side).
    let feeds = |side: Side, q: &[usize; D], a: usize| {
        let t: Vec<f64> = (0..D).filter(|&o| o != a).map(|o| (q[o] as f64 + 0.5) / dims[o] as f64).collect();
        matches!(side, Side::Inflow(p) if match t[..] { [t] => p.at(t), [t1, t2] => p.across(t1, t2), _ => 0.0 } != 0.0)
    };
    let mut region = vec![usize::MAX; n];
    let mut stack = Vec::new();
    for start in 0..n {
        if solid[start] || region[start] != usize::MAX {
            continue;
        }
        region[start] = start;
        stack.push(start);
        let (mut cells, mut fed, mut drains) = (0, None, false);
        while let Some(c) = stack.pop() {
            cells += 1;
            let q: [usize; D] = std::array::from_fn(|a| (c / strides[a]) % dims[a]);
            for a in 0..D {
                let [lo, hi] = sides[a];
                let periodic = lo == Side::Periodic;
                // Up first, then down: the order 2D has always searched in.
                for (edge, side, up) in [(q[a] + 1 == dims[a], hi, true), (q[a] == 0, lo, false)] {
                    if edge {
                        drains |= side == Side::Outflow;
                        if fed.is_none() && feeds(side, &q, a) {
                            fed = Some(q);
                        }
                    }
                    // The neighbour across this face, if fluid can pass.
                    let m = match (edge, up) {
                        (false, true) => Some(c + strides[a]),
                        (false, false) => Some(c - strides[a]),
                        (true, true) => periodic.then(|| c - (dims[a] - 1) * strides[a]),
                        (true, false) => periodic.then(|| c + (dims[a] - 1) * strides[a]),
                    };
                    if let Some(m) = m
                        && !solid[m]
                        && region[m] == usize::MAX
                    {
                        region[m] = start;
                        stack.push(m);
                    }
                }
            }
        }
        if let (Some(at), false) = (fed, drains) {
            return Some(SealedRegion { cells, at });
        }
    }
    None
}

/// The two cells a face separates, `None` outside the box, and whether the
/// pressure projection changes the face's velocity.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Face {
    /// Index of the face in its velocity array.
    pub index: usize,
    /// The cell on the lower side (left of an x-face, below a y-face).
    pub lower: Option<usize>,
    /// The cell on the upper side.
    pub upper: Option<usize>,
    /// Whether the face is a degree of freedom of the projection (interior,
    /// periodic or outflow); closed and inflow faces keep their velocity.
    pub projected: bool,
    /// The side the face lies on; `None` inside the box.
    pub side: Option<Side>,
    /// On a periodic axis, face `0`'s duplicate (face `N`), which holds a
    /// copy of its velocity.
    pub copy: Option<usize>,
}

/// Calls `visit` for each face normal to `axis` of a box of `n` cells whose
/// sides are `b`, in memory order (x fastest, the face array's extents
/// those of the cells with one more along `axis`), with the cells beside it
/// (across a periodic side: the last cell and the first) and what the
/// projection does with it ([`Face`]). A periodic axis's duplicate last
/// faces are left out (each is the `copy` of its face `0`). Plain loops:
/// the projection calls this every step.
#[inline]
pub fn for_each_face<const D: usize>(n: [usize; D], b: &Boundary<D>, axis: usize, mut visit: impl FnMut(Face)) {
    let [lo, hi] = b.axis(axis);
    let mut e = n;
    e[axis] += 1;
    // Strides of the cell array and of the face array.
    let (mut cs, mut fs) = ([1; D], [1; D]);
    for a in 1..D {
        cs[a] = cs[a - 1] * n[a - 1];
        fs[a] = fs[a - 1] * e[a - 1];
    }
    let total: usize = e.iter().product();
    let mut q = [0; D];
    for index in 0..total {
        if let Some(f) = axis_face(q[axis], n[axis], lo, hi) {
            // Offsets of the face's row of cells and faces, the axis's own
            // position left out.
            let (mut cell, mut face) = (0, 0);
            for a in 0..D {
                if a != axis {
                    cell += q[a] * cs[a];
                    face += q[a] * fs[a];
                }
            }
            visit(Face {
                index,
                lower: f.lower.map(|l| cell + l * cs[axis]),
                upper: f.upper.map(|u| cell + u * cs[axis]),
                projected: f.projected,
                side: f.side,
                copy: f.copy.map(|c| face + c * fs[axis]),
            });
        }
        // The next face in memory order.
        for a in 0..D {
            q[a] += 1;
            if q[a] < e[a] {
                break;
            }
            q[a] = 0;
        }
    }
}

/// The faces of [`for_each_face`], collected.
pub fn faces<const D: usize>(n: [usize; D], b: &Boundary<D>, axis: usize) -> Vec<Face> {
    let mut all = Vec::new();
    for_each_face(n, b, axis, |f| all.push(f));
    all
}
