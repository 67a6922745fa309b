"""``nanostage predict``: simulate an identified model in closed loop for given references
and known disturbances, and write the predicted position, velocity and command.

Manifest (TOML)::

    [model]
    preset = "emps"                      # a name in nanostage.presets.PRESETS
    [model.overrides]                    # identified values (dotted paths into the System)
    "plant.mass_kg" = 94.8

    [[experiment]]
    name = "pulses"
    file = "pulses.csv"                  # relative to the manifest

Each trace file is a CSV with a header naming ``time_s`` and ``reference_m`` and optionally
``disturbance_v`` (known command disturbance, added after the controller's saturation),
``disturbance_n`` (known force on the table) and ``position_m`` (a measurement to compare
with). ``DIR/<name>.csv`` gets ``time_s, reference_m, position_m, velocity_m_per_s,
command_v``; ``DIR/predict.json`` the relative errors against a given measurement.
"""

from __future__ import annotations

import csv
import json
import math
import sys
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from .config import System
from .diagnosis.manifest import preset_names, preset_system, replace_paths
from .simulate import simulate

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10
    import tomli as tomllib

__all__ = ["PredictError", "predict", "read_prediction_input"]

FloatArray = npt.NDArray[np.float64]
_COLUMNS = ("time_s", "reference_m", "disturbance_v", "disturbance_n", "position_m")


class PredictError(ValueError):
    """A bad manifest or trace (names the file and the key, line or column)."""


def read_prediction_input(path: Path) -> dict[str, FloatArray]:
    """Read a prediction trace (CSV, header row): the columns above."""
    try:
        with path.open(newline="") as f:
            rows = list(csv.reader(f))
    except OSError as exc:
        raise PredictError(f"{path}: cannot read ({exc.strerror})") from exc
    if not rows:
        raise PredictError(f"{path}: empty file")
    head = [h.strip() for h in rows[0]]
    for req in ("time_s", "reference_m"):
        if req not in head:
            raise PredictError(f"{path}: line 1: missing column {req!r} (found {head})")
    unknown = [h for h in head if h not in _COLUMNS]
    if unknown:
        raise PredictError(f"{path}: line 1: unknown columns {unknown}; valid: {_COLUMNS}")
    cols: dict[str, list[float]] = {h: [] for h in head}
    for ln, row in enumerate(rows[1:], start=2):
        if len(row) != len(head):
            raise PredictError(f"{path}: line {ln}: {len(row)} cells, expected {len(head)}")
        for h, cell in zip(head, row, strict=True):
            try:
                v = float(cell)
            except ValueError as exc:
                raise PredictError(
                    f"{path}: line {ln}, column {h!r}: {cell!r} is not a number"
                ) from exc
            if not math.isfinite(v):
                raise PredictError(f"{path}: line {ln}, column {h!r}: {cell!r} is not finite")
            cols[h].append(v)
    out = {h: np.asarray(v, dtype=np.float64) for h, v in cols.items()}
    t = out["time_s"]
    if len(t) < 2:
        raise PredictError(f"{path}: fewer than 2 samples")
    bad = np.flatnonzero(np.diff(t) <= 0)
    if bad.size:
        raise PredictError(
            f"{path}: line {int(bad[0]) + 3}, column 'time_s': time does not increase"
        )
    return out


def _model(data: dict[str, Any], path: Path) -> System:
    model = data.get("model")
    if not isinstance(model, dict) or "preset" not in model:
        raise PredictError(f'{path}: key "model.preset": missing (e.g. preset = "emps")')
    name = model["preset"]
    if name not in preset_names():
        raise PredictError(
            f'{path}: key "model.preset": unknown preset {name!r}; valid: {preset_names()}'
        )
    overrides = model.get("overrides", {})
    if not isinstance(overrides, dict):
        raise PredictError(f'{path}: key "model.overrides": expected a table')
    try:
        system: System = replace_paths(preset_system(name), overrides)
    except (ValueError, KeyError, TypeError, AttributeError) as exc:
        raise PredictError(f'{path}: key "model.overrides": {exc}') from exc
    return system


def predict(manifest: str | Path, out_dir: str | Path) -> dict[str, Any]:
    """Run every experiment of the manifest; returns (and writes) the summary."""
    path = Path(manifest)
    try:
        data = tomllib.loads(path.read_text())
    except OSError as exc:
        raise PredictError(f"{path}: cannot read ({exc.strerror})") from exc
    except tomllib.TOMLDecodeError as exc:
        raise PredictError(f"{path}: {exc}") from exc
    system = _model(data, path)
    exps = data.get("experiment")
    if not isinstance(exps, list) or not exps:
        raise PredictError(f'{path}: key "experiment": at least one [[experiment]] is needed')
    inputs = []
    for i, e in enumerate(exps):
        if not isinstance(e, dict) or "file" not in e or "name" not in e:
            raise PredictError(f'{path}: key "experiment[{i}]": needs name and file')
        f = (path.parent / str(e["file"])).resolve()
        if not f.exists():
            raise PredictError(f'{path}: key "experiment[{i}].file": {f} does not exist')
        cols = read_prediction_input(f)
        dt = float(np.median(np.diff(cols["time_s"])))
        if abs(dt - system.sample_period_s) > 1e-3 * system.sample_period_s:
            raise PredictError(
                f"{f}: column 'time_s': sampled every {dt:g} s, the controller every "
                f"{system.sample_period_s:g} s"
            )
        inputs.append((str(e["name"]), cols))
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    summary: dict[str, Any] = {"manifest": str(path), "experiments": {}}
    for name, cols in inputs:
        x0 = float(cols["position_m"][0]) if "position_m" in cols else float(cols["reference_m"][0])
        tr = simulate(
            system,
            cols["reference_m"],
            command_disturbance_v=cols.get("disturbance_v"),
            force_disturbance_n=cols.get("disturbance_n"),
            initial_position_m=x0,
        )
        pos = tr.motor_position_m if system.encoder.side == "motor" else tr.position_m
        reading = tr.encoder_position_m
        vel = np.gradient(pos, tr.time_s)
        with (out / f"{name}.csv").open("w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(["time_s", "reference_m", "position_m", "velocity_m_per_s", "command_v"])
            for row in zip(
                cols["time_s"], cols["reference_m"], reading, vel, tr.command, strict=True
            ):
                w.writerow([repr(float(v)) for v in row])
        entry: dict[str, Any] = {"samples": len(reading), "file": str(out / f"{name}.csv")}
        if "position_m" in cols:
            m = cols["position_m"]
            entry["position_relative_error"] = float(
                np.linalg.norm(m - reading) / np.linalg.norm(m)
            )
        summary["experiments"][name] = entry
    (out / "predict.json").write_text(json.dumps(summary, indent=1))
    return summary
