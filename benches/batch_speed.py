"""Time one batch of a diagnosis case's experiments per model and integrator tolerance.

Writes one case of the independent truth family (``--hidden``, ``--seed``: case id
seed·10 000), builds its manifest's nominal model and each named candidate at its start
values, and times the simulation of all the case's experiments as one batch of the core
(the unit of work of the diagnosis's fits) on ``--threads`` threads: the median of
``--repeats`` batches, for each integrator tolerance ``RTOL,ATOL_M`` given (the first is
the reference: the model's own, rtol 1e-6 and atol 1e-11 m, by default). Each further
tolerance also prints the largest difference of the readings (m) and of the commands (V)
from the reference's: in a quantised loop a looser tolerance flips counts near an edge and
from there follows another trajectory. Run it alone: the machine is shared.

    python benches/batch_speed.py [--hidden none] [--seed 10100] [--repeats 20]
        [--models nominal backlash drive_compliance amplifier_dynamics]
        [--tolerances 1e-6,1e-11 1e-6,1e-10 1e-5,1e-9] [--threads 2]
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

from nanostage.diagnosis import independent_truth
from nanostage.diagnosis.candidates import CANDIDATES, applicable_candidates
from nanostage.diagnosis.manifest import load_manifest
from nanostage.diagnosis.objective import simulate_readings_and_commands


def _tolerance(text: str) -> tuple[float, float]:
    try:
        rtol, atol = (float(x) for x in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"tolerance {text!r}: expected RTOL,ATOL_M (e.g. 1e-6,1e-11)"
        ) from None
    return rtol, atol


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--hidden", default="none", choices=independent_truth.HIDDEN_EFFECTS)
    ap.add_argument("--seed", type=int, default=10100)
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument(
        "--models",
        nargs="+",
        default=["nominal", "backlash", "drive_compliance", "amplifier_dynamics"],
        choices=["nominal", *CANDIDATES],
    )
    ap.add_argument(
        "--tolerances", nargs="+", type=_tolerance, default=[(1e-6, 1e-11), (1e-5, 1e-9)]
    )
    a = ap.parse_args()
    if a.repeats < 1:
        ap.error(f"--repeats {a.repeats}: must be at least 1")
    if a.threads < 0:
        ap.error(f"--threads {a.threads}: must be 0 (one per CPU) or more")
    root = Path(tempfile.mkdtemp(prefix="nanostage-batch-speed-"))
    manifest, _ = independent_truth.write_case(a.hidden, a.seed * 10_000, root)
    m = load_manifest(manifest)
    nominal = m.system()
    experiments = [e for _, e in m.experiments()]
    n = len(experiments)
    print(f"case {a.hidden} of seed {a.seed}: {n} experiments per batch, {a.threads} threads")
    for name in a.models:
        system = nominal
        if name != "nominal":
            found, skipped = applicable_candidates(nominal, [name])
            if not found:
                print(f"{name:20s} skipped: {skipped.get(name, 'not applicable')}")
                continue
            cand = found[0]
            system = cand.apply(nominal, [p.initial for p in cand.params])
        ref: tuple[np.ndarray, np.ndarray] | None = None
        for rtol, atol in a.tolerances:
            integ = dataclasses.replace(system.integrator, rtol=rtol, atol_position_m=atol)
            s = dataclasses.replace(system, integrator=integ)
            times = []
            out = []
            for _ in range(a.repeats):
                t0 = time.perf_counter()
                out = simulate_readings_and_commands([s] * n, experiments, threads=a.threads)
                times.append(time.perf_counter() - t0)
            reading = np.concatenate([o[0] for o in out])
            command = np.concatenate([o[1] for o in out])
            ms = statistics.median(times) * 1e3
            line = f"{name:20s} rtol {rtol:7.0e} atol {atol:7.0e} m: {ms:8.2f} ms"
            if ref is None:
                ref = (reading, command)
            else:
                line += (
                    f"  readings differ by up to {np.max(np.abs(reading - ref[0])):.2e} m, "
                    f"commands by {np.max(np.abs(command - ref[1])):.2e} V"
                )
            print(line, flush=True)


if __name__ == "__main__":
    main()
