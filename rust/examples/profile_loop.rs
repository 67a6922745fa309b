//! Work profile of the rigid seed closed loop.
//!
//! `cargo run --release --no-default-features --example profile_loop -- step` runs the 1 s,
//! 1 mm step; `... -- iso FILE` runs one campaign trial of the ISO standard cycle whose
//! reference (one value per line, m) is in FILE (written by `benches/dump_iso_reference.py`).
//! It replays the loop of `run_extended` (rigid plant, FPGA PID, every effect off) with the
//! same plant and controller objects, checks that it reproduces `run_extended` bit for bit,
//! and prints the integrator's work per phase of the motion. `... -- bare step|iso FILE` runs
//! only `run_extended` once (for `valgrind --tool=callgrind`; `REPS=n` repeats it, `REPS=0`
//! measures the start-up and file-reading cost alone); `... -- bare-at step|iso FILE` runs
//! `run_extended_at` instead (what a campaign trial runs: no trace, positions kept only at the
//! sample before each reference jump and at the last sample). `... -- accuracy step|iso FILE` runs
//! the default and a tight (rtol 1e-10, atol 1e-14 m) integrator and prints the largest
//! position difference up to the first sample where the encoder counts differ (`SHOW_DX=1`
//! lists it per sample, `LOOSE_RTOL=x` changes the default run's rtol, `SAVE_TIGHT=1` /
//! `SAVE_LOOSE=1` write the positions to /tmp). `stepX` (e.g. `step5e-4`) is a step of X m
//! with the Table 1 gains for that size.
use nanostage::control::{flags, Pid};
use nanostage::integrate::{Rodas4, Stats};
use nanostage::model::{Axis, Mode, Plant};
#[path = "../tests/support/presets.rs"]
mod presets;
use nanostage::sim::{
    run_extended, trial_seed, ExtendedConfig, KnownInputs, SpreadDistribution, StochasticFriction,
};
use presets::seed_closed_loop;
use rand::SeedableRng;
use rand_pcg::Pcg64Mcg;

#[derive(Default, Clone, Copy)]
struct Phase {
    periods: u64,
    lat: Stats,
    main: Stats,
}

fn sub(a: Stats, b: Stats) -> Stats {
    Stats {
        n_rhs: a.n_rhs - b.n_rhs,
        n_jac: a.n_jac - b.n_jac,
        n_lu: a.n_lu - b.n_lu,
        n_accepted: a.n_accepted - b.n_accepted,
        n_rejected: a.n_rejected - b.n_rejected,
        n_events: a.n_events - b.n_events,
    }
}

fn step_size(args: &[String]) -> f64 {
    args.first()
        .and_then(|a| a.strip_prefix("step"))
        .and_then(|s| s.parse().ok())
        .unwrap_or(1e-3)
}

fn config(iso: bool, step_m: f64) -> ExtendedConfig {
    let mut cfg = ExtendedConfig::from_closed_loop(&seed_closed_loop(step_m));
    if iso {
        cfg.stochastic = Some(StochasticFriction {
            level_spread: 0.2,
            distribution: SpreadDistribution::LogNormal,
            within_spread: 0.0,
            correlation_time_s: 1.0,
        });
        cfg.seed = trial_seed(1, 0);
    }
    cfg
}

