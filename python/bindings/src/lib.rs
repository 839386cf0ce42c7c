//! `diffsim._diffsim`: diffsim's operators, benchmark problems and scenes
//! for Python, on NumPy arrays (float64). The Python package `diffsim`
//! re-exports it with docstrings and type hints; `diffsim.jax` wraps the
//! operators as JAX functions with custom VJPs.
//!
//! Every input is checked here before any generated code runs (a panic
//! inside generated code cannot be caught); errors become Python
//! exceptions (`diffsim.DiffsimError`, a `ValueError`, for inputs that
//! cannot be used; `diffsim.SimulationError`, a `RuntimeError`, for a run
//! that failed); a panic becomes `diffsim.InternalError`. Calls release the
//! GIL; the long ones (rollouts, scenes, checks) run on a worker thread
//! and return at Ctrl-C with `KeyboardInterrupt` (the worker finishes
//! alone and its result is dropped).

use std::path::PathBuf;
use std::sync::Arc;
use std::time::Duration;

use numpy::{IxDyn, PyArray1, PyArrayDyn, PyArrayMethods, PyReadonlyArrayDyn};
use pyo3::create_exception;
use pyo3::exceptions::{PyRuntimeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::PyDict;
use rayon::prelude::*;

mod ffi;

use diffsim::check::{CheckOptions, check_all};
use diffsim::op::{Jvp, Vjp};
use diffsim::problems::burgers::{BurgersEnzyme, P1};
use diffsim::rollout::{Checkpointing, Rollout, RolloutLoss, Wrt};
use diffsim::scene::{AnyScene, Scene};

create_exception!(_diffsim, DiffsimError, PyValueError, "An input diffsim cannot use: a malformed scene, a bad argument, an array of the wrong shape.");
create_exception!(_diffsim, SimulationError, PyRuntimeError, "A simulation or gradient that failed: a non-finite state, a diverging solve.");
create_exception!(_diffsim, InternalError, PyRuntimeError, "A panic inside diffsim (a bug): the message says where.");

/// Why a call failed, before it becomes a Python exception (made without
/// the GIL, on any thread).
enum Failure {
    Input(String),
    Simulation(String),
    Panic(String),
}

impl From<Failure> for PyErr {
    fn from(f: Failure) -> PyErr {
        match f {
            Failure::Input(m) => DiffsimError::new_err(m),
            Failure::Simulation(m) => SimulationError::new_err(m),
            Failure::Panic(m) => InternalError::new_err(format!("diffsim panicked: {m}")),
        }
    }
}

fn input(m: impl Into<String>) -> Failure {
    Failure::Input(m.into())
}

fn simulation(e: impl std::fmt::Display) -> Failure {
    Failure::Simulation(e.to_string())
}

fn panic_message(p: Box<dyn std::any::Any + Send>) -> String {
    p.downcast_ref::<String>().cloned().or_else(|| p.downcast_ref::<&str>().map(|s| s.to_string())).unwrap_or_else(|| "(no message)".into())
}

/// Runs `f` without the GIL on this thread (a short call); a panic is an
/// exception.
fn quick<T: Send>(py: Python<'_>, f: impl FnOnce() -> Result<T, Failure> + Send) -> PyResult<T> {
    py.detach(|| std::panic::catch_unwind(std::panic::AssertUnwindSafe(f)).unwrap_or_else(|p| Err(Failure::Panic(panic_message(p))))).map_err(PyErr::from)
}

/// Runs `f` on a worker thread without the GIL, checking for Ctrl-C every
/// 20 ms: a long call that Python can interrupt.
fn interruptible<T: Send + 'static>(py: Python<'_>, f: impl FnOnce() -> Result<T, Failure> + Send + 'static) -> PyResult<T> {
    let (tx, rx) = std::sync::mpsc::channel();
    // Waited on without the GIL: shared with that closure by reference.
    let rx = std::sync::Mutex::new(rx);
    std::thread::spawn(move || {
        let r = std::panic::catch_unwind(std::panic::AssertUnwindSafe(f)).unwrap_or_else(|p| Err(Failure::Panic(panic_message(p))));
        let _ = tx.send(r);
    });
    loop {
        match py.detach(|| rx.lock().unwrap_or_else(|e| e.into_inner()).recv_timeout(Duration::from_millis(20))) {
            Ok(r) => return r.map_err(PyErr::from),
            Err(std::sync::mpsc::RecvTimeoutError::Timeout) => py.check_signals()?,
            Err(std::sync::mpsc::RecvTimeoutError::Disconnected) => return Err(InternalError::new_err("the worker thread ended without a result")),
        }
    }
}

