//! The component plant of the effect library: every effect the diagnosis can name is a
//! component here (friction models and modifiers, drive-train links, drive electronics).
//! With no effect switched on, the closed loop uses the rigid seed plant of [`crate::model`]
//! (analytic Jacobian, exact stuck phases); the two agree (tests/drive.rs).
mod model;
mod params;
mod response;

pub use model::{
    AnyDrivePlant, Drive, DrivePlant, Inputs, MassMode, GMS_ELASTIC_FRACTION, MAX_MASSES,
};
pub use params::{
    Actuator, Amplifier, DriveParams, DwellStatic, Gms, Link, LuGre, Modulation, Side, StaticMap,
    TableFriction, MAX_GMS_ELEMENTS, MAX_MODULATION_TERMS,
};
pub use response::{friction_response, friction_response_polled};
