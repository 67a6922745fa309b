//! The component plant against the rigid seed plant, and effect physics that are cheapest to
//! check in Rust.
use nanostage::model::{AnyDrivePlant, DriveParams, Inputs, Link};
#[path = "support/presets.rs"]
mod presets;
use nanostage::sim::{run_closed_loop, run_extended, ExtendedConfig, KnownInputs};
use nanostage::SimError;
use presets::{seed_axis, seed_closed_loop};

fn step(n: usize, size_m: f64) -> Vec<f64> {
    (0..n).map(|k| if k < 5 { 0.0 } else { size_m }).collect()
}

#[test]
fn component_plant_matches_rigid_plant_with_effects_off() {
    let mut cfg = seed_closed_loop(1e-3);
    cfg.integrator.rtol = 1e-9;
    cfg.integrator.atol_position_m = 1e-13;
    let r = step(400, 1e-3);
    let rigid = run_closed_loop(&cfg, &r, None).expect("rigid run");
    let mut ext = ExtendedConfig::from_closed_loop(&cfg);
    ext.axis = None; // force the component plant
    let comp = run_extended(&ext, &r, KnownInputs::default(), None).expect("component run");
    let mut worst: f64 = 0.0;
    for (a, b) in rigid.position_m.iter().zip(&comp.position_m) {
        worst = worst.max((a - b).abs());
    }
    assert!(worst < 1e-9, "max |Δx| = {worst:e} m");
    assert_eq!(rigid.encoder_counts, comp.encoder_counts);
    assert_eq!(rigid.stuck, comp.stuck);
}

#[test]
fn component_plant_holds_still_below_breakaway() {
    let p = seed_axis();
    let mut d = DriveParams::from_axis(&p);
    d.n_links = 1;
    d.links[0] = Link {
        stiffness_n_per_m: 5e7,
        damping_n_s_per_m: 2e3,
        backlash_m: 2e-5,
    };
    let mut plant = AnyDrivePlant::new(d, Default::default()).expect("plant");
    // A voltage well below breakaway (0.5 of the stall voltage of the static torque).
    let m = p.motor;
    let u = 0.5 * p.motor_friction.static_torque_nm / m.torque_constant_nm_per_a * m.resistance_ohm;
    for k in 0..100 {
        plant
            .advance(&Inputs::voltage(u), k as f64 * 0.1, (k + 1) as f64 * 0.1)
            .expect("advance");
    }
    let y = plant.state();
    assert_eq!(y[0], 0.0, "motor side moved: {}", y[0]);
    assert_eq!(y[2], 0.0, "table moved: {}", y[2]);
}

/// The event budget holds on the component plant: a table with a falling (Stribeck) friction
/// pulled through a soft link by a motor at constant voltage sticks and slips a few times in
/// each 0.5 s interval, so a budget of two events per interval ends the run with
/// `TooManyEvents` (time, state), while the default budget lets it complete.
#[test]
fn the_event_budget_of_a_control_interval_ends_a_run() {
    use nanostage::model::{StaticMap, TableFriction};
    use nanostage::sim::run_drive_open_loop;
    let mut ext = ExtendedConfig::from_closed_loop(&seed_closed_loop(1e-4));
    ext.drive.motor_friction = None;
    ext.drive.table_friction = TableFriction::Static(StaticMap {
        static_force_n: 40.0,
        coulomb_force_n: 20.0,
        viscous_n_s_per_m: 0.0,
        stribeck_velocity_m_per_s: 1e-3,
        stribeck_exponent: 2.0,
        asymmetry: 0.0,
        viscous_asymmetry: 0.0,
        dwell: None,
        memory_lag_s: None,
    });
    ext.drive.n_links = 1;
    ext.drive.links[0] = Link {
        stiffness_n_per_m: 1e5,
        damping_n_s_per_m: 0.0,
        backlash_m: 0.0,
    };
    let u = vec![0.8; 5];
    let ok = run_drive_open_loop(&ext, &u, &[], 0.5).expect("default budget");
    assert!(ok.stats.n_events >= 10, "{:?}", ok.stats);
    ext.integrator.max_events = 2;
    match run_drive_open_loop(&ext, &u, &[], 0.5) {
        Err(SimError::TooManyEvents {
            t_s,
            max_events: 2,
            state,
        }) => {
            assert!(t_s > 0.0 && t_s < 2.5, "{t_s}");
            assert!(state.iter().all(|v| v.is_finite()) && !state.is_empty());
        }
        other => panic!("expected TooManyEvents, got {:?}", other.map(|t| t.stats)),
    }
}
