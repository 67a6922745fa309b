"""``nanostage reproduce``: the paper's four step experiments with the Table 1 gains.

Every function takes an optional ``model`` (a :class:`~nanostage.System`, e.g. from
:func:`nanostage.load_model`): the axis is then that model, with the Table 1 gains of each
step size in place of its PID gains (:func:`nanostage.presets.table1_system`), or with
``gains="model"`` with its own PID gains at every step size (:func:`study_system`); without
it, the seed preset.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Final, Literal

from .. import presets
from .._core import ConfigError
from ..analysis import StepMetrics, step_metrics
from ..config import FpgaPid, Plant, System
from ..output import staged_output, write_json
from ..simulate import Trace, simulate_step

#: (step size, simulated duration) of the paper's experiments.
EXPERIMENTS_M_S: tuple[tuple[float, float], ...] = (
    (100e-6, 0.5),
    (500e-6, 0.5),
    (1e-3, 0.6),
    (10e-3, 1.5),
)


def slew_velocity_m_per_s(plant: Plant, voltage_v: float) -> float:
    """Table speed of the constant-slope ramp at the voltage limit, from the force balance.

    At steady sliding the Dahl force has reached Fc, the current is (V − k_e·ω)/R, and
    η·(k_t·i − T_c − b·ω)/r = F_c + F_ext (the Stribeck term has decayed at these speeds), so
    ω = (k_t·V/R − T_c − r·(F_c + F_ext)/η) / (k_t·k_e/R + b) and v = r·ω.
    """
    m = plant.motor
    f = plant.motor_friction
    r = plant.transmission_m_per_rad
    eta = plant.gearhead.efficiency * plant.screw.efficiency
    load = r * (plant.dahl.coulomb_force_n + plant.table.external_force_n) / eta
    drive = m.torque_constant_nm_per_a * voltage_v / m.resistance_ohm
    damping = m.torque_constant_nm_per_a * m.back_emf_v_s_per_rad / m.resistance_ohm
    w = (drive - f.coulomb_torque_nm - load) / (damping + f.viscous_nm_s_per_rad)
    return r * w


#: Where the PID gains of a study's axis come from: ``table1``, the paper's Table 1 gains of
#: each step size; ``model``, the model's own gains at every step size.
GainSource = Literal["table1", "model"]
GAIN_SOURCES: Final[tuple[str, ...]] = ("table1", "model")


def study_system(
    step_m: float, model: System | None = None, gains: GainSource = "table1"
) -> System:
    """The axis of a Table 1 study at ``step_m``: :func:`nanostage.presets.table1_system`
    (the seed preset, or ``model`` with the Table 1 gains of ``step_m``), or with
    ``gains="model"`` ``model`` as it is, its own PID gains included.

    Raises
    ------
    ConfigError
        If ``gains`` is not one of :data:`GAIN_SOURCES`, if ``gains="model"`` comes without
        a ``model``, or if ``model`` is not a Table 1 axis (a rigid-axis plant with an FPGA
        PID).
    """
    if gains not in GAIN_SOURCES:
        raise ConfigError(
            f"gains = {gains!r} is invalid: expected one of {', '.join(map(repr, GAIN_SOURCES))}"
        )
    system = presets.table1_system(step_m, model)
    if gains == "table1":
        return system
    if model is None:
        raise ConfigError(
            "gains = 'model' needs a model (a model file: nanostage.load_model(path), or "
            "--model FILE) whose PID gains to keep; without one the axis is the seed preset "
            "with the Table 1 gains (gains = 'table1')"
        )
    return model


@dataclass(frozen=True, slots=True, kw_only=True)
class Experiment:
    """One reproduced step: its gains, trace and figures."""

    step_m: float
    gains: tuple[float, float, float]
    trace: Trace
    metrics: StepMetrics


def run_experiments(model: System | None = None, gains: GainSource = "table1") -> list[Experiment]:
    """Simulate the four Table 1 steps on the seed axis (or on ``model`` with the Table 1
    gains, or with its own with ``gains="model"``)."""
    systems = [study_system(step, model, gains) for step, _ in EXPERIMENTS_M_S]
    out = []
    for (step, duration), system in zip(EXPERIMENTS_M_S, systems, strict=True):
        tr = simulate_step(system, step, duration_s=duration)
        c = system.controller
        assert isinstance(c, FpgaPid)
        out.append(
            Experiment(step_m=step, gains=(c.kp, c.ki, c.kd), trace=tr, metrics=step_metrics(tr))
        )
    return out


def _fmt(v: float, scale: float, digits: int = 1) -> str:
    return "—" if math.isnan(v) else f"{v * scale:.{digits}f}"


def table(exps: list[Experiment]) -> str:
    """The response figures as a Markdown table."""
    rows = [
        "| step | Kp, Ki, Kd | rise 10–90 % [ms] | overshoot [µm] | settling ±1 count [ms] "
        "| final error [nm] | max speed [mm/s] | at voltage limit [ms] |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for e in exps:
        m = e.metrics
        rows.append(
            f"| {e.step_m * 1e6:.0f} µm | {e.gains[0]:g}, {e.gains[1]:g}, {e.gains[2]:g} "
            f"| {_fmt(m.rise_time_s, 1e3)} | {_fmt(m.overshoot_m, 1e6)} "
            f"| {_fmt(m.settling_time_s, 1e3, 0)} | {_fmt(m.final_error_m, 1e9)} "
            f"| {_fmt(m.max_velocity_m_per_s, 1e3, 2)} "
            f"| {_fmt(m.time_at_voltage_limit_s, 1e3, 0)} |"
        )
    return "\n".join(rows)


def reproduce(
    out_dir: str | Path,
    *,
    plot: bool = True,
    model: System | None = None,
    gains: GainSource = "table1",
) -> dict[str, object]:
    """Run the experiments, write ``summary.json`` (and ``steps.png``), return the summary.

    The folder is written whole or not at all (:func:`nanostage.output.staged_output`): it
    must be new, empty or an earlier run's folder, which is checked before any work.
    ``model`` and ``gains``: the axis and its gains (module docstring), checked before any
    work.
    """
    study_system(1e-3, model, gains)
    with staged_output(out_dir, "reproduce") as folder:
        return reproduce_into(folder, plot=plot, model=model, gains=gains)


def reproduce_into(
    folder: Path,
    *,
    plot: bool = True,
    model: System | None = None,
    gains: GainSource = "table1",
) -> dict[str, object]:
    """:func:`reproduce` writing straight into an existing ``folder`` (a staged one)."""
    out = Path(folder)
    system = study_system(1e-3, model, gains)
    t0 = time.perf_counter()
    exps = run_experiments(model, gains)
    compute_s = time.perf_counter() - t0
    v_lim = system.output_stage.amplifier_limit_v
    assert isinstance(system.plant, Plant)
    v_slew = slew_velocity_m_per_s(system.plant, v_lim)
    summary: dict[str, object] = {
        "steps": [
            {
                **e.metrics.to_dict(),
                "kp": e.gains[0],
                "ki": e.gains[1],
                "kd": e.gains[2],
                "integrator_stats": e.trace.stats,
            }
            for e in exps
        ],
        "slew_at_voltage_limit": {
            "voltage_v": v_lim,
            "predicted_velocity_m_per_s": v_slew,
            "explanation": slew_velocity_m_per_s.__doc__,
        },
        "compute_time_s": compute_s,
    }
    write_json(summary, out / "summary.json", indent=2)
    if plot:
        from ..plotting import plot_steps

        pick = [e for e in exps if e.step_m in (100e-6, 1e-3)]
        plot_steps(
            [e.trace for e in pick],
            [f"{e.step_m * 1e6:.0f} µm step, (Kp, Ki, Kd) = {e.gains}" for e in pick],
            out / "steps.png",
        )
    summary["table_markdown"] = table(exps)
    return summary
