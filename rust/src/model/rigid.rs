//! The rigid seed axis as a hybrid (stick/slip) ODE.
use super::hybrid::{self, HybridPlant, StuckPhase};
use super::params::AxisParams;
use crate::error::{ConfigError, SimError};
use crate::integrate::{IntegratorOptions, OdeSystem, Rodas4, SegmentEnd};
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
    /// Stribeck exponent above which the motor friction's exponential does not change the
    /// torque (`StribeckFriction::negligible_exponent`).
    pub stribeck_negligible_exponent: f64,
    /// `T_s − T_c` of the motor friction.
    stribeck_span_nm: f64,
    /// The seed axis's laws: Stribeck exponent 2 with `T_s ≠ T_c`, Dahl exponent 1, current
    /// as a state. The slip right-hand side then skips the checks for the other cases
    /// (`Segment::seed_slip_rhs`: the same operations, bit for bit).
    seed_laws: bool,
}

impl Axis {
    /// Validate the parameters and derive the lumped constants.
    pub fn new(params: AxisParams) -> Result<Self, ConfigError> {
        params.validate()?;
        let r = params.screw.metres_per_motor_radian(&params.gearhead);
        let k = params.screw.screw_radians_per_metre();
        let eta = params.gearhead.efficiency * params.screw.efficiency;
        Ok(Self {
            params,
            transmission_m_per_rad: r,
            efficiency: eta,
            equivalent_mass_kg: params.table.mass_kg
                + eta * params.motor.rotor_inertia_kg_m2 / (r * r)
                + params.screw.efficiency * params.screw.inertia_kg_m2 * k * k,
            stribeck_negligible_exponent: params.motor_friction.negligible_exponent(),
            stribeck_span_nm: params.motor_friction.static_torque_nm
                - params.motor_friction.coulomb_torque_nm,
            seed_laws: params.motor_friction.static_torque_nm
                - params.motor_friction.coulomb_torque_nm
                != 0.0
                && params.motor_friction.stribeck_exponent == 2.0
                && params.dahl.exponent == 1.0
                && !params.motor.quasi_static_current,
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

impl Segment<'_> {
    /// The slip right-hand side given the motor friction torque `tf` and the Dahl rate `dz`
    /// at `y`.
    #[inline(always)]
    fn slip_rhs(&self, y: &State, tf: f64, dz: f64, dy: &mut State) {
        let a = self.axis;
        let p = &a.params;
        let m = &p.motor;
        let r = a.transmission_m_per_rad;
        let w = y[V] / r;
        let i = a.current(y, self.u_v);
        let f_drive = a.efficiency * (m.torque_constant_nm_per_a * i - tf) / r;
        dy[X] = y[V];
        dy[V] = (f_drive - y[Z] - p.table.external_force_n) / a.equivalent_mass_kg;
        dy[Z] = dz;
        dy[I] = if m.quasi_static_current {
            0.0
        } else {
            (self.u_v - m.resistance_ohm * y[I] - m.back_emf_v_s_per_rad * w) / m.inductance_h
        };
    }

    /// The slip right-hand side of an axis with `seed_laws`: [`StribeckFriction::torque_value`]
    /// with δ = 2 and `T_s ≠ T_c`, [`DahlFriction::rate`] with exponent 1 and
    /// [`Self::slip_rhs`] with the current as a state, written out without the checks for the
    /// other cases: the same operations in the same order, so the same values bit for bit.
    ///
    /// [`StribeckFriction::torque_value`]: super::params::StribeckFriction::torque_value
    /// [`DahlFriction::rate`]: super::params::DahlFriction::rate
    #[inline(always)]
    fn seed_slip_rhs(&self, y: &State, d: f64, dy: &mut State) {
        let a = self.axis;
        let p = &a.params;
        let m = &p.motor;
        let f = &p.motor_friction;
        let r = a.transmission_m_per_rad;
        let w = y[V] / r;
        let q = (w.abs() / f.stribeck_velocity_rad_per_s).max(1e-12);
        let q2 = q * q;
        let e = if q2 > 746.0 || q2 > a.stribeck_negligible_exponent {
            0.0
        } else {
            (-q * q).exp()
        };
        let tf = d * (f.coulomb_torque_nm + a.stribeck_span_nm * e) + f.viscous_nm_s_per_rad * w;
        let dz = p.dahl.stiffness_n_per_m * y[V] * (1.0 - y[Z] * d / p.dahl.coulomb_force_n);
        let f_drive = a.efficiency * (m.torque_constant_nm_per_a * y[I] - tf) / r;
        dy[X] = y[V];
        dy[V] = (f_drive - y[Z] - p.table.external_force_n) / a.equivalent_mass_kg;
        dy[Z] = dz;
        dy[I] = (self.u_v - m.resistance_ohm * y[I] - m.back_emf_v_s_per_rad * w) / m.inductance_h;
    }

    /// [`OdeSystem::rhs_and_jacobian`] in slip for an axis with `seed_laws`:
    /// [`StribeckFriction::torque`] with δ = 2 and `T_s ≠ T_c`, [`DahlFriction::rate`] with
    /// exponent 1, then [`Self::slip_rhs`] and [`Self::slip_jacobian`] with the current as a
    /// state, written out without the checks for the other cases (the same operations in the
    /// same order).
    ///
    /// [`StribeckFriction::torque`]: super::params::StribeckFriction::torque
    /// [`DahlFriction::rate`]: super::params::DahlFriction::rate
    #[inline(always)]
    fn seed_slip_rhs_and_jacobian(&self, y: &State, d: f64, dy: &mut State, jac: &mut Jac) {
        let a = self.axis;
        let p = &a.params;
        let m = &p.motor;
        let f = &p.motor_friction;
        let r = a.transmission_m_per_rad;
        // StribeckFriction::torque.
        let w = y[V] / r;
        let ws = f.stribeck_velocity_rad_per_s;
        let span = a.stribeck_span_nm;
        let q = (w.abs() / ws).max(1e-12);
        let e = if q * q > 746.0 { 0.0 } else { (-q * q).exp() };
        let de_dw = -e * 2.0 * q * w.signum() / ws;
        let tf = d * (f.coulomb_torque_nm + span * e) + f.viscous_nm_s_per_rad * w;
        let dtf_dw = d * span * de_dw + f.viscous_nm_s_per_rad;
        // DahlFriction::rate.
        let sigma = p.dahl.stiffness_n_per_m;
        let fc = p.dahl.coulomb_force_n;
        let qz = 1.0 - y[Z] * d / fc;
        let (dz, dz_dv, dz_dz) = (sigma * y[V] * qz, sigma * qz, -sigma * y[V] * d / fc);
        // slip_rhs.
        let f_drive = a.efficiency * (m.torque_constant_nm_per_a * y[I] - tf) / r;
        dy[X] = y[V];
        dy[V] = (f_drive - y[Z] - p.table.external_force_n) / a.equivalent_mass_kg;
        dy[Z] = dz;
        dy[I] = (self.u_v - m.resistance_ohm * y[I] - m.back_emf_v_s_per_rad * w) / m.inductance_h;
        // slip_jacobian.
        jac.fill(0.0);
        let meq = a.equivalent_mass_kg;
        let kt = m.torque_constant_nm_per_a;
        let di_dv = 0.0;
        let df_dv = a.efficiency * (kt * di_dv - dtf_dw / r) / r;
        jac[(X, V)] = 1.0;
        jac[(V, V)] = df_dv / meq;
        jac[(V, Z)] = -1.0 / meq;
        jac[(Z, V)] = dz_dv;
        jac[(Z, Z)] = dz_dz;
        jac[(V, I)] = a.efficiency * kt / (r * meq);
        jac[(I, V)] = -m.back_emf_v_s_per_rad / (r * m.inductance_h);
        jac[(I, I)] = -m.resistance_ohm / m.inductance_h;
    }

    /// The slip Jacobian given ∂T_f/∂w and the Dahl rate's partial derivatives.
    #[inline(always)]
    fn slip_jacobian(&self, dtf_dw: f64, dz_dv: f64, dz_dz: f64, jac: &mut Jac) {
        let a = self.axis;
        let p = &a.params;
        let m = &p.motor;
        let r = a.transmission_m_per_rad;
        jac.fill(0.0);
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
        jac[(Z, V)] = dz_dv;
        jac[(Z, Z)] = dz_dz;
        if !m.quasi_static_current {
            jac[(V, I)] = a.efficiency * kt / (r * meq);
            jac[(I, V)] = -m.back_emf_v_s_per_rad / (r * m.inductance_h);
            jac[(I, I)] = -m.resistance_ohm / m.inductance_h;
        }
    }
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
            Mode::Slip(d) if a.seed_laws => self.seed_slip_rhs(y, d, dy),
            Mode::Slip(d) => {
                let tf = p
                    .motor_friction
                    .torque_value(y[V] / r, d, a.stribeck_negligible_exponent);
                let (dz, _, _) = p.dahl.rate(y[V], y[Z], d);
                self.slip_rhs(y, tf, dz, dy);
            }
        }
    }

    fn rhs_and_jacobian(&self, y: &State, dy: &mut State, jac: &mut Jac) {
        match self.mode {
            Mode::Stuck => {
                self.rhs(y, dy);
                self.jacobian(y, jac);
            }
            Mode::Slip(d) if self.axis.seed_laws => self.seed_slip_rhs_and_jacobian(y, d, dy, jac),
            Mode::Slip(d) => {
                // One friction evaluation (an exponential) for both.
                let p = &self.axis.params;
                let (tf, dtf_dw) = p
                    .motor_friction
                    .torque(y[V] / self.axis.transmission_m_per_rad, d);
                let (dz, dz_dv, dz_dz) = p.dahl.rate(y[V], y[Z], d);
                self.slip_rhs(y, tf, dz, dy);
                self.slip_jacobian(dtf_dw, dz_dv, dz_dz, jac);
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
                let (_, dtf_dw) = p.motor_friction.torque(y[V] / r, d);
                let (_, dz_dv, dz_dz) = p.dahl.rate(y[V], y[Z], d);
                self.slip_jacobian(dtf_dw, dz_dv, dz_dz, jac);
            }
        }
    }

    /// Position, Dahl force and current each couple only to the velocity (and the stuck
    /// Jacobian is diagonal).
    fn arrowhead_hub(&self) -> Option<usize> {
        Some(V)
    }

    /// Slip: g = v·d, so g' = v'·d. Stuck: not given.
    fn event_rate(&self, _y: &State, f: &State) -> Option<f64> {
        match self.mode {
            Mode::Slip(d) => Some(f[V] * d),
            Mode::Stuck => None,
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
    /// Voltage of the last `advance` call (NaN before the first).
    u_last: f64,
    /// Error norm per (volt of input jump · s³ of first step) seen after the last jump.
    jump_error_rate: Option<f64>,
}

impl Plant {
    /// A plant at rest and stuck at x = 0, z = 0, i = 0.
    pub fn new(axis: Axis, integrator: Rodas4<STATE_DIM>) -> Self {
        let atol = axis.state_scales() * integrator.options.atol_position_m;
        Self {
            axis,
            y: State::zeros(),
            mode: Mode::Stuck,
            integrator,
            atol,
            u_last: f64::NAN,
            jump_error_rate: None,
        }
    }

    /// Motor current at the present state for a held voltage `u_v`.
    pub fn current(&self, u_v: f64) -> f64 {
        self.axis.current(&self.y, u_v)
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

    /// Advance from `t0` to `t1` with the voltage `u_v` held, handling stick/slip events.
    ///
    /// A jump of the held voltage excites the electrical transient (time constant L/R), which
    /// the step-size warm start (the last step of the previous segment, often the largest
    /// allowed) does not foresee: the first trial steps after a jump would be rejected
    /// several times. The error of that first step grows about as `|Δu|·h³` (measured on the
    /// seed axis), so the plant remembers the ratio seen after the last jump and starts the
    /// segment with the step that ratio predicts to give an error norm of 0.8 (never larger
    /// than the warm start). Error control itself is unchanged: every accepted step meets
    /// the tolerance.
    ///
    /// The work of one call is bounded: at most `max_steps` integrator steps over all its
    /// segments ([`SimError::TooManySteps`]) and at most `max_events` stick/slip transitions
    /// ([`SimError::TooManyEvents`]); transitions at one instant beyond
    /// `MAX_EVENTS_AT_ONE_INSTANT` leave the axis stuck, so every further segment starts
    /// later than the last. A state that is not finite at the end is
    /// [`SimError::NonFinite`], never returned.
    pub fn advance(&mut self, u_v: f64, t0: f64, t1: f64) -> Result<(), SimError> {
        self.advance_polled(u_v, t0, t1, &mut || false)
    }

    /// [`Self::advance`] asking `poll` every `POLL_EVERY_STEPS` integrator steps whether to
    /// stop (true: [`SimError::Interrupted`]).
    pub fn advance_polled(
        &mut self,
        u_v: f64,
        t0: f64,
        t1: f64,
        poll: &mut dyn FnMut() -> bool,
    ) -> Result<(), SimError> {
        hybrid::advance(self, &u_v, t0, t1, poll)
    }
}

impl HybridPlant for Plant {
    type Input = f64;

    fn voltage(u_v: &f64) -> f64 {
        *u_v
    }

    fn last_voltage(&mut self) -> &mut f64 {
        &mut self.u_last
    }

    fn options(&self) -> &IntegratorOptions {
        &self.integrator.options
    }

    fn state(&self) -> &[f64] {
        self.y.as_slice()
    }

    /// Break away from stiction if the holding torque exceeds the static torque.
    fn try_breakaway(&mut self, u_v: &f64) {
        if self.mode == Mode::Stuck {
            let t_req = self.axis.holding_torque(&self.y, *u_v);
            if t_req.abs() > self.axis.params.motor_friction.static_torque_nm {
                self.mode = Mode::Slip(t_req.signum());
            }
        }
    }

    fn stuck_phase(&mut self, u_v: &f64, t: f64, t1: f64) -> StuckPhase {
        if self.mode != Mode::Stuck {
            return StuckPhase::Integrate;
        }
        // Nothing moves; the current is algebraic or a first-order lag solved exactly.
        match self.stuck_current(*u_v, t1 - t) {
            None => StuckPhase::HeldToEnd,
            Some(dt) => StuckPhase::BreakawayAt(t + dt),
        }
    }

    fn start_slip(&mut self, u_v: &f64) {
        let t_req = self.axis.holding_torque(&self.y, *u_v);
        self.mode = Mode::Slip(t_req.signum());
    }

    fn integrate_segment(
        &mut self,
        u_v: &f64,
        t: f64,
        t1: f64,
        after_jump: Option<f64>,
        steps: &mut usize,
        poll: &mut dyn FnMut() -> bool,
    ) -> Result<SegmentEnd, SimError> {
        let seg = Segment {
            axis: &self.axis,
            mode: self.mode,
            u_v: *u_v,
        };
        self.integrator.integrate_after_jump(
            &seg,
            t,
            t1,
            &mut self.y,
            &self.atol,
            after_jump,
            &mut self.jump_error_rate,
            steps,
            poll,
        )
    }

    fn resolve_event(&mut self, u_v: &f64, force_stuck: bool) {
        let u_v = *u_v;
        match self.mode {
            Mode::Slip(d) => {
                self.y[V] = 0.0;
                let t_req = self.axis.holding_torque(&self.y, u_v);
                let ts = self.axis.params.motor_friction.static_torque_nm;
                self.mode = if t_req.abs() <= ts || force_stuck {
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
    }
}

#[cfg(test)]
mod tests {
    use super::{Axis, Jac, Mode, Plant, Segment, State, V};
    use crate::error::SimError;
    use crate::integrate::{IntegratorOptions, OdeSystem, Rodas4};
    use crate::model::AxisParams;
    use crate::presets::seed_axis;

    /// The seed axis with a Stribeck law that the stick/slip logic cannot resolve: exponent
    /// 0.5 (a friction slope unbounded at rest) and the smallest Stribeck velocity. Valid, but
    /// a breakaway chatters between stick and slip at ever shorter intervals.
    fn chattering_axis() -> AxisParams {
        let mut p = seed_axis();
        p.motor_friction.stribeck_exponent = 0.5;
        p.motor_friction.stribeck_velocity_rad_per_s = 1e-3;
        p
    }

    fn plant(p: AxisParams, options: IntegratorOptions) -> Plant {
        let axis = Axis::new(p).unwrap_or_else(|e| panic!("{e}"));
        Plant::new(axis, Rodas4::new(options).unwrap_or_else(|e| panic!("{e}")))
    }

    /// Advance 1 ms intervals at `u_v` until one fails (or 50 pass).
    fn first_failure(plant: &mut Plant, u_v: f64) -> Option<SimError> {
        (0..50).find_map(|k| {
            let t0 = k as f64 * 1e-3;
            plant.advance(u_v, t0, t0 + 1e-3).err()
        })
    }

    #[test]
    fn chattering_stick_slip_ends_with_too_many_events() {
        let mut p = plant(chattering_axis(), IntegratorOptions::default());
        match first_failure(&mut p, 1.0) {
            Some(SimError::TooManyEvents {
                t_s,
                max_events,
                state,
            }) => {
                assert_eq!(max_events, 10_000);
                assert!((0.0..0.05).contains(&t_s), "{t_s}");
                assert_eq!(state.len(), 4);
                assert!(state.iter().all(|v| v.is_finite()));
                // The budget counts located events and breakaways from stiction alike; the
                // integrator counts the located ones.
                let located = p.integrator.stats.n_events;
                assert!((1_000..=10_001).contains(&located), "{located}");
            }
            other => panic!("expected TooManyEvents, got {other:?}"),
        }
        // The same voltage on the seed axis: a handful of events per interval.
        let mut seed = plant(seed_axis(), IntegratorOptions::default());
        assert!(first_failure(&mut seed, 1.0).is_none());
        assert!(seed.integrator.stats.n_events < 50);
    }

    #[test]
    fn the_event_budget_is_the_option() {
        let options = IntegratorOptions {
            max_events: 25,
            ..IntegratorOptions::default()
        };
        let mut p = plant(chattering_axis(), options);
        match first_failure(&mut p, 1.0) {
            Some(SimError::TooManyEvents { max_events: 25, .. }) => {
                assert!(p.integrator.stats.n_events <= 26 * 50);
            }
            other => panic!("expected TooManyEvents after 25, got {other:?}"),
        }
    }

    #[test]
    fn the_step_budget_spans_the_segments_of_an_interval() {
        // Events without limit, so every segment between two events is short: only a count
        // over the whole interval stops the run.
        let options = IntegratorOptions {
            max_events: 1_000_000_000,
            max_steps: 2_000,
            ..IntegratorOptions::default()
        };
        let mut p = plant(chattering_axis(), options);
        let before = p.integrator.stats;
        match first_failure(&mut p, 1.0) {
            Some(SimError::TooManySteps { max_steps, .. }) => {
                assert_eq!(max_steps, 2_000);
                let s = p.integrator.stats;
                let events = s.n_events - before.n_events;
                // Many segments, each far below the limit.
                assert!(events > 100, "{events}");
            }
            other => panic!("expected TooManySteps, got {other:?}"),
        }
    }

    #[test]
    fn a_state_that_is_not_finite_is_an_error_not_a_result() {
        // A resistance far below the valid range (set after validation): the stalled current
        // u/R overflows while the axis is stuck, where no integrator step would notice.
        let mut p = plant(seed_axis(), IntegratorOptions::default());
        p.axis.params.motor.resistance_ohm = 5e-324;
        match p.advance(0.5, 0.0, 1e-3) {
            Err(SimError::NonFinite { t_s, state }) => {
                assert_eq!(t_s, 1e-3);
                assert!(state[3].is_nan());
            }
            other => panic!("expected NonFinite, got {other:?}"),
        }
    }

    /// The seed-law slip right-hand side (alone and with the Jacobian) equals the general one
    /// bit for bit: states from rest
    /// to slewing speed (through the Stribeck range and past the exponential's cut-off), Dahl
    /// forces across ±F_c, both directions, friction levels scaled as in a campaign.
    #[test]
    fn seed_slip_rhs_is_the_general_rhs_bit_for_bit() {
        let mut s = 0x9e37_79b9_7f4a_7c15_u64;
        let mut next = || {
            s ^= s << 13;
            s ^= s >> 7;
            s ^= s << 17;
            (s >> 11) as f64 / (1u64 << 53) as f64 * 2.0 - 1.0
        };
        for scale in [1.0, 0.7, 1.3] {
            let fast =
                Axis::new(seed_axis().with_friction_scale(scale)).unwrap_or_else(|e| panic!("{e}"));
            assert!(fast.seed_laws);
            let mut general = fast;
            general.seed_laws = false;
            let fc = fast.params.dahl.coulomb_force_n;
            for k in 0..20_000 {
                let v = 0.02 * next() * 10f64.powf(-4.0 * (next() + 1.0) / 2.0);
                let y = State::new(1e-3 * next(), v, 1.2 * fc * next(), 2.0 * next());
                let d = if k % 2 == 0 { 1.0 } else { -1.0 };
                let u_v = 6.0 * next();
                let (mut a, mut b) = (State::zeros(), State::zeros());
                Segment {
                    axis: &fast,
                    mode: Mode::Slip(d),
                    u_v,
                }
                .rhs(&y, &mut a);
                Segment {
                    axis: &general,
                    mode: Mode::Slip(d),
                    u_v,
                }
                .rhs(&y, &mut b);
                for i in 0..4 {
                    assert_eq!(
                        a[i].to_bits(),
                        b[i].to_bits(),
                        "{y} d {d} u {u_v} (v {})",
                        y[V]
                    );
                }
                let (mut ja, mut jb) = (Jac::zeros(), Jac::zeros());
                Segment {
                    axis: &fast,
                    mode: Mode::Slip(d),
                    u_v,
                }
                .rhs_and_jacobian(&y, &mut a, &mut ja);
                Segment {
                    axis: &general,
                    mode: Mode::Slip(d),
                    u_v,
                }
                .rhs_and_jacobian(&y, &mut b, &mut jb);
                for i in 0..4 {
                    assert_eq!(a[i].to_bits(), b[i].to_bits(), "{y} d {d} u {u_v}");
                    for j in 0..4 {
                        assert_eq!(ja[(i, j)].to_bits(), jb[(i, j)].to_bits(), "{y} d {d}");
                    }
                }
            }
        }
    }
}
