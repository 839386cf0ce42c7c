//! The scene file's shape (TOML, read with serde) and its first-level
//! checks. Every key is documented in `docs/scenes.md`.
//!
//! Effects are read one table at a time (the `kind` key chooses the
//! table's shape), so that an error names the effect it is in.

use serde::Deserialize;
use toml::Spanned;

use super::SceneError;

/// A scene file as written. Tables keep their place in the file
/// ([`Spanned`]) so that errors found after parsing name the line.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SceneFile {
    /// The box and its boundary.
    pub domain: Spanned<DomainSpec>,
    /// Time step and number of steps (a scene stepped in time).
    pub time: Option<Spanned<TimeSpec>>,
    /// The steady viscous flow, in place of `[time]` (a steady scene).
    pub steady: Option<Spanned<SteadySpec>>,
    /// Initial values of the fields the scene uses.
    #[serde(default)]
    pub fields: FieldsSpec,
    /// The effects, in the order they run each step (parsed by [`effect`]).
    #[serde(default)]
    pub effects: Vec<Spanned<toml::Table>>,
    /// Solid shapes.
    #[serde(default)]
    pub obstacles: Vec<Spanned<ShapeSpec>>,
    /// What `diffsim grad` differentiates (parsed by [`loss`]).
    pub loss: Option<Spanned<toml::Table>>,
}

/// `[domain]`.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DomainSpec {
    /// Cells, x first: `[n]` for a line, `[nx, ny]` for a box.
    pub size: Vec<i64>,
    /// Length of a 1D domain (default: `n`, unit cells).
    pub length: Option<f64>,
    /// Cell width of a steady scene's box (default 1).
    pub cell: Option<f64>,
    /// `"closed"` (or `"free-slip"`), `"no-slip"`, `"periodic"`, `"outflow"`, per axis `{ x = …, y = … }`,
    /// or per side `{ left = …, right = …, bottom = …, top = … }`.
    #[serde(default)]
    pub boundary: Option<toml::Value>,
}

/// `[time]`.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TimeSpec {
    /// Time step.
    pub dt: f64,
    /// Number of steps.
    pub steps: i64,
}

/// `[steady]`: the steady incompressible Navier–Stokes equations around
/// the obstacles, solved by Newton's method.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SteadySpec {
    /// Kinematic viscosity ν.
    pub viscosity: f64,
    /// Newton stops when the largest residual falls below this (default 1e-10).
    #[serde(default = "newton_tolerance")]
    pub tolerance: f64,
    /// Newton steps before giving up (default 40).
    #[serde(default = "newton_steps")]
    pub max_iterations: i64,
}

fn newton_tolerance() -> f64 {
    1e-10
}

fn newton_steps() -> i64 {
    40
}

/// `[fields]`.
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FieldsSpec {
    /// `[fields.smoke]`.
    pub smoke: Option<Spanned<FieldSpec>>,
    /// `[fields.velocity]`.
    pub velocity: Option<Spanned<FieldSpec>>,
}

/// One field's initial value.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FieldSpec {
    /// The initial value.
    pub init: InitSpec,
}

/// An initial value: `"zero"`, a shape with a value, a uniform vector, a
/// sine, or `.npy` files. Coordinates have one entry per axis, x first.
#[derive(Debug, Clone, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum InitSpec {
    /// Zero everywhere.
    Zero,
    /// `value` inside the disc (cell centres within `radius` of `center`).
    Disc {
        /// Centre, x first, in cells.
        center: Vec<f64>,
        /// Radius in cells.
        radius: f64,
        /// The value inside (default 1).
        #[serde(default = "one")]
        value: f64,
    },
    /// `value` inside the box `[lower, upper)`.
    Box {
        /// Lower corner, x first.
        lower: Vec<f64>,
        /// Upper corner, x first.
        upper: Vec<f64>,
        /// The value inside (default 1).
        #[serde(default = "one")]
        value: f64,
    },
    /// `value` inside the ball (3D: cell centres within `radius` of `center`).
    Sphere {
        /// Centre `[x, y, z]`, in cells.
        center: Vec<f64>,
        /// Radius in cells.
        radius: f64,
        /// The value inside (default 1).
        #[serde(default = "one")]
        value: f64,
    },
    /// `amplitude·sin(2π·(kx·x + ky·y)/L)` (for a 2D velocity: on each
    /// face, both components).
    Sine {
        /// Amplitude.
        amplitude: f64,
        /// Wave numbers, x first.
        wavenumber: Vec<f64>,
    },
    /// The same vector on every face (velocity only), x first.
    Uniform(Vec<f64>),
    /// The Taylor–Green vortex of this amplitude, one period across the box
    /// (2D velocity only): `u = A·sin(2πx/Lx)·cos(2πy/Ly)`, `v =
    /// −A·(Ly/Lx)·cos(2πx/Lx)·sin(2πy/Ly)`, divergence-free; with periodic
    /// sides an exact solution that decays as `e^{−ν·(k_x² + k_y²)·t}`.
    TaylorGreen(f64),
    /// The Arnold–Beltrami–Childress flow (`A = B = C`) of this amplitude,
    /// one period across the box (3D velocity only): in a periodic cube an
    /// exact solution that decays as `e^{−ν·k²·t}`, `k = 2π/L`.
    Abc(f64),
    /// Values from `.npy` files (float64 or float32), paths relative to the
    /// scene file: one file for a scalar field or a 1D velocity, two
    /// (`[u, v]`) for a 2D velocity.
    Npy(NpyPaths),
}

