//! The stick/slip event loop both plants run, written once: over an interval with the inputs
//! held, integrate the slipping (or free) motion to the next stick/slip event, resolve the
//! event, and solve a stuck phase in closed form where the plant can. What differs between the
//! rigid and the component plant (the segment's ODE, the breakaway rule, the closed-form stuck
//! phase, how an event sets the new mode) is a [`HybridPlant`] hook.
use crate::error::SimError;
use crate::integrate::{IntegratorOptions, SegmentEnd};

/// Events at one instant beyond which the mode logic is considered chattering (Zeno guard).
pub(super) const MAX_EVENTS_AT_ONE_INSTANT: usize = 4;

/// What a plant does at the start of a segment.
pub(super) enum StuckPhase {
    /// Integrate the next segment.
    Integrate,
    /// Stuck to the end of the interval (the state is left at the end).
    HeldToEnd,
    /// Stuck until breakaway at this time (the state is left at the breakaway).
    BreakawayAt(f64),
}

/// The plant-specific hooks of [`advance`].
pub(super) trait HybridPlant {
    /// The inputs held over an interval.
    type Input: ?Sized;

    /// The command voltage in `inp` (its jumps size the first step after them).
    fn voltage(inp: &Self::Input) -> f64;
    /// The command voltage of the last interval (NaN before the first).
    fn last_voltage(&mut self) -> &mut f64;
    /// The integrator options.
    fn options(&self) -> &IntegratorOptions;
    /// The state as the integrator's errors report it.
    fn state(&self) -> &[f64];
    /// Break away every stuck mass whose holding force exceeds what static friction holds.
    fn try_breakaway(&mut self, inp: &Self::Input);
    /// Solve a stuck phase starting at `t` in closed form, if the plant is in one it can.
    fn stuck_phase(&mut self, inp: &Self::Input, t: f64, t1: f64) -> StuckPhase;
    /// The slip mode after a breakaway found by [`Self::stuck_phase`].
    fn start_slip(&mut self, inp: &Self::Input);
    /// Integrate one segment from `t` towards `t1` in the present modes.
    fn integrate_segment(
        &mut self,
        inp: &Self::Input,
        t: f64,
        t1: f64,
        after_jump: Option<f64>,
        steps: &mut usize,
        poll: &mut dyn FnMut() -> bool,
    ) -> Result<SegmentEnd, SimError>;
    /// Set the modes after a stick/slip event (`force_stuck`: the Zeno guard holds the mass).
    fn resolve_event(&mut self, inp: &Self::Input, force_stuck: bool);
}

/// Advance `plant` from `t0` to `t1` with the inputs `inp` held, handling stick/slip events,
/// asking `poll` every `POLL_EVERY_STEPS` integrator steps whether to stop. The work is
/// bounded by the options' `max_steps` (over all segments) and `max_events`; transitions at
/// one instant beyond [`MAX_EVENTS_AT_ONE_INSTANT`] leave the mass stuck. A state that is not
/// finite at the end is [`SimError::NonFinite`].
pub(super) fn advance<P: HybridPlant>(
    plant: &mut P,
    inp: &P::Input,
    t0: f64,
    t1: f64,
    poll: &mut dyn FnMut() -> bool,
) -> Result<(), SimError> {
    let u_v = P::voltage(inp);
    let jump = (u_v - *plant.last_voltage()).abs();
    *plant.last_voltage() = u_v;
    let mut at_jump = jump > 0.0;
    let mut t = t0;
    let mut events_here = 0usize;
    let mut t_last_event = f64::NEG_INFINITY;
    let mut steps = 0usize;
    let mut events = 0usize;
    loop {
        if events_here < MAX_EVENTS_AT_ONE_INSTANT {
            plant.try_breakaway(inp);
        }
        match plant.stuck_phase(inp, t, t1) {
            StuckPhase::Integrate => {}
            StuckPhase::HeldToEnd => return check_finite(plant, t1),
            StuckPhase::BreakawayAt(t_s) => {
                t = t_s;
                count_event(plant, &mut events, t)?;
                plant.start_slip(inp);
                continue;
            }
        }
        let after_jump = (at_jump && t == t0).then_some(jump);
        at_jump = false;
        let end = plant.integrate_segment(inp, t, t1, after_jump, &mut steps, poll)?;
        match end {
            SegmentEnd::Reached => return check_finite(plant, t1),
            SegmentEnd::Event { t_s } => {
                count_event(plant, &mut events, t_s)?;
                if t_s - t_last_event <= plant.options().event_tol_s {
                    events_here += 1;
                } else {
                    events_here = 0;
                }
                t_last_event = t_s;
                t = t_s;
                plant.resolve_event(inp, events_here >= MAX_EVENTS_AT_ONE_INSTANT);
                check_finite(plant, t)?;
            }
        }
    }
}

/// Count one stick/slip transition at `t_s` against the `max_events` of the interval.
fn count_event<P: HybridPlant>(plant: &P, events: &mut usize, t_s: f64) -> Result<(), SimError> {
    *events += 1;
    let max_events = plant.options().max_events;
    if *events > max_events {
        return Err(SimError::TooManyEvents {
            t_s,
            max_events,
            state: plant.state().to_vec(),
        });
    }
    Ok(())
}

/// [`SimError::NonFinite`] at `t_s` unless every state is finite.
fn check_finite<P: HybridPlant>(plant: &P, t_s: f64) -> Result<(), SimError> {
    if plant.state().iter().all(|v| v.is_finite()) {
        Ok(())
    } else {
        Err(SimError::NonFinite {
            t_s,
            state: plant.state().to_vec(),
        })
    }
}
