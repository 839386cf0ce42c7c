//! Steady scenes: `[steady]` in place of `[time]`. The incompressible
//! Navier–Stokes equations around the obstacles are solved for their steady
//! state by Newton's method ([`SteadyFlow`]: cut cells, so a body's shape
//! enters smoothly); a drag or lift loss and its gradient with respect to
//! the obstacles' shape parameters come from the implicit (fixed-point)
//! adjoint of the converged state.
//!
//! Closed sides are no-slip walls at rest; an inflow side sets its profile;
//! an outflow side has zero pressure outside.

use diffsim_solvers::boundary::Side;
use diffsim_solvers::flow::{Convection, Flow2d, FlowError, NewtonParams, Shape, SteadyFlow, SteadyState, WallSpeed};

use super::SceneError;
use super::build::{at, domain_boundary, placed};
use super::init::shape_of;
use super::spec::{LossSpec, SceneFile};
use super::value::{count, positive};
use crate::problems::drag::SteadyForce;

/// Most Newton steps a steady scene may ask for.
const MAX_NEWTON_STEPS: usize = 1000;

/// A steady scene: the flow, its bodies and the loss.
#[derive(Debug)]
pub struct SteadyScene {
    /// The grid, viscosity and sides.
    pub flow: Flow2d,
    /// The bodies, in `[[obstacles]]` order.
    pub shapes: Vec<Shape>,
    /// When Newton's method stops.
    pub newton: NewtonParams,
    /// Newton's starting velocity: at rest with the sides' values, except
    /// that a left inflow's profile fills every x-face of its row.
    pub start: Vec<f64>,
    /// Per body, the box of cells `[i0, i1, j0, j1]` whose momentum balance
    /// gives its force: its bounding box and two cells more, holding no
    /// other body.
    pub boxes: Vec<[usize; 4]>,
    /// The loss, when declared.
    pub loss: Option<ForceLoss>,
}

/// A drag or lift loss.
#[derive(Clone, Debug, PartialEq)]
pub struct ForceLoss {
    /// Lift (force along y) rather than drag (along x).
    pub lift: bool,
    /// The body.
    pub obstacle: usize,
    /// The factor from the force to the loss: 1, or `2/(U²L)` for a
    /// coefficient.
    pub scale: f64,
    /// The bodies whose shape parameters the gradient is taken for, as
    /// written (`obstacles[k].shape`) and by index.
    pub with_respect_to: Vec<(String, usize)>,
}

impl ForceLoss {
    /// `"drag"` or `"lift"`.
    pub fn kind(&self) -> &'static str {
        if self.lift { "lift" } else { "drag" }
    }

    /// The loss as `weights · force`.
    pub fn weights(&self) -> [f64; 2] {
        if self.lift { [0.0, self.scale] } else { [self.scale, 0.0] }
    }
}

/// A solved steady scene.
#[derive(Debug)]
pub struct SteadyRun {
    /// The equations solved.
    pub flow: SteadyFlow,
    /// The state (velocity, pressure, Newton steps).
    pub state: SteadyState,
    /// The force `[F_x, F_y]` on each body.
    pub forces: Vec<[f64; 2]>,
}

/// The loss of a steady scene and its gradient.
#[derive(Clone, Debug)]
pub struct SteadyGradient {
    /// The loss.
    pub loss: f64,
    /// Per entry of `with_respect_to`: its name, the parameters' names and
    /// the gradient.
    pub inputs: Vec<(String, Vec<String>, Vec<f64>)>,
}

/// The names of a shape's parameters, as in [`Shape::params`].
pub fn param_names(shape: &Shape) -> Vec<String> {
    match shape {
        Shape::Circle { .. } => vec!["cx".into(), "cy".into(), "radius".into()],
        Shape::Fourier { cos, sin, .. } => ["cx", "cy", "r0"]
            .iter()
            .map(|s| s.to_string())
            .chain((1..=cos.len()).map(|k| format!("cos[{}]", k - 1)))
            .chain((1..=sin.len()).map(|k| format!("sin[{}]", k - 1)))
            .collect(),
        Shape::Polygon { vertices } => (0..vertices.len()).flat_map(|k| [format!("vertices[{k}].x"), format!("vertices[{k}].y")]).collect(),
    }
}

impl SteadyScene {
    /// Solves for the steady state and the force on every body.
    pub fn solve(&self) -> Result<SteadyRun, FlowError> {
        let flow = SteadyFlow::new(self.flow, &self.shapes)?;
        let state = flow.solve(&self.start, &self.newton)?;
        let forces = self.boxes.iter().map(|b| flow.force(&state, *b)).collect();
        Ok(SteadyRun { flow, state, forces })
    }

