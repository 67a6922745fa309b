//! The seed axis for the Rust tests, benches and examples, read from the model file the
//! Python package ships (`python/nanostage/model_files/seed.model.toml`, docs/model-file.md):
//! the one place its numbers are written. Included with `#[path]` by the test and bench
//! crates, and as `crate::presets` by the library's unit tests (`cfg(test)`); needs the `toml`
//! dev-dependency. A malformed file is a panic naming the file and the key.
#![allow(dead_code)]

use std::sync::OnceLock;

use nanostage::control::{
    AntiWindup, Encoder, FxpFormat, OutputStage, Overflow, PidConfig, Rounding,
};
use nanostage::integrate::IntegratorOptions;
use nanostage::model::{
    AxisParams, BallScrew, DahlFriction, Gearhead, Gms, Link, Motor, StribeckFriction, Table,
    TableFriction,
};
use nanostage::sim::ClosedLoopConfig;

const FILE: &str = "python/nanostage/model_files/seed.model.toml";
const TEXT: &str = include_str!("../../../python/nanostage/model_files/seed.model.toml");

/// The seed file read once: the closed loop with the controller's (1 mm) gains and the
/// Table 1 rows (step size, m → (Kp, Ki, Kd)).
struct Seed {
    closed_loop: ClosedLoopConfig,
    table1: Vec<(f64, (f64, f64, f64))>,
}

fn seed() -> &'static Seed {
    static SEED: OnceLock<Seed> = OnceLock::new();
    SEED.get_or_init(|| {
        let doc: toml::Table = TEXT
            .parse()
            .unwrap_or_else(|e| panic!("{FILE}: not valid TOML: {e}"));
        parse(&doc)
    })
}

fn table<'a>(t: &'a toml::Table, path: &str, key: &str) -> &'a toml::Table {
    t.get(key)
        .and_then(toml::Value::as_table)
        .unwrap_or_else(|| panic!("{FILE}: missing table [{path}{key}]"))
}

fn value<'a>(t: &'a toml::Table, path: &str, key: &str) -> &'a toml::Value {
    t.get(key)
        .unwrap_or_else(|| panic!("{FILE}: missing key {path}{key}"))
}

fn num(t: &toml::Table, path: &str, key: &str) -> f64 {
    match value(t, path, key) {
        toml::Value::Float(x) => *x,
        toml::Value::Integer(i) => *i as f64,
        other => panic!("{FILE}: {path}{key} = {other:?} is invalid: expected a number"),
    }
}

fn int(t: &toml::Table, path: &str, key: &str) -> i64 {
    value(t, path, key)
        .as_integer()
        .unwrap_or_else(|| panic!("{FILE}: {path}{key} is invalid: expected an integer"))
}

fn flag(t: &toml::Table, path: &str, key: &str) -> bool {
    value(t, path, key)
        .as_bool()
        .unwrap_or_else(|| panic!("{FILE}: {path}{key} is invalid: expected true or false"))
}

fn text<'a>(t: &'a toml::Table, path: &str, key: &str) -> &'a str {
    value(t, path, key)
        .as_str()
        .unwrap_or_else(|| panic!("{FILE}: {path}{key} is invalid: expected a string"))
}

fn fxp(ctl: &toml::Table, key: &str) -> FxpFormat {
    let t = table(ctl, "controller.", key);
    let path = format!("controller.{key}.");
    let word = int(t, &path, "word_bits");
    let int_bits = int(t, &path, "int_bits");
    FxpFormat {
        signed: flag(t, &path, "signed"),
        word_bits: u32::try_from(word)
            .unwrap_or_else(|_| panic!("{FILE}: {path}word_bits = {word} is out of range")),
        int_bits: i32::try_from(int_bits)
            .unwrap_or_else(|_| panic!("{FILE}: {path}int_bits = {int_bits} is out of range")),
        rounding: match text(t, &path, "rounding") {
            "truncate" => Rounding::Truncate,
            "half_up" => Rounding::HalfUp,
            "half_even" => Rounding::HalfEven,
            other => panic!("{FILE}: {path}rounding = {other:?} is invalid"),
        },
        overflow: match text(t, &path, "overflow") {
            "saturate" => Overflow::Saturate,
            "wrap" => Overflow::Wrap,
            other => panic!("{FILE}: {path}overflow = {other:?} is invalid"),
        },
    }
}

