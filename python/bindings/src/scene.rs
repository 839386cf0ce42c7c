//! Scene files from Python: [`SceneFile`] (read and checked once, built
//! afresh per call) and a scene's loss as an operator ([`SceneLoss`]).

use std::path::PathBuf;
use std::sync::Arc;

use numpy::{PyArray1, PyArrayMethods, PyReadonlyArrayDyn};
use pyo3::prelude::*;
use pyo3::types::PyDict;

use diffsim::rollout::Checkpointing;
use diffsim::scene::{AnyScene, Scene};

use super::ops::{rollout_loss_check, rollout_loss_jvp};
use super::{DiffsimError, Failure, Operator, PyOp, finite, input, interruptible, message, read, simulation, to_numpy};

/// A scene file, read and checked: its initial state, and the runs, losses
/// and gradients of the scene (each call builds the scene afresh from the
/// text read here).
#[pyclass(frozen, module = "diffsim._diffsim")]
pub(crate) struct SceneFile {
    text: String,
    dir: PathBuf,
    path: String,
    x0: Vec<f64>,
    fields: Vec<(String, Vec<usize>, std::ops::Range<usize>)>,
    has_loss: bool,
}

fn build(text: &str, dir: &std::path::Path) -> Result<Scene, Failure> {
    match AnyScene::parse_in(text, dir).map_err(|e| input(e.to_string()))? {
        AnyScene::Stepped(s) => Ok(*s),
        AnyScene::Steady(_) => Err(input("a steady scene ([steady]) has no state stepped in time; run it with `diffsim run`")),
    }
}

#[pymethods]
impl SceneFile {
    #[new]
    fn new(path: PathBuf) -> PyResult<Self> {
        let text = diffsim::files::read_text(&path, diffsim::scene::MAX_SCENE_BYTES, "scene file").map_err(|e| DiffsimError::new_err(e.to_string()))?;
        let dir = path.parent().map_or_else(|| PathBuf::from("."), |d| d.to_path_buf());
        let scene = build(&text, &dir).map_err(|e| PyErr::from(Failure::Input(format!("{}: {}", path.display(), message(e)))))?;
        let fields = scene
            .fields
            .iter()
            .flat_map(|&f| {
                scene.domain.arrays(f).into_iter().map(move |a| (format!("{}{}", f.name(), a.suffix), a.shape.iter().map(|&s| s as usize).collect(), a.range))
            })
            .collect();
        Ok(Self { x0: scene.x0.clone(), fields, has_loss: scene.loss.is_some(), text, dir, path: path.display().to_string() })
    }

    fn __repr__(&self) -> String {
        format!("SceneFile({:?}, state of {} values)", self.path, self.x0.len())
    }

    /// The packed initial state (every field, in the order of `fields`).
    #[getter]
    fn x0<'py>(&self, py: Python<'py>) -> Bound<'py, PyArray1<f64>> {
        PyArray1::from_vec(py, self.x0.clone())
    }

    /// The fields' names in the packed state (`smoke`, `velocity_u`, …).
    #[getter]
    fn fields(&self) -> Vec<String> {
        self.fields.iter().map(|f| f.0.clone()).collect()
    }

    /// A packed state as a dict of arrays shaped as the fields.
    fn unpack<'py>(&self, py: Python<'py>, x: PyReadonlyArrayDyn<'py, f64>) -> PyResult<Bound<'py, PyDict>> {
        let x = read(&x);
        if x.values.len() != self.x0.len() {
            return Err(DiffsimError::new_err(format!("a state of this scene has {} values, got {}", self.x0.len(), x.values.len())));
        }
        let d = PyDict::new(py);
        for (name, shape, range) in &self.fields {
            d.set_item(name, to_numpy(py, shape, x.values[range.clone()].to_vec())?)?;
        }
        Ok(d)
    }

    /// Runs the scene from `x0` (default: its own initial state); returns
    /// the final fields as a dict of arrays.
    #[pyo3(signature = (x0 = None))]
    fn run<'py>(&self, py: Python<'py>, x0: Option<PyReadonlyArrayDyn<'py, f64>>) -> PyResult<Bound<'py, PyDict>> {
        let x0 = self.state(x0.as_ref())?;
        let (text, dir) = (self.text.clone(), self.dir.clone());
        let x = interruptible(py, move || {
            let mut scene = build(&text, &dir)?;
            scene.x0 = x0;
            scene.run(|_, _| {}).map_err(simulation)
        })?;
        self.unpack(py, PyArray1::from_vec(py, x).to_dyn().readonly())
    }

    /// The loss and its gradient with respect to every input the scene's
    /// `[loss]` names (`with_respect_to`): `(loss, {name: array})`, the
    /// arrays named and shaped as `diffsim grad` writes them.
    fn gradient<'py>(&self, py: Python<'py>) -> PyResult<(f64, Bound<'py, PyDict>)> {
        self.needs_loss()?;
        let (text, dir) = (self.text.clone(), self.dir.clone());
        let g = interruptible(py, move || {
            let scene = build(&text, &dir)?;
            let loss = scene.loss.as_ref().expect("checked above");
            scene.gradient(loss, Checkpointing::periodic_sqrt(scene.steps)).map_err(simulation)
        })?;
        let d = PyDict::new(py);
        for input in g.inputs {
            for (stem, shape, values) in input.arrays {
                let shape: Vec<usize> = shape.iter().map(|&s| s as usize).collect();
                d.set_item(stem.trim_start_matches("grad_"), to_numpy(py, &shape, values)?)?;
            }
        }
        Ok((g.loss, d))
    }

    /// The scene's loss as an operator of the packed initial state (`n_in`
    /// = the state's length, one output, no parameters): forward, VJP
    /// (through every step) and JVP by diffsim.
    fn loss_operator(&self) -> PyResult<Operator> {
        self.needs_loss()?;
        let op = SceneLoss { text: self.text.clone(), dir: self.dir.clone(), n: self.x0.len() };
        Ok(Operator::new(Arc::new(op), format!("scene_loss({})", self.path)))
    }
}