/// One `.npy` path or several.
#[derive(Debug, Clone, Deserialize)]
#[serde(untagged)]
pub enum NpyPaths {
    /// One file.
    One(String),
    /// Several files.
    Many(Vec<String>),
}

impl NpyPaths {
    /// The paths as a list.
    pub fn list(&self) -> Vec<&str> {
        match self {
            NpyPaths::One(p) => vec![p.as_str()],
            NpyPaths::Many(v) => v.iter().map(String::as_str).collect(),
        }
    }
}

fn one() -> f64 {
    1.0
}

/// A solid shape in `[[obstacles]]`: in a scene stepped in time, the cells
/// whose centre lies inside; in a steady scene, the body cut from the grid.
#[derive(Debug, Clone, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ShapeSpec {
    /// A box `[lower, upper)`, x first.
    Box {
        /// Lower corner.
        lower: Vec<f64>,
        /// Upper corner.
        upper: Vec<f64>,
    },
    /// A disc.
    Disc {
        /// Centre, x first.
        center: Vec<f64>,
        /// Radius.
        radius: f64,
    },
    /// A body with radius `r(θ) = r0 + Σₖ cos[k−1]·cos kθ + sin[k−1]·sin kθ`
    /// about its centre (2D).
    Fourier {
        /// Centre `[x, y]`.
        center: Vec<f64>,
        /// Mean radius.
        r0: f64,
        /// Cosine coefficients `a₁, a₂, …` (default none).
        #[serde(default)]
        cos: Vec<f64>,
        /// Sine coefficients `b₁, b₂, …` (default none).
        #[serde(default)]
        sin: Vec<f64>,
    },
    /// A simple polygon through its vertices, in order (2D).
    Polygon {
        /// Vertices `[[x, y], …]`.
        vertices: Vec<Vec<f64>>,
    },
    /// A ball (3D).
    Sphere {
        /// Centre `[x, y, z]`.
        center: Vec<f64>,
        /// Radius.
        radius: f64,
    },
    /// A circular cylinder along an axis (3D).
    Cylinder {
        /// A point on its centre line, `[x, y, z]` (the coordinate along
        /// the axis is not used).
        center: Vec<f64>,
        /// Radius.
        radius: f64,
        /// `"x"`, `"y"` or `"z"` (default `"z"`).
        #[serde(default = "z_axis")]
        axis: String,
        /// From and to along the axis (default: through the box).
        extent: Option<Vec<f64>>,
    },
    /// Solid cells from a `.npy` file (3D: shape `[nz, ny, nx]`, solid
    /// where the value is not zero), path relative to the scene file.
    Npy(String),
}

fn z_axis() -> String {
    "z".into()
}

/// `[loss]`, by its `kind` (default `"field"`).
#[derive(Debug)]
pub enum LossSpec {
    /// `kind = "field"`.
    Field(FieldLossSpec),
    /// `kind = "drag"` or `"lift"`.
    Force {
        /// Lift (else drag).
        lift: bool,
        /// The rest.
        spec: ForceLossSpec,
    },
}

/// The loss kinds, as written.
pub const LOSS_KINDS: [&str; 3] = ["field", "drag", "lift"];

/// `[loss] kind = "field"`: `½·Σ_t Σ (field_t − target)²` over the listed
/// steps (default: the last).
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FieldLossSpec {
    /// The field compared (`"smoke"` or `"velocity"`).
    pub field: String,
    /// The target, an initial value of that field.
    pub target: InitSpec,
    /// The steps with a term (1 ≤ t ≤ steps; default the last).
    pub steps: Option<Vec<i64>>,
    /// What the gradient is taken for: `smoke.init`, `velocity.init`,
    /// `<effect kind>.<parameter>` (e.g. `buoyancy.coefficient`), and
    /// `force.control` (the force field of every step).
    pub with_respect_to: Vec<String>,
}

