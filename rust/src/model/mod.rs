//! Physics: what the plant is.
//!
//! State `y = [x_m, v_m_per_s, z_n, i_a]` (table position, table velocity, Dahl friction
//! force, motor current) plus a discrete mode (stuck, or slipping in a direction).
//! The equations are written out in `docs/model.md`.

mod axis;
mod friction;
mod params;

pub use axis::{Axis, Mode, Plant, STATE_DIM};
pub use params::{
    AxisParams, BallScrew, DahlFriction, Gearhead, Motor, StribeckFriction, Table,
    MIN_COULOMB_FORCE_N, MIN_EFFICIENCY, MIN_INDUCTANCE_H, MIN_LEAD_M, MIN_MASS_KG,
    MIN_PRESLIDING_STIFFNESS_N_PER_M, MIN_RESISTANCE_OHM, MIN_ROTOR_INERTIA_KG_M2,
    MIN_STRIBECK_VELOCITY_RAD_PER_S,
};