fn ticks(t: &toml::Table, key: &str) -> u64 {
    let v = int(t, "controller.", key);
    u64::try_from(v).unwrap_or_else(|_| panic!("{FILE}: controller.{key} = {v} is negative"))
}

fn count(t: &toml::Table, key: &str) -> usize {
    let v = int(t, "integrator.", key);
    usize::try_from(v).unwrap_or_else(|_| panic!("{FILE}: integrator.{key} = {v} is negative"))
}

fn parse(doc: &toml::Table) -> Seed {
    let plant = table(doc, "", "plant");
    assert_eq!(
        text(plant, "plant.", "kind"),
        "rigid_axis",
        "{FILE}: plant.kind"
    );
    let m = table(plant, "plant.", "motor");
    let mf = table(plant, "plant.", "motor_friction");
    let g = table(plant, "plant.", "gearhead");
    let s = table(plant, "plant.", "screw");
    let tb = table(plant, "plant.", "table");
    let d = table(plant, "plant.", "dahl");
    let axis = AxisParams {
        motor: Motor {
            resistance_ohm: num(m, "plant.motor.", "resistance_ohm"),
            inductance_h: num(m, "plant.motor.", "inductance_h"),
            torque_constant_nm_per_a: num(m, "plant.motor.", "torque_constant_nm_per_a"),
            back_emf_v_s_per_rad: num(m, "plant.motor.", "back_emf_v_s_per_rad"),
            rotor_inertia_kg_m2: num(m, "plant.motor.", "rotor_inertia_kg_m2"),
            quasi_static_current: flag(m, "plant.motor.", "quasi_static_current"),
        },
        motor_friction: StribeckFriction {
            static_torque_nm: num(mf, "plant.motor_friction.", "static_torque_nm"),
            coulomb_torque_nm: num(mf, "plant.motor_friction.", "coulomb_torque_nm"),
            viscous_nm_s_per_rad: num(mf, "plant.motor_friction.", "viscous_nm_s_per_rad"),
            stribeck_velocity_rad_per_s: num(
                mf,
                "plant.motor_friction.",
                "stribeck_velocity_rad_per_s",
            ),
            stribeck_exponent: num(mf, "plant.motor_friction.", "stribeck_exponent"),
        },
        gearhead: Gearhead {
            ratio: num(g, "plant.gearhead.", "ratio"),
            efficiency: num(g, "plant.gearhead.", "efficiency"),
        },
        screw: BallScrew {
            lead_m: num(s, "plant.screw.", "lead_m"),
            efficiency: num(s, "plant.screw.", "efficiency"),
            inertia_kg_m2: num(s, "plant.screw.", "inertia_kg_m2"),
        },
        table: Table {
            mass_kg: num(tb, "plant.table.", "mass_kg"),
            external_force_n: num(tb, "plant.table.", "external_force_n"),
        },
        dahl: DahlFriction {
            coulomb_force_n: num(d, "plant.dahl.", "coulomb_force_n"),
            stiffness_n_per_m: num(d, "plant.dahl.", "stiffness_n_per_m"),
            exponent: num(d, "plant.dahl.", "exponent"),
        },
    };
    let c = table(doc, "", "controller");
    assert_eq!(
        text(c, "controller.", "kind"),
        "fpga_pid",
        "{FILE}: controller.kind"
    );
    let pid = PidConfig {
        kp: num(c, "controller.", "kp"),
        ki: num(c, "controller.", "ki"),
        kd: num(c, "controller.", "kd"),
        gain_format: fxp(c, "gain_format"),
        measurement_format: fxp(c, "measurement_format"),
        error_format: fxp(c, "error_format"),
        term_format: fxp(c, "term_format"),
        integrator_format: fxp(c, "integrator_format"),
        output_format: fxp(c, "output_format"),
        dac_format: fxp(c, "dac_format"),
        dac_scale_format: fxp(c, "dac_scale_format"),
        output_min: num(c, "controller.", "output_min"),
        output_max: num(c, "controller.", "output_max"),
        anti_windup: match text(c, "controller.", "anti_windup") {
            "none" => AntiWindup::None,
            "clamp" => AntiWindup::Clamp,
            "conditional" => AntiWindup::Conditional,
            other => panic!("{FILE}: controller.anti_windup = {other:?} is invalid"),
        },
        output_unit_v: num(c, "controller.", "output_unit_v"),
        dac_lsb_v: num(c, "controller.", "dac_lsb_v"),
        clock_hz: num(c, "controller.", "clock_hz"),
        ticks_per_sample: ticks(c, "ticks_per_sample"),
        latency_ticks: ticks(c, "latency_ticks"),
    };
    let e = table(doc, "", "encoder");
    let o = table(doc, "", "output_stage");
    let i = table(doc, "", "integrator");
    let closed_loop = ClosedLoopConfig {
        axis,
        pid,
        encoder: Encoder {
            count_m: num(e, "encoder.", "count_m"),
        },
        output: OutputStage {
            amplifier_gain: num(o, "output_stage.", "amplifier_gain"),
            amplifier_limit_v: num(o, "output_stage.", "amplifier_limit_v"),
        },
        integrator: IntegratorOptions {
            rtol: num(i, "integrator.", "rtol"),
            atol_position_m: num(i, "integrator.", "atol_position_m"),
            h_init_s: num(i, "integrator.", "h_init_s"),
            h_min_s: num(i, "integrator.", "h_min_s"),
            h_max_s: num(i, "integrator.", "h_max_s"),
            max_steps: count(i, "max_steps"),
            max_events: count(i, "max_events"),
            event_tol_s: num(i, "integrator.", "event_tol_s"),
        },
    };
    let prov = table(doc, "", "provenance");
    let rows = value(prov, "provenance.", "table1_gains")
        .as_array()
        .unwrap_or_else(|| panic!("{FILE}: provenance.table1_gains is not an array"));
    let table1 = rows
        .iter()
        .enumerate()
        .map(|(k, row)| {
            let path = format!("provenance.table1_gains[{k}].");
            let r = row
                .as_table()
                .unwrap_or_else(|| panic!("{FILE}: {path} is not a table"));
            (
                num(r, &path, "step_m"),
                (
                    num(r, &path, "kp"),
                    num(r, &path, "ki"),
                    num(r, &path, "kd"),
                ),
            )
        })
        .collect();
    Seed {
        closed_loop,
        table1,
    }
}