impl SceneFile {
    fn needs_loss(&self) -> PyResult<()> {
        if self.has_loss { Ok(()) } else { Err(DiffsimError::new_err(format!("{}: the scene has no [loss] table", self.path))) }
    }

    /// `x0` checked against the scene's state, or its own.
    fn state(&self, x0: Option<&PyReadonlyArrayDyn<'_, f64>>) -> PyResult<Vec<f64>> {
        let Some(x0) = x0 else { return Ok(self.x0.clone()) };
        let x = read(x0);
        if x.values.len() != self.x0.len() || x.shape.len() != 1 {
            return Err(DiffsimError::new_err(format!("x0 has shape {:?}; this scene's packed state has {} values", x.shape, self.x0.len())));
        }
        finite(&x, "x0")?;
        Ok(x.values)
    }
}

/// A scene's loss as an operator of its packed initial state (the scene
/// is built afresh per call: its operators stay on the calling thread).
struct SceneLoss {
    text: String,
    dir: PathBuf,
    n: usize,
}

impl PyOp for SceneLoss {
    fn heavy(&self) -> bool {
        true
    }
    fn sizes(&self) -> (usize, usize, usize) {
        (self.n, 1, 0)
    }
    fn forward(&self, x: &[f64], _p: &[f64], y: &mut [f64]) -> Result<(), Failure> {
        let scene = build(&self.text, &self.dir)?;
        let loss = scene.loss.as_ref().ok_or_else(|| input("no [loss]"))?;
        y[0] = scene.loss_value(loss, x, &scene.rollout_params()).map_err(simulation)?;
        Ok(())
    }
    fn vjp(&self, x: &[f64], _p: &[f64], dy: &[f64], dx: &mut [f64], _dp: &mut [f64]) -> Result<(), Failure> {
        let scene = build(&self.text, &self.dir)?;
        let loss = scene.loss.as_ref().ok_or_else(|| input("no [loss]"))?;
        let p = scene.rollout_params();
        let g =
            scene.rollout(&p).map_err(simulation)?.value_and_grad(x, &scene.loss_terms(loss), Checkpointing::periodic_sqrt(scene.steps)).map_err(simulation)?;
        for (d, g) in dx.iter_mut().zip(&g.dx0) {
            *d = dy[0] * g;
        }
        Ok(())
    }
    fn jvp(&self, x: &[f64], p: &[f64], tx: &[f64], _tp: &[f64], y: &mut [f64], ty: &mut [f64]) -> Result<(), Failure> {
        self.forward(x, p, y)?;
        let scene = build(&self.text, &self.dir)?;
        let loss = scene.loss.as_ref().ok_or_else(|| input("no [loss]"))?;
        let params = scene.rollout_params();
        rollout_loss_jvp(scene.rollout(&params).map_err(simulation)?, &scene.loss_terms(loss), x, tx, y, ty)
    }
    fn check(&self, x: &[f64], _p: &[f64]) -> Result<(&'static str, String), Failure> {
        let scene = build(&self.text, &self.dir)?;
        let loss = scene.loss.as_ref().ok_or_else(|| input("no [loss]"))?;
        let params = scene.rollout_params();
        rollout_loss_check(scene.rollout(&params).map_err(simulation)?, &scene.loss_terms(loss), x)
    }
}
