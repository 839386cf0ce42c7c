//! Scenes: a TOML file declares a 2D domain, its boundary, the initial
//! fields, obstacles, the effects that run each step (in the order listed)
//! and optionally a loss; [`Scene::load`] checks it and builds the step as a
//! [`Chain`] of exactly the declared effects. An effect that is not
//! declared is never constructed, so it allocates and costs nothing.
//!
//! Every key is documented in `docs/scenes.md`; every mistake is a
//! [`SceneError`] naming the key (syntax errors also the line).

pub mod spec;

use std::ops::Range;
use std::path::Path;

use diffsim_solvers::boundary::{Boundary, Profile, Side};
use diffsim_solvers::diffusion::EXPLICIT_LIMIT;
use diffsim_solvers::smoke::{Preconditioner, Scheme, Smoke2d, obstacle_box, obstacle_disc};

use crate::fluids::{Advect, AdvectUpwind, Buoyancy, Diffuse, Force, Inflow, Project};
use crate::op::{Chain, Effect, Forward};
use spec::{EffectSpec, InitSpec, SceneFile, ShapeSpec, unknown};

/// A scene that cannot be read or built.
#[derive(Debug, thiserror::Error)]
pub enum SceneError {
    /// The file could not be read.
    #[error("cannot read scene {path}: {source}")]
    Read {
        /// The file.
        path: std::path::PathBuf,
        /// The cause.
        source: std::io::Error,
    },
    /// The TOML is malformed or a value has the wrong type (the message
    /// names the line and key).
    #[error("scene: {0}")]
    Syntax(String),
    /// A key has a value the scene cannot use.
    #[error("scene: `{key}`: {reason}")]
    Key {
        /// The key, as a path (`effects[2].scheme`).
        key: String,
        /// What is wrong.
        reason: String,
    },
}

impl SceneError {
    /// An error at `key`.
    pub fn key(key: impl Into<String>, reason: impl Into<String>) -> Self {
        SceneError::Key { key: key.into(), reason: reason.into() }
    }
}

/// A built scene: the grid, the step, its parameters and initial state.
#[derive(Debug)]
pub struct Scene {
    /// The grid and its boundary.
    pub cfg: Smoke2d,
    /// Time step.
    pub dt: f64,
    /// Number of steps.
    pub steps: usize,
    /// One step: the declared effects in order.
    pub step: Chain,
    /// The effects' parameters, concatenated in order (`step`'s `p`).
    pub params: Vec<f64>,
    /// Named scalar parameters: name, index in `params`, and the factor
    /// from the written value to the parameter (κ = ν·dt: `dt`).
    pub named: Vec<(String, usize, f64)>,
    /// The effects' names, in order (`kind` as written).
    pub effects: Vec<String>,
    /// The packed initial state `[s, u, v]`.
    pub x0: Vec<f64>,
    /// Solid cells, when there are obstacles.
    pub solid: Option<Vec<bool>>,
    /// The loss target (smoke) and what to differentiate, when declared.
    pub loss: Option<(Vec<f64>, Vec<String>)>,
}

impl Scene {
    /// Reads and builds the scene in `path`.
    pub fn load(path: &Path) -> Result<Scene, SceneError> {
        let text = std::fs::read_to_string(path).map_err(|source| SceneError::Read { path: path.to_path_buf(), source })?;
        Self::parse(&text)
    }

    /// Builds a scene from its TOML text.
    pub fn parse(text: &str) -> Result<Scene, SceneError> {
        let file: SceneFile = toml::from_str(text).map_err(|e| SceneError::Syntax(spec::suggest_field(&e.to_string())))?;
        build(file)
    }

    /// The range of the smoke in the packed state.
    pub fn smoke_range(&self) -> Range<usize> {
        0..self.cfg.n_s()
    }
}

fn positive(key: &str, v: f64) -> Result<f64, SceneError> {
    if v.is_finite() && v > 0.0 { Ok(v) } else { Err(SceneError::key(key, format!("must be a positive finite number, got {v}"))) }
}