/// Two arrays returned together (a VJP's `dx, dp`, a JVP's `y, ty`).
type Pair<'py> = (Bound<'py, PyArrayDyn<f64>>, Bound<'py, PyArrayDyn<f64>>);

/// An array read into C order: its shape and values.
struct Array {
    shape: Vec<usize>,
    values: Vec<f64>,
}

fn read(a: &PyReadonlyArrayDyn<'_, f64>) -> Array {
    let view = a.as_array();
    // A C-contiguous array is one copy; any other layout is read in order.
    let values = a.as_slice().map_or_else(|_| view.iter().copied().collect(), <[f64]>::to_vec);
    Array { shape: view.shape().to_vec(), values }
}

fn to_numpy<'py>(py: Python<'py>, shape: &[usize], values: Vec<f64>) -> PyResult<Bound<'py, PyArrayDyn<f64>>> {
    PyArray1::from_vec(py, values).reshape(IxDyn(shape))
}

/// The leading (batch) dimensions of `a`, whose last axis must be `n`
/// long (`what` names the argument in the message).
fn batch_of(a: &Array, n: usize, what: &str) -> Result<Vec<usize>, Failure> {
    match a.shape.split_last() {
        Some((&last, lead)) if last == n => Ok(lead.to_vec()),
        _ if n == 0 && a.values.is_empty() => Ok(a.shape.get(..a.shape.len().saturating_sub(1)).unwrap_or(&[]).to_vec()),
        _ => Err(input(format!("{what} has shape {:?}; its last axis must have length {n}", a.shape))),
    }
}

fn finite(a: &Array, what: &str) -> Result<(), Failure> {
    match a.values.iter().position(|v| !v.is_finite()) {
        Some(i) => Err(input(format!("{what} holds a non-finite value ({}) at flat index {i}", a.values[i]))),
        None => Ok(()),
    }
}

/// An operator as Python sees it: sizes, forward, VJP, JVP, checks, over
/// batches of inputs.
trait PyOp: Send + Sync {
    fn sizes(&self) -> (usize, usize, usize);
    fn forward(&self, x: &[f64], p: &[f64], y: &mut [f64]) -> Result<(), Failure>;
    /// `dx = J_xᵀ·dy`, `dp = J_pᵀ·dy` (overwritten).
    fn vjp(&self, x: &[f64], p: &[f64], dy: &[f64], dx: &mut [f64], dp: &mut [f64]) -> Result<(), Failure>;
    fn jvp(&self, x: &[f64], p: &[f64], tx: &[f64], tp: &[f64], y: &mut [f64], ty: &mut [f64]) -> Result<(), Failure>;
    fn check(&self, x: &[f64], p: &[f64]) -> Result<(&'static str, String), Failure>;
    /// A whole rollout or scene per element (rather than one step): worth
    /// a thread per element even in small batches.
    fn heavy(&self) -> bool {
        false
    }
}

/// Below this many state values per call, a batch runs on the calling
/// thread: waking rayon's workers from JAX's callback thread costs more
/// (measured: 85 µs against 20 µs for 32 steps of 32 cells).
const PARALLEL_FROM: usize = 1 << 16;

/// Whether a batch of `count` elements is worth rayon's threads.
fn parallel(op: &dyn PyOp, count: usize) -> bool {
    count > 1 && (op.heavy() || count * op.sizes().0 >= PARALLEL_FROM)
}

/// `f(k)` for every element `k < count`, in parallel when the work is large.
fn over_batch<T: Send>(op: &dyn PyOp, count: usize, f: impl Fn(usize) -> Result<T, Failure> + Sync + Send) -> Result<Vec<T>, Failure> {
    if parallel(op, count) { (0..count).into_par_iter().map(f).collect() } else { (0..count).map(f).collect() }
}

/// `pass`, `fail`, or `inconclusive` (a check that met a kink and could
/// not decide: not a failure).
fn verdict(r: &diffsim::check::FullReport) -> &'static str {
    if r.passed() {
        "pass"
    } else if r.failed() {
        "fail"
    } else {
        "inconclusive"
    }
}

/// A diffsim step operator (no state of its own between calls).
struct StepOp<O>(O);

