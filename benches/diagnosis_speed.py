"""Time one gap diagnosis against every candidate effect, on either truth family.

For each hidden effect (default: every one the family draws) it writes a synthetic case and
runs `nanostage.diagnose` on the files with the default settings (all 17 candidates, forward
selection), prints the wall time of the diagnosis (the case's generation is not timed),
then the median and the slowest case. ``--truth own``: the 10 experiments of
`nanostage.diagnosis.benchmark.SPEED_DESIGN` (the blind benchmark's truth, noise and
stochastic friction); ``--truth independent``: the 12-experiment design of
`nanostage.diagnosis.independent_truth` (with the command, its manifest's uncertain
nominal parameters free). The goal is a median ≤ 30 s and a slowest case ≤ 60 s on the
project's 2-core machine. Run it alone: the machine is shared and the times are wall times.

``--phases`` also prints, per case, the wall time and the simulations run (cache misses)
of each phase: calibration (with the loop's other work), screening, refinement, refit
control, cross-judging (the refitted candidates judged on every experiment), cross-fit,
report. ``--screen-fits-nominal`` screens with the free nominal
parameters fitted too (``DiagnosisSettings.screen_holds_nominal = False``, the earlier
default), for a comparison on the same cases.

    python benches/diagnosis_speed.py [--truth own|independent] [--seed 1]
        [--hidden none backlash ...] [--out DIR] [--phases] [--screen-fits-nominal]
"""

from __future__ import annotations

import argparse
import contextlib
import statistics
import tempfile
import threading
import time
from collections import defaultdict
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

from nanostage.diagnosis import fit, independent_truth, loop, objective, run
from nanostage.diagnosis.benchmark import HIDDEN_EFFECTS, SPEED_DESIGN, generate_case
from nanostage.diagnosis.manifest import load_manifest
from nanostage.diagnosis.run import diagnose
from nanostage.diagnosis.settings import DiagnosisSettings


@contextlib.contextmanager
def phases() -> Iterator[dict[str, list[float]]]:
    """Per phase of the diagnosis: [wall seconds, simulations run]. Wraps the engine's
    functions while the block runs (one diagnosis at a time)."""
    out: dict[str, list[float]] = defaultdict(lambda: [0.0, 0.0])
    now = ["calibration"]
    lock = threading.Lock()
    saved: list[tuple[Any, str, Any]] = []

    def patch(mod: Any, name: str, new: Any) -> None:
        saved.append((mod, name, getattr(mod, name)))
        setattr(mod, name, new)

    real_sim = objective.simulate_readings_and_commands

    def sim(systems: Any, experiments: Any, threads: int = 0) -> Any:
        with lock:
            out[now[0]][1] += len(systems)
        return real_sim(systems, experiments, threads)

    def timed(phase: str, f: Callable[..., Any]) -> Callable[..., Any]:
        def g(*a: Any, **k: Any) -> Any:
            before, now[0] = now[0], phase
            t0 = time.perf_counter()
            try:
                return f(*a, **k)
            finally:
                out[phase][0] += time.perf_counter() - t0
                now[0] = before

        return g

    real_conc = loop._concurrently

    def conc(items: Any, state: Any, ctx: Any, screen: bool, **k: Any) -> Any:
        phase = "screening" if screen else "refinement"
        if now[0] == "cross-judge":  # its refits are its own phase
            yield from real_conc(items, state, ctx, screen, **k)
            return
        t0 = time.perf_counter()
        now[0] = phase
        try:
            yield from real_conc(items, state, ctx, screen, **k)
        finally:
            out[phase][0] += time.perf_counter() - t0
            now[0] = "calibration"

    for mod in (objective, fit, run):
        patch(mod, "simulate_readings_and_commands", sim)
    patch(loop, "_concurrently", conc)
    patch(loop, "_refit_control", timed("refit control", loop._refit_control))
    patch(loop, "_cross_judge", timed("cross-judge", loop._cross_judge))
    patch(run, "diagnose_experiments", timed("calibration", loop.diagnose_experiments))
    patch(run, "crossfit_models", timed("cross-fit", loop.crossfit_models))
    patch(run, "assemble_report", timed("report", run.assemble_report))
    try:
        yield out
    finally:
        for mod, name, f in reversed(saved):
            setattr(mod, name, f)
        # The engine's phases ran inside the diagnosis's own time: calibration is what is
        # left of it.
        inner = sum(out[p][0] for p in ("screening", "refinement", "refit control", "cross-judge"))
        out["calibration"][0] -= inner


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--truth", choices=("own", "independent"), default="own")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument(
        "--hidden",
        nargs="+",
        default=None,
        choices=sorted(set(HIDDEN_EFFECTS) | set(independent_truth.HIDDEN_EFFECTS)),
    )
    ap.add_argument("--out", type=Path, default=None, help="keep the cases here")
    ap.add_argument("--phases", action="store_true", help="time and count each phase")
    ap.add_argument(
        "--screen-fits-nominal",
        action="store_true",
        help="screen with the free nominal parameters fitted too",
    )
    a = ap.parse_args()
    family = HIDDEN_EFFECTS if a.truth == "own" else independent_truth.HIDDEN_EFFECTS
    hidden = a.hidden or list(family)
    wrong = [h for h in hidden if h not in family]
    if wrong:
        ap.error(f"--hidden {' '.join(wrong)}: not drawn by the {a.truth} family ({family})")
    root = a.out or Path(tempfile.mkdtemp(prefix="nanostage-diagnosis-speed-"))
    walls = []
    n_exp = len(SPEED_DESIGN) if a.truth == "own" else len(independent_truth.experiment_design())
    print(f"{a.truth} truth, {n_exp} experiments per diagnosis; cases in {root}")
    for k, h in enumerate(hidden):
        case = root / f"case{k:02d}_{h}"
        if a.truth == "own":
            manifest, _ = generate_case(h, a.seed * 10_000 + k, case, design=SPEED_DESIGN)
        else:
            manifest, _ = independent_truth.write_case(h, a.seed * 10_000 + k, case)
        st = (
            DiagnosisSettings(
                seed=load_manifest(manifest).diagnosis.seed, screen_holds_nominal=False
            )
            if a.screen_fits_nominal
            else None
        )
        with phases() if a.phases else contextlib.nullcontext() as spent:
            t0 = time.perf_counter()
            rep = diagnose(
                manifest, case / "report", settings=st, progress=False, figures=False
            ).report
            wall = time.perf_counter() - t0
        walls.append(wall)
        found = ", ".join(rep["selected"]) or "none"
        sims = rep["simulations"]
        print(
            f"hidden {h:24s} selected {found:40s} {wall:6.1f} s  "
            f"({sims['simulated']} simulations, {sims['reused']} looked up)",
            flush=True,
        )
        if spent is not None:
            print(
                "    "
                + ", ".join(f"{p} {t:.1f} s ({n:.0f} simulations)" for p, (t, n) in spent.items()),
                flush=True,
            )
    print(
        f"median {statistics.median(walls):.1f} s, slowest {max(walls):.1f} s "
        f"over {len(walls)} diagnoses (goal: median ≤ 30 s, slowest ≤ 60 s)"
    )


if __name__ == "__main__":
    main()
