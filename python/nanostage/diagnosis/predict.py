"""``nanostage predict``: simulate an identified model in closed loop for given references
and known disturbances, and write the predicted position, velocity and command.

Manifest (TOML): the schema of the diagnosis manifest (docs/diagnosis.md, checked by the
same code, :func:`nanostage.diagnosis.manifest.load_prediction_manifest`) without its
diagnosis keys::

    [model]
    preset = "emps"                      # a name in nanostage.presets.PRESETS, or
    # file = "axis.model.toml"           #   a model file (docs/model-file.md) in its place
    file = "model.toml"                  # optional with a preset: overrides from a file
    travel_m = 0.5                       # optional: the axis travel, m (default: the preset's)
    [model.overrides]                    # identified values (dotted paths into the System)
    "plant.mass_kg" = 94.8

    [controller]                         # optional gains, as in the diagnosis manifest

    [[experiment]]
    name = "pulses"                      # becomes the output file name pulses.csv
    file = "pulses.csv"                  # relative to the manifest, inside its folder
    units = "mm"                         # optional: the file's lengths are in mm
    columns = { reference_m = "qg" }     # optional column map
    window_s = [0.0, 10.0]               # optional time window [start, stop)

Each trace file (CSV, ``.npz`` or ``.mat``) has the columns ``time_s`` and ``reference_m``
and optionally ``disturbance_v`` (known command disturbance, added after the controller's
saturation), ``disturbance_n`` (known force on the table) and ``position_m`` (a measurement
to compare with); any other CSV column is an error (a misspelt disturbance would otherwise
be left out).

Checks, all before any simulation and before anything is written (a :class:`PredictError`
naming the manifest key or the file, line and column):

* unknown or misspelt keys (with a "did you mean"), diagnosis-only keys, bad overrides;
* experiment names must be safe, unique file names (letters, digits, ``_``, ``-``, ``.``;
  no ``/``, no ``..``, not hidden; unique case-insensitively);
* trace files must resolve (after symbolic links) inside the manifest's folder, unless
  ``trace_root`` (CLI ``--trace-root``) names another folder;
* size limits (:class:`~nanostage.diagnosis.traces.TraceLimits`): 2 000 000 samples and
  1.02 GB per trace, 10 000 000 samples for all the experiments together
  (:data:`~nanostage.diagnosis.traces.PREDICTION_MAX_SAMPLES_TOTAL`), checked before a
  file is read whole;
* every check of a diagnosis trace: UTF-8, numeric and finite cells, time strictly
  increasing without gaps or jitter (±50 % of the median step), at least 10 samples, the
  sample period of the controller;
* plausibility against the axis travel: a length column whose peak-to-peak exceeds the
  travel (or a value beyond ten travels from the origin) is taken for millimetres; the
  message names the fix (``units = "mm"``, or convert). A reference of ``10`` on the seed
  axis (50 mm travel) is an error, not a 10 m move;
* the output folder (:func:`nanostage.output.check_output_dir`).

Output, written whole or not at all (:func:`nanostage.output.staged_output`):
``DIR/<name>.csv`` with ``time_s, reference_m, position_m, velocity_m_per_s, command_v``:
the encoder reading, its velocity, and the controller output in volts at the amplifier
input (the controller's output units times ``output_unit_v``, the conversion the diagnosis
uses: 6.0 V, not 60 000, at the seed axis's limit); ``DIR/predict.json`` (strict JSON)
with each experiment's sample count, file and, given a measurement, the relative error
``‖measured − predicted‖ / ‖measured‖`` (null when the measurement is zero throughout).
"""

from __future__ import annotations

import csv
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from ..config import System
from ..output import OutputError, check_output_dir, staged_output, write_json
from ..simulate import simulate
from .manifest import (
    ManifestError,
    check_total_samples,
    load_prediction_manifest,
)
from .traces import (
    PREDICTION_COLUMNS,
    PREDICTION_MAX_SAMPLES_TOTAL,
    TraceError,
    TraceLimits,
    read_prediction_trace,
)

__all__ = ["PredictError", "predict", "read_prediction_input"]

FloatArray = npt.NDArray[np.float64]
_COLUMNS = PREDICTION_COLUMNS
#: Header of each output file.
OUTPUT_COLUMNS = ("time_s", "reference_m", "position_m", "velocity_m_per_s", "command_v")


class PredictError(ValueError):
    """A bad manifest, trace or output folder (names the file and the key, line or
    column)."""


def _located(exc: TraceError) -> str:
    """A trace error as ``<file>: line <n>, column '<c>': <reason>``."""
    parts = []
    if exc.line is not None:
        parts.append(f"line {exc.line}")
    elif exc.sample is not None:
        parts.append(f"sample {exc.sample}")
    if exc.column is not None:
        parts.append(f"column {exc.column!r}")
    where = f"{exc.file}: {', '.join(parts)}" if parts else exc.file
    return f"{where}: {exc.reason}"


