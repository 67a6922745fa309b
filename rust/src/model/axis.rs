//! The rigid seed axis as a hybrid (stick/slip) ODE.
use super::params::AxisParams;
use crate::error::{ConfigError, SimError};
use crate::integrate::{Lu, OdeSystem, Rodas4, SegmentEnd, Stats};
use nalgebra::{SMatrix, SVector};

/// Dimension of the plant state.
pub const STATE_DIM: usize = 4;
type State = SVector<f64, STATE_DIM>;
type Jac = SMatrix<f64, STATE_DIM, STATE_DIM>;

const X: usize = 0;
const V: usize = 1;
const Z: usize = 2;
const I: usize = 3;

/// The discrete mode of the drive train.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Mode {
    /// Held by the motor-shaft stiction: v = 0 exactly, position frozen.
    Stuck,
    /// Slipping in direction `d` (±1); `d` replaces sgn v in the friction laws.
    Slip(f64),
}

/// Validated parameters plus the derived constants of the lumped axis.
#[derive(Debug, Clone, Copy)]
pub struct Axis {
    /// The parameters it was built from.
    pub params: AxisParams,
    /// Transmission r = P/(2π·N), m per motor radian.
    pub transmission_m_per_rad: f64,
    /// Overall efficiency η = η_g·η_s.
    pub efficiency: f64,
    /// Equivalent mass at the table m + η·J_m/r² + η_s·J_s·(2π/P)², kg (forward efficiency
    /// also scales the reflected inertias; docs/model.md).
    pub equivalent_mass_kg: f64,
}

impl Axis {
    /// Validate the parameters and derive the lumped constants.
    pub fn new(params: AxisParams) -> Result<Self, ConfigError> {
        params.validate()?;
        let r = params.screw.lead_m / (2.0 * std::f64::consts::PI * params.gearhead.ratio);
        let k = 2.0 * std::f64::consts::PI / params.screw.lead_m;
        let eta = params.gearhead.efficiency * params.screw.efficiency;
        Ok(Self {
            params,
            transmission_m_per_rad: r,
            efficiency: eta,
            equivalent_mass_kg: params.table.mass_kg
                + eta * params.motor.rotor_inertia_kg_m2 / (r * r)
                + params.screw.efficiency * params.screw.inertia_kg_m2 * k * k,
        })
    }

    /// Scales mapping `atol_position_m` to each state's absolute tolerance: position 1,
    /// velocity 1e3/s (one position tolerance per ms), Dahl force σ (the force of one
    /// position tolerance of presliding), and for the current the larger of (a) the current
    /// that produces that force and (b) the current error whose transient, decaying with the
    /// electrical time constant τ_e = L/R, moves the table by one position tolerance:
    /// `δx ≈ δi·(η·k_t/r)·τ_e²/m_eq`. A current error is not sustained (the current relaxes to
    /// its quasi-static value within a few τ_e), so only its integrated effect on the position
    /// matters; holding it to (a) alone cost about half of all steps in motion without
    /// changing the position by more than 1e-11 m (docs/model.md, "Tolerances").
    pub fn state_scales(&self) -> State {
        let p = &self.params;
        let force = p.dahl.stiffness_n_per_m;
        let force_per_amp =
            self.efficiency * p.motor.torque_constant_nm_per_a / self.transmission_m_per_rad;
        let current_force = force / force_per_amp;
        let tau_e = p.motor.inductance_h / p.motor.resistance_ohm;
        let current_transient = self.equivalent_mass_kg / (tau_e * tau_e * force_per_amp);
        State::new(1.0, 1e3, force, current_force.max(current_transient))
    }

    /// Motor current: the state, or the algebraic value when quasi-static.
    #[inline]
    pub fn current(&self, y: &State, u_v: f64) -> f64 {
        let m = &self.params.motor;
        if m.quasi_static_current {
            (u_v - m.back_emf_v_s_per_rad * y[V] / self.transmission_m_per_rad) / m.resistance_ohm
        } else {
            y[I]
        }
    }

    /// Torque the motor-shaft friction must supply to hold the axis at rest, N·m.
    #[inline]
    pub fn holding_torque(&self, y: &State, u_v: f64) -> f64 {
        let p = &self.params;
        let i = if p.motor.quasi_static_current {
            u_v / p.motor.resistance_ohm
        } else {
            y[I]
        };
        p.motor.torque_constant_nm_per_a * i
            - self.transmission_m_per_rad * (y[Z] + p.table.external_force_n) / self.efficiency
    }