impl<O: Vjp + Jvp + Send + Sync> PyOp for StepOp<O> {
    fn sizes(&self) -> (usize, usize, usize) {
        (self.0.n_in(), self.0.n_out(), self.0.n_params())
    }
    fn forward(&self, x: &[f64], p: &[f64], y: &mut [f64]) -> Result<(), Failure> {
        self.0.forward(x, p, y);
        self.0.take_error().map_or(Ok(()), |e| Err(simulation(e)))
    }
    fn vjp(&self, x: &[f64], p: &[f64], dy: &[f64], dx: &mut [f64], dp: &mut [f64]) -> Result<(), Failure> {
        dx.fill(0.0);
        dp.fill(0.0);
        let mut dy = dy.to_vec();
        self.0.vjp(x, p, &mut dy, dx, dp);
        self.0.take_error().map_or(Ok(()), |e| Err(simulation(e)))
    }
    fn jvp(&self, x: &[f64], p: &[f64], tx: &[f64], tp: &[f64], y: &mut [f64], ty: &mut [f64]) -> Result<(), Failure> {
        self.0.jvp(x, p, tx, tp, y, ty);
        self.0.take_error().map_or(Ok(()), |e| Err(simulation(e)))
    }
    fn check(&self, x: &[f64], p: &[f64]) -> Result<(&'static str, String), Failure> {
        let r = check_all(&self.0, x, p, &CheckOptions::default());
        Ok((verdict(&r), r.to_string()))
    }
}

/// P1's loss `L(u_0) = ½·dx·Σ (u_T − u*)²` as an operator of `u_0` (one
/// output), through the whole rollout with the Enzyme-generated step VJPs
/// (periodic √T checkpointing).
struct P1Loss {
    problem: P1,
}

impl P1Loss {
    fn at(&self, x: &[f64]) -> P1 {
        P1 { u0: x.to_vec(), target: self.problem.target.clone(), ..self.problem }
    }
}

impl PyOp for P1Loss {
    fn heavy(&self) -> bool {
        true
    }
    fn sizes(&self) -> (usize, usize, usize) {
        (self.problem.cfg.n, 1, 0)
    }
    fn forward(&self, x: &[f64], _p: &[f64], y: &mut [f64]) -> Result<(), Failure> {
        y[0] = self.at(x).value().map_err(simulation)?;
        Ok(())
    }
    fn vjp(&self, x: &[f64], _p: &[f64], dy: &[f64], dx: &mut [f64], _dp: &mut [f64]) -> Result<(), Failure> {
        let g = self.at(x).grad_enzyme(Checkpointing::periodic_sqrt(self.problem.steps)).map_err(simulation)?;
        for (d, g) in dx.iter_mut().zip(&g.dx0) {
            *d = dy[0] * g;
        }
        Ok(())
    }
    fn jvp(&self, x: &[f64], p: &[f64], tx: &[f64], tp: &[f64], y: &mut [f64], ty: &mut [f64]) -> Result<(), Failure> {
        // A rollout that fails is a simulation error, not the panic of
        // RolloutLoss's JVP.
        self.forward(x, p, y)?;
        let step = BurgersEnzyme(self.problem.cfg);
        let rollout = Rollout::new(&step, &[], self.problem.steps).map_err(simulation)?;
        let loss = self.problem.loss();
        let op = RolloutLoss::new(rollout, x, &loss, Checkpointing::Store, Wrt::X0).map_err(simulation)?;
        op.jvp(x, p, tx, tp, y, ty);
        Ok(())
    }
    fn check(&self, x: &[f64], _p: &[f64]) -> Result<(&'static str, String), Failure> {
        let step = BurgersEnzyme(self.problem.cfg);
        let rollout = Rollout::new(&step, &[], self.problem.steps).map_err(simulation)?;
        let loss = self.problem.loss();
        let op = RolloutLoss::new(rollout, x, &loss, Checkpointing::periodic_sqrt(self.problem.steps), Wrt::X0).map_err(simulation)?;
        let r = check_all(&op, x, &[], &CheckOptions::default());
        Ok((verdict(&r), r.to_string()))
    }
}

/// A smoke benchmark's loss (P2, P4) as an operator of the packed initial
/// state (one output): the rollout forward, its VJP through Enzyme's step
/// adjoints and the implicit adjoint of the pressure solves. The problem
/// owns solver buffers: one call at a time.
struct SmokeLoss<S> {
    problem: std::sync::Mutex<diffsim::problems::SmokeBenchmark<S>>,
    n: usize,
}