fn finite(key: &str, v: f64) -> Result<f64, SceneError> {
    if v.is_finite() { Ok(v) } else { Err(SceneError::key(key, format!("must be finite, got {v}"))) }
}

fn count(key: &str, v: i64) -> Result<usize, SceneError> {
    if v >= 1 { Ok(v as usize) } else { Err(SceneError::key(key, format!("must be at least 1, got {v}"))) }
}

fn build(file: SceneFile) -> Result<Scene, SceneError> {
    // Domain.
    let size = &file.domain.size;
    if size.len() != 2 {
        return Err(SceneError::key("domain.size", format!("expected [nx, ny] (2D), got {} value(s); 1D scenes are not supported yet", size.len())));
    }
    let (nx, ny) = (count("domain.size[0]", size[0])?, count("domain.size[1]", size[1])?);
    if nx != ny {
        return Err(SceneError::key("domain.size", format!("only square domains are supported for now, got [{nx}, {ny}]")));
    }
    if nx < 4 {
        return Err(SceneError::key("domain.size", format!("need at least 4 cells per side, got {nx}")));
    }
    let n = nx;
    let boundary = match &file.domain.boundary {
        None => Boundary::CLOSED,
        Some(v) => boundary(v)?,
    };
    boundary.validate().map_err(|e| SceneError::key("domain.boundary", e.to_string()))?;
    let cfg = Smoke2d { n, buoyancy: 0.0, boundary };
    let dt = positive("time.dt", file.time.dt)?;
    let steps = count("time.steps", file.time.steps)?;

    // Obstacles.
    let mut solid: Option<Vec<bool>> = None;
    for (k, shape) in file.obstacles.iter().enumerate() {
        let cells = shape_cells(&format!("obstacles[{k}]"), n, shape)?;
        let all = solid.get_or_insert_with(|| vec![false; n * n]);
        for (a, c) in all.iter_mut().zip(cells) {
            *a |= c;
        }
    }

    // Initial state.
    let mut x0 = vec![0.0; cfg.n_state()];
    if let Some(f) = &file.fields.smoke {
        let s = scalar_init("fields.smoke.init", n, &f.init)?;
        x0[..cfg.n_s()].copy_from_slice(&s);
    }
    if let Some(f) = &file.fields.velocity {
        velocity_init("fields.velocity.init", &cfg, &f.init, &mut x0)?;
    }
    let has = |field: &str| match field {
        "smoke" => file.fields.smoke.is_some(),
        _ => file.fields.velocity.is_some(),
    };

    // Effects, in order.
    let mut ops: Vec<Box<dyn Effect>> = Vec::new();
    let mut params = Vec::new();
    let mut named = Vec::new();
    let mut effects = Vec::new();
    let mut projected = false;
    for (k, table) in file.effects.iter().enumerate() {
        let at = |key: &str| format!("effects[{k}].{key}");
        let e = spec::effect(k, table)?;
        let name = |kind: &str, param: &str, index: usize, factor: f64, named: &mut Vec<(String, usize, f64)>| {
            let short = format!("{kind}.{param}");
            if !named.iter().any(|(n, _, _)| *n == short) {
                named.push((short, index, factor));
            }
            named.push((format!("effects[{k}].{param}"), index, factor));
        };
        let fields_of = |key: &str, fields: &[String]| -> Result<(bool, bool), SceneError> {
            let (mut s, mut v) = (false, false);
            for f in fields {
                match f.as_str() {
                    "smoke" => s = true,
                    "velocity" => v = true,
                    other => return Err(SceneError::key(at(key), unknown("field", other, &["smoke", "velocity"]))),
                }
                if !has(f) {
                    return Err(SceneError::key(at(key), format!("needs the field `{f}`, which the scene does not declare (add [fields.{f}])")));
                }
            }
            if !s && !v {
                return Err(SceneError::key(at(key), "names no field"));
            }
            Ok((s, v))
        };
        match e {
            EffectSpec::Advection(a) => {
                let (s, v) = fields_of("fields", &a.fields)?;
                effects.push("advection".to_string());
                match a.scheme.as_str() {
                    "semi_lagrangian" | "maccormack" => {
                        let scheme = if a.scheme == "maccormack" { Scheme::MacCormack { limiter: a.limiter } } else { Scheme::SemiLagrangian };
                        ops.push(Box::new(Advect { cfg, scheme, dt, smoke: s, velocity: v }));
                    }
                    "upwind" => {
                        if v {
                            return Err(SceneError::key(
                                at("scheme"),
                                "upwind advects scalars only; advect the velocity in its own effect with semi_lagrangian or maccormack",
                            ));
                        }
                        if !has("velocity") {
                            return Err(SceneError::key(at("scheme"), "upwind needs a velocity field (add [fields.velocity])"));
                        }
                        ops.push(Box::new(AdvectUpwind { cfg, dt }));
                    }
                    other => return Err(SceneError::key(at("scheme"), unknown("scheme", other, &["semi_lagrangian", "maccormack", "upwind"]))),
                }
            }
            EffectSpec::Diffusion(d) => {
                let (s, v) = fields_of("fields", &d.fields)?;
                let nu = finite(&at("viscosity"), d.viscosity)?;
                if nu < 0.0 {
                    return Err(SceneError::key(at("viscosity"), format!("must not be negative, got {nu}")));
                }
                let kappa = nu * dt;
                effects.push("diffusion".to_string());
                match d.scheme.as_str() {
                    "explicit" => {
                        if kappa > EXPLICIT_LIMIT {
                            return Err(SceneError::key(
                                at("scheme"),
                                format!(
                                    "explicit diffusion is unstable here: viscosity·dt = {kappa} exceeds the limit {EXPLICIT_LIMIT}; use dt ≤ {:.4} or scheme = \"implicit\"",
                                    EXPLICIT_LIMIT / nu
                                ),
                            ));
                        }
                        ops.push(Box::new(Diffuse::explicit(cfg, s, v)));
                    }
                    "implicit" => {
                        let tol = positive(&at("tolerance"), d.tolerance)?;
                        let max = count(&at("max_iterations"), d.max_iterations)?;
                        ops.push(Box::new(Diffuse::implicit(cfg, s, v, tol, max)));
                    }
                    other => return Err(SceneError::key(at("scheme"), unknown("scheme", other, &["explicit", "implicit"]))),
                }
                name("diffusion", "viscosity", params.len(), dt, &mut named);
                params.push(kappa);
            }
            EffectSpec::Pressure(p) => {
                if !has("velocity") {
                    return Err(SceneError::key(at("kind"), "pressure needs the field `velocity` (add [fields.velocity])"));
                }
                let tol = positive(&at("tolerance"), p.tolerance)?;
                let max = count(&at("max_iterations"), p.max_iterations)?;
                let precond = match p.preconditioner.as_str() {
                    "multigrid" => Preconditioner::Multigrid,
                    "mic0" => Preconditioner::Mic0,
                    "none" => Preconditioner::None,
                    other => return Err(SceneError::key(at("preconditioner"), unknown("preconditioner", other, &["multigrid", "mic0", "none"]))),
                };
                effects.push("pressure".to_string());
                ops.push(Box::new(match &solid {
                    Some(s) => Project::with_obstacles(cfg, tol, max, s),
                    None => Project::new(cfg, tol, max, precond),
                }));
                projected = true;
            }
            EffectSpec::Buoyancy(b) => {
                if b.field != "smoke" {
                    return Err(SceneError::key(at("field"), unknown("field", &b.field, &["smoke"])));
                }
                for f in ["smoke", "velocity"] {
                    if !has(f) {
                        return Err(SceneError::key(at("kind"), format!("buoyancy needs the field `{f}` (add [fields.{f}])")));
                    }
                }
                effects.push("buoyancy".to_string());
                ops.push(Box::new(Buoyancy { cfg, dt }));
                name("buoyancy", "coefficient", params.len(), 1.0, &mut named);
                params.push(finite(&at("coefficient"), b.coefficient)?);
            }
            EffectSpec::Force(f) => {
                if !has("velocity") {
                    return Err(SceneError::key(at("kind"), "force needs the field `velocity` (add [fields.velocity])"));
                }
                let (fx, fy) = (finite(&at("value[0]"), f.value[0])?, finite(&at("value[1]"), f.value[1])?);
                effects.push("force".to_string());
                ops.push(Box::new(Force { cfg, dt }));
                params.extend(std::iter::repeat_n(fx, cfg.n_u()));
                params.extend(std::iter::repeat_n(fy, cfg.n_u()));
            }
            EffectSpec::Inflow(i) => {
                let region = match i.region {
                    ShapeSpec::Box { lower, upper } => {
                        let clip = |v: f64| v.clamp(0.0, n as f64);
                        let (i0, j0) = (clip(lower[0]).round() as usize, clip(lower[1]).round() as usize);
                        let (i1, j1) = (clip(upper[0]).round() as usize, clip(upper[1]).round() as usize);
                        if i0 >= i1 || j0 >= j1 {
                            return Err(SceneError::key(at("region"), "the box covers no cell of the domain"));
                        }
                        [i0, i1, j0, j1]
                    }
                    ShapeSpec::Disc { .. } => return Err(SceneError::key(at("region"), "an inflow region must be a box")),
                };
                effects.push("inflow".to_string());
                ops.push(Box::new(Inflow { cfg, region }));
                let values = [finite(&at("smoke"), i.smoke)?, finite(&at("velocity[0]"), i.velocity[0])?, finite(&at("velocity[1]"), i.velocity[1])?];
                params.extend(values);
            }
        }
    }
    if ops.is_empty() {
        return Err(SceneError::key("effects", "the scene declares no effect"));
    }
    if solid.is_some() && !projected {
        return Err(SceneError::key("obstacles", "obstacles need a pressure effect (no flow through solids is enforced by the projection)"));
    }

    // Loss.
    let loss = match &file.loss {
        None => None,
        Some(l) => {
            if l.field != "smoke" {
                return Err(SceneError::key("loss.field", unknown("field", &l.field, &["smoke"])));
            }
            let target = scalar_init("loss.target", n, &l.target)?;
            let known: Vec<&str> = ["smoke.init", "velocity.init"].into_iter().chain(named.iter().map(|(s, _, _)| s.as_str())).collect();
            for w in &l.with_respect_to {
                if !known.contains(&w.as_str()) {
                    return Err(SceneError::key("loss.with_respect_to", unknown("input", w, &known)));
                }
            }
            Some((target, l.with_respect_to.clone()))
        }
    };
    Ok(Scene { cfg, dt, steps, step: Chain::new(ops), params, named, effects, x0, solid, loss })
}

