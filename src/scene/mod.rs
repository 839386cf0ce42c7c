//! Scenes: a TOML file declares a domain (a line or a box), its boundary,
//! the initial fields, obstacles, the effects that run each step (in the
//! order listed) and optionally a loss; [`Scene::load`] checks it and builds
//! the step as a [`Chain`] of exactly the declared effects. An effect that
//! is not declared is never constructed, so it allocates and costs nothing
//! ([`crate::op::count`] shows that none of its code runs).
//!
//! A scene with `[steady]` in place of `[time]` is a [`SteadyScene`]: the
//! steady viscous flow around its obstacles, with a drag or lift loss
//! differentiated with respect to their shapes. [`AnyScene::load`] reads
//! either kind.
//!
//! Every key is documented in `docs/scenes.md`; every mistake is a
//! [`SceneError`] naming the key and, where the file has it, the line.

mod build;
mod init;
pub mod spec;
mod steady;
mod value;

pub use init::npy_values;
pub use steady::{ForceLoss, SteadyGradient, SteadyRun, SteadyScene, param_names};

use std::ops::Range;
use std::path::Path;

use diffsim_solvers::smoke::MacGrid;

use crate::op::Chain;
use crate::rollout::{AtSteps, Checkpointing, Loss, Rollout, RolloutError};

/// The largest scene file read (a scene's arrays belong in `.npy` files).
pub const MAX_SCENE_BYTES: u64 = 1 << 20;

/// A scene that cannot be read or built.
#[derive(Debug, thiserror::Error)]
pub enum SceneError {
    /// The file could not be read (or is not a regular file, or is larger
    /// than [`MAX_SCENE_BYTES`]).
    #[error("scene: {0}")]
    Read(#[from] crate::files::ReadError),
    /// The TOML is malformed or a value has the wrong type (the message
    /// names the line and key).
    #[error("scene: {0}")]
    Syntax(String),
    /// A key has a value the scene cannot use.
    #[error("scene: {}`{key}`: {reason}", line.map(|l| format!("line {l}: ")).unwrap_or_default())]
    Key {
        /// The key, as a path (`effects[2].scheme`).
        key: String,
        /// What is wrong.
        reason: String,
        /// The line of the table the key is in, when known.
        line: Option<usize>,
    },
}

impl SceneError {
    /// An error at `key`.
    pub fn key(key: impl Into<String>, reason: impl Into<String>) -> Self {
        SceneError::Key { key: key.into(), reason: reason.into(), line: None }
    }

    /// The same error, placed at `line` unless it already has one.
    pub fn at_line(self, at: usize) -> Self {
        match self {
            SceneError::Key { key, reason, line } => SceneError::Key { key, reason, line: line.or(Some(at)) },
            e => e,
        }
    }
}

/// A field of a scene's state.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Field {
    /// A passive scalar (smoke, dye, temperature).
    Smoke,
    /// The velocity (in 1D the Burgers variable `u`).
    Velocity,
}

impl Field {
    /// The name in scene files.
    pub fn name(self) -> &'static str {
        match self {
            Field::Smoke => "smoke",
            Field::Velocity => "velocity",
        }
    }
}

/// A 1D periodic or closed line of `n` cells of width `dx`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Line {
    /// Cells.
    pub n: usize,
    /// Cell width.
    pub dx: f64,
    /// Whether the line wraps (else no flux leaves it).
    pub periodic: bool,
}

/// The domain of a scene. The state always holds both fields, smoke first
/// (`[s, u]` on a line, `[s, u, v]` in a box, `[s, u, v, w]` in a 3D box),
/// whether declared or not.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Domain {
    /// A line (1D scenes: Burgers, heat).
    Line(Line),
    /// A box of `nx × ny` unit cells with its boundary (2D).
    Box(MacGrid<2>),
    /// A closed box of `nx × ny × nz` unit cells (3D), its time step in
    /// `dt` (the advection's).
    Box3(MacGrid<3>),
}

