//! `Operator.repeat(steps)`: any state-to-state operator Python holds, run
//! `steps` times with the same parameters, as one operator of the initial
//! state and the parameters ([`diffsim::rollout::Repeat`]): one call from
//! Python for a whole rollout, its VJP one backward pass in Rust under a
//! checkpointing chosen by the memory budget (or named).

use std::sync::{Arc, Mutex};

use diffsim::check::{CheckParams, check_all};
use diffsim::op::{Forward, Jvp, OpError, OpMessage, Vjp};
use diffsim::rollout::{Checkpointing, Repeat};

use super::{Failure, PyOp, input, simulation};

/// A Python-side operator as a diffsim step, so that [`Repeat`] chains it.
/// A step's failure is kept whole (its kind and message) and handed to
/// the rollout as the step's error.
struct Stepper {
    op: Arc<dyn PyOp>,
    failure: Mutex<Option<Failure>>,
    /// Set once a step failed; the rollout takes its error.
    failed: Mutex<bool>,
}

impl Stepper {
    fn keep(&self, r: Result<(), Failure>) {
        if let Err(f) = r {
            let mut first = self.failure.lock().unwrap_or_else(|e| e.into_inner());
            if first.is_none() {
                *first = Some(f);
            }
            *self.failed.lock().unwrap_or_else(|e| e.into_inner()) = true;
        }
    }
}

impl diffsim::op::Operator for Stepper {
    fn n_in(&self) -> usize {
        self.op.sizes().0
    }
    fn n_out(&self) -> usize {
        self.op.sizes().1
    }
    fn n_params(&self) -> usize {
        self.op.sizes().2
    }
}

impl Forward for Stepper {
    fn forward(&self, x: &[f64], p: &[f64], y: &mut [f64]) {
        self.keep(self.op.forward(x, p, y));
    }

    fn smooth_radius(&self, x: &[f64], p: &[f64], dx: &[f64], dp: &[f64]) -> f64 {
        self.op.smooth_radius(x, p, dx, dp)
    }

    fn take_error(&self) -> Option<OpError> {
        let mut failed = self.failed.lock().unwrap_or_else(|e| e.into_inner());
        std::mem::take(&mut *failed).then(|| OpError::Input(OpMessage::new("a step failed")))
    }
}

impl Vjp for Stepper {
    fn vjp(&self, x: &[f64], p: &[f64], dy: &mut [f64], dx: &mut [f64], dp: &mut [f64]) {
        let (mut dxs, mut dps) = (vec![0.0; dx.len()], vec![0.0; dp.len()]);
        self.keep(self.op.vjp(x, p, dy, &mut dxs, &mut dps));
        dx.iter_mut().zip(&dxs).for_each(|(d, v)| *d += v);
        dp.iter_mut().zip(&dps).for_each(|(d, v)| *d += v);
        dy.fill(0.0);
    }

    fn vjp_overwrite(&self, x: &[f64], p: &[f64], dy: &mut [f64], dx: &mut [f64], dp: &mut [f64]) {
        let mut dps = vec![0.0; dp.len()];
        self.keep(self.op.vjp(x, p, dy, dx, &mut dps));
        dp.iter_mut().zip(&dps).for_each(|(d, v)| *d += v);
    }
}

impl Jvp for Stepper {
    fn jvp(&self, x: &[f64], p: &[f64], tx: &[f64], tp: &[f64], y: &mut [f64], ty: &mut [f64]) {
        self.keep(self.op.jvp(x, p, tx, tp, y, ty));
    }
}

/// `steps` checked (at least one) and `checkpoint` read as `diffsim bench
/// --checkpoint` takes it (`store`, `periodic[:K]`, `binomial[:S]`);
/// `None` leaves the choice to the memory budget.
pub(crate) fn mode(steps: usize, checkpoint: Option<&str>) -> Result<Option<Checkpointing>, Failure> {
    if steps == 0 {
        return Err(input("repeat: steps = 0; give at least one step"));
    }
    checkpoint.map(|c| c.parse::<Checkpointing>().map(|m| m.resolve(steps)).map_err(|e| input(format!("repeat: checkpoint: {e}")))).transpose()
}

/// The [`PyOp`] of `Operator.repeat`: a fresh [`Repeat`] per call, so that
/// the elements of a batch, run on several threads, keep their errors apart.
pub(crate) struct Repeated {
    op: Arc<dyn PyOp>,
    steps: usize,
    mode: Option<Checkpointing>,
}

impl Repeated {
    /// `steps` steps of `op`, their states kept as `mode` says ([`mode`]).
    pub(crate) fn new(op: Arc<dyn PyOp>, steps: usize, mode: Option<Checkpointing>) -> Result<Self, Failure> {
        let (n_in, n_out, _) = op.sizes();
        if n_in != n_out {
            return Err(input(format!("repeat: the operator maps {n_in} values to {n_out}; a repeated step must map a state to a state of the same size")));
        }
        Ok(Self { op, steps, mode })
    }

    /// Runs `f` on a fresh rollout; its failure, the failing step's own
    /// if a step failed (its kind and whole message), else the rollout's.
    fn run<T>(&self, f: impl FnOnce(&Repeat<Stepper>) -> T) -> Result<T, Failure> {
        let stepper = Stepper { op: self.op.clone(), failure: Mutex::new(None), failed: Mutex::new(false) };
        let repeat = Repeat::new(stepper, self.steps).map_err(|e| input(format!("repeat: {e}")))?;
        let repeat = match self.mode {
            Some(m) => repeat.with_checkpointing(m),
            None => repeat,
        };
        let out = f(&repeat);
        let rollout = repeat.take_rollout_error();
        if let Some(f) = repeat.op().failure.lock().unwrap_or_else(|e| e.into_inner()).take() {
            return Err(f);
        }
        match rollout {
            Some(e) => Err(simulation(format!("{} steps of the operator: {e}", self.steps))),
            None => Ok(out),
        }
    }
}

impl PyOp for Repeated {
    fn sizes(&self) -> (usize, usize, usize) {
        self.op.sizes()
    }
    fn heavy(&self) -> bool {
        true
    }
    fn forward(&self, x: &[f64], p: &[f64], y: &mut [f64]) -> Result<(), Failure> {
        self.run(|r| r.forward(x, p, y))
    }
    fn vjp(&self, x: &[f64], p: &[f64], dy: &[f64], dx: &mut [f64], dp: &mut [f64]) -> Result<(), Failure> {
        dx.fill(0.0);
        dp.fill(0.0);
        let mut dy = dy.to_vec();
        self.run(|r| r.vjp(x, p, &mut dy, dx, dp))
    }
    fn jvp(&self, x: &[f64], p: &[f64], tx: &[f64], tp: &[f64], y: &mut [f64], ty: &mut [f64]) -> Result<(), Failure> {
        self.run(|r| r.jvp(x, p, tx, tp, y, ty))
    }
    fn smooth_radius(&self, x: &[f64], p: &[f64], dx: &[f64], dp: &[f64]) -> f64 {
        self.run(|r| r.smooth_radius(x, p, dx, dp)).unwrap_or(0.0)
    }
    fn check(&self, x: &[f64], p: &[f64]) -> Result<(&'static str, String), Failure> {
        let report = self.run(|r| check_all(r, x, p, &CheckParams::default()))?;
        Ok((super::ops::verdict(&report), report.to_string()))
    }
}
