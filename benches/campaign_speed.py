"""Monte Carlo campaign throughput: simulated moves per second, 1→2 thread scaling, memory.

Runs `--trials` trials of an ISO 230-2 standard test cycle on the seed axis (11 targets over
`--travel-mm`, 5 runs, both directions: 110 measured approaches per trial, plus the overrun
moves) with a per-trial stochastic friction level (spread 0.2), on 1 and on 2 threads of the
local pool, `--repeats` times each, and prints the median wall time, moves per second (every
reference move of the cycle, measured approaches and overrun moves) and the scaling. Memory:
the peak RSS of a fresh process running N and 4·N trials (flat: only the measured positions
are kept per trial).

Goals: ≥ 10 000 moves/s on the 2-core machine, scaling ≥ 1.8×, memory flat.

    python benches/campaign_speed.py [--trials 1000] [--repeats 3]
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from nanostage import presets
from nanostage.campaign import run_campaign
from nanostage.cycles import MoveProfile, standard_test_cycle
from nanostage.tune import with_friction_spread


def setup(travel_mm: float, dwell_s: float):  # type: ignore[no-untyped-def]
    system = with_friction_spread(presets.seed(1e-3), 0.2)
    cycle = standard_test_cycle(
        travel_m=travel_mm * 1e-3,
        n_targets=11,
        runs=5,
        overrun_m=0.1 * travel_mm * 1e-3,
        dwell_s=dwell_s,
        move=MoveProfile(),
        sample_period_s=1e-3,
        seed=1,
    )
    moves = int(np.count_nonzero(np.diff(cycle.reference_m) != 0.0))
    return system, cycle, moves


def peak_rss(trials: int, travel_mm: float, dwell_s: float) -> float:
    """Peak RSS [MiB] of a fresh process that runs one campaign of ``trials`` trials."""
    code = (
        "import resource\n"
        "from campaign_speed import run_campaign, setup\n"
        f"s, c, _ = setup({travel_mm}, {dwell_s})\n"
        f"run_campaign(s, c, n_trials={trials}, seed=1, progress=False)\n"
        "print(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss)\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code],
        capture_output=True,
        text=True,
        check=True,
        cwd=Path(__file__).parent,
    )
    return float(out.stdout.strip()) / 1024.0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=1000)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--travel-mm", type=float, default=10.0)
    ap.add_argument("--dwell-s", type=float, default=0.2)
    ap.add_argument("--json", default=None, help="also write the numbers to this file")
    a = ap.parse_args()
    system, cycle, moves = setup(a.travel_mm, a.dwell_s)
    print(
        f"standard cycle: {cycle.n_measurements} measured approaches, {moves} reference "
        f"jumps per trial, {cycle.duration_s:.1f} s simulated per trial; {a.trials} trials"
    )
    walls: dict[int, list[float]] = {1: [], 2: []}
    ref = None
    for _ in range(a.repeats):
        for threads in (1, 2):
            t0 = time.perf_counter()
            r = run_campaign(
                system, cycle, n_trials=a.trials, seed=1, threads=threads, progress=False
            )
            walls[threads].append(time.perf_counter() - t0)
            assert r.n_failed == 0, r.failures[:3]
            if ref is None:
                ref = r.position_m
            else:
                assert np.array_equal(ref, r.position_m, equal_nan=True)  # same for any threads
    med = {t: statistics.median(w) for t, w in walls.items()}
    total_moves = moves * a.trials
    out = {
        "trials": a.trials,
        "moves_per_trial": moves,
        "simulated_s_per_trial": cycle.duration_s,
        "median_wall_s": med,
        "moves_per_s": {t: total_moves / med[t] for t in med},
        "scaling_1_to_2": med[1] / med[2],
    }
    for t in (1, 2):
        print(
            f"{t} thread(s): median {med[t]:.2f} s, {total_moves / med[t]:.0f} moves/s, "
            f"{a.trials / med[t]:.1f} trials/s"
        )
    print(f"scaling 1→2 threads: {out['scaling_1_to_2']:.2f}× (goal ≥ 1.8×); goal ≥ 10 000 moves/s")
    small = max(1, a.trials // 4)
    rss = {
        small: peak_rss(small, a.travel_mm, a.dwell_s),
        4 * small: peak_rss(4 * small, a.travel_mm, a.dwell_s),
    }
    out["peak_rss_mib"] = rss
    big = 4 * small
    print(f"peak RSS: {small} trials {rss[small]:.0f} MiB, {big} trials {rss[big]:.0f} MiB")
    if a.json:
        with open(a.json, "w") as f:
            json.dump(out, f, indent=1)


if __name__ == "__main__":
    main()