/// The seed axis plant.
pub fn seed_axis() -> AxisParams {
    seed().closed_loop.axis
}

/// Table 1 gains (Kp, Ki, Kd) of the paper for a step size: the nearest row (log scale).
pub fn table1_gains(step_m: f64) -> (f64, f64, f64) {
    let rows = &seed().table1;
    let s = step_m.abs().max(1e-12).ln();
    let mut best = rows[0];
    for &row in rows {
        if (row.0.ln() - s).abs() < (best.0.ln() - s).abs() {
            best = row;
        }
    }
    best.1
}

/// The seed FPGA loop with the given gains (formats, limits and timing of the seed file).
pub fn seed_pid(kp: f64, ki: f64, kd: f64) -> PidConfig {
    PidConfig {
        kp,
        ki,
        kd,
        ..seed().closed_loop.pid
    }
}

/// The seed closed loop with Table 1 gains for `step_m`.
pub fn seed_closed_loop(step_m: f64) -> ClosedLoopConfig {
    let (kp, ki, kd) = table1_gains(step_m);
    ClosedLoopConfig {
        pid: seed_pid(kp, ki, kd),
        ..seed().closed_loop
    }
}

/// The heavy table friction of the speed cases (criterion bench `closed_loop_1s_gms6*` and
/// `examples/profile_drive.rs`): a six-element Generalized Maxwell-Slip model at the seed's
/// Coulomb level, static level 36 N.
pub fn speed_case_gms6() -> TableFriction {
    TableFriction::Gms(Gms {
        n_elements: 6,
        stiffness_n_per_m: [3e7, 2e7, 1e7, 6e6, 4e6, 2e6, 1.0, 1.0],
        weights: [0.1, 0.15, 0.2, 0.2, 0.2, 0.15, 0.0, 0.0],
        coulomb_force_n: seed_axis().dahl.coulomb_force_n,
        static_force_n: 36.0,
        stribeck_velocity_m_per_s: 1e-3,
        viscous_n_s_per_m: 0.0,
        asymmetry: 0.0,
    })
}

/// The drive-train link of the speed cases: the seed's 20 µm gearhead backlash at the table
/// with a compliant coupling (two-mass drive train).
pub fn speed_case_backlash_link() -> Link {
    Link {
        stiffness_n_per_m: 4.9e7,
        damping_n_s_per_m: 2e3,
        backlash_m: 20e-6,
    }
}