/// The boundary of `domain.boundary`.
fn boundary(v: &toml::Value) -> Result<Boundary, SceneError> {
    const KEY: &str = "domain.boundary";
    match v {
        toml::Value::String(_) => {
            let s = side(KEY, v, None)?;
            if matches!(s, Side::Inflow(_)) {
                return Err(SceneError::key(KEY, "inflow must be given per side"));
            }
            Ok(Boundary::all(s))
        }
        toml::Value::Table(t) if t.contains_key("x") || t.contains_key("y") => {
            for k in t.keys() {
                if k != "x" && k != "y" {
                    return Err(SceneError::key(format!("{KEY}.{k}"), unknown("axis", k, &["x", "y"])));
                }
            }
            let axis = |a: &str| t.get(a).map_or(Ok(Side::Closed), |v| side(&format!("{KEY}.{a}"), v, None));
            Ok(Boundary::axes(axis("x")?, axis("y")?))
        }
        toml::Value::Table(t) => {
            const SIDES: [&str; 4] = ["left", "right", "bottom", "top"];
            for k in t.keys() {
                if !SIDES.contains(&k.as_str()) {
                    return Err(SceneError::key(format!("{KEY}.{k}"), unknown("side", k, &["left", "right", "bottom", "top", "x", "y"])));
                }
            }
            let one = |name: &str, inward: [f64; 2]| t.get(name).map_or(Ok(Side::Closed), |v| side(&format!("{KEY}.{name}"), v, Some(inward)));
            Ok(Boundary {
                left: one("left", [1.0, 0.0])?,
                right: one("right", [-1.0, 0.0])?,
                bottom: one("bottom", [0.0, 1.0])?,
                top: one("top", [0.0, -1.0])?,
            })
        }
        _ => Err(SceneError::key(
            KEY,
            "expected a kind (\"closed\", \"periodic\", \"outflow\"), { x = …, y = … } or { left = …, right = …, bottom = …, top = … }",
        )),
    }
}