/// One array of a field as written to `.npy`: its file-name suffix, its
/// range in the state (or parameter block) and its shape (numpy order: a 2D
/// array is `[rows = y, columns = x]`).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct Array {
    /// `""`, `"_u"`, `"_v"` or `"_w"`.
    pub suffix: &'static str,
    /// Where the values are.
    pub range: Range<usize>,
    /// Their shape.
    pub shape: Vec<u64>,
}

impl Domain {
    /// Length of the packed state.
    pub fn n_state(&self) -> usize {
        match self {
            Domain::Line(l) => 2 * l.n,
            Domain::Box(cfg) => cfg.n_state(),
            Domain::Box3(cfg) => cfg.n_state(),
        }
    }

    /// Number of axes.
    pub fn dims(&self) -> usize {
        match self {
            Domain::Line(_) => 1,
            Domain::Box(_) => 2,
            Domain::Box3(_) => 3,
        }
    }

    /// The range of `field` in the packed state.
    pub fn range(&self, field: Field) -> Range<usize> {
        let ns = match self {
            Domain::Line(l) => l.n,
            Domain::Box(cfg) => cfg.n_s(),
            Domain::Box3(cfg) => cfg.n_s(),
        };
        match field {
            Field::Smoke => 0..ns,
            Field::Velocity => ns..self.n_state(),
        }
    }

    /// The arrays `field` is written as.
    pub fn arrays(&self, field: Field) -> Vec<Array> {
        let r = self.range(field);
        match (self, field) {
            (Domain::Line(l), _) => vec![Array { suffix: "", range: r, shape: vec![l.n as u64] }],
            (Domain::Box(cfg), Field::Smoke) => vec![Array { suffix: "", range: r, shape: vec![cfg.n[1] as u64, cfg.n[0] as u64] }],
            (Domain::Box(cfg), Field::Velocity) => {
                let (nx, ny, nu) = (cfg.n[0] as u64, cfg.n[1] as u64, cfg.n_face(0));
                vec![
                    Array { suffix: "_u", range: r.start..r.start + nu, shape: vec![ny, nx + 1] },
                    Array { suffix: "_v", range: r.start + nu..r.end, shape: vec![ny + 1, nx] },
                ]
            }
            (Domain::Box3(cfg), Field::Smoke) => vec![Array { suffix: "", range: r, shape: vec![cfg.n[2] as u64, cfg.n[1] as u64, cfg.n[0] as u64] }],
            (Domain::Box3(cfg), Field::Velocity) => {
                let mut start = r.start;
                ["_u", "_v", "_w"]
                    .into_iter()
                    .enumerate()
                    .map(|(axis, suffix)| {
                        let len = cfg.n_face(axis);
                        // numpy order: z, y, x.
                        let shape = cfg.face_dims(axis).iter().rev().map(|&n| n as u64).collect();
                        start += len;
                        Array { suffix, range: start - len..start, shape }
                    })
                    .collect()
            }
        }
    }
}

/// A scene's loss: `½·Σ_{t ∈ steps} Σ (field_t − target)²`.
#[derive(Clone, Debug)]
pub struct SceneLoss {
    /// The field compared.
    pub field: Field,
    /// The target (the field's length).
    pub target: Vec<f64>,
    /// The steps with a term, ascending (1-based; default the last).
    pub steps: Vec<usize>,
    /// What the gradient is taken for, as written.
    pub with_respect_to: Vec<String>,
}

/// A parameter field that may change from step to step (a control): its
/// name and where its arrays lie in one step's parameters.
#[derive(Clone, Debug)]
pub struct Control {
    /// `force.control` or `effects[k].control`.
    pub name: String,
    /// The arrays, with ranges into one step's parameter block.
    pub arrays: Vec<Array>,
}