    /// Motor friction torque reflected to the table as a force (N), for recording.
    pub fn motor_friction_force(&self, y: &State, mode: Mode, u_v: f64) -> f64 {
        let r = self.transmission_m_per_rad;
        match mode {
            Mode::Slip(d) => self.efficiency * self.params.motor_friction.torque(y[V] / r, d).0 / r,
            Mode::Stuck => self.efficiency * self.holding_torque(y, u_v) / r,
        }
    }
}

/// The axis over one segment: a mode and a held voltage. Implements [`OdeSystem`].
struct Segment<'a> {
    axis: &'a Axis,
    mode: Mode,
    u_v: f64,
}

impl OdeSystem<STATE_DIM> for Segment<'_> {
    #[inline(always)]
    fn rhs(&self, y: &State, dy: &mut State) {
        let a = self.axis;
        let p = &a.params;
        let m = &p.motor;
        let r = a.transmission_m_per_rad;
        match self.mode {
            Mode::Stuck => {
                dy[X] = 0.0;
                dy[V] = 0.0;
                dy[Z] = 0.0;
                dy[I] = if m.quasi_static_current {
                    0.0
                } else {
                    (self.u_v - m.resistance_ohm * y[I]) / m.inductance_h
                };
            }
            Mode::Slip(d) => {
                let w = y[V] / r;
                let (tf, _) = p.motor_friction.torque(w, d);
                let i = a.current(y, self.u_v);
                let f_drive = a.efficiency * (m.torque_constant_nm_per_a * i - tf) / r;
                dy[X] = y[V];
                dy[V] = (f_drive - y[Z] - p.table.external_force_n) / a.equivalent_mass_kg;
                dy[Z] = p.dahl.rate(y[V], y[Z], d).0;
                dy[I] = if m.quasi_static_current {
                    0.0
                } else {
                    (self.u_v - m.resistance_ohm * y[I] - m.back_emf_v_s_per_rad * w)
                        / m.inductance_h
                };
            }
        }
    }

    fn jacobian(&self, y: &State, jac: &mut Jac) {
        let a = self.axis;
        let p = &a.params;
        let m = &p.motor;
        let r = a.transmission_m_per_rad;
        jac.fill(0.0);
        match self.mode {
            Mode::Stuck => {
                if !m.quasi_static_current {
                    jac[(I, I)] = -m.resistance_ohm / m.inductance_h;
                }
            }
            Mode::Slip(d) => {
                let w = y[V] / r;
                let (_, dtf_dw) = p.motor_friction.torque(w, d);
                let meq = a.equivalent_mass_kg;
                let kt = m.torque_constant_nm_per_a;
                let di_dv = if m.quasi_static_current {
                    -m.back_emf_v_s_per_rad / (r * m.resistance_ohm)
                } else {
                    0.0
                };
                let df_dv = a.efficiency * (kt * di_dv - dtf_dw / r) / r;
                jac[(X, V)] = 1.0;
                jac[(V, V)] = df_dv / meq;
                jac[(V, Z)] = -1.0 / meq;
                let (_, dz_dv, dz_dz) = p.dahl.rate(y[V], y[Z], d);
                jac[(Z, V)] = dz_dv;
                jac[(Z, Z)] = dz_dz;
                if !m.quasi_static_current {
                    jac[(V, I)] = a.efficiency * kt / (r * meq);
                    jac[(I, V)] = -m.back_emf_v_s_per_rad / (r * m.inductance_h);
                    jac[(I, I)] = -m.resistance_ohm / m.inductance_h;
                }
            }
        }
    }

    fn event(&self, y: &State) -> Option<f64> {
        match self.mode {
            Mode::Slip(d) => Some(y[V] * d),
            Mode::Stuck => {
                if self.axis.params.motor.quasi_static_current {
                    None
                } else {
                    Some(
                        self.axis.params.motor_friction.static_torque_nm
                            - self.axis.holding_torque(y, self.u_v).abs(),
                    )
                }
            }
        }
    }
}

/// A slip segment with the fast electrical mode split off and solved exactly.
///
/// With `J0` the Jacobian at the segment start `y0`, `λ` its fast eigenvalue (the electrical
/// pole, near −R/L) and `φ` its eigenvector, the exact change of variables
/// `y = ỹ + w(s)`, `w(s) = w0·exp(λ·s)`, `w0 = c·φ`, `s` the time since the start, turns
/// `y' = f(y)` into `ỹ' = f(ỹ + w(s)) − λ·w(s)`. The amplitude `c` is the fast-mode content of
/// the start: with `ψ` the left eigenvector, `c = ψᵀ·f(y0)/(λ·ψᵀ·φ)` puts `ỹ(0)` on the slow
/// manifold of the linearised system (`ψᵀ·f = 0`). The transient a voltage jump excites is
/// then carried by `w` exactly, and the integrated `ỹ` only sees it through the change of
/// the Jacobian along the trajectory (`(J(ỹ + w) − J0)·w`), which is small. The state is
/// `[ỹ, s]` (time as a state makes the system autonomous, so RODAS4 with the exact Jacobian
/// applies unchanged); the error is controlled on `ỹ`, whose error is the error of `y`
/// (`w` is exact).
struct SplitSegment<'a> {
    seg: Segment<'a>,
    lambda: f64,
    w0: State,
}