/// One side: a kind, or `{ inflow = [vx, vy], profile = "uniform" | "parabolic" }`
/// (`inward`: the side's inward normal, for the inflow speed).
fn side(key: &str, v: &toml::Value, inward: Option<[f64; 2]>) -> Result<Side, SceneError> {
    const KINDS: [&str; 4] = ["closed", "periodic", "outflow", "inflow"];
    match v {
        toml::Value::String(s) => match s.as_str() {
            "closed" => Ok(Side::Closed),
            "periodic" => Ok(Side::Periodic),
            "outflow" => Ok(Side::Outflow),
            "inflow" => Err(SceneError::key(key, "inflow needs its velocity: { inflow = [vx, vy] }")),
            other => Err(SceneError::key(key, unknown("boundary kind", other, &KINDS))),
        },
        toml::Value::Table(t) => {
            let Some(normal) = inward else {
                return Err(SceneError::key(key, "inflow is given per side (left, right, bottom, top)"));
            };
            for k in t.keys() {
                if k != "inflow" && k != "profile" {
                    return Err(SceneError::key(format!("{key}.{k}"), unknown("key", k, &["inflow", "profile"])));
                }
            }
            let vel: [f64; 2] = t
                .get("inflow")
                .ok_or_else(|| SceneError::key(key, "expected { inflow = [vx, vy] }"))?
                .clone()
                .try_into()
                .map_err(|_| SceneError::key(format!("{key}.inflow"), "expected two numbers [vx, vy]"))?;
            let speed = finite(&format!("{key}.inflow"), vel[0] * normal[0] + vel[1] * normal[1])?;
            if speed <= 0.0 {
                return Err(SceneError::key(format!("{key}.inflow"), format!("the velocity {vel:?} does not point into the domain")));
            }
            match t.get("profile").and_then(|p| p.as_str()).unwrap_or("uniform") {
                "uniform" => Ok(Side::Inflow(Profile::Uniform(speed))),
                "parabolic" => Ok(Side::Inflow(Profile::Parabolic(speed))),
                other => Err(SceneError::key(format!("{key}.profile"), unknown("profile", other, &["uniform", "parabolic"]))),
            }
        }
        _ => Err(SceneError::key(key, "expected a kind or { inflow = [vx, vy] }")),
    }
}

