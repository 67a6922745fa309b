//! Physics: what the plant is. The one home of the drive train's equations.
//!
//! - [`params`](AxisParams): the rigid seed axis's components (motor, gearhead, ball screw,
//!   table, friction), with the transmission `P/(2πN)` of [`BallScrew`].
//! - `friction.rs`: every friction law (Stribeck, Dahl, static maps, LuGre, GMS, position
//!   modulation).
//! - `rigid.rs` ([`Plant`]): the rigid seed axis, the fast path. State
//!   `y = [x_m, v_m_per_s, z_n, i_a]` (table position, table velocity, Dahl friction force,
//!   motor current) plus a discrete mode (stuck, or slipping in a direction).
//! - `component_params.rs` and `component.rs` ([`AnyDrivePlant`]): the component plant of
//!   the effect library. Every effect the diagnosis can name is a component here (friction
//!   models and modifiers, drive-train links, drive electronics). With no effect switched on,
//!   the closed loop uses the rigid plant (analytic Jacobian, exact stuck phases); the two
//!   agree (tests/drive.rs).
//! - `hybrid.rs`: the stick/slip event loop both plants run, with plant-specific hooks.
//! - `response.rs`: a friction component driven along a prescribed motion.
//!
//! The equations are written out in `docs/model.md`.

mod component;
mod component_params;
mod friction;
mod hybrid;
mod params;
mod response;
mod rigid;

pub use component::{AnyDrivePlant, Drive, DrivePlant, Inputs, MassMode, MAX_MASSES};
pub use component_params::{
    Actuator, Amplifier, DriveParams, DwellStatic, Gms, Link, LuGre, Modulation, Side, StaticMap,
    TableDahl, TableFriction, MAX_GMS_ELEMENTS, MAX_MODULATION_TERMS,
};
pub use friction::GMS_ELASTIC_FRACTION;
pub use params::{
    AxisParams, BallScrew, DahlFriction, Gearhead, Motor, StribeckFriction, Table,
    MIN_COULOMB_FORCE_N, MIN_EFFICIENCY, MIN_INDUCTANCE_H, MIN_LEAD_M, MIN_MASS_KG,
    MIN_PRESLIDING_STIFFNESS_N_PER_M, MIN_RESISTANCE_OHM, MIN_ROTOR_INERTIA_KG_M2,
    MIN_STRIBECK_VELOCITY_RAD_PER_S,
};
pub use response::{friction_response, friction_response_polled};
pub use rigid::{Axis, Mode, Plant, STATE_DIM};
