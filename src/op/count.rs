//! Operation counts: how often each operator's forward, VJP and JVP ran on
//! this thread, while counting is on. Scenes use it to show that an effect
//! they do not declare never runs.
//!
//! Off by default; when off, recording costs one thread-local read.
//! Operators made with [`differentiable!`](crate::differentiable) and
//! [`stencil3!`](crate::stencil3) record themselves under their type name,
//! the framework's hand-written operators under theirs.
//!
//! ```
//! use diffsim::op::count;
//! count::start();
//! // … run operators …
//! let counts = count::stop();
//! assert!(counts.iter().all(|c| c.name != "Project"));
//! ```

use std::cell::{Cell, RefCell};

thread_local! {
    static ON: Cell<bool> = const { Cell::new(false) };
    static COUNTS: RefCell<Vec<Count>> = const { RefCell::new(Vec::new()) };
}

/// The calls of one operator type.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Count {
    /// The operator's type name (as written at its definition).
    pub name: &'static str,
    /// Forward evaluations.
    pub forward: u64,
    /// VJPs.
    pub vjp: u64,
    /// JVPs.
    pub jvp: u64,
}

/// Which method ran.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Method {
    /// [`Forward::forward`](crate::op::Forward::forward).
    Forward,
    /// [`Vjp::vjp`](crate::op::Vjp::vjp) or its overwriting form.
    Vjp,
    /// [`Jvp::jvp`](crate::op::Jvp::jvp).
    Jvp,
}

/// Starts counting on this thread, from zero.
pub fn start() {
    COUNTS.with_borrow_mut(|c| c.clear());
    ON.set(true);
}

/// Stops counting and returns the counts since [`start`].
pub fn stop() -> Vec<Count> {
    ON.set(false);
    COUNTS.with_borrow_mut(std::mem::take)
}

/// Records one call of `name`'s `method` (when counting is on).
#[inline]
pub fn record(name: &'static str, method: Method) {
    if !ON.get() {
        return;
    }
    COUNTS.with_borrow_mut(|all| {
        let i = match all.iter().position(|c| c.name == name) {
            Some(i) => i,
            None => {
                all.push(Count { name, forward: 0, vjp: 0, jvp: 0 });
                all.len() - 1
            }
        };
        match method {
            Method::Forward => all[i].forward += 1,
            Method::Vjp => all[i].vjp += 1,
            Method::Jvp => all[i].jvp += 1,
        }
    });
}
