//! Controller emulation: the bit-exact FPGA loop (integers and fixed point only) and its
//! boundary to the physical world (encoder, DAC, amplifier).

pub mod cascade;
pub mod fixed;
pub mod io;
pub mod pid;

pub use cascade::{Cascade, CascadeConfig};
pub use fixed::{FxpFormat, Overflow, Rounding};
pub use io::{Encoder, OutputStage};
pub use pid::{flags, AntiWindup, Pid, PidConfig, PidOutput};