type State5 = SVector<f64, 5>;
const S: usize = 4;

impl SplitSegment<'_> {
    /// The split-off part at split state `y`: `w(s)`.
    #[inline(always)]
    fn w(&self, y: &State5) -> State {
        self.w0 * (self.lambda * y[S]).exp()
    }

    /// The physical state at split state `y`.
    #[inline(always)]
    fn join(&self, y: &State5) -> State {
        State::new(y[X], y[V], y[Z], y[I]) + self.w(y)
    }

    /// An integrator failure with the state it reports mapped back to the physical state.
    fn physical_error(&self, e: SimError) -> SimError {
        let join = |state: Vec<f64>| -> Vec<f64> {
            if state.len() == 5 {
                self.join(&State5::from_column_slice(&state))
                    .iter()
                    .copied()
                    .collect()
            } else {
                state
            }
        };
        match e {
            SimError::StepSizeTooSmall { t_s, h_s, state } => SimError::StepSizeTooSmall {
                t_s,
                h_s,
                state: join(state),
            },
            SimError::SingularMatrix { t_s, state } => SimError::SingularMatrix {
                t_s,
                state: join(state),
            },
            SimError::NonFinite { t_s, state } => SimError::NonFinite {
                t_s,
                state: join(state),
            },
            SimError::TooManySteps {
                t_s,
                max_steps,
                state,
            } => SimError::TooManySteps {
                t_s,
                max_steps,
                state: join(state),
            },
            other => other,
        }
    }

    /// Split the physical state `y` at the segment start (s = 0).
    fn split(&self, y: &State) -> State5 {
        let t = y - self.w0;
        State5::new(t[X], t[V], t[Z], t[I], 0.0)
    }

    /// The split of segment `seg` at `y0`: `None` when the fast mode cannot be found (then
    /// the segment is integrated as it is).
    fn new<'a>(seg: Segment<'a>, y0: &State) -> Option<SplitSegment<'a>> {
        let m = &seg.axis.params.motor;
        let shift = -m.resistance_ohm / m.inductance_h;
        let mut f0 = State::zeros();
        let mut j0 = Jac::zeros();
        seg.rhs(y0, &mut f0);
        seg.jacobian(y0, &mut j0);
        let shifted = j0 - Jac::identity() * shift;
        let lu = Lu::new(&shifted)?;
        let lu_t = Lu::new(&shifted.transpose())?;
        let mut phi = State::new(0.0, 0.0, 0.0, 1.0);
        let mut psi = phi;
        for _ in 0..3 {
            phi = lu.solve(&phi);
            phi /= phi[I];
            psi = lu_t.solve(&psi);
            psi /= psi[I];
        }
        let pp = psi.dot(&phi);
        let lambda = psi.dot(&(j0 * phi)) / pp;
        let c = psi.dot(&f0) / (lambda * pp);
        let w0 = phi * c;
        if !(lambda < 0.0 && w0.iter().all(|v| v.is_finite())) {
            return None;
        }
        Some(SplitSegment { seg, lambda, w0 })
    }
}

impl OdeSystem<5> for SplitSegment<'_> {
    #[inline(always)]
    fn rhs(&self, y: &State5, dy: &mut State5) {
        let w = self.w(y);
        let p = State::new(y[X], y[V], y[Z], y[I]) + w;
        let mut d = State::zeros();
        self.seg.rhs(&p, &mut d);
        let d = d - w * self.lambda;
        dy[X] = d[X];
        dy[V] = d[V];
        dy[Z] = d[Z];
        dy[I] = d[I];
        dy[S] = 1.0;
    }

    fn jacobian(&self, y: &State5, jac: &mut SMatrix<f64, 5, 5>) {
        let w = self.w(y);
        let p = State::new(y[X], y[V], y[Z], y[I]) + w;
        let mut j = Jac::zeros();
        self.seg.jacobian(&p, &mut j);
        // ∂/∂s of f(ỹ + w(s)) − λ·w(s) is (J − λ·I)·w'(s), w' = λ·w.
        let col = (j - Jac::identity() * self.lambda) * (w * self.lambda);
        jac.fill(0.0);
        for r in 0..4 {
            for c in 0..4 {
                jac[(r, c)] = j[(r, c)];
            }
            jac[(r, S)] = col[r];
        }
    }

    fn event(&self, y: &State5) -> Option<f64> {
        self.seg.event(&self.join(y))
    }
}