impl<S: Vjp + Jvp + Send> PyOp for SmokeLoss<S> {
    fn heavy(&self) -> bool {
        true
    }
    fn sizes(&self) -> (usize, usize, usize) {
        (self.n, 1, 0)
    }
    fn forward(&self, x: &[f64], _p: &[f64], y: &mut [f64]) -> Result<(), Failure> {
        let mut b = self.problem.lock().unwrap_or_else(|e| e.into_inner());
        b.x0.copy_from_slice(x);
        y[0] = b.value().map_err(simulation)?;
        Ok(())
    }
    fn vjp(&self, x: &[f64], _p: &[f64], dy: &[f64], dx: &mut [f64], _dp: &mut [f64]) -> Result<(), Failure> {
        let mut b = self.problem.lock().unwrap_or_else(|e| e.into_inner());
        b.x0.copy_from_slice(x);
        let g = b.grad_in(&mut diffsim::rollout::Workspace::default(), Checkpointing::periodic_sqrt(b.steps)).map_err(simulation)?;
        for (d, g) in dx.iter_mut().zip(&g.dx0) {
            *d = dy[0] * g;
        }
        Ok(())
    }
    fn jvp(&self, x: &[f64], p: &[f64], tx: &[f64], tp: &[f64], y: &mut [f64], ty: &mut [f64]) -> Result<(), Failure> {
        self.forward(x, p, y)?;
        let b = self.problem.lock().unwrap_or_else(|e| e.into_inner());
        let loss = b.loss();
        let op = RolloutLoss::new(Rollout::new(&b.step, &[], b.steps).map_err(simulation)?, x, &loss, Checkpointing::Store, Wrt::X0).map_err(simulation)?;
        op.jvp(x, p, tx, tp, y, ty);
        Ok(())
    }
    fn check(&self, x: &[f64], _p: &[f64]) -> Result<(&'static str, String), Failure> {
        let b = self.problem.lock().unwrap_or_else(|e| e.into_inner());
        let loss = b.loss();
        let op = RolloutLoss::new(Rollout::new(&b.step, &[], b.steps).map_err(simulation)?, x, &loss, Checkpointing::periodic_sqrt(b.steps), Wrt::X0)
            .map_err(simulation)?;
        let r = check_all(&op, x, &[], &CheckOptions::default());
        Ok((verdict(&r), r.to_string()))
    }
}

/// A smoke benchmark's data as a dict: `{"x0", "target", "steps"}`.
fn smoke_problem<'py, S>(py: Python<'py>, b: &diffsim::problems::SmokeBenchmark<S>) -> PyResult<Bound<'py, PyDict>> {
    let d = PyDict::new(py);
    d.set_item("x0", PyArray1::from_vec(py, b.x0.clone()))?;
    d.set_item("target", PyArray1::from_vec(py, b.target.clone()))?;
    d.set_item("steps", b.steps)?;
    Ok(d)
}

fn smoke_sizes(what: &str, n: usize, steps: usize, max: usize) -> PyResult<()> {
    if !(4..=max).contains(&n) || steps < 1 {
        return Err(DiffsimError::new_err(format!("{what} needs 4 ≤ n ≤ {max} and steps ≥ 1, got n = {n}, steps = {steps}")));
    }
    Ok(())
}

fn p2(n: usize, steps: usize) -> PyResult<diffsim::problems::smoke::P2> {
    smoke_sizes("P2", n, steps, 1024)?;
    Ok(diffsim::problems::smoke::P2::new(n, steps, diffsim_solvers::smoke::Preconditioner::Multigrid))
}

fn p4(n: usize, steps: usize) -> PyResult<diffsim::problems::smoke3d::P4> {
    smoke_sizes("P4", n, steps, 256)?;
    Ok(diffsim::problems::smoke3d::P4::new(n, steps, diffsim_solvers::smoke::Preconditioner::Multigrid))
}

/// P2 of the shared benchmarks (2D smoke, `n × n`, `steps` steps):
/// `{"x0": packed initial state, "target": target smoke, "steps"}`.
#[pyfunction]
fn p2_problem<'py>(py: Python<'py>, n: usize, steps: usize) -> PyResult<Bound<'py, PyDict>> {
    smoke_problem(py, &p2(n, steps)?)
}

/// P2's loss `½·Σ (s_T − s*)²` as an operator of the packed initial state.
#[pyfunction]
fn p2_loss(n: usize, steps: usize) -> PyResult<Operator> {
    let b = p2(n, steps)?;
    let size = b.x0.len();
    Ok(Operator::new(Arc::new(SmokeLoss { problem: std::sync::Mutex::new(b), n: size }), format!("p2_loss(n={n}, steps={steps})")))
}