fn reference(args: &[String]) -> (bool, Vec<f64>) {
    match args.first().map(String::as_str) {
        Some("iso") => {
            let path = args.get(1).expect("iso needs the reference file");
            let text = std::fs::read_to_string(path).expect("reference file");
            let r = text
                .lines()
                .filter(|l| !l.trim().is_empty())
                .map(|l| l.trim().parse::<f64>().expect("a number per line"))
                .collect();
            (true, r)
        }
        _ => {
            let step = step_size(args);
            let n = if step > 5e-3 { 1500 } else { 1000 };
            (
                false,
                (0..n).map(|k| if k >= 10 { step } else { 0.0 }).collect(),
            )
        }
    }
}

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    if args.first().map(String::as_str) == Some("accuracy") {
        let (iso, r) = reference(&args[1..]);
        let cfg = config(iso, step_size(&args[1..]));
        let mut tight = cfg;
        tight.integrator.rtol = 1e-10;
        tight.integrator.atol_position_m = 1e-14;
        let loose = match std::env::var("LOOSE_RTOL")
            .ok()
            .and_then(|v| v.parse::<f64>().ok())
        {
            Some(rt) => {
                let mut c = cfg;
                c.integrator.rtol = rt;
                c
            }
            None => cfg,
        };
        let a = run_extended(&loose, &r, KnownInputs::default(), None).expect("run");
        if std::env::var_os("SAVE_LOOSE").is_some() {
            let text: String = a
                .position_m
                .iter()
                .zip(&a.velocity_m_per_s)
                .zip(&a.current_a)
                .map(|((x, v), i)| format!("{x:e} {v:e} {i:e}\n"))
                .collect();
            std::fs::write("/tmp/loose_positions.txt", text).expect("write");
        }
        if std::env::var_os("SAVE_TIGHT").is_some() {
            let b = run_extended(&tight, &r, KnownInputs::default(), None).expect("run");
            let text: String = b.position_m.iter().map(|x| format!("{x:e}\n")).collect();
            std::fs::write("/tmp/tight_positions.txt", text).expect("write");
        }
        let b = run_extended(&tight, &r, KnownInputs::default(), None).expect("run");
        let first = a
            .encoder_counts
            .iter()
            .zip(&b.encoder_counts)
            .position(|(x, y)| x != y)
            .unwrap_or(r.len());
        let worst = a.position_m[..first]
            .iter()
            .zip(&b.position_m[..first])
            .fold(0.0_f64, |m, (x, y)| m.max((x - y).abs()));
        if std::env::var_os("SHOW_DX").is_some() {
            for k in (0..first).step_by(1) {
                let d = (a.position_m[k] - b.position_m[k]).abs();
                if d > 1e-11 {
                    println!(
                        "k={k} dx={d:.2e} v={:.3e} stuck={}",
                        a.velocity_m_per_s[k], a.stuck[k]
                    );
                }
            }
        }
        let differing = a
            .encoder_counts
            .iter()
            .zip(&b.encoder_counts)
            .filter(|(x, y)| x != y)
            .count();
        println!(
            "default vs tight: max |dx| {worst:.3e} m over the first {first} of {} samples \
             (counts identical up to there); {differing} samples with another count; \
             default {:?}",
            r.len(),
            a.stats
        );
        return;
    }
    if args.first().map(String::as_str) == Some("bare-at") {
        let (iso, r) = reference(&args[1..]);
        let cfg = config(iso, step_size(&args[1..]));
        let mut idx: Vec<usize> = (1..r.len())
            .filter(|&k| r[k] != r[k - 1])
            .map(|k| k - 1)
            .collect();
        idx.push(r.len() - 1);
        idx.dedup();
        let reps: usize = std::env::var("REPS")
            .ok()
            .and_then(|s| s.parse().ok())
            .unwrap_or(1);
        for _ in 0..reps {
            let m = nanostage::sim::run_extended_at(&cfg, &r, KnownInputs::default(), None, &idx)
                .expect("run");
            std::hint::black_box(&m);
            if reps == 1 {
                let h = m.position_m.iter().fold(0xcbf2_9ce4_8422_2325_u64, |h, v| {
                    (h ^ v.to_bits()).wrapping_mul(0x0100_0000_01b3)
                });
                let cnt: i64 = m.encoder_counts.iter().sum();
                println!(
                    "{:?} {} measurements, hash {h:016x} count sum {cnt}",
                    m.stats,
                    idx.len()
                );
            }
        }
        return;
    }
    if args.first().map(String::as_str) == Some("bare") {
        let (iso, r) = reference(&args[1..]);
        let cfg = config(iso, step_size(&args[1..]));
        let reps: usize = std::env::var("REPS")
            .ok()
            .and_then(|s| s.parse().ok())
            .unwrap_or(1);
        for _ in 0..reps {
            let tr = run_extended(&cfg, &r, KnownInputs::default(), None).expect("run");
            std::hint::black_box(&tr);
            if reps == 1 {
                let h = tr
                    .position_m
                    .iter()
                    .chain(tr.velocity_m_per_s.iter())
                    .fold(0xcbf2_9ce4_8422_2325_u64, |h, v| {
                        (h ^ v.to_bits()).wrapping_mul(0x0100_0000_01b3)
                    });
                let cnt: i64 = tr.encoder_counts.iter().sum();
                println!("{:?} trace hash {h:016x} count sum {cnt}", tr.stats);
            }
        }
        return;
    }
    let (iso, r) = reference(&args);
    let cfg = config(iso, step_size(&args));
    let reference_trace = run_extended(&cfg, &r, KnownInputs::default(), None).expect("run");
    let nanostage::sim::ControllerKind::Fpga { pid: pcfg, output } = cfg.controller else {
        unreachable!()
    };
    let axis_p = cfg.axis.expect("rigid");
    let level = cfg.stochastic.map_or(1.0, |s| {
        let mut rng = Pcg64Mcg::seed_from_u64(nanostage::sim::stream_seed(cfg.seed, 1));
        s.draw_level(&mut rng)
    });
    let axis = Axis::new(axis_p.with_friction_scale(level)).expect("axis");
    let mut plant = Plant::new(axis, Rodas4::new(cfg.integrator).expect("integ"));
    let mut pid = Pid::new(pcfg).expect("pid");
    let enc = cfg.sensors.encoder;
    let t_s = pcfg.ticks_per_sample as f64 / pcfg.clock_hz;
    let lat = pcfg.latency_ticks as f64 / pcfg.clock_hz;
    let names = ["stuck", "slew (sat.)", "braking |e|>10", "settle |e|<=10"];
    let mut ph = [Phase::default(); 4];
    let mut u_held = 0.0;
    let mut max_dev = 0.0_f64;
    let mut hist_main = [0u64; 12];
    for (k, &r_m) in r.iter().enumerate() {
        let t_n = (k as u64 * pcfg.ticks_per_sample) as f64 / pcfg.clock_hz;
        let t_next = ((k + 1) as u64 * pcfg.ticks_per_sample) as f64 / pcfg.clock_hz;
        let _ = t_s;
        max_dev = max_dev.max((plant.y[0] - reference_trace.position_m[k]).abs());
        let counts = enc.read(plant.y[0]);
        let rc = enc.reference_counts(r_m);
        let out = pid.step(rc, counts);
        let (u, sat) = output.motor_voltage(out.code, pcfg.dac_lsb_v);
        let _ = out.flags & flags::AMPLIFIER_SATURATED;
        let s0 = plant.integrator.stats;
        let stuck0 = plant.mode == Mode::Stuck;
        let s1 = if u == u_held {
            plant.integrator.stats
        } else {
            plant.advance(u_held, t_n, t_n + lat).expect("advance");
            plant.integrator.stats
        };
        let t_from = if u == u_held { t_n } else { t_n + lat };
        u_held = u;
        plant.advance(u_held, t_from, t_next).expect("advance");
        let s2 = plant.integrator.stats;
        let main = sub(s2, s1);
        let latd = sub(s1, s0);
        let e = (rc - counts).abs();
        let idx = if main.n_accepted + latd.n_accepted == 0 && stuck0 {
            0
        } else if sat {
            1
        } else if e > 10 {
            2
        } else {
            3
        };
        if idx != 0 {
            hist_main[(main.n_accepted as usize).min(11)] += 1;
        }
        ph[idx].periods += 1;
        ph[idx].lat += latd;
        ph[idx].main += main;
    }
    println!(
        "{} periods, replay max |x - run_extended| = {max_dev:e} m, total {:?}",
        r.len(),
        plant.integrator.stats
    );
    assert_eq!(
        plant.integrator.stats, reference_trace.stats,
        "replay differs"
    );
    println!(
        "{:16} {:>7} | {:>23} | {:>40}",
        "phase", "periods", "latency seg acc/rej/ev", "main seg acc/rej/rhs/ev  (acc per period)"
    );
    for (n, p) in names.iter().zip(ph.iter()) {
        println!(
            "{:16} {:>7} | {:>7} {:>7} {:>7} | {:>7} {:>7} {:>8} {:>6} ({:.2})",
            n,
            p.periods,
            p.lat.n_accepted,
            p.lat.n_rejected,
            p.lat.n_events,
            p.main.n_accepted,
            p.main.n_rejected,
            p.main.n_rhs,
            p.main.n_events,
            p.main.n_accepted as f64 / p.periods.max(1) as f64
        );
    }
    println!(
        "histogram of accepted main-segment steps per moving period (0..=10, 11+): {hist_main:?}"
    );
}