/// A built scene: the domain, the step, its parameters and initial state.
#[derive(Debug)]
pub struct Scene {
    /// The domain and its boundary.
    pub domain: Domain,
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
    /// Parameter fields that can vary per step.
    pub controls: Vec<Control>,
    /// The effects' names, in order (`kind` as written).
    pub effects: Vec<String>,
    /// The declared fields.
    pub fields: Vec<Field>,
    /// The packed initial state.
    pub x0: Vec<f64>,
    /// Solid cells, when there are obstacles.
    pub solid: Option<Vec<bool>>,
    /// The loss, when declared.
    pub loss: Option<SceneLoss>,
}

impl Scene {
    /// Reads and builds the scene in `path` (`.npy` paths in it are relative
    /// to its folder).
    pub fn load(path: &Path) -> Result<Scene, SceneError> {
        Self::stepped(AnyScene::load(path)?)
    }

    /// Builds a scene from its TOML text (`.npy` paths relative to the
    /// current folder).
    pub fn parse(text: &str) -> Result<Scene, SceneError> {
        Self::parse_in(text, Path::new("."))
    }

    /// Builds a scene from its TOML text, `.npy` paths relative to `dir`.
    pub fn parse_in(text: &str, dir: &Path) -> Result<Scene, SceneError> {
        Self::stepped(AnyScene::parse_in(text, dir)?)
    }

    /// The scene if it is stepped in time.
    fn stepped(scene: AnyScene) -> Result<Scene, SceneError> {
        match scene {
            AnyScene::Stepped(scene) => Ok(*scene),
            AnyScene::Steady(_) => Err(SceneError::key("steady", "a steady scene: read it with AnyScene::load")),
        }
    }

    /// The 2D grid.
    ///
    /// # Panics
    /// For a 1D or 3D scene.
    pub fn cfg(&self) -> &MacGrid<2> {
        match &self.domain {
            Domain::Box(cfg) => cfg,
            Domain::Line(_) | Domain::Box3(_) => panic!("Scene::cfg: a {}D scene has no 2D grid", self.domain.dims()),
        }
    }

    /// Whether the gradient is taken for a control, so that the rollout
    /// runs with parameters per step.
    pub fn per_step(&self) -> bool {
        self.loss.as_ref().is_some_and(|l| l.with_respect_to.iter().any(|w| self.controls.iter().any(|c| c.name == *w)))
    }

    /// The rollout's parameters: [`Scene::params`], repeated for every step
    /// when [`Scene::per_step`].
    pub fn rollout_params(&self) -> Vec<f64> {
        if self.per_step() { self.params.repeat(self.steps) } else { self.params.clone() }
    }

    /// The rollout with parameters `p` (one block, or one per step when
    /// [`Scene::per_step`]).
    pub fn rollout<'a>(&'a self, p: &'a [f64]) -> Result<Rollout<'a, Chain>, RolloutError> {
        if self.per_step() { Rollout::per_step(&self.step, p, self.steps) } else { Rollout::new(&self.step, p, self.steps) }
    }

    /// The loss as a rollout [`Loss`].
    pub fn loss_terms<'a>(&'a self, loss: &'a SceneLoss) -> impl Loss + 'a {
        let r = self.domain.range(loss.field);
        AtSteps {
            steps: loss.steps.clone(),
            f: move |_t: usize, x: &[f64], g: &mut [f64]| {
                g.fill(0.0);
                let mut value = 0.0;
                for ((g, x), t) in g[r.clone()].iter_mut().zip(&x[r.clone()]).zip(&loss.target) {
                    let d = x - t;
                    *g = d;
                    value += 0.5 * d * d;
                }
                value
            },
        }
    }

    /// The loss for initial state `x0` and parameters `p` (as
    /// [`Scene::rollout_params`]), without gradient.
    pub fn loss_value(&self, loss: &SceneLoss, x0: &[f64], p: &[f64]) -> Result<f64, RolloutError> {
        self.rollout(p)?.loss(x0, &self.loss_terms(loss))
    }