/// P4 of the shared benchmarks (3D smoke, `n³`, `steps` steps), as
/// `p2_problem`.
#[pyfunction]
fn p4_problem<'py>(py: Python<'py>, n: usize, steps: usize) -> PyResult<Bound<'py, PyDict>> {
    smoke_problem(py, &p4(n, steps)?)
}

/// P4's loss as an operator of the packed initial state.
#[pyfunction]
fn p4_loss(n: usize, steps: usize) -> PyResult<Operator> {
    let b = p4(n, steps)?;
    let size = b.x0.len();
    Ok(Operator::new(Arc::new(SmokeLoss { problem: std::sync::Mutex::new(b), n: size }), format!("p4_loss(n={n}, steps={steps})")))
}

/// A diffsim operator: `y = f(x, p)` with its VJP and JVP, all computed by
/// diffsim. `x` may have leading batch axes (`[..., n_in]`), evaluated in
/// parallel; `p` is shared (`[n_params]`) or batched like `x`.
#[pyclass(frozen, module = "diffsim._diffsim")]
struct Operator {
    op: Arc<dyn PyOp>,
    name: String,
    /// Its id in the FFI registry, once handed to XLA.
    ffi_id: std::sync::OnceLock<usize>,
}

/// `x` and `p` checked: the batch shape and whether `p` is batched.
fn inputs(op: &dyn PyOp, x: &Array, p: &Array) -> Result<(Vec<usize>, bool), Failure> {
    let (n_in, _, n_params) = op.sizes();
    let batch = batch_of(x, n_in, "x")?;
    finite(x, "x")?;
    finite(p, "p")?;
    let p_batched = p.shape.len() > 1;
    if p_batched {
        let pb = batch_of(p, n_params, "p")?;
        if pb != batch {
            return Err(input(format!("p has batch shape {pb:?} but x has {batch:?}")));
        }
    } else if p.values.len() != n_params {
        return Err(input(format!("p has {} values; this operator has {n_params} parameters", p.values.len())));
    }
    Ok((batch, p_batched))
}

/// Applies `f(x_k, p_k)` to every batch element ([`over_batch`]).
fn per_element<T: Send>(
    op: &dyn PyOp,
    batch: &[usize],
    x: &Array,
    p: &Array,
    p_batched: bool,
    f: impl Fn(&[f64], &[f64]) -> Result<T, Failure> + Sync + Send,
) -> Result<Vec<T>, Failure> {
    let count: usize = batch.iter().product();
    let (n_in, _, n_params) = op.sizes();
    over_batch(op, count, |k| {
        let pk = if p_batched { &p.values[k * n_params..(k + 1) * n_params] } else { &p.values[..] };
        f(&x.values[k * n_in..(k + 1) * n_in], pk)
    })
}

#[pymethods]
impl Operator {
    /// Inputs per element (the state `x`).
    #[getter]
    fn n_in(&self) -> usize {
        self.op.sizes().0
    }
    /// Outputs per element.
    #[getter]
    fn n_out(&self) -> usize {
        self.op.sizes().1
    }
    /// Parameters (`p`).
    #[getter]
    fn n_params(&self) -> usize {
        self.op.sizes().2
    }
    /// What it is.
    #[getter]
    fn name(&self) -> String {
        self.name.clone()
    }

    /// The id by which compiled JAX code calls this operator through XLA's
    /// FFI (the `op_id` attribute of the targets `ffi_targets()` lists);
    /// registered on the first call.
    fn ffi_id(&self) -> usize {
        *self.ffi_id.get_or_init(|| {
            let mut registry = ffi::REGISTRY.lock().unwrap_or_else(|e| e.into_inner());
            registry.push(self.op.clone());
            registry.len() - 1
        })
    }

    fn __repr__(&self) -> String {
        let (i, o, p) = self.op.sizes();
        format!("Operator({}, n_in={i}, n_out={o}, n_params={p})", self.name)
    }