/// `[loss] kind = "drag" | "lift"` (steady scenes): the force on one
/// obstacle along x (drag) or y (lift), per unit depth at density 1, or its
/// coefficient `2F/(U²L)`.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ForceLossSpec {
    /// The obstacle, by its place in `[[obstacles]]` (default 0).
    #[serde(default)]
    pub obstacle: i64,
    /// `{ speed = U, length = L }`: the loss is the coefficient `2F/(U²L)`.
    pub reference: Option<ReferenceSpec>,
    /// `obstacles[k].shape` for any obstacle `k`.
    pub with_respect_to: Vec<String>,
}

/// The reference speed and length of a force coefficient.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ReferenceSpec {
    /// Speed `U`.
    pub speed: f64,
    /// Length `L`.
    pub length: f64,
}

/// Parses the `[loss]` table.
pub fn loss(table: &toml::Table) -> Result<LossSpec, SceneError> {
    let (kind, value, fail) = split_kind(table, "loss", Some("field"), &LOSS_KINDS)?;
    Ok(match kind {
        "field" => LossSpec::Field(value.try_into().map_err(fail)?),
        "drag" | "lift" => LossSpec::Force { lift: kind == "lift", spec: value.try_into().map_err(fail)? },
        other => return Err(SceneError::key("loss.kind", unknown("loss kind", other, &LOSS_KINDS))),
    })
}

/// One effect, by its `kind`.
#[derive(Debug)]
pub enum EffectSpec {
    /// `kind = "advection"`.
    Advection(AdvectionSpec),
    /// `kind = "diffusion"`.
    Diffusion(DiffusionSpec),
    /// `kind = "pressure"`.
    Pressure(PressureSpec),
    /// `kind = "buoyancy"`.
    Buoyancy(BuoyancySpec),
    /// `kind = "force"`.
    Force(ForceSpec),
    /// `kind = "inflow"`.
    Inflow(InflowSpec),
    /// `kind = "navier_stokes"`.
    NavierStokes(NavierStokesSpec),
}

/// The effect kinds, as written.
pub const EFFECT_KINDS: [&str; 7] = ["advection", "diffusion", "pressure", "buoyancy", "force", "inflow", "navier_stokes"];

/// `kind = "navier_stokes"`: one step of incompressible Navier–Stokes on the
/// velocity (`diffsim::navier_stokes::NavierStokes`): advection of the
/// velocity by itself, viscosity, projection, split into stable sub-steps,
/// the domain's sides and obstacles.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct NavierStokesSpec {
    /// Kinematic viscosity ν (per unit time, unit cells).
    pub viscosity: f64,
    /// `"maccormack"` (default) or `"semi_lagrangian"`.
    #[serde(default = "maccormack")]
    pub scheme: String,
    /// MacCormack's limiter (default off: the scheme's second order).
    #[serde(default)]
    pub limiter: bool,
    /// `"explicit"` (default: its limit enters the sub-steps) or `"implicit"`.
    #[serde(default = "explicit")]
    pub viscous: String,
    /// Relative tolerance of the solves: the projection's and the implicit
    /// viscosity's (default 1e-8).
    #[serde(default = "tolerance")]
    pub tolerance: f64,
    /// Iteration cap of each solve (default 1000).
    #[serde(default = "max_iterations")]
    pub max_iterations: i64,
    /// The projection's preconditioner: `"multigrid"` (default), `"mic0"`
    /// or `"none"`.
    #[serde(default = "multigrid")]
    pub preconditioner: String,
}

fn maccormack() -> String {
    "maccormack".into()
}

fn explicit() -> String {
    "explicit".into()
}

/// `kind = "advection"`.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AdvectionSpec {
    /// `"semi_lagrangian"` (default), `"maccormack"` or `"upwind"` (smoke only).
    #[serde(default = "semi_lagrangian")]
    pub scheme: String,
    /// MacCormack's limiter (default on).
    #[serde(default = "yes")]
    pub limiter: bool,
    /// The fields advected (default both).
    #[serde(default = "both_fields")]
    pub fields: Vec<String>,
}

fn semi_lagrangian() -> String {
    "semi_lagrangian".into()
}

fn yes() -> bool {
    true
}

fn both_fields() -> Vec<String> {
    vec!["smoke".into(), "velocity".into()]
}