    /// The loss's value in a solved scene.
    pub fn loss_value(&self, loss: &ForceLoss, run: &SteadyRun) -> f64 {
        let [wx, wy] = loss.weights();
        let f = run.forces[loss.obstacle];
        wx * f[0] + wy * f[1]
    }

    /// The loss and its gradient with respect to the shapes it names: one
    /// Newton solve and one transposed solve.
    pub fn gradient(&self, loss: &ForceLoss) -> Result<(SteadyRun, SteadyGradient), FlowError> {
        let run = self.solve()?;
        let g = run.flow.force_gradient(&run.state, self.boxes[loss.obstacle], loss.weights());
        let inputs = loss
            .with_respect_to
            .iter()
            .map(|(name, k)| {
                let r = self.param_range(*k);
                (name.clone(), param_names(&self.shapes[*k]), g[r].to_vec())
            })
            .collect();
        let value = self.loss_value(loss, &run);
        Ok((run, SteadyGradient { loss: value, inputs }))
    }

    /// Where body `k`'s parameters lie among all bodies' parameters.
    pub fn param_range(&self, k: usize) -> std::ops::Range<usize> {
        let start: usize = self.shapes[..k].iter().map(Shape::n_params).sum();
        start..start + self.shapes[k].n_params()
    }

    /// Every body's parameters, concatenated.
    pub fn params(&self) -> Vec<f64> {
        self.shapes.iter().flat_map(Shape::params).collect()
    }

    /// The force on body `obstacle` as an operator of every body's
    /// parameters ([`SteadyForce`]), for the gradient checks.
    pub fn force_operator(&self, obstacle: usize) -> Result<SteadyForce, FlowError> {
        Ok(SteadyForce::new(self.flow, self.shapes.clone(), self.start.clone(), self.boxes[obstacle])?.with_newton(self.newton))
    }
}

/// Refuses a grid whose Newton solve exceeds the memory budget. The sparse
/// LU of the coupled Jacobian holds about 16-21 kB per cell at 9 000 to
/// 144 000 cells, growing a little faster than the cell count (measured
/// by `diffsim pareto cylinder`, docs/accuracy.md): the estimate is 21 kB
/// per cell, times `(cells / 144 000)^¼` beyond that.
fn newton_fits(nx: u64, ny: u64) -> Result<(), SceneError> {
    let cells = nx.checked_mul(ny);
    let need = cells.and_then(|c| {
        let growth = (c as f64 / 144_000.0).powf(0.25).max(1.0);
        let bytes = c as f64 * 21_000.0 * growth;
        (bytes < 1.8e19).then_some(bytes as u64)
    });
    let detail = format!("the Newton solve's sparse LU on {nx}×{ny} cells, about 21 kB per cell");
    crate::memory::check("the steady scene", detail, need, Some("use a coarser `domain.cell`".into()))
        .map_err(|e| SceneError::key("domain.size", e.to_string()))
}