    /// `y = f(x, p)`, shape `[..., n_out]`.
    #[pyo3(signature = (x, p = None))]
    fn forward<'py>(&self, py: Python<'py>, x: PyReadonlyArrayDyn<'py, f64>, p: Option<PyReadonlyArrayDyn<'py, f64>>) -> PyResult<Bound<'py, PyArrayDyn<f64>>> {
        let (x, p) = (read(&x), p.as_ref().map_or(Array { shape: vec![0], values: vec![] }, read));
        let op = self.op.clone();
        let (batch, out) = self.call(py, move || {
            let (batch, pb) = inputs(&*op, &x, &p)?;
            let n_out = op.sizes().1;
            let ys = per_element(&*op, &batch, &x, &p, pb, |xk, pk| {
                let mut y = vec![0.0; n_out];
                op.forward(xk, pk, &mut y)?;
                Ok(y)
            })?;
            Ok((batch, ys.concat()))
        })?;
        to_numpy(py, &[batch, vec![self.op.sizes().1]].concat(), out)
    }

    /// `(dx, dp) = (J_xᵀ·dy, J_pᵀ·dy)` at `(x, p)`: `dx` of `x`'s shape, `dp`
    /// per element (`[..., n_params]`; sum over the batch for a shared `p`).
    #[pyo3(signature = (x, p, dy))]
    fn vjp<'py>(
        &self,
        py: Python<'py>,
        x: PyReadonlyArrayDyn<'py, f64>,
        p: Option<PyReadonlyArrayDyn<'py, f64>>,
        dy: PyReadonlyArrayDyn<'py, f64>,
    ) -> PyResult<Pair<'py>> {
        let (x, p, dy) = (read(&x), p.as_ref().map_or(Array { shape: vec![0], values: vec![] }, read), read(&dy));
        let op = self.op.clone();
        let (batch, dx, dp) = self.call(py, move || {
            let (batch, pb) = inputs(&*op, &x, &p)?;
            let (n_in, n_out, n_params) = op.sizes();
            if batch_of(&dy, n_out, "dy")? != batch {
                return Err(input(format!("dy has shape {:?}; expected {:?}", dy.shape, [batch.clone(), vec![n_out]].concat())));
            }
            finite(&dy, "dy")?;
            let count: usize = batch.iter().product();
            let parts = over_batch(&*op, count, |k| {
                let pk = if pb { &p.values[k * n_params..(k + 1) * n_params] } else { &p.values[..] };
                let (mut dx, mut dp) = (vec![0.0; n_in], vec![0.0; n_params]);
                op.vjp(&x.values[k * n_in..(k + 1) * n_in], pk, &dy.values[k * n_out..(k + 1) * n_out], &mut dx, &mut dp)?;
                Ok((dx, dp))
            })?;
            let (dx, dp): (Vec<Vec<f64>>, Vec<Vec<f64>>) = parts.into_iter().unzip();
            Ok((batch, dx.concat(), dp.concat()))
        })?;
        let (n_in, _, n_params) = self.op.sizes();
        Ok((to_numpy(py, &[batch.clone(), vec![n_in]].concat(), dx)?, to_numpy(py, &[batch, vec![n_params]].concat(), dp)?))
    }

    /// `(y, ty) = (f(x, p), J_x·tx + J_p·tp)`.
    #[pyo3(signature = (x, p, tx, tp = None))]
    fn jvp<'py>(
        &self,
        py: Python<'py>,
        x: PyReadonlyArrayDyn<'py, f64>,
        p: Option<PyReadonlyArrayDyn<'py, f64>>,
        tx: PyReadonlyArrayDyn<'py, f64>,
        tp: Option<PyReadonlyArrayDyn<'py, f64>>,
    ) -> PyResult<Pair<'py>> {
        let empty = || Array { shape: vec![0], values: vec![] };
        let (x, p, tx, tp) = (read(&x), p.as_ref().map_or_else(empty, read), read(&tx), tp.as_ref().map_or_else(empty, read));
        let op = self.op.clone();
        let (batch, y, ty) = self.call(py, move || {
            let (batch, pb) = inputs(&*op, &x, &p)?;
            let (n_in, n_out, n_params) = op.sizes();
            if tx.shape != x.shape {
                return Err(input(format!("tx has shape {:?}; x has {:?}", tx.shape, x.shape)));
            }
            let tp = if tp.values.is_empty() { Array { shape: p.shape.clone(), values: vec![0.0; p.values.len()] } } else { tp };
            if tp.shape != p.shape {
                return Err(input(format!("tp has shape {:?}; p has {:?}", tp.shape, p.shape)));
            }
            finite(&tx, "tx")?;
            finite(&tp, "tp")?;
            let count: usize = batch.iter().product();
            let parts = over_batch(&*op, count, |k| {
                let (pk, tpk) = if pb {
                    (&p.values[k * n_params..(k + 1) * n_params], &tp.values[k * n_params..(k + 1) * n_params])
                } else {
                    (&p.values[..], &tp.values[..])
                };
                let (mut y, mut ty) = (vec![0.0; n_out], vec![0.0; n_out]);
                let xs = k * n_in..(k + 1) * n_in;
                op.jvp(&x.values[xs.clone()], pk, &tx.values[xs], tpk, &mut y, &mut ty)?;
                Ok((y, ty))
            })?;
            let (y, ty): (Vec<Vec<f64>>, Vec<Vec<f64>>) = parts.into_iter().unzip();
            Ok((batch, y.concat(), ty.concat()))
        })?;
        let shape = [batch, vec![self.op.sizes().1]].concat();
        Ok((to_numpy(py, &shape, y)?, to_numpy(py, &shape, ty)?))
    }

    /// The three gradient checks (finite differences, Taylor remainder,
    /// dot product) at one point `(x, p)` (no batch axes): `(verdict,
    /// report)`, the verdict `"pass"`, `"fail"` or `"inconclusive"` (a
    /// kink within the steps, as a fluid at rest has: not a failure).
    #[pyo3(signature = (x, p = None))]
    fn check<'py>(&self, py: Python<'py>, x: PyReadonlyArrayDyn<'py, f64>, p: Option<PyReadonlyArrayDyn<'py, f64>>) -> PyResult<(&'static str, String)> {
        let (x, p) = (read(&x), p.as_ref().map_or(Array { shape: vec![0], values: vec![] }, read));
        let op = self.op.clone();
        interruptible(py, move || {
            let (batch, _) = inputs(&*op, &x, &p)?;
            if !batch.is_empty() {
                return Err(input(format!("check takes one point; x has batch axes {batch:?}")));
            }
            op.check(&x.values, &p.values)
        })
    }
}

