//! One instance of an operator per worker thread. Operators that own work
//! buffers behind a `RefCell` (a pressure solver's vectors, a chain's
//! intermediate states) are `Send` but not `Sync`; batch code such as
//! [`crate::train::batch_gradient`] runs samples on rayon's threads and
//! needs `Sync`. [`PerThread`] gives every rayon worker its own instance
//! (and one more for threads outside the pool), each behind an uncontended
//! mutex. Results do not depend on which instance ran a sample, as long as
//! the operator's result depends only on its arguments (true of every
//! operator here: solves start from zero, buffers are overwritten).

use std::sync::{Mutex, MutexGuard};

use super::{Forward, Jvp, OpError, Operator, Vjp};

/// `O` once per rayon worker thread, plus one for other threads.
#[derive(Debug)]
pub struct PerThread<O> {
    slots: Vec<Mutex<O>>,
    /// `(n_in, n_out, n_params)`, read without locking (size checks run on
    /// every call; locking slot 0 for them would wait for whichever thread
    /// is computing with it).
    sizes: (usize, usize, usize),
}

impl<O: Send> PerThread<O> {
    /// Calls `make` once per slot: the current rayon pool's threads, plus one.
    pub fn new(make: impl Fn() -> O) -> Self
    where
        O: Operator,
    {
        let n = rayon::current_num_threads() + 1;
        let slots: Vec<Mutex<O>> = (0..n).map(|_| Mutex::new(make())).collect();
        let sizes = {
            let o = slots[0].lock().unwrap_or_else(|e| e.into_inner());
            (o.n_in(), o.n_out(), o.n_params())
        };
        Self { slots, sizes }
    }

    /// The calling thread's instance: its rayon index, or the last slot
    /// outside the pool (a thread of a larger pool shares the last worker
    /// slot, correctly but serialised by the mutex).
    fn mine(&self) -> MutexGuard<'_, O> {
        let outside = self.slots.len() - 1;
        let k = rayon::current_thread_index().map_or(outside, |i| i.min(outside.saturating_sub(1)));
        // A panic in another call cannot leave a half-made result here:
        // every call overwrites its outputs, so a poisoned lock is usable.
        self.slots[k].lock().unwrap_or_else(|e| e.into_inner())
    }

    /// Slot 0, for inspection (it may wait for a thread computing with it).
    pub fn first(&self) -> MutexGuard<'_, O> {
        self.slots[0].lock().unwrap_or_else(|e| e.into_inner())
    }
}

impl<O: Operator + Send> Operator for PerThread<O> {
    fn n_in(&self) -> usize {
        self.sizes.0
    }
    fn n_out(&self) -> usize {
        self.sizes.1
    }
    fn n_params(&self) -> usize {
        self.sizes.2
    }
}

impl<O: Forward + Send> Forward for PerThread<O> {
    fn forward(&self, x: &[f64], p: &[f64], y: &mut [f64]) {
        self.mine().forward(x, p, y)
    }
    fn smooth_radius(&self, x: &[f64], p: &[f64], dx: &[f64], dp: &[f64]) -> f64 {
        self.mine().smooth_radius(x, p, dx, dp)
    }
    fn solve_tolerance(&self) -> f64 {
        self.mine().solve_tolerance()
    }
    fn name(&self) -> super::OpName {
        self.mine().name()
    }
    fn locate_non_finite(&self, x: &[f64], p: &[f64]) -> super::OpName {
        self.mine().locate_non_finite(x, p)
    }
    /// The first error any instance recorded (each instance's is taken).
    fn take_error(&self) -> Option<OpError> {
        let mut first = None;
        for s in &self.slots {
            let e = s.lock().unwrap_or_else(|e| e.into_inner()).take_error();
            first = first.or(e);
        }
        first
    }
}

impl<O: Vjp + Send> Vjp for PerThread<O> {
    fn vjp(&self, x: &[f64], p: &[f64], dy: &mut [f64], dx: &mut [f64], dp: &mut [f64]) {
        self.mine().vjp(x, p, dy, dx, dp)
    }
}

impl<O: Jvp + Send> Jvp for PerThread<O> {
    fn jvp(&self, x: &[f64], p: &[f64], tx: &[f64], tp: &[f64], y: &mut [f64], ty: &mut [f64]) {
        self.mine().jvp(x, p, tx, tp, y, ty)
    }
}

impl<O: super::LocalInverse + Send> super::LocalInverse for PerThread<O> {
    fn local_inverse(&self, x: &[f64], p: &[f64], dy: &[f64], dx: &mut [f64]) {
        self.mine().local_inverse(x, p, dy, dx)
    }
}
