//! Criterion benches: one controller update, one plant control period, one 1-s trial.
//! Emulated FPGA ticks per controller update are printed once (they are configuration, not
//! a measurement): `latency_ticks` of the seed schedule.
use criterion::{criterion_group, criterion_main, Criterion};
use nanostage::control::Pid;
use nanostage::integrate::Rodas4;
use nanostage::model::{Axis, Plant};
#[path = "../rust/tests/support/presets.rs"]
mod presets;
use nanostage::sim::{run_closed_loop, run_extended, ExtendedConfig, KnownInputs};
use presets::{seed_closed_loop, seed_pid, speed_case_backlash_link, speed_case_gms6};
use std::hint::black_box;

fn controller_update(c: &mut Criterion) {
    let cfg = seed_pid(450.0, 5.0, 10.0);
    println!(
        "emulated FPGA ticks per controller update (seed schedule): {} of {} per sample",
        cfg.latency_ticks, cfg.ticks_per_sample
    );
    let mut pid = Pid::new(cfg).expect("seed pid");
    let mut k = 0i64;
    c.bench_function("pid_update", |b| {
        b.iter(|| {
            k = (k + 7) % 2000;
            black_box(pid.step(black_box(10_000), black_box(9_000 + k)))
        })
    });
}

fn plant_period(c: &mut Criterion) {
    let cfg = seed_closed_loop(1e-3);
    let axis = Axis::new(cfg.axis).expect("seed axis");
    let mut plant = Plant::new(axis, Rodas4::new(cfg.integrator).expect("options"));
    let mut t = 0.0;
    let mut u = 3.0;
    c.bench_function("plant_1ms_sliding", |b| {
        b.iter(|| {
            u = -u;
            plant.advance(black_box(u), t, t + 1e-3).expect("advance");
            t += 1e-3;
        })
    });
}

fn closed_loop_trial(c: &mut Criterion) {
    let cfg = seed_closed_loop(1e-3);
    let r: Vec<f64> = (0..1000)
        .map(|k| if k >= 10 { 1e-3 } else { 0.0 })
        .collect();
    c.bench_function("closed_loop_1s_1mm_step", |b| {
        b.iter(|| black_box(run_closed_loop(&cfg, black_box(&r), None).expect("trial")))
    });
}

/// The same 1-s trial with the effect library's heavy components on (speed goal:
/// at most 3× the plain seed trial): GMS with 6 elements on the table, gearhead backlash
/// (20 µm) and a two-mass drive train; and each alone, and the component plant with every
/// effect off (the general path's own overhead).
fn closed_loop_trial_effects(c: &mut Criterion) {
    let cfg = seed_closed_loop(1e-3);
    let r: Vec<f64> = (0..1000)
        .map(|k| if k >= 10 { 1e-3 } else { 0.0 })
        .collect();
    let base = ExtendedConfig::from_closed_loop(&cfg);
    let gms = speed_case_gms6();
    let link = speed_case_backlash_link();
    let mut all = base;
    all.drive.table_friction = gms;
    all.drive.n_links = 1;
    all.drive.links[0] = link;
    let mut general = base;
    general.axis = None;
    let mut only_gms = base;
    only_gms.drive.table_friction = gms;
    let mut only_backlash = base;
    only_backlash.drive.n_links = 1;
    only_backlash.drive.links[0] = link;
    for (name, ext) in [
        ("closed_loop_1s_component_plant_effects_off", general),
        ("closed_loop_1s_gms6", only_gms),
        ("closed_loop_1s_two_mass_backlash", only_backlash),
        ("closed_loop_1s_gms6_backlash_two_mass", all),
    ] {
        c.bench_function(name, |b| {
            b.iter(|| {
                black_box(
                    run_extended(&ext, black_box(&r), KnownInputs::default(), None).expect("trial"),
                )
            })
        });
    }
}

/// A campaign: 64 trials of three 100 µm steps (0.52 s simulated each, stochastic friction
/// so every trial differs) on a local pool of 1 and 2 threads; throughput in trials/s.
fn campaign_threads(c: &mut Criterion) {
    use criterion::{BenchmarkId, Throughput};
    use nanostage::sim::{run_campaign, Campaign, SpreadDistribution, StochasticFriction};
    let mut cfg = ExtendedConfig::from_closed_loop(&seed_closed_loop(100e-6));
    cfg.stochastic = Some(StochasticFriction {
        level_spread: 0.2,
        distribution: SpreadDistribution::LogNormal,
        within_spread: 0.0,
        correlation_time_s: 0.1,
    });
    let mut r = vec![0.0; 40];
    let mut idx = Vec::new();
    for _ in 0..3 {
        r.extend(std::iter::repeat_n(100e-6, 120));
        idx.push(r.len() - 1);
        r.extend(std::iter::repeat_n(0.0, 40));
    }
    let campaign = Campaign {
        config: &cfg,
        reference_m: &r,
        measure_index: &idx,
    };
    let n_trials = 64u64;
    let mut g = c.benchmark_group("campaign_64_trials");
    g.sample_size(10);
    g.throughput(Throughput::Elements(n_trials));
    for threads in [1usize, 2] {
        g.bench_with_input(BenchmarkId::new("threads", threads), &threads, |b, &t| {
            b.iter(|| {
                black_box(run_campaign(&campaign, 1, 0, n_trials, t, None, None).expect("campaign"))
            })
        });
    }
    g.finish();
}

criterion_group!(
    benches,
    controller_update,
    plant_period,
    closed_loop_trial,
    closed_loop_trial_effects,
    campaign_threads
);
criterion_main!(benches);