/// Cells whose centre lies inside a shape, clipped to the domain; a shape
/// wholly outside is an error.
fn shape_cells(key: &str, n: usize, shape: &ShapeSpec) -> Result<Vec<bool>, SceneError> {
    let cells = match *shape {
        ShapeSpec::Box { lower, upper } => {
            for v in lower.iter().chain(&upper) {
                finite(key, *v)?;
            }
            obstacle_box(n, lower, upper)
        }
        ShapeSpec::Disc { center, radius } => {
            finite(key, center[0])?;
            finite(key, center[1])?;
            positive(&format!("{key}.radius"), radius)?;
            obstacle_disc(n, center, radius)
        }
    };
    cells.ok_or_else(|| SceneError::key(key, format!("the shape lies wholly outside the {n}×{n} domain")))
}

/// A cell-centred field from an initial-value spec.
fn scalar_init(key: &str, n: usize, init: &InitSpec) -> Result<Vec<f64>, SceneError> {
    let shape = |shape: ShapeSpec, value: f64| -> Result<Vec<f64>, SceneError> {
        let value = finite(&format!("{key}.value"), value)?;
        Ok(shape_cells(key, n, &shape)?.into_iter().map(|c| if c { value } else { 0.0 }).collect())
    };
    match *init {
        InitSpec::Zero => Ok(vec![0.0; n * n]),
        InitSpec::Disc { center, radius, value } => shape(ShapeSpec::Disc { center, radius }, value),
        InitSpec::Box { lower, upper, value } => shape(ShapeSpec::Box { lower, upper }, value),
        InitSpec::Sine { amplitude, wavenumber } => {
            let a = finite(&format!("{key}.sine.amplitude"), amplitude)?;
            let nf = n as f64;
            Ok((0..n * n).map(|c| a * sine(wavenumber, (c % n) as f64 + 0.5, (c / n) as f64 + 0.5, nf)).collect())
        }
        InitSpec::Uniform(_) => Err(SceneError::key(key, "`uniform` is for the velocity; use a shape, `sine` or \"zero\"")),
    }
}