impl Operator {
    /// Runs `f`: on this thread when the operator is one step, on an
    /// interruptible worker when it is a whole rollout.
    fn call<T: Send + 'static>(&self, py: Python<'_>, f: impl FnOnce() -> Result<T, Failure> + Send + 'static) -> PyResult<T> {
        if self.op.heavy() { interruptible(py, f) } else { quick(py, f) }
    }
}

impl Operator {
    fn new(op: Arc<dyn PyOp>, name: String) -> Self {
        Self { op, name, ffi_id: std::sync::OnceLock::new() }
    }
}

/// The XLA FFI targets (name, function address) that `diffsim.jax`
/// registers with `jax.ffi.register_ffi_target`.
#[pyfunction]
fn ffi_targets() -> Vec<(&'static str, usize)> {
    ffi::targets()
}

/// One step of P1's Burgers scheme (upwind advection, explicit diffusion) on
/// a periodic line of `n` cells and length `length`: `u ↦ u_next`, no
/// parameters, Enzyme's VJP.
#[pyfunction]
#[pyo3(signature = (n, dt, nu, length = std::f64::consts::TAU))]
fn burgers_step(n: usize, dt: f64, nu: f64, length: f64) -> PyResult<Operator> {
    if n < 3 {
        return Err(DiffsimError::new_err(format!("n = {n}: need at least 3 cells")));
    }
    for (name, v) in [("dt", dt), ("length", length)] {
        if !(v.is_finite() && v > 0.0) {
            return Err(DiffsimError::new_err(format!("{name} = {v}: must be positive")));
        }
    }
    if !(nu.is_finite() && nu >= 0.0) {
        return Err(DiffsimError::new_err(format!("nu = {nu}: must be zero or positive")));
    }
    let dx = length / n as f64;
    if nu > 0.0 && dt > 0.5 * dx * dx / nu {
        return Err(DiffsimError::new_err(format!("dt = {dt} is unstable for the explicit diffusion: need dt ≤ dx²/(2ν) = {}", 0.5 * dx * dx / nu)));
    }
    let cfg = diffsim_solvers::burgers::Burgers1d { n, dx, dt, nu };
    Ok(Operator::new(Arc::new(StepOp(BurgersEnzyme(cfg))), format!("burgers_step(n={n}, dt={dt}, nu={nu})")))
}

/// P1 of the shared benchmarks at `n` cells and `steps` steps:
/// `{"u0", "target", "dx", "dt", "nu"}`.
#[pyfunction]
fn p1_problem<'py>(py: Python<'py>, n: usize, steps: usize) -> PyResult<Bound<'py, PyDict>> {
    let p = p1(n, steps)?;
    let d = PyDict::new(py);
    d.set_item("u0", PyArray1::from_vec(py, p.u0.clone()))?;
    d.set_item("target", PyArray1::from_vec(py, p.target.clone()))?;
    d.set_item("dx", p.cfg.dx)?;
    d.set_item("dt", p.cfg.dt)?;
    d.set_item("nu", p.cfg.nu)?;
    d.set_item("steps", steps)?;
    Ok(d)
}

