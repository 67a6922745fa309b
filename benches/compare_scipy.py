"""Time nanostage against scipy ``solve_ivp`` on the identical model and controller.

Both sides run the seed axis in closed loop with the same FPGA PID (bit-exact integer model
in plain Python for scipy, ``tests/pid_reference.py``; the Rust emulation for nanostage), the
same 130-tick output latency and the same hybrid stick/slip plant (``tests/scipy_reference.py``
for scipy). For each integrator the loosest tolerance whose position error against a tight
reference (nanostage at rtol 1e-10, which agrees with scipy Radau at rtol 1e-10 to 1e-12 m)
is ≤ 1 nm is chosen; then the wall time per simulated second is the median of repeats.

Usage: python benches/compare_scipy.py [--duration 0.3] [--repeats 3]
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))

import nanostage as ns

import pid_reference
from scipy_reference import simulate_plant_scipy

STEP_M = 1e-3


def scipy_closed_loop(system: ns.System, reference_m: np.ndarray, method: str, rtol: float):
    c = system.controller
    params = dataclasses.asdict(system.plant)
    pid = pid_reference.ReferencePid(c.to_dict())
    count = system.encoder.count_m
    lsb = c.dac_lsb_v
    lim = system.output_stage.amplifier_limit_v
    gain = system.output_stage.amplifier_gain
    t_lat = c.latency_ticks / c.clock_hz
    t_rest = c.sample_period_s - t_lat
    state = {
        "position_m": 0.0,
        "velocity_m_per_s": 0.0,
        "dahl_force_n": 0.0,
        "current_a": 0.0,
        "stuck": True,
    }
    atol = np.array([1e-13, 1e-10, 1e-7, 1e-9]) * (rtol / 1e-10)
    u_held = 0.0
    pos = np.empty(reference_m.size)

    def advance(u: float, dt: float) -> None:
        out = simulate_plant_scipy(
            params, [u], dt, method=method, rtol=rtol, atol=atol, initial=state
        )
        for k in ("position_m", "velocity_m_per_s", "dahl_force_n", "current_a"):
            state[k] = float(out[k][-1])
        state["stuck"] = bool(out["stuck"][-1])

    for n, r in enumerate(reference_m):
        x = state["position_m"]
        pos[n] = x
        y = int(np.floor(x / count))
        rc = int(np.round(r / count))
        code = pid.step(rc, y)["code"]
        u_new = float(np.clip(gain * code * lsb, -lim, lim))
        advance(u_held, t_lat)
        u_held = u_new
        advance(u_held, t_rest)
    return pos


def nanostage_closed_loop(system: ns.System, reference_m: np.ndarray, rtol: float):
    s = dataclasses.replace(
        system, integrator=ns.IntegratorOptions(rtol=rtol, atol_position_m=1e-11 * rtol / 1e-6)
    )
    return ns.simulate(s, reference_m).position_m


def timed(fn, repeats: int) -> tuple[float, np.ndarray]:
    times, out = [], None
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--duration", type=float, default=1.0, help="simulated seconds (1 mm step)")
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    system = ns.presets.seed(STEP_M)
    ref = ns.step_reference(
        STEP_M, duration_s=args.duration, sample_period_s=system.controller.sample_period_s
    )
    tight = nanostage_closed_loop(system, ref, 1e-10)
    rows = []
    for name, run in [
        ("nanostage RODAS4", lambda rt: nanostage_closed_loop(system, ref, rt)),
        ("scipy LSODA", lambda rt: scipy_closed_loop(system, ref, "LSODA", rt)),
        ("scipy Radau", lambda rt: scipy_closed_loop(system, ref, "Radau", rt)),
    ]:
        chosen = None
        for rtol in (1e-4, 1e-5, 1e-6, 1e-7, 1e-8, 1e-9, 1e-10):
            pos = run(rtol)
            err = float(np.max(np.abs(pos - tight)))
            if err <= 1e-9:
                chosen = (rtol, err)
                break
        if chosen is None:
            print(f"{name}: no tolerance reached 1 nm")
            continue
        rtol, err = chosen
        reps = args.repeats if name.startswith("nanostage") else 1
        wall, _ = timed(lambda rt=rtol, run=run: run(rt), max(reps, 1))
        rows.append((name, rtol, err, wall / args.duration))
        print(
            f"{name:18s} rtol {rtol:.0e}  max|x − x_tight| {err:.2e} m  "
            f"wall per simulated second {wall / args.duration * 1e3:10.2f} ms",
            flush=True,
        )
    base = {r[0]: r[3] for r in rows}
    ours = base.get("nanostage RODAS4")
    if ours:
        for name, per_s in base.items():
            if name != "nanostage RODAS4":
                print(f"speed-up over {name}: {per_s / ours:,.0f}×")


if __name__ == "__main__":
    main()
