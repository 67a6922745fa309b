//! Criterion benches: one controller update, one plant control period, one 1-s trial.
//! Emulated FPGA ticks per controller update are printed once (they are configuration, not
//! a measurement): `latency_ticks` of the seed schedule.
use criterion::{criterion_group, criterion_main, Criterion};
use nanostage::control::Pid;
use nanostage::integrate::Rodas4;
use nanostage::model::{Axis, Plant};
use nanostage::presets::{seed_closed_loop, seed_pid};
use nanostage::sim::run_closed_loop;
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

criterion_group!(benches, controller_update, plant_period, closed_loop_trial);
criterion_main!(benches);