    /// The loss and its gradient with respect to every input the loss
    /// names, by the chained per-step VJPs under `mode`.
    pub fn gradient(&self, loss: &SceneLoss, mode: Checkpointing) -> Result<SceneGradient, RolloutError> {
        let p = self.rollout_params();
        let g = self.rollout(&p)?.value_and_grad(&self.x0, &self.loss_terms(loss), mode)?;
        let np = self.params.len();
        let mut inputs = Vec::new();
        for w in &loss.with_respect_to {
            let stem = grad_stem(w);
            let field = match w.as_str() {
                "smoke.init" => Some(Field::Smoke),
                "velocity.init" => Some(Field::Velocity),
                _ => None,
            };
            let arrays = if let Some(field) = field {
                self.domain.arrays(field).into_iter().map(|a| (format!("{stem}{}", a.suffix), a.shape, g.dx0[a.range].to_vec())).collect()
            } else if let Some((_, index, factor)) = self.named.iter().find(|(s, _, _)| s == w) {
                // A parameter used at every step: the sum of its per-step gradients.
                let blocks = g.dp.len() / np.max(1);
                let d: f64 = (0..blocks).map(|t| g.dp[t * np + index]).sum::<f64>() * factor;
                vec![(stem, vec![1], vec![d])]
            } else {
                let c = self.controls.iter().find(|c| c.name == *w).expect("names are checked when the scene is built");
                c.arrays
                    .iter()
                    .map(|a| {
                        let values: Vec<f64> = (0..self.steps).flat_map(|t| g.dp[t * np + a.range.start..t * np + a.range.end].iter().copied()).collect();
                        let shape = std::iter::once(self.steps as u64).chain(a.shape.iter().copied()).collect();
                        (format!("{stem}{}", a.suffix), shape, values)
                    })
                    .collect()
            };
            inputs.push(GradInput { name: w.clone(), arrays });
        }
        Ok(SceneGradient { loss: g.loss, inputs })
    }
}

/// The file stem of the gradient with respect to an input named as in
/// `with_respect_to`: `smoke.init` → `grad_smoke_init`,
/// `obstacles[0].shape` → `grad_obstacles_0_shape`.
pub fn grad_stem(name: &str) -> String {
    format!("grad_{}", name.replace(['.', '['], "_").replace(']', ""))
}

/// The files a scene file reads besides itself: every `npy = "…"` path
/// in it (initial fields, targets, masks), relative to its folder. Empty
/// when the file cannot be read (loading it reports why).
pub fn input_files(path: &Path) -> Vec<std::path::PathBuf> {
    fn walk(v: &toml::Value, npy: bool, dir: &Path, out: &mut Vec<std::path::PathBuf>) {
        match v {
            toml::Value::String(s) if npy => out.push(dir.join(s)),
            toml::Value::Array(a) => a.iter().for_each(|x| walk(x, npy, dir, out)),
            toml::Value::Table(t) => t.iter().for_each(|(k, x)| walk(x, k == "npy", dir, out)),
            _ => {}
        }
    }
    let dir = path.parent().unwrap_or(Path::new("."));
    let mut out = Vec::new();
    if let Ok(table) = crate::files::read_text(path, MAX_SCENE_BYTES, "scene file").map(|t| t.parse::<toml::Table>()) {
        table.iter().flat_map(|t| t.iter()).for_each(|(k, v)| walk(v, k == "npy", dir, &mut out));
    }
    out
}

/// A scene of either kind.
#[derive(Debug)]
pub enum AnyScene {
    /// Stepped in time (`[time]`).
    Stepped(Box<Scene>),
    /// A steady flow (`[steady]`).
    Steady(Box<SteadyScene>),
}

