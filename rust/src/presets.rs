//! The seed axis (Kamenar, Zelenika et al.) as numbers. Units, sources and confidence of
//! every value are tabulated in `python/nanostage/presets.py`; the Python
//! preset reads its numbers from here so that there is one source.
use crate::control::{AntiWindup, Encoder, FxpFormat, OutputStage, Overflow, PidConfig, Rounding};
use crate::integrate::IntegratorOptions;
use crate::model::{AxisParams, BallScrew, DahlFriction, Gearhead, Motor, StribeckFriction, Table};
use crate::sim::ClosedLoopConfig;

/// The seed axis plant.
pub fn seed_axis() -> AxisParams {
    AxisParams {
        motor: Motor {
            resistance_ohm: 3.4,
            inductance_h: 70e-6,
            torque_constant_nm_per_a: 6.6e-3,
            back_emf_v_s_per_rad: 6.6e-3,
            rotor_inertia_kg_m2: 1.0e-7,
            quasi_static_current: false,
        },
        motor_friction: StribeckFriction {
            static_torque_nm: 0.12e-3,
            coulomb_torque_nm: 0.10e-3,
            viscous_nm_s_per_rad: 2.0e-8,
            stribeck_velocity_rad_per_s: 10.0,
            stribeck_exponent: 2.0,
        },
        gearhead: Gearhead {
            ratio: 19.0,
            efficiency: 0.8,
        },
        screw: BallScrew {
            lead_m: 2e-3,
            efficiency: 0.9,
            inertia_kg_m2: 1.0e-7,
        },
        table: Table {
            mass_kg: 0.5,
            external_force_n: 0.0,
        },
        dahl: DahlFriction {
            coulomb_force_n: 30.4,
            stiffness_n_per_m: 75e6,
            exponent: 1.0,
        },
    }
}

const fn fxp(signed: bool, word_bits: u32, int_bits: i32, overflow: Overflow) -> FxpFormat {
    FxpFormat {
        signed,
        word_bits,
        int_bits,
        rounding: Rounding::HalfEven,
        overflow,
    }
}

/// Table 1 gains (Kp, Ki, Kd) of the paper for a step size: 100/500 µm → (450, 2, 40),
/// 1 mm → (450, 5, 10), 10 mm → (450, 5, 25); other sizes take the nearest row (log scale).
pub fn table1_gains(step_m: f64) -> (f64, f64, f64) {
    let rows: [(f64, (f64, f64, f64)); 4] = [
        (100e-6, (450.0, 2.0, 40.0)),
        (500e-6, (450.0, 2.0, 40.0)),
        (1e-3, (450.0, 5.0, 10.0)),
        (10e-3, (450.0, 5.0, 25.0)),
    ];
    let s = step_m.abs().max(1e-12).ln();
    let mut best = rows[0];
    for row in rows {
        if (row.0.ln() - s).abs() < (best.0.ln() - s).abs() {
            best = row;
        }
    }
    best.1
}

/// The seed FPGA loop with the given gains (output unit 0.1 mV, ±6 V range, conditional
/// integration, 40 MHz clock, 1 ms period, 130-tick latency).
pub fn seed_pid(kp: f64, ki: f64, kd: f64) -> PidConfig {
    PidConfig {
        kp,
        ki,
        kd,
        gain_format: fxp(true, 24, 16, Overflow::Saturate),
        measurement_format: fxp(true, 32, 32, Overflow::Wrap),
        error_format: fxp(true, 32, 32, Overflow::Saturate),
        term_format: fxp(true, 48, 40, Overflow::Saturate),
        integrator_format: fxp(true, 48, 40, Overflow::Saturate),
        output_format: fxp(true, 32, 24, Overflow::Saturate),
        dac_format: fxp(true, 16, 16, Overflow::Saturate),
        dac_scale_format: fxp(false, 16, 0, Overflow::Saturate),
        output_min: -60_000.0,
        output_max: 60_000.0,
        anti_windup: AntiWindup::Conditional,
        output_unit_v: 1e-4,
        dac_lsb_v: 20.0 / 65536.0,
        clock_hz: 40e6,
        ticks_per_sample: 40_000,
        latency_ticks: 130,
    }
}

/// The seed closed loop with Table 1 gains for `step_m`.
pub fn seed_closed_loop(step_m: f64) -> ClosedLoopConfig {
    let (kp, ki, kd) = table1_gains(step_m);
    ClosedLoopConfig {
        axis: seed_axis(),
        pid: seed_pid(kp, ki, kd),
        encoder: Encoder { count_m: 100e-9 },
        output: OutputStage {
            amplifier_gain: 1.0,
            amplifier_limit_v: 6.0,
        },
        integrator: IntegratorOptions::default(),
    }
}

/// The heavy table friction of the issue-3 speed cases (criterion bench
/// `closed_loop_1s_gms6*` and `examples/profile_drive.rs`): a six-element Generalized
/// Maxwell-Slip model at the seed's Coulomb level, static level 36 N.
pub fn speed_case_gms6() -> crate::model::TableFriction {
    crate::model::TableFriction::Gms(crate::model::Gms {
        n_elements: 6,
        stiffness_n_per_m: [3e7, 2e7, 1e7, 6e6, 4e6, 2e6, 1.0, 1.0],
        weights: [0.1, 0.15, 0.2, 0.2, 0.2, 0.15, 0.0, 0.0],
        coulomb_force_n: 30.4,
        static_force_n: 36.0,
        stribeck_velocity_m_per_s: 1e-3,
        viscous_n_s_per_m: 0.0,
    })
}

/// The drive-train link of the issue-3 speed cases: the seed's 20 µm gearhead backlash at
/// the table with a compliant coupling (two-mass drive train).
pub fn speed_case_backlash_link() -> crate::model::Link {
    crate::model::Link {
        stiffness_n_per_m: 4.9e7,
        damping_n_s_per_m: 2e3,
        backlash_m: 20e-6,
    }
}
