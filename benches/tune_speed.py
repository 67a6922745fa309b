"""Time the off-line tuning of one step size with a 200-trial robust objective.

Runs `nanostage.tune.tune` on the seed axis (100 µm step, Table 1 start, per-trial friction
level spread 0.2, `Objective.mix()`, the default search budget) `--repeats` times and prints
the median wall time, the candidates evaluated, and the simulated trial throughput. The goal
is ≤ 2 minutes on the project's 2-core machine.

    python benches/tune_speed.py [--step-um 100] [--trials 200] [--repeats 3] [--threads N]
"""

from __future__ import annotations

import argparse
import statistics
import time

from nanostage import presets
from nanostage.tune import Objective, evaluate_gains, tune, tuning_cycle, with_friction_spread


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--step-um", type=float, default=100.0)
    ap.add_argument("--trials", type=int, default=200)
    ap.add_argument("--repeats", type=int, default=3)
    ap.add_argument("--popsize", type=int, default=5)
    ap.add_argument("--maxiter", type=int, default=10)
    ap.add_argument("--threads", type=int, default=None)
    a = ap.parse_args()
    step = a.step_um * 1e-6
    system = with_friction_spread(presets.seed(step), 0.2)
    cycle = tuning_cycle(step)
    obj = Objective.mix()
    # One candidate alone (the unit of work), median of 5.
    one = []
    for _ in range(5):
        t0 = time.perf_counter()
        evaluate_gains(system, cycle, objective=obj, n_trials=a.trials, seed=0, threads=a.threads)
        one.append(time.perf_counter() - t0)
    walls, distinct = [], []
    for r in range(a.repeats):
        res = tune(
            system,
            cycle,
            objective=obj,
            n_trials=a.trials,
            seed=r,
            popsize=a.popsize,
            maxiter=a.maxiter,
            threads=a.threads,
            progress=False,
        )
        walls.append(res.wall_s)
        distinct.append(len(res.history))
        b = res.best
        print(
            f"run {r}: {res.wall_s:.1f} s, {len(res.history)} distinct candidates "
            f"({res.n_evaluations} calls); best Kp {b.kp:g} Ki {b.ki:g} Kd {b.kd:g} "
            f"{b.anti_windup}: J {b.objective:.4g} (Table 1: {res.start.objective:.4g})"
        )
    cand_s = statistics.median(one)
    sim_s = cycle.duration_s * a.trials
    print(
        f"\n{a.step_um:g} µm step, {a.trials} trials per candidate, cycle {cycle.duration_s:.2f} s "
        f"simulated per trial"
    )
    print(
        f"one candidate: median {cand_s:.3f} s ({a.trials / cand_s:.0f} trials/s, "
        f"{sim_s / cand_s:.0f} simulated s per wall s)"
    )
    print(
        f"tuning: median {statistics.median(walls):.1f} s over {a.repeats} seeds "
        f"(median {statistics.median(distinct):.0f} distinct candidates); goal <= 120 s"
    )


if __name__ == "__main__":
    main()