def _default_limits() -> TraceLimits:
    return TraceLimits(max_samples_total=PREDICTION_MAX_SAMPLES_TOTAL)


def read_prediction_input(
    path: Path,
    *,
    units: str | Mapping[str, str] | None = None,
    travel_m: float | None = None,
    limits: TraceLimits | None = None,
) -> dict[str, FloatArray]:
    """Read a prediction trace (the columns above), checked as described in the module
    docstring (:func:`nanostage.diagnosis.traces.read_prediction_trace`).

    Raises
    ------
    PredictError
        Naming the file, the line and the column.
    """
    try:
        return read_prediction_trace(path, units=units, travel_m=travel_m, limits=limits)
    except TraceError as exc:
        raise PredictError(_located(exc)) from exc


def predict(
    manifest: str | Path,
    out_dir: str | Path,
    *,
    trace_root: str | Path | None = None,
    limits: TraceLimits | None = None,
    model: System | None = None,
) -> dict[str, Any]:
    """Run every experiment of the manifest; returns (and writes) the summary.

    Parameters
    ----------
    manifest : str or Path
        The manifest (module docstring).
    out_dir : str or Path
        The output folder: new, empty, or one an earlier nanostage run wrote (replaced).
    trace_root : str or Path, optional
        The folder the files named in the manifest must resolve inside; default: the
        manifest's folder.
    limits : TraceLimits, optional
        Size limits; default ``TraceLimits(max_samples_total=PREDICTION_MAX_SAMPLES_TOTAL)``.
    model : System, optional
        The nominal model (e.g. :func:`nanostage.load_model`) in place of the manifest's
        preset or model file; the manifest's overrides and controller gains apply to it.

    Returns
    -------
    dict
        ``{"manifest": str, "experiments": {name: {"samples", "file",
        ["position_relative_error"]}}}``, as written to ``predict.json``.

    Raises
    ------
    PredictError
        Every input and output-folder problem, before any simulation.
    """
    path = Path(manifest)
    try:
        m = load_prediction_manifest(
            path,
            trace_root=trace_root,
            limits=_default_limits() if limits is None else limits,
            model=model,
        )
    except ManifestError as exc:
        raise PredictError(str(exc)) from exc
    try:
        check_output_dir(out_dir)
    except OutputError as exc:
        raise PredictError(str(exc)) from exc
    inputs = []
    total = 0
    for spec in m.experiment_specs:
        system = m.system(spec)
        try:
            cols = read_prediction_trace(
                spec.file,
                columns=spec.columns,
                window_s=spec.window_s,
                units=spec.units,
                travel_m=m.model.travel_m,
                limits=m.limits,
                group=spec.group,
            )
        except TraceError as exc:
            raise PredictError(f"{_located(exc)} (experiment {spec.name!r} of {path})") from exc
        total += len(cols["time_s"])
        try:
            check_total_samples(total, m.limits, spec, m.path)
        except ManifestError as exc:
            raise PredictError(str(exc)) from exc
        dt = float(np.median(np.diff(cols["time_s"])))
        if abs(dt - system.sample_period_s) > 1e-3 * system.sample_period_s:
            raise PredictError(
                f"{spec.file}: column 'time_s': sampled every {dt:g} s, the controller every "
                f"{system.sample_period_s:g} s (experiment {spec.name!r}; declare "
                'units = { time_s = "ms" } for a time in ms)'
            )
        inputs.append((spec.name, system, cols))
    summary: dict[str, Any] = {"manifest": str(path), "experiments": {}}
    try:
        with staged_output(out_dir, "predict") as folder:
            for name, system, cols in inputs:
                summary["experiments"][name] = _predict_one(
                    system, cols, folder / f"{name}.csv", Path(out_dir) / f"{name}.csv"
                )
            write_json(summary, folder / "predict.json", indent=1)
    except OutputError as exc:
        raise PredictError(str(exc)) from exc
    return summary


def _predict_one(
    system: Any, cols: dict[str, FloatArray], file: Path, final: Path
) -> dict[str, Any]:
    """Simulate one experiment, write its CSV to ``file``; its summary entry."""
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
    # The controller output in volts at the amplifier input (as the diagnosis converts it).
    command_v = tr.command * tr.output_unit_v
    with file.open("w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(OUTPUT_COLUMNS)
        for row in zip(cols["time_s"], cols["reference_m"], reading, vel, command_v, strict=True):
            w.writerow([repr(float(v)) for v in row])
    entry: dict[str, Any] = {"samples": len(reading), "file": str(final)}
    if "position_m" in cols:
        meas = cols["position_m"]
        norm = float(np.linalg.norm(meas))
        entry["position_relative_error"] = (
            float(np.linalg.norm(meas - reading) / norm) if norm > 0.0 else None
        )
    return entry