fn sine(k: [f64; 2], x: f64, y: f64, n: f64) -> f64 {
    (2.0 * std::f64::consts::PI * (k[0] * x / n + k[1] * y / n)).sin()
}

/// Writes the velocity part of `x` from an initial-value spec.
fn velocity_init(key: &str, cfg: &Smoke2d, init: &InitSpec, x: &mut [f64]) -> Result<(), SceneError> {
    let n = cfg.n;
    let (_, u, v) = cfg.split_mut(x);
    match *init {
        InitSpec::Zero => {}
        InitSpec::Uniform(vel) => {
            u.fill(finite(&format!("{key}.uniform[0]"), vel[0])?);
            v.fill(finite(&format!("{key}.uniform[1]"), vel[1])?);
        }
        InitSpec::Sine { amplitude, wavenumber } => {
            let a = finite(&format!("{key}.sine.amplitude"), amplitude)?;
            let nf = n as f64;
            for j in 0..n {
                for i in 0..=n {
                    u[j * (n + 1) + i] = a * sine(wavenumber, i as f64, j as f64 + 0.5, nf);
                }
            }
            for j in 0..=n {
                for i in 0..n {
                    v[j * n + i] = a * sine(wavenumber, i as f64 + 0.5, j as f64, nf);
                }
            }
        }
        InitSpec::Disc { .. } | InitSpec::Box { .. } => return Err(SceneError::key(key, "the velocity starts \"zero\", `uniform = [vx, vy]` or `sine`")),
    }
    diffsim_solvers::smoke::enforce_boundary(cfg, u, v);
    Ok(())
}

impl Scene {
    /// Runs the scene, calling `frame(step, state)` after every step; stops
    /// at the first failed solve, unstable step or non-finite value.
    pub fn run(&self, frame: impl FnMut(usize, &[f64])) -> Result<Vec<f64>, RunError> {
        self.run_with(frame, |_| {})
    }

    /// [`Scene::run`], also calling `after_effect(k)` after the `k`-th
    /// effect of every step (for profiling).
    pub fn run_with(&self, mut frame: impl FnMut(usize, &[f64]), mut after_effect: impl FnMut(usize)) -> Result<Vec<f64>, RunError> {
        let mut x = self.x0.clone();
        let mut y = vec![0.0; x.len()];
        for k in 1..=self.steps {
            self.step.forward_with(&x, &self.params, &mut y, &mut after_effect);
            if let Some(error) = self.step.take_error() {
                return Err(RunError::Operator { step: k, error });
            }
            if let Some(at) = y.iter().position(|v| !v.is_finite()) {
                let field = if at < self.cfg.n_s() { "smoke" } else { "velocity" };
                return Err(RunError::NonFinite { step: k, field });
            }
            std::mem::swap(&mut x, &mut y);
            frame(k, &x);
        }
        Ok(x)
    }
}

/// A scene run that failed.
#[derive(Clone, Copy, Debug, PartialEq, thiserror::Error)]
pub enum RunError {
    /// An effect failed (a solve that did not converge, an unstable step).
    #[error("step {step}: {error}")]
    Operator {
        /// The step (1-based).
        step: usize,
        /// What failed.
        error: crate::op::OpError,
    },
    /// A value became NaN or infinite.
    #[error("step {step}: the {field} became non-finite")]
    NonFinite {
        /// The step (1-based).
        step: usize,
        /// `"smoke"` or `"velocity"`.
        field: &'static str,
    },
}