/// A running plant: the axis, its state and mode, and the integrator.
#[derive(Debug, Clone)]
pub struct Plant {
    /// The axis.
    pub axis: Axis,
    /// Continuous state `[x_m, v_m_per_s, z_n, i_a]`.
    pub y: State,
    /// Discrete mode.
    pub mode: Mode,
    /// The integrator (keeps its step-size warm start and counters).
    pub integrator: Rodas4<STATE_DIM>,
    atol: State,
    /// The integrator of the split slip segments (its counters are added to `integrator`'s).
    split: Rodas4<5>,
}

/// Longest first step of a split segment whose split-off mode is not negligible, in time
/// constants of that mode (see `Plant::integrate_split`).
const SPLIT_FIRST_STEP_TIME_CONSTANTS: f64 = 10.0;

/// Events at one instant beyond which the mode logic is considered chattering (Zeno guard).
const MAX_EVENTS_AT_ONE_INSTANT: usize = 4;

impl Plant {
    /// A plant at rest and stuck at x = 0, z = 0, i = 0.
    pub fn new(axis: Axis, integrator: Rodas4<STATE_DIM>) -> Self {
        let atol = axis.state_scales() * integrator.options.atol_position_m;
        Self {
            axis,
            y: State::zeros(),
            mode: Mode::Stuck,
            split: integrator.resized::<5>(),
            integrator,
            atol,
        }
    }

    /// Motor current at the present state for a held voltage `u_v`.
    pub fn current(&self, u_v: f64) -> f64 {
        self.axis.current(&self.y, u_v)
    }

    /// Break away from stiction if the holding torque exceeds the static torque.
    fn try_breakaway(&mut self, u_v: f64) {
        if self.mode == Mode::Stuck {
            let t_req = self.axis.holding_torque(&self.y, u_v);
            if t_req.abs() > self.axis.params.motor_friction.static_torque_nm {
                self.mode = Mode::Slip(t_req.signum());
            }
        }
    }

    /// While stuck, advance the motor current exactly over at most `dt` seconds:
    /// `i(t) = u/R + (i0 − u/R)·exp(−R·t/L)` (nothing else moves). Returns the time to
    /// breakaway if the holding torque reaches the static torque within `dt` (the current is
    /// then left exactly at the breakaway value), `None` otherwise.
    fn stuck_current(&mut self, u_v: f64, dt: f64) -> Option<f64> {
        let p = &self.axis.params;
        let m = &p.motor;
        if m.quasi_static_current {
            return None;
        }
        let i_inf = u_v / m.resistance_ohm;
        let i0 = self.y[I];
        let rate = m.resistance_ohm / m.inductance_h;
        let kt = m.torque_constant_nm_per_a;
        let load = self.axis.transmission_m_per_rad * (self.y[Z] + p.table.external_force_n)
            / self.axis.efficiency;
        let ts = p.motor_friction.static_torque_nm;
        let t_final = kt * i_inf - load;
        if t_final.abs() > ts && i0 != i_inf {
            // The current that puts the holding torque just past the static limit (a relative
            // margin of 1e-12 so that the slip starts with a strictly positive acceleration).
            let margin = 1e-12
                * (ts
                    + self.axis.transmission_m_per_rad
                        * (p.dahl.coulomb_force_n + p.table.external_force_n.abs())
                        / self.axis.efficiency);
            let i_star = (load + (ts + margin) * t_final.signum()) / kt;
            let ratio = (i_star - i_inf) / (i0 - i_inf);
            if ratio > 0.0 && ratio <= 1.0 {
                let t_star = -ratio.ln() / rate;
                if t_star <= dt {
                    self.y[I] = i_star;
                    return Some(t_star);
                }
            }
        }
        self.y[I] = i_inf + (i0 - i_inf) * (-rate * dt).exp();
        None
    }