fn p1(n: usize, steps: usize) -> PyResult<P1> {
    if n < 3 || steps < 1 {
        return Err(DiffsimError::new_err(format!("P1 needs n ≥ 3 and steps ≥ 1, got n = {n}, steps = {steps}")));
    }
    Ok(P1::new(n, steps))
}

/// P1's loss as an operator of `u0` (`n_in = n`, one output, no
/// parameters): the whole rollout of `steps` steps in diffsim, its VJP
/// through Enzyme's step VJPs.
#[pyfunction]
fn p1_loss(n: usize, steps: usize) -> PyResult<Operator> {
    Ok(Operator::new(Arc::new(P1Loss { problem: p1(n, steps)? }), format!("p1_loss(n={n}, steps={steps})")))
}

/// One step of P2's smoke solver on `n × n` cells (semi-Lagrangian
/// advection, buoyancy, pressure projection by multigrid-preconditioned
/// CG): the packed state (smoke, then the face velocities) in and out.
#[pyfunction]
fn smoke_step(n: usize) -> PyResult<Operator> {
    if !(4..=1024).contains(&n) {
        return Err(DiffsimError::new_err(format!("n = {n}: need 4 ≤ n ≤ 1024")));
    }
    // One solver (with its work buffers) per thread of the batch.
    let step = diffsim::op::PerThread::new(|| diffsim::problems::smoke::P2::new(n, 1, diffsim_solvers::smoke::Preconditioner::Multigrid).step);
    Ok(Operator::new(Arc::new(StepOp(step)), format!("smoke_step(n={n})")))
}

/// A scene file, read and checked: its initial state, and the runs, losses
/// and gradients of the scene (each call builds the scene afresh from the
/// text read here).
#[pyclass(frozen, module = "diffsim._diffsim")]
struct SceneFile {
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
    fn jvp(&self, x: &[f64], p: &[f64], tx: &[f64], tp: &[f64], y: &mut [f64], ty: &mut [f64]) -> Result<(), Failure> {
        self.forward(x, p, y)?;
        let scene = build(&self.text, &self.dir)?;
        let loss = scene.loss.as_ref().ok_or_else(|| input("no [loss]"))?;
        let params = scene.rollout_params();
        let terms = scene.loss_terms(loss);
        let op = RolloutLoss::new(scene.rollout(&params).map_err(simulation)?, x, &terms, Checkpointing::Store, Wrt::X0).map_err(simulation)?;
        op.jvp(x, p, tx, tp, y, ty);
        Ok(())
    }
    fn check(&self, x: &[f64], _p: &[f64]) -> Result<(&'static str, String), Failure> {
        let scene = build(&self.text, &self.dir)?;
        let loss = scene.loss.as_ref().ok_or_else(|| input("no [loss]"))?;
        let params = scene.rollout_params();
        let terms = scene.loss_terms(loss);
        let op =
            RolloutLoss::new(scene.rollout(&params).map_err(simulation)?, x, &terms, Checkpointing::periodic_sqrt(scene.steps), Wrt::X0).map_err(simulation)?;
        let r = check_all(&op, x, &[], &CheckOptions::default());
        Ok((verdict(&r), r.to_string()))
    }
}

fn message(f: Failure) -> String {
    match f {
        Failure::Input(m) | Failure::Simulation(m) | Failure::Panic(m) => m,
    }
}

/// diffsim's Python module.
#[pymodule]
pub fn _diffsim(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add("DiffsimError", m.py().get_type::<DiffsimError>())?;
    m.add("SimulationError", m.py().get_type::<SimulationError>())?;
    m.add("InternalError", m.py().get_type::<InternalError>())?;
    m.add_class::<Operator>()?;
    m.add_class::<SceneFile>()?;
    m.add_function(wrap_pyfunction!(burgers_step, m)?)?;
    m.add_function(wrap_pyfunction!(smoke_step, m)?)?;
    m.add_function(wrap_pyfunction!(p1_problem, m)?)?;
    m.add_function(wrap_pyfunction!(p1_loss, m)?)?;
    m.add_function(wrap_pyfunction!(ffi_targets, m)?)?;
    m.add_function(wrap_pyfunction!(p2_problem, m)?)?;
    m.add_function(wrap_pyfunction!(p2_loss, m)?)?;
    m.add_function(wrap_pyfunction!(p4_problem, m)?)?;
    m.add_function(wrap_pyfunction!(p4_loss, m)?)?;
    Ok(())
}
