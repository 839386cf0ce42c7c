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
//!
//! Here: the errors, the runners (GIL, Ctrl-C), arrays in and out, the
//! [`PyOp`] contract and the `Operator` class that serves any of them.
//! [`ops`]: the solver steps and benchmark losses; [`repeat`]: any step
//! run many times as one operator; [`scene`]: scene files;
//! [`ffi`]: the same operators as XLA FFI custom calls for `diffsim.jax`.

use std::sync::Arc;
use std::time::Duration;

use numpy::{IxDyn, PyArray1, PyArrayDyn, PyArrayMethods, PyReadonlyArrayDyn};
use pyo3::create_exception;
use pyo3::exceptions::{PyRuntimeError, PyValueError};
use pyo3::prelude::*;
use rayon::prelude::*;

mod ffi;
mod ops;
mod repeat;
mod scene;

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
    /// How far from `(x, p)` along `(dx, dp)` the operator stays smooth and
    /// defined (a time step that must stay positive, say): the checks of a
    /// rollout built on it keep their steps within it.
    fn smooth_radius(&self, x: &[f64], p: &[f64], dx: &[f64], dp: &[f64]) -> f64 {
        let _ = (x, p, dx, dp);
        f64::INFINITY
    }
    /// A whole rollout or scene per element (rather than one step): worth
    /// a thread per element even in small batches.
    fn heavy(&self) -> bool {
        false
    }
    /// `steps` of this operator as one, when it knows a better way than
    /// chaining its own calls (a step on cell-centred values converts to
    /// the faces once, not at every step); `None`: the generic
    /// [`repeat::Repeated`].
    fn repeat(&self, steps: usize, mode: Option<diffsim::rollout::Checkpointing>) -> Option<Result<Arc<dyn PyOp>, Failure>> {
        let _ = (steps, mode);
        None
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

/// `y_k = f(x_k, p_b)` for every element `k`, `b = k / per` (`per`
/// consecutive elements share a block of `p`: all of them for a shared
/// `p`, one for `p` batched like `x`), written into `y`'s rows, in
/// parallel when the work is large. The Python methods and the XLA FFI
/// handlers both run batches through here.
fn forward_rows(op: &dyn PyOp, x: &[f64], p: &[f64], per: usize, y: &mut [f64]) -> Result<(), Failure> {
    let (n_in, n_out, n_params) = op.sizes();
    let one = |(k, yk): (usize, &mut [f64])| {
        let b = k / per;
        op.forward(&x[k * n_in..(k + 1) * n_in], &p[b * n_params..(b + 1) * n_params], yk)
    };
    if parallel(op, y.len() / n_out.max(1)) {
        y.par_chunks_mut(n_out.max(1)).enumerate().try_for_each(one)
    } else {
        y.chunks_mut(n_out.max(1)).enumerate().try_for_each(one)
    }
}

/// `(dx_k, dp_k) = (J_xᵀ·dy_k, J_pᵀ·dy_k)` for every element, as
/// [`forward_rows`].
fn vjp_rows(op: &dyn PyOp, x: &[f64], p: &[f64], per: usize, dy: &[f64], dx: &mut [f64], dp: &mut [f64]) -> Result<(), Failure> {
    let (n_in, n_out, n_params) = op.sizes();
    let count = dx.len() / n_in.max(1);
    // `dp`'s rows; with no parameters, empty rows (chunks of an empty
    // slice would be none at all).
    let mut dp_rows: Vec<&mut [f64]> = if n_params == 0 { (0..count).map(|_| &mut [][..]).collect() } else { dp.chunks_mut(n_params).collect() };
    let one = |(k, (dxk, dpk)): (usize, (&mut [f64], &mut &mut [f64]))| {
        let b = k / per;
        op.vjp(&x[k * n_in..(k + 1) * n_in], &p[b * n_params..(b + 1) * n_params], &dy[k * n_out..(k + 1) * n_out], dxk, dpk)
    };
    if parallel(op, count) {
        dx.par_chunks_mut(n_in.max(1)).zip(dp_rows.par_iter_mut()).enumerate().try_for_each(one)
    } else {
        dx.chunks_mut(n_in.max(1)).zip(dp_rows.iter_mut()).enumerate().try_for_each(one)
    }
}

/// `(y_k, ty_k) = (f(x_k, p_b), J_x·tx_k + J_p·tp_b)` for every element
/// (`tp` laid out as `p`), as [`forward_rows`].
#[allow(clippy::too_many_arguments)]
fn jvp_rows(op: &dyn PyOp, x: &[f64], p: &[f64], per: usize, tx: &[f64], tp: &[f64], y: &mut [f64], ty: &mut [f64]) -> Result<(), Failure> {
    let (n_in, n_out, n_params) = op.sizes();
    let one = |(k, (yk, tyk)): (usize, (&mut [f64], &mut [f64]))| {
        let (xs, ps) = (k * n_in..(k + 1) * n_in, (k / per) * n_params..(k / per + 1) * n_params);
        op.jvp(&x[xs.clone()], &p[ps.clone()], &tx[xs], &tp[ps], yk, tyk)
    };
    let m = n_out.max(1);
    if parallel(op, y.len() / m) {
        y.par_chunks_mut(m).zip(ty.par_chunks_mut(m)).enumerate().try_for_each(one)
    } else {
        y.chunks_mut(m).zip(ty.chunks_mut(m)).enumerate().try_for_each(one)
    }
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
            let count: usize = batch.iter().product();
            let mut y = vec![0.0; count * op.sizes().1];
            forward_rows(&*op, &x.values, &p.values, if pb { 1 } else { count.max(1) }, &mut y)?;
            Ok((batch, y))
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
            let (mut dx, mut dp) = (vec![0.0; count * n_in], vec![0.0; count * n_params]);
            vjp_rows(&*op, &x.values, &p.values, if pb { 1 } else { count.max(1) }, &dy.values, &mut dx, &mut dp)?;
            Ok((batch, dx, dp))
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
            let n_out = op.sizes().1;
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
            let (mut y, mut ty) = (vec![0.0; count * n_out], vec![0.0; count * n_out]);
            jvp_rows(&*op, &x.values, &p.values, if pb { 1 } else { count.max(1) }, &tx.values, &tp.values, &mut y, &mut ty)?;
            Ok((batch, y, ty))
        })?;
        let shape = [batch, vec![self.op.sizes().1]].concat();
        Ok((to_numpy(py, &shape, y)?, to_numpy(py, &shape, ty)?))
    }

    /// `steps` applications of this operator (a step: `n_in == n_out`)
    /// with the same `p`, as one operator `(x_0, p) ↦ x_T`: one call for a
    /// whole rollout, its VJP (`∂x_T/∂x_0` and `∂x_T/∂p` summed over the
    /// steps) one backward pass, keeping its states as `checkpoint` says
    /// (`"store"`, `"periodic[:K]"`, `"binomial[:S]"`), by default the
    /// fastest way that fits the memory budget.
    #[pyo3(signature = (steps, checkpoint = None))]
    fn repeat(&self, steps: usize, checkpoint: Option<&str>) -> PyResult<Operator> {
        let mode = repeat::mode(steps, checkpoint)?;
        let op: Arc<dyn PyOp> = match self.op.repeat(steps, mode) {
            Some(own) => own?,
            None => Arc::new(repeat::Repeated::new(self.op.clone(), steps, mode)?),
        };
        Ok(Operator::new(op, format!("{}.repeat({steps})", self.name)))
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
/// Keeps the memory the process frees instead of returning each large
/// block to the system (glibc; elsewhere nothing happens): the adjoints
/// Enzyme generates allocate their buffers afresh on every call, and
/// mapping them again each time costs a page fault per page (8 % of the
/// periodic Navier–Stokes VJP at 64², docs/navier-stokes.md). A setting of
/// the whole process, so not made on import: call it once, early, in a
/// program that runs many gradients.
#[pyfunction]
fn keep_freed_memory() {
    diffsim::memory::keep_freed_memory();
}

#[pyfunction]
fn ffi_targets() -> Vec<(&'static str, usize)> {
    ffi::targets()
}

fn message(f: Failure) -> String {
    match f {
        Failure::Input(m) | Failure::Simulation(m) | Failure::Panic(m) => m,
    }
}

/// An operator that panics in every method (a bug stood in for): for the
/// tests of the panic path, which must end in `InternalError` (or an XLA
/// error) with the panic's message and leave the interpreter running.
struct Panics;

impl PyOp for Panics {
    fn sizes(&self) -> (usize, usize, usize) {
        (1, 1, 0)
    }
    fn forward(&self, _: &[f64], _: &[f64], _: &mut [f64]) -> Result<(), Failure> {
        panic!("a deliberate panic in forward")
    }
    fn vjp(&self, _: &[f64], _: &[f64], _: &[f64], _: &mut [f64], _: &mut [f64]) -> Result<(), Failure> {
        panic!("a deliberate panic in vjp")
    }
    fn jvp(&self, _: &[f64], _: &[f64], _: &[f64], _: &[f64], _: &mut [f64], _: &mut [f64]) -> Result<(), Failure> {
        panic!("a deliberate panic in jvp")
    }
    fn check(&self, _: &[f64], _: &[f64]) -> Result<(&'static str, String), Failure> {
        panic!("a deliberate panic in check")
    }
}

/// An operator (one input, one output) whose every method panics: only for
/// testing that a panic inside diffsim becomes an exception.
#[pyfunction]
fn _panicking_operator() -> Operator {
    Operator::new(Arc::new(Panics), "_panicking_operator()".into())
}

/// diffsim's Python module.
#[pymodule]
pub fn _diffsim(m: &Bound<'_, PyModule>) -> PyResult<()> {
    diffsim_solvers::simd::max_isa_from_env().map_err(|e| PyValueError::new_err(e.to_string()))?;
    m.add("DiffsimError", m.py().get_type::<DiffsimError>())?;
    m.add("SimulationError", m.py().get_type::<SimulationError>())?;
    m.add("InternalError", m.py().get_type::<InternalError>())?;
    m.add_class::<Operator>()?;
    m.add_class::<scene::SceneFile>()?;
    m.add_function(wrap_pyfunction!(ops::burgers_step, m)?)?;
    m.add_function(wrap_pyfunction!(ops::smoke_step, m)?)?;
    m.add_function(wrap_pyfunction!(ops::navier_stokes_step, m)?)?;
    m.add_function(wrap_pyfunction!(ops::p1_problem, m)?)?;
    m.add_function(wrap_pyfunction!(ops::p1_loss, m)?)?;
    m.add_function(wrap_pyfunction!(ffi_targets, m)?)?;
    m.add_function(wrap_pyfunction!(keep_freed_memory, m)?)?;
    m.add_function(wrap_pyfunction!(ops::p2_problem, m)?)?;
    m.add_function(wrap_pyfunction!(ops::p2_loss, m)?)?;
    m.add_function(wrap_pyfunction!(ops::p4_problem, m)?)?;
    m.add_function(wrap_pyfunction!(ops::p4_loss, m)?)?;
    m.add_function(wrap_pyfunction!(ops::oscillators, m)?)?;
    m.add_function(wrap_pyfunction!(_panicking_operator, m)?)?;
    Ok(())
}