    /// Integrate one slip segment with the fast electrical mode split off (`SplitSegment`).
    fn integrate_split(
        &mut self,
        mode: Mode,
        u_v: f64,
        t: f64,
        t1: f64,
    ) -> Result<SegmentEnd, SimError> {
        let axis = self.axis;
        let seg = Segment {
            axis: &axis,
            mode,
            u_v,
        };
        let Some(sys) = SplitSegment::new(seg, &self.y) else {
            let seg = Segment {
                axis: &axis,
                mode,
                u_v,
            };
            return self
                .integrator
                .integrate(&seg, t, t1, &mut self.y, &self.atol);
        };
        let mut y5 = sys.split(&self.y);
        // The residual forcing (J(ỹ + w) − J0)·w lives in the first few time constants of
        // the split-off mode. A first step much longer than that puts every RODAS4 stage
        // where w has decayed, so neither solution nor error estimate sees it (measured: a
        // velocity error of ~10 tolerances at a reversal). When w is not negligible (some
        // component above its absolute tolerance) the first step is held to 10 time
        // constants, e^−10 of the mode's initial size at its end; then the estimate sees
        // the forcing and what is left after it is negligible.
        if (0..STATE_DIM).any(|k| sys.w0[k].abs() > self.atol[k]) {
            self.split
                .limit_next_step(SPLIT_FIRST_STEP_TIME_CONSTANTS / -sys.lambda);
        }
        let atol5 = State5::new(self.atol[X], self.atol[V], self.atol[Z], self.atol[I], 1.0);
        let before = self.split.stats;
        let res = self
            .split
            .integrate(&sys, t, t1, &mut y5, &atol5)
            .map_err(|e| sys.physical_error(e));
        let after = self.split.stats;
        self.integrator.stats += Stats {
            n_rhs: after.n_rhs - before.n_rhs,
            n_jac: after.n_jac - before.n_jac,
            n_lu: after.n_lu - before.n_lu,
            n_accepted: after.n_accepted - before.n_accepted,
            n_rejected: after.n_rejected - before.n_rejected,
            n_events: after.n_events - before.n_events,
        };
        let end = res?;
        self.y = sys.join(&y5);
        Ok(end)
    }

    /// Advance from `t0` to `t1` with the voltage `u_v` held, handling stick/slip events.
    ///
    /// Slip segments with a dynamic current are integrated with the fast electrical mode
    /// split off and solved exactly (`SplitSegment`): a jump of the held voltage excites the
    /// electrical transient (time constant about L/R = 21 µs), which RODAS4 would otherwise
    /// have to follow with several small steps after every output update.
    pub fn advance(&mut self, u_v: f64, t0: f64, t1: f64) -> Result<(), SimError> {
        let mut t = t0;
        let mut events_here = 0usize;
        let mut t_last_event = f64::NEG_INFINITY;
        loop {
            if events_here < MAX_EVENTS_AT_ONE_INSTANT {
                self.try_breakaway(u_v);
            }
            if self.mode == Mode::Stuck {
                // Nothing moves; the current is algebraic or a first-order lag solved exactly.
                match self.stuck_current(u_v, t1 - t) {
                    None => return Ok(()),
                    Some(dt) => {
                        t += dt;
                        let t_req = self.axis.holding_torque(&self.y, u_v);
                        self.mode = Mode::Slip(t_req.signum());
                        continue;
                    }
                }
            }
            let seg = Segment {
                axis: &self.axis,
                mode: self.mode,
                u_v,
            };
            let end = if self.axis.params.motor.quasi_static_current {
                self.integrator
                    .integrate(&seg, t, t1, &mut self.y, &self.atol)?
            } else {
                self.integrate_split(seg.mode, seg.u_v, t, t1)?
            };
            match end {
                SegmentEnd::Reached => return Ok(()),
                SegmentEnd::Event { t_s } => {
                    if t_s - t_last_event <= self.integrator.options.event_tol_s {
                        events_here += 1;
                    } else {
                        events_here = 0;
                    }
                    t_last_event = t_s;
                    t = t_s;
                    match self.mode {
                        Mode::Slip(d) => {
                            self.y[V] = 0.0;
                            let t_req = self.axis.holding_torque(&self.y, u_v);
                            let ts = self.axis.params.motor_friction.static_torque_nm;
                            self.mode =
                                if t_req.abs() <= ts || events_here >= MAX_EVENTS_AT_ONE_INSTANT {
                                    Mode::Stuck
                                } else if t_req.signum() == d {
                                    // Net torque still pushes along d although v reached 0
                                    // (numerically at the event): continue along d.
                                    Mode::Slip(d)
                                } else {
                                    Mode::Slip(-d)
                                };
                        }
                        Mode::Stuck => {
                            let t_req = self.axis.holding_torque(&self.y, u_v);
                            self.mode = Mode::Slip(t_req.signum());
                        }
                    }
                    if !self.y.iter().all(|v| v.is_finite()) {
                        return Err(SimError::NonFinite {
                            t_s: t,
                            state: self.y.iter().copied().collect(),
                        });
                    }
                }
            }
        }
    }
}
