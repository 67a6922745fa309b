//! The plant a run drives, behind one dispatch: the rigid seed plant (the fast path) or the
//! component plant of the effect library.
use crate::error::{ConfigError, SimError};
use crate::integrate::{IntegratorOptions, Rodas4, Stats};
use crate::model::{AnyDrivePlant, Axis, AxisParams, DriveParams, Inputs, MassMode, Mode, Plant};

/// The plant of one run: the rigid seed plant (analytic Jacobian, exact stuck phases) or the
/// component plant. Every choice between the two is made here.
pub(super) enum AnyPlant {
    Rigid(Box<Plant>),
    Drive(AnyDrivePlant),
}

impl AnyPlant {
    /// The rigid plant of `rigid` (friction levels scaled by `level`) when `drive` is that
    /// axis's component plant, otherwise the component plant of `drive`.
    pub(super) fn new(
        drive: &DriveParams,
        rigid: Option<&AxisParams>,
        level: f64,
        integrator: IntegratorOptions,
    ) -> Result<Self, ConfigError> {
        Ok(match rigid {
            Some(axis) if DriveParams::from_axis(axis) == *drive => {
                let a =
                    Axis::new(axis.with_friction_scale(level)).map_err(|e| e.within("plant"))?;
                let integ = Rodas4::new(integrator).map_err(|e| e.within("integrator"))?;
                Self::Rigid(Box::new(Plant::new(a, integ)))
            }
            _ => Self::component(drive, integrator)?,
        })
    }

    /// The component plant of `drive`.
    pub(super) fn component(
        drive: &DriveParams,
        integrator: IntegratorOptions,
    ) -> Result<Self, ConfigError> {
        Ok(Self::Drive(
            AnyDrivePlant::new(*drive, integrator).map_err(|e| e.within("plant"))?,
        ))
    }

    /// Place every mass at `x_m` (at rest, relaxed), the drive side of a dead band at
    /// `flank` (see [`AnyDrivePlant::set_position`]).
    pub(super) fn set_position(&mut self, x_m: f64, flank: f64) {
        match self {
            Self::Rigid(p) => p.y[0] = x_m,
            Self::Drive(p) => p.set_position(x_m, flank),
        }
    }

    /// Whether this is the rigid plant.
    pub(super) fn is_rigid(&self) -> bool {
        matches!(self, Self::Rigid(_))
    }

    pub(super) fn advance(
        &mut self,
        inp: &Inputs,
        t0: f64,
        t1: f64,
        poll: &mut dyn FnMut() -> bool,
    ) -> Result<(), SimError> {
        if t1 <= t0 {
            return Ok(());
        }
        match self {
            Self::Rigid(p) => p.advance_polled(inp.u_v, t0, t1, poll),
            Self::Drive(p) => p.advance_polled(inp, t0, t1, poll),
        }
    }

    /// (table position, motor-side position): what the sensors need (equal to the first two
    /// entries of [`Self::observe`]).
    #[inline]
    pub(super) fn positions(&self) -> (f64, f64) {
        match self {
            Self::Rigid(p) => (p.y[0], p.y[0]),
            Self::Drive(p) => {
                let y = p.state();
                (y[2 * p.drive().table()], y[0])
            }
        }
    }

    /// (table position, motor-side position, table velocity, current, motor friction,
    /// table friction, stuck)
    pub(super) fn observe(&self, inp: &Inputs) -> (f64, f64, f64, f64, f64, f64, bool) {
        match self {
            Self::Rigid(p) => (
                p.y[0],
                p.y[0],
                p.y[1],
                p.current(inp.u_v),
                p.axis.motor_friction_force(&p.y, p.mode, inp.u_v),
                p.y[2],
                p.mode == Mode::Stuck,
            ),
            Self::Drive(p) => {
                let d = p.drive();
                let y = p.state();
                let modes = p.modes();
                let t = d.table();
                let (fm, ft) = d.friction_forces(y, inp, &modes);
                (
                    y[2 * t],
                    y[0],
                    y[2 * t + 1],
                    d.current_a(y, inp),
                    fm,
                    ft,
                    modes[0] == MassMode::Stuck || modes[t] == MassMode::Stuck,
                )
            }
        }
    }

    pub(super) fn stats(&self) -> Stats {
        match self {
            Self::Rigid(p) => p.integrator.stats,
            Self::Drive(p) => p.stats(),
        }
    }

    /// [`SimError::NonFinite`] at `t_s` (with the plant's state) unless every value of
    /// `observed` is finite: a recorded channel that is not finite is an error, never output.
    pub(super) fn check_finite(&self, t_s: f64, observed: &[f64]) -> Result<(), SimError> {
        if observed.iter().all(|v| v.is_finite()) {
            return Ok(());
        }
        Err(SimError::NonFinite {
            t_s,
            state: match self {
                Self::Rigid(p) => p.y.iter().copied().collect(),
                Self::Drive(p) => p.state().to_vec(),
            },
        })
    }
}
