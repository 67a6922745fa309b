//! Work profile of the component-plant closed loop (the general path).
//!
//! `cargo run --release --no-default-features --example profile_drive [REPS] [CASE]` runs a
//! 100 µm step of 0.32 s (the diagnosis's typical experiment) and the 1 s, 1 mm step of the
//! criterion bench for the rigid seed loop and each component-plant case, printing the best
//! wall time of REPS runs (default 20), the integrator's counters and a checksum of the
//! positions (to see whether a change moved the trajectory). `CASE` filters by name.
use nanostage::model::{DwellStatic, Link, TableFriction};
#[path = "../tests/support/presets.rs"]
mod presets;
use nanostage::sim::{run_extended, ExtendedConfig, KnownInputs};
use presets::{seed_closed_loop, speed_case_backlash_link, speed_case_gms6};
use std::time::Instant;

fn cases(step_m: f64) -> Vec<(&'static str, ExtendedConfig)> {
    let base = ExtendedConfig::from_closed_loop(&seed_closed_loop(step_m));
    let mut general = base;
    general.axis = None;
    let fs_motor = base.drive.motor_friction.map_or(1.0, |m| m.static_force_n);
    let mut dwell = general;
    if let Some(m) = dwell.drive.motor_friction.as_mut() {
        m.dwell = Some(DwellStatic {
            rise_n: 0.3 * fs_motor,
            time_constant_s: 0.1,
            slip_distance_m: None,
        });
    }
    let mut memory = general;
    if let Some(m) = memory.drive.motor_friction.as_mut() {
        m.memory_lag_s = Some(5e-3);
    }
    let mut lead = general;
    lead.drive.motor_modulation.n_terms = 1;
    lead.drive.motor_modulation.amplitude[0] = 0.0707;
    lead.drive.motor_modulation.wavenumber_rad_per_m[0] = 2.0 * std::f64::consts::PI / 1e-3;
    lead.drive.motor_modulation.phase_rad[0] = -0.785;
    let fc = match base.drive.table_friction {
        TableFriction::Dahl(d) => d.law.coulomb_force_n,
        _ => 1.0,
    };
    let mut cv = general;
    cv.drive.table_friction = TableFriction::Static(nanostage::model::StaticMap {
        static_force_n: fc,
        coulomb_force_n: fc,
        viscous_n_s_per_m: 100.0,
        stribeck_velocity_m_per_s: 1e-3,
        stribeck_exponent: 2.0,
        asymmetry: 0.0,
        viscous_asymmetry: 0.0,
        dwell: None,
        memory_lag_s: None,
    });
    let mut lugre = general;
    lugre.drive.table_friction = TableFriction::LuGre(nanostage::model::LuGre {
        stiffness_n_per_m: 1e7,
        damping_n_s_per_m: 0.0,
        viscous_n_s_per_m: 0.0,
        coulomb_force_n: fc,
        static_force_n: 1.3 * fc,
        stribeck_velocity_m_per_s: 5e-4,
        asymmetry: 0.0,
    });
    let gms = speed_case_gms6();
    let backlash = speed_case_backlash_link();
    let mut gms6 = general;
    gms6.drive.table_friction = gms;
    let mut bl = general;
    bl.drive.n_links = 1;
    bl.drive.links[0] = backlash;
    let mut compliance = general;
    compliance.drive.n_links = 1;
    compliance.drive.links[0] = Link {
        backlash_m: 0.0,
        ..backlash
    };
    let mut all = bl;
    all.drive.table_friction = gms;
    let mut amp = general;
    amp.drive.amplifier = Some(nanostage::model::Amplifier {
        bandwidth_hz: 300.0,
        slew_v_per_s: 1e9,
    });
    vec![
        ("rigid", base),
        ("general", general),
        ("coulomb_viscous", cv),
        ("dwell", dwell),
        ("memory", memory),
        ("lead", lead),
        ("lugre", lugre),
        ("gms6", gms6),
        ("backlash", bl),
        ("compliance", compliance),
        ("amplifier", amp),
        ("gms6_backlash", all),
    ]
}

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let reps: usize = args.first().and_then(|s| s.parse().ok()).unwrap_or(20);
    let filter = args.get(1).cloned().unwrap_or_default();
    if let Ok(case) = std::env::var("PHASES") {
        phases(&case);
        return;
    }
    if std::env::var("ACCURACY").is_ok() {
        accuracy();
        return;
    }
    for (label, step_m, n, start) in [("100um_0.32s", 100e-6, 320, 10), ("1mm_1s", 1e-3, 1000, 10)]
    {
        let r: Vec<f64> = (0..n)
            .map(|k| if k >= start { step_m } else { 0.0 })
            .collect();
        let mut t_rigid = f64::NAN;
        for (name, cfg) in cases(step_m) {
            if !filter.is_empty() && !name.contains(&filter) && name != "rigid" {
                continue;
            }
            let mut best = f64::INFINITY;
            let mut tr = None;
            for _ in 0..reps.max(1) {
                let t0 = Instant::now();
                let out = run_extended(&cfg, &r, KnownInputs::default(), None).expect("run");
                best = best.min(t0.elapsed().as_secs_f64());
                tr = Some(out);
            }
            let Some(tr) = tr else { continue };
            if name == "rigid" {
                t_rigid = best;
            }
            let s = tr.stats;
            let sum: f64 = tr.position_m.iter().sum();
            println!(
                "{label:12} {name:16} {:9.3} ms ({:6.1}x) acc {:6} rej {:5} rhs {:7} jac {:6} ev {:4} final {:.6e} sum {:.9e}",
                1e3 * best,
                best / t_rigid,
                s.n_accepted,
                s.n_rejected,
                s.n_rhs,
                s.n_jac,
                s.n_events,
                tr.position_m[n - 1],
                sum
            );
        }
    }
}

