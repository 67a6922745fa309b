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

``--phases`` also prints, per case, the wall time and the simulations run (not looked up
in the diagnosis's cache) of each phase, summed over the rounds: the report's ``phases``
(calibration, screening, refinement, refit control, selection, judged on every
experiment, report, cross-fit). ``--screen-fits-nominal`` screens with the free nominal
parameters fitted too (``DiagnosisSettings.screen_holds_nominal = False``, the earlier
default), for a comparison on the same cases. ``--parallel-candidates N`` fits N candidates
at once (``DiagnosisSettings.parallel_candidates``; the results do not depend on it). Each
line also gives the cores the diagnosis kept busy: the process's CPU time (user and
system) over the wall time.

    python benches/diagnosis_speed.py [--truth own|independent] [--seed 1]
        [--hidden none backlash ...] [--out DIR] [--phases] [--screen-fits-nominal]
        [--parallel-candidates N]
"""

from __future__ import annotations

import argparse
import os
import statistics
import tempfile
import time
from pathlib import Path

from nanostage.diagnosis import independent_truth
from nanostage.diagnosis.benchmark import HIDDEN_EFFECTS, SPEED_DESIGN, generate_case
from nanostage.diagnosis.manifest import load_manifest
from nanostage.diagnosis.run import diagnose
from nanostage.diagnosis.settings import DiagnosisSettings


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
    ap.add_argument(
        "--parallel-candidates",
        type=int,
        default=None,
        help="candidates fitted at once (default: the settings' default)",
    )
    a = ap.parse_args()
    if a.parallel_candidates is not None and a.parallel_candidates < 1:
        ap.error(f"--parallel-candidates {a.parallel_candidates}: must be at least 1")
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
        changes: dict[str, object] = {}
        if a.screen_fits_nominal:
            changes["screen_holds_nominal"] = False
        if a.parallel_candidates is not None:
            changes["parallel_candidates"] = a.parallel_candidates
        st = None
        if changes:
            # The settings `diagnose` would build from the manifest, with the changes.
            d = load_manifest(manifest).diagnosis
            st = DiagnosisSettings(seed=d.seed, level_scatter=d.level_scatter, **changes)  # type: ignore[arg-type]
        t0 = time.perf_counter()
        c0 = os.times()
        rep = diagnose(manifest, case / "report", settings=st, progress=False, figures=False).report
        c1 = os.times()
        wall = time.perf_counter() - t0
        cores = (c1.user - c0.user + c1.system - c0.system) / wall
        walls.append(wall)
        found = ", ".join(rep["selected"]) or "none"
        sims = rep["simulations"]
        print(
            f"hidden {h:24s} selected {found:40s} {wall:6.1f} s on {cores:.2f} cores "
            f"({sims['simulated']} simulations, {sims['reused']} looked up)",
            flush=True,
        )
        if a.phases:
            spent: dict[str, list[float]] = {}
            for e in rep["phases"]:
                t_n = spent.setdefault(e["phase"], [0.0, 0.0])
                t_n[0] += e["seconds"]
                t_n[1] += e["simulated"] or 0
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
