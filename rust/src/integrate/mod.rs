//! Numerics: how an [`OdeSystem`] is advanced.
//!
//! One method: RODAS4, a 6-stage, order-4(3), L-stable, stiffly accurate Rosenbrock method
//! (Hairer & Wanner, *Solving ODEs II*, 2nd ed., §IV.7; coefficients of their `rodas.f`).
//! It is linearly implicit: one Jacobian and one LU factorisation of `I/(h·γ) − J` per step,
//! no Newton iteration, which suits small stiff systems (friction states with ~27 µs time
//! constants, the motor's electrical pole) integrated between 1 ms control ticks.
//! Step size: error-controlled with an embedded order-3 estimate; the integrator steps
//! exactly to the end of each segment (the input is held constant inside a segment).
//! State events (a sign change of [`OdeSystem::event`]) end a segment early; they are
//! located on the step size by the Illinois method, started at the root of the step's cubic
//! Hermite interpolant of the event function (where [`OdeSystem::event_rate`] is given) and
//! closed from both sides by Newton trials just past the root.

mod arrow;
mod lu;
mod rodas;

pub use arrow::Arrow;
pub use lu::Lu;

pub use rodas::{
    IntegratorOptions, Rodas4, SegmentEnd, Stats, JUMP_FIRST_STEP_ERROR, POLL_EVERY_STEPS,
};

use nalgebra::{SMatrix, SVector};

/// Samples of a run (a control loop's, an open loop's, a friction response's) between two
/// polls of its stop request. A second constant beside [`POLL_EVERY_STEPS`] because the unit
/// differs: a sample is one whole control interval, which can take from one to `max_steps`
/// integrator steps; a long interval polls within itself, by steps.
pub const POLL_EVERY_SAMPLES: usize = 16;

/// An autonomous ODE `dy/dt = f(y)` of fixed dimension `N` (inputs are held constant by the
/// caller over a segment), with an analytic Jacobian and an optional event function.
pub trait OdeSystem<const N: usize> {
    /// Right-hand side `f(y)`, written into `dy`.
    fn rhs(&self, y: &SVector<f64, N>, dy: &mut SVector<f64, N>);
    /// Jacobian `∂f/∂y`, written into `jac`.
    fn jacobian(&self, y: &SVector<f64, N>, jac: &mut SMatrix<f64, N, N>);
    /// `f(y)` and `∂f/∂y` at the same `y` (a system can share work between them; the results
    /// must equal those of [`Self::rhs`] and [`Self::jacobian`]).
    fn rhs_and_jacobian(
        &self,
        y: &SVector<f64, N>,
        dy: &mut SVector<f64, N>,
        jac: &mut SMatrix<f64, N, N>,
    ) {
        self.rhs(y, dy);
        self.jacobian(y, jac);
    }
    /// `Some(k)` when every nonzero off-diagonal entry of `∂f/∂y` lies in row `k` or column
    /// `k` (an arrowhead Jacobian, hub `k`) wherever the integrator evaluates it: the
    /// iteration matrix is then solved by [`Arrow`] (elimination into the hub), not by a dense
    /// LU. `None` (the default): dense.
    fn arrowhead_hub(&self) -> Option<usize> {
        None
    }
    /// Event function. `None` when the system has no event. An event happens where the value
    /// goes from `≥ 0` at the start of a step to `< 0` at its end.
    fn event(&self, _y: &SVector<f64, N>) -> Option<f64> {
        None
    }
    /// Rate of the event function along the solution, `∇g(y)·f(y)`, given `f = f(y)`
    /// (`None`: not known; event location then uses values alone).
    fn event_rate(&self, _y: &SVector<f64, N>, _f: &SVector<f64, N>) -> Option<f64> {
        None
    }
}
