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

    python benches/diagnosis_speed.py [--truth own|independent] [--seed 1]
        [--hidden none backlash ...] [--out DIR]
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

from nanostage.diagnosis import independent_truth
from nanostage.diagnosis.benchmark import HIDDEN_EFFECTS, SPEED_DESIGN, generate_case
from nanostage.diagnosis.run import diagnose


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
        t0 = time.perf_counter()
        rep = diagnose(manifest, case / "report", progress=False, figures=False).report
        wall = time.perf_counter() - t0
        walls.append(wall)
        found = ", ".join(rep["selected"]) or "none"
        sims = rep["simulations"]
        print(
            f"hidden {h:24s} selected {found:40s} {wall:6.1f} s  "
            f"({sims['simulated']} simulations, {sims['reused']} looked up)",
            flush=True,
        )
    print(
        f"median {statistics.median(walls):.1f} s, slowest {max(walls):.1f} s "
        f"over {len(walls)} diagnoses (goal: median ≤ 30 s, slowest ≤ 60 s)"
    )


if __name__ == "__main__":
    main()