/// Builds a steady scene.
pub(super) fn build(file: SceneFile, text: &str) -> Result<SteadyScene, SceneError> {
    let steady = file.steady.as_ref().expect("a steady scene has [steady]");
    if file.time.is_some() {
        return Err(placed(text, steady, SceneError::key("steady", "a scene has either [time] (stepped in time) or [steady], not both")));
    }
    // (Two checks written out: a by-value array of (name, flag) pairs crashes
    // Enzyme's type analysis in this crate; docs/pitfalls.md.)
    let whole = "a steady scene solves the Navier–Stokes equations as a whole; fields and effects belong to scenes stepped in time";
    if file.fields.smoke.is_some() || file.fields.velocity.is_some() {
        return Err(SceneError::key("fields", whole));
    }
    if !file.effects.is_empty() {
        return Err(SceneError::key("effects", whole));
    }
    let (nu, newton) = at(text, steady, |s| {
        let nu = positive("steady.viscosity", s.viscosity)?;
        let tolerance = positive("steady.tolerance", s.tolerance)?;
        let max_steps = count("steady.max_iterations", s.max_iterations)?;
        if max_steps > MAX_NEWTON_STEPS {
            return Err(SceneError::key(
                "steady.max_iterations",
                format!("{max_steps} Newton steps; at most {MAX_NEWTON_STEPS} (Newton converges in tens of steps or not at all)"),
            ));
        }
        Ok((nu, NewtonParams { tolerance, max_steps }))
    })?;
    let flow = at(text, &file.domain, |d| {
        let [nx, ny] = match d.size[..] {
            [nx, ny] => [count("domain.size[0]", nx)?, count("domain.size[1]", ny)?],
            _ => return Err(SceneError::key("domain.size", format!("a steady scene is 2D: expected [nx, ny], got {} value(s)", d.size.len()))),
        };
        if nx.min(ny) < 4 {
            return Err(SceneError::key("domain.size", format!("need at least 4 cells per side, got [{nx}, {ny}]")));
        }
        if d.length.is_some() {
            return Err(SceneError::key("domain.length", "`length` is for 1D domains; a box gives its cell width as `cell`"));
        }
        newton_fits(nx as u64, ny as u64)?;
        let h = positive("domain.cell", d.cell.unwrap_or(1.0))?;
        let flow = Flow2d { nx, ny, h, nu, boundary: domain_boundary(d)?, wall_speed: WallSpeed::default(), convection: Convection::default() };
        flow.validate().map_err(|e| SceneError::key("domain.boundary", e.to_string()))?;
        Ok(flow)
    })?;

    // Bodies, each inside the domain, and a box for each force.
    let mut shapes = Vec::new();
    let mut bounds = Vec::new();
    for (k, spec) in file.obstacles.iter().enumerate() {
        let key = format!("obstacles[{k}]");
        let shape = at(text, spec, |s| {
            let shape = shape_of(&key, s)?;
            shape.validate(&flow).map_err(|e| SceneError::key(&key, e.to_string()))?;
            Ok(shape)
        })?;
        bounds.push(shape.bounds().expect("checked by shape_of"));
        shapes.push(shape);
    }
    let cell = |v: f64| (v / flow.h).floor() as i64;
    let boxes: Vec<[usize; 4]> = bounds
        .iter()
        .map(|b| {
            let clip = |v: i64, n: usize| v.clamp(0, n as i64) as usize;
            [clip(cell(b[0]) - 2, flow.nx), clip(cell(b[1]) + 3, flow.nx), clip(cell(b[2]) - 2, flow.ny), clip(cell(b[3]) + 3, flow.ny)]
        })
        .collect();
    for (k, bx) in boxes.iter().enumerate() {
        for (m, b) in bounds.iter().enumerate() {
            let h = flow.h;
            let apart = b[1] < bx[0] as f64 * h || b[0] > bx[1] as f64 * h || b[3] < bx[2] as f64 * h || b[2] > bx[3] as f64 * h;
            if m != k && !apart {
                let (a, z) = (k.min(m), k.max(m));
                let e = SceneError::key(
                    format!("obstacles[{z}]"),
                    format!("overlaps obstacles[{a}] or lies within two cells of it; their forces cannot be told apart"),
                );
                return Err(placed(text, &file.obstacles[z], e));
            }
        }
    }

    // Newton's start.
    let mut start = flow.rest();
    if let Side::Inflow(profile) = flow.boundary.lower(0) {
        for j in 0..flow.ny {
            let u = profile.at((j as f64 + 0.5) / flow.ny as f64);
            start[j * (flow.nx + 1)..(j + 1) * (flow.nx + 1)].fill(u);
        }
    }

    let loss = match &file.loss {
        None => None,
        Some(l) => Some(at(text, l, |l| {
            let (lift, spec) = match super::spec::loss(l)? {
                LossSpec::Force { lift, spec } => (lift, spec),
                LossSpec::Field(_) => return Err(SceneError::key("loss.kind", "a steady scene's loss is \"drag\" or \"lift\" on an obstacle")),
            };
            if shapes.is_empty() {
                return Err(SceneError::key("loss", "a drag or lift loss needs an obstacle ([[obstacles]])"));
            }
            let obstacle = usize::try_from(spec.obstacle)
                .ok()
                .filter(|&k| k < shapes.len())
                .ok_or_else(|| SceneError::key("loss.obstacle", format!("no obstacle {}; the scene has obstacles 0..={}", spec.obstacle, shapes.len() - 1)))?;
            let scale = match &spec.reference {
                None => 1.0,
                Some(r) => {
                    let (u, l) = (positive("loss.reference.speed", r.speed)?, positive("loss.reference.length", r.length)?);
                    2.0 / (u * u * l)
                }
            };
            let known: Vec<String> = (0..shapes.len()).map(|k| format!("obstacles[{k}].shape")).collect();
            let with_respect_to = spec
                .with_respect_to
                .iter()
                .map(|w| match known.iter().position(|k| k == w) {
                    Some(k) => Ok((w.clone(), k)),
                    None => {
                        Err(SceneError::key("loss.with_respect_to", crate::words::unknown("input", w, &known.iter().map(String::as_str).collect::<Vec<_>>())))
                    }
                })
                .collect::<Result<_, _>>()?;
            Ok(ForceLoss { lift, obstacle, scale, with_respect_to })
        })?),
    };
    Ok(SteadyScene { flow, shapes, newton, start, boxes, loss })
}
