//! What watches a run: an [`Observer`] sees every Newton iteration and every step with the
//! state after it. The step ([`crate::Integrator::step`]) and the executor
//! ([`crate::Integrator::run`]) both call it, so it lives apart from both.

use std::ops::ControlFlow;

use crate::report::{IterationReport, StepReport};
use crate::state::State;

/// Watches a run: every Newton iteration and every step, with the state after it. All
/// methods do nothing by default.
pub trait Observer {
    /// After each Newton iteration.
    fn iteration(&mut self, _report: &IterationReport) {}
    /// After each step, with the state it produced; `Break` ends the run
    /// ([`crate::Termination::Stopped`]).
    fn step(&mut self, _report: &StepReport, _state: &State) -> ControlFlow<()> {
        ControlFlow::Continue(())
    }
}

/// The observer that watches nothing.
#[derive(Debug, Default, Clone, Copy)]
pub struct NoObserver;

impl Observer for NoObserver {}

/// An observer of steps from a closure: `OnStep(|report, state| { ... })`.
pub struct OnStep<F>(pub F);

impl<F: FnMut(&StepReport, &State)> Observer for OnStep<F> {
    fn step(&mut self, report: &StepReport, state: &State) -> ControlFlow<()> {
        (self.0)(report, state);
        ControlFlow::Continue(())
    }
}