impl AnyScene {
    /// Reads and builds the scene in `path` (`.npy` paths in it are relative
    /// to its folder).
    pub fn load(path: &Path) -> Result<AnyScene, SceneError> {
        let text = crate::files::read_text(path, MAX_SCENE_BYTES, "scene file")?;
        Self::parse_in(&text, path.parent().unwrap_or(Path::new(".")))
    }

    /// Builds a scene from its TOML text, `.npy` paths relative to `dir`.
    pub fn parse_in(text: &str, dir: &Path) -> Result<AnyScene, SceneError> {
        let file: spec::SceneFile = toml::from_str(text).map_err(|e| SceneError::Syntax(crate::words::toml_error(&e, text)))?;
        if file.steady.is_some() {
            steady::build(file, text).map(|s| AnyScene::Steady(Box::new(s)))
        } else {
            build::build(file, text, dir).map(|s| AnyScene::Stepped(Box::new(s)))
        }
    }
}

/// The gradient of a scene's loss.
#[derive(Clone, Debug)]
pub struct SceneGradient {
    /// The loss.
    pub loss: f64,
    /// One entry per name in `with_respect_to`, in order.
    pub inputs: Vec<GradInput>,
}

/// The gradient with respect to one input, as arrays.
#[derive(Clone, Debug)]
pub struct GradInput {
    /// The input, as written in `with_respect_to`.
    pub name: String,
    /// File stem (`grad_smoke_init`, `grad_velocity_init_u`, …), shape
    /// (numpy order; a control has the steps first) and values.
    pub arrays: Vec<(String, Vec<u64>, Vec<f64>)>,
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
            // The effect that failed, by its place in the file (one
            // operator per effect).
            let errors: Vec<(usize, crate::op::OpError)> = self.step.ops().iter().enumerate().filter_map(|(e, op)| op.take_error().map(|x| (e, x))).collect();
            if let Some((e, error)) = errors.into_iter().next() {
                let effect = format!("effects[{e}] ({})", self.effects.get(e).map_or("?", String::as_str));
                return Err(RunError::Operator { step: k, effect, error });
            }
            if let Some(at) = y.iter().position(|v| !v.is_finite()) {
                let field = if self.domain.range(Field::Smoke).contains(&at) { "smoke" } else { "velocity" };
                return Err(RunError::NonFinite { step: k, field, effect: self.non_finite_effect(&x) });
            }
            std::mem::swap(&mut x, &mut y);
            frame(k, &x);
        }
        Ok(x)
    }
}

impl Scene {
    /// The first effect whose output is not finite when the step runs from
    /// `x`, as `effects[k] (kind)` (only called once a step went wrong: it
    /// replays the step effect by effect).
    fn non_finite_effect(&self, x: &[f64]) -> String {
        let mut state = x.to_vec();
        for (k, op) in self.step.ops().iter().enumerate() {
            let mut out = vec![0.0; op.n_out()];
            op.forward(&state, &self.params[self.step.param_range(k)], &mut out);
            op.take_error();
            if out.iter().any(|v| !v.is_finite()) {
                return format!("effects[{k}] ({})", self.effects.get(k).map_or("?", String::as_str));
            }
            state = out;
        }
        "the step".to_string()
    }
}

/// A scene run that failed.
#[derive(Clone, Debug, PartialEq, thiserror::Error)]
pub enum RunError {
    /// An effect failed (a solve that did not converge, an unstable step).
    #[error("step {step}: {effect}: {error}")]
    Operator {
        /// The step (1-based).
        step: usize,
        /// Which effect, as `effects[k] (kind)`.
        effect: String,
        /// What failed.
        error: crate::op::OpError,
    },
    /// A value became NaN or infinite.
    #[error("step {step}: {effect}: the {field} became non-finite (its values left f64's range, or an effect divided by zero)")]
    NonFinite {
        /// The step (1-based).
        step: usize,
        /// `"smoke"` or `"velocity"`.
        field: &'static str,
        /// The first effect whose output was not finite, as
        /// `effects[k] (kind)`.
        effect: String,
    },
}