/// Steps per stretch of the 100 µm step for one case (`PHASES=case`).
#[allow(dead_code)]
pub fn phases(case: &str) {
    let r: Vec<f64> = (0..320)
        .map(|k| if k >= 10 { 100e-6 } else { 0.0 })
        .collect();
    let Some((_, cfg)) = cases(100e-6).into_iter().find(|(n, _)| *n == case) else {
        return;
    };
    let mut prev = (0u64, 0u64, 0u64);
    for n in [10usize, 12, 15, 20, 30, 40, 60, 80, 120, 160, 240, 320] {
        let tr = run_extended(&cfg, &r[..n], KnownInputs::default(), None).expect("run");
        let s = tr.stats;
        let stuck = tr.stuck.iter().filter(|b| **b).count();
        println!(
            "to {n:4}: acc {:6} rej {:5} ev {:4}  stuck samples {stuck}  x {:.4e} xm {:.4e}",
            s.n_accepted - prev.0,
            s.n_rejected - prev.1,
            s.n_events - prev.2,
            tr.position_m[n - 1],
            tr.motor_position_m[n - 1],
        );
        prev = (s.n_accepted, s.n_rejected, s.n_events);
    }
}

/// Each case with the default and a tight (rtol 1e-10, atol 1e-14 m) integrator: the largest
/// position difference up to the first sample where the encoder counts differ, and that
/// sample (`ACCURACY=1`).
pub fn accuracy() {
    for (label, step_m, n) in [("100um_0.32s", 100e-6, 320usize), ("1mm_1s", 1e-3, 1000)] {
        let r: Vec<f64> = (0..n).map(|k| if k >= 10 { step_m } else { 0.0 }).collect();
        for (name, cfg) in cases(step_m) {
            let mut tight = cfg;
            tight.integrator.rtol = 1e-10;
            tight.integrator.atol_position_m = 1e-14;
            let a = run_extended(&cfg, &r, KnownInputs::default(), None).expect("run");
            let b = run_extended(&tight, &r, KnownInputs::default(), None).expect("run");
            let first = (0..n).find(|&k| a.encoder_counts[k] != b.encoder_counts[k]);
            let upto = first.unwrap_or(n);
            let worst = (0..upto)
                .map(|k| (a.position_m[k] - b.position_m[k]).abs())
                .fold(0.0_f64, f64::max);
            let all = (0..n)
                .map(|k| (a.position_m[k] - b.position_m[k]).abs())
                .fold(0.0_f64, f64::max);
            println!(
                "{label:12} {name:16} max|dx| before first count difference {worst:.2e} m; first count difference at {}; max|dx| overall {all:.2e} m",
                first.map_or("none".to_string(), |k| k.to_string()),
            );
        }
    }
}
