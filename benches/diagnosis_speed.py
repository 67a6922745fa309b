"""Time one gap diagnosis of about 10 experiments against every candidate effect.

For each hidden effect (default: every one the blind benchmark draws) it writes a synthetic
case of the 10 experiments of `nanostage.diagnosis.benchmark.SPEED_DESIGN` (the blind
benchmark's truth, noise and stochastic friction), runs `nanostage.diagnose` on the files
with the default settings (all 17 candidates, forward selection) and prints the wall time,
then the median and the slowest case. The goal is ≤ 60 s per diagnosis on the
project's 2-core machine. Run it alone: the machine is shared and the times are wall times.

    python benches/diagnosis_speed.py [--seed 1] [--hidden none backlash ...] [--out DIR]
"""

from __future__ import annotations

import argparse
import statistics
import tempfile
import time
from pathlib import Path

from nanostage.diagnosis.benchmark import HIDDEN_EFFECTS, SPEED_DESIGN, generate_case
from nanostage.diagnosis.run import diagnose


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--hidden", nargs="+", default=list(HIDDEN_EFFECTS), choices=HIDDEN_EFFECTS)
    ap.add_argument("--out", type=Path, default=None, help="keep the cases here")
    a = ap.parse_args()
    root = a.out or Path(tempfile.mkdtemp(prefix="nanostage-diagnosis-speed-"))
    walls = []
    print(f"{len(SPEED_DESIGN)} experiments per diagnosis; cases in {root}")
    for k, h in enumerate(a.hidden):
        case = root / f"case{k:02d}_{h}"
        manifest, _ = generate_case(h, a.seed * 10_000 + k, case, design=SPEED_DESIGN)
        t0 = time.perf_counter()
        rep = diagnose(manifest, case / "report", progress=False, figures=False).report
        wall = time.perf_counter() - t0
        walls.append(wall)
        found = ", ".join(rep["selected"]) or "none"
        print(f"hidden {h:24s} selected {found:40s} {wall:6.1f} s", flush=True)
    print(
        f"median {statistics.median(walls):.1f} s, slowest {max(walls):.1f} s "
        f"over {len(walls)} diagnoses (goal ≤ 60 s)"
    )


if __name__ == "__main__":
    main()