/// `kind = "diffusion"`.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DiffusionSpec {
    /// The fields diffused (`"smoke"`, `"velocity"`: viscosity).
    pub fields: Vec<String>,
    /// Diffusivity / kinematic viscosity ν (per unit time; κ = ν·dt).
    pub viscosity: f64,
    /// `"implicit"` (default) or `"explicit"`.
    #[serde(default = "implicit")]
    pub scheme: String,
    /// Relative tolerance of the implicit solve (default 1e-8).
    #[serde(default = "tolerance")]
    pub tolerance: f64,
    /// Iteration cap of the implicit solve (default 1000).
    #[serde(default = "max_iterations")]
    pub max_iterations: i64,
}

fn implicit() -> String {
    "implicit".into()
}

fn tolerance() -> f64 {
    1e-8
}

fn max_iterations() -> i64 {
    1000
}

/// `kind = "pressure"`.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PressureSpec {
    /// Relative tolerance on the true residual (default 1e-8).
    #[serde(default = "tolerance")]
    pub tolerance: f64,
    /// Iteration cap (default 1000).
    #[serde(default = "max_iterations")]
    pub max_iterations: i64,
    /// `"multigrid"` (default), `"mic0"` or `"none"` (closed box without
    /// obstacles; other boxes use plain CG).
    #[serde(default = "multigrid")]
    pub preconditioner: String,
}

fn multigrid() -> String {
    "multigrid".into()
}

/// `kind = "buoyancy"`.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BuoyancySpec {
    /// The field that lifts (`"smoke"`).
    #[serde(default = "smoke")]
    pub field: String,
    /// Acceleration per unit of smoke (along +y; negative: down).
    pub coefficient: f64,
    /// The axis it acts along (3D: `"x"`, `"y"` or `"z"`; default `"y"`).
    #[serde(default = "y_axis")]
    pub axis: String,
}

fn y_axis() -> String {
    "y".into()
}

fn smoke() -> String {
    "smoke".into()
}

/// `kind = "force"`: an acceleration on the velocity, uniform at the start
/// (as a control, it may differ per face and step).
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ForceSpec {
    /// The acceleration, x first (one entry per axis).
    pub value: Vec<f64>,
}

/// `kind = "inflow"`: a region whose smoke and velocity are set every step.
#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct InflowSpec {
    /// The region: `{ box = { lower, upper } }` (cells whose centre lies inside).
    pub region: ShapeSpec,
    /// The smoke value set there.
    #[serde(default)]
    pub smoke: f64,
    /// The velocity set there, x first (one entry per axis; default zero).
    #[serde(default)]
    pub velocity: Vec<f64>,
}

/// Parses the `k`-th `[[effects]]` table.
pub fn effect(k: usize, table: &toml::Table) -> Result<EffectSpec, SceneError> {
    let at = format!("effects[{k}]");
    let (kind, value, fail) = split_kind(table, &at, None, &EFFECT_KINDS)?;
    Ok(match kind {
        "advection" => EffectSpec::Advection(value.try_into().map_err(fail)?),
        "diffusion" => EffectSpec::Diffusion(value.try_into().map_err(fail)?),
        "pressure" => EffectSpec::Pressure(value.try_into().map_err(fail)?),
        "buoyancy" => EffectSpec::Buoyancy(value.try_into().map_err(fail)?),
        "force" => EffectSpec::Force(value.try_into().map_err(fail)?),
        "inflow" => EffectSpec::Inflow(value.try_into().map_err(fail)?),
        "navier_stokes" => EffectSpec::NavierStokes(value.try_into().map_err(fail)?),
        other => return Err(SceneError::key(format!("{at}.kind"), unknown("effect kind", other, &EFFECT_KINDS))),
    })
}

/// A table chosen by its `kind` key (`default` when absent, else an error
/// listing `kinds`): the kind, the other keys, and the error for them.
fn split_kind<'a>(
    table: &'a toml::Table,
    at: &str,
    default: Option<&'a str>,
    kinds: &[&str],
) -> Result<(&'a str, toml::Value, impl Fn(toml::de::Error) -> SceneError + use<'a>), SceneError> {
    let kind = match (table.get("kind"), default) {
        (Some(toml::Value::String(s)), _) => s.as_str(),
        (Some(_), _) => return Err(SceneError::key(format!("{at}.kind"), "must be a string")),
        (None, Some(d)) => d,
        (None, None) => return Err(SceneError::key(format!("{at}.kind"), format!("missing; one of {}", kinds.join(", ")))),
    };
    let mut rest = table.clone();
    rest.remove("kind");
    let at = at.to_string();
    Ok((kind, toml::Value::Table(rest), move |e: toml::de::Error| match crate::words::plain(&e.to_string()) {
        (Some(key), text) => SceneError::key(format!("{at}.{key}"), text),
        (None, text) => SceneError::key(format!("{at} (kind = \"{kind}\")"), text),
    }))
}

use crate::words::unknown;
