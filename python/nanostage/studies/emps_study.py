"""EMPS in closed loop with the same components as the seed axis: the authors' yardstick,
output-error identification by closed-loop simulation, the gap diagnosis on real data, and
prediction under a known command disturbance (``nanostage emps``, ``nanostage predict``).
"""

from __future__ import annotations

import dataclasses
import math
import shutil
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt
from scipy.optimize import least_squares

from .. import presets
from .._core import __version__
from ..blas import single_threaded_blas
from ..config import ForceDrivePlant, System, get_path, replace_paths
from ..experiment import Experiment
from ..model_file import IdentifiedParameter, save_model
from ..output import check_output_dir, staged_output, write_json
from ..simulate import Trace, simulate
from .emps import EmpsData, controller_fit, emps_velocity_force, load_emps, relative_error

__all__ = [
    "MODEL_FILE",
    "OutputErrorFit",
    "Yardstick",
    "check_study_data",
    "output_error_fit",
    "simulate_experiment",
    "yardstick",
]

FloatArray = npt.NDArray[np.float64]

#: The model file of the identified model that ``emps_study`` writes into its folder.
MODEL_FILE = "model.toml"

#: Parameters the output-error identification fits, with their starting bounds.
OE_PARAMETERS: tuple[tuple[str, float, float], ...] = (
    ("plant.mass_kg", 50.0, 200.0),
    ("plant.friction.viscous_n_s_per_m", 10.0, 1000.0),
    ("plant.friction.coulomb_force_n", 0.0, 60.0),
    ("plant.external_force_n", -20.0, 20.0),
)


def simulate_experiment(system: System, e: Experiment, *, seed: int = 0) -> Trace:
    """Closed-loop simulation of ``system`` over the experiment's reference and known
    disturbances, starting at rest at the first measured position."""
    return simulate(
        system,
        e.reference_m,
        force_disturbance_n=e.disturbance_n,
        command_disturbance_v=e.disturbance_v,
        initial_position_m=float(e.position_m[0]),
        seed=seed,
    )


@dataclasses.dataclass(frozen=True, slots=True, kw_only=True)
class Yardstick:
    """The authors' relative errors ‖measured − simulated‖/‖measured‖ (fractions)."""

    position: float
    velocity: float
    force: float

    def to_dict(self) -> dict[str, float]:
        return {"position": self.position, "velocity": self.velocity, "force": self.force}


def yardstick(system: System, data: EmpsData, experiment: Experiment | None = None) -> Yardstick:
    """Relative errors of the closed-loop simulation of ``system`` against the measurement:
    position (encoder reading), velocity (the same filtered central difference of both
    positions) and force (``gtau·command``)."""
    e = experiment or data.experiment
    tr = simulate_experiment(system, e)
    sim = Experiment(
        name="simulated",
        time_s=e.time_s,
        reference_m=e.reference_m,
        position_m=tr.encoder_position_m,
        command_v=tr.command,
    )
    g = data.drive_gain_n_per_v
    meas = emps_velocity_force(e, g)
    simv = emps_velocity_force(sim, g)
    return Yardstick(
        position=relative_error(e.position_m, tr.encoder_position_m),
        velocity=relative_error(meas.velocity_m_per_s, simv.velocity_m_per_s),
        force=relative_error(meas.force_n, simv.force_n),
    )


@dataclasses.dataclass(frozen=True, slots=True, kw_only=True)
class OutputErrorFit:
    """Parameters found by output-error identification, with standard errors."""

    values: dict[str, float]
    std_errors: dict[str, float]
    system: System = dataclasses.field(repr=False)
    cost: float
    n_evaluations: int


@single_threaded_blas()
def output_error_fit(
    data: EmpsData,
    system: System | None = None,
    *,
    parameters: Sequence[tuple[str, float, float]] = OE_PARAMETERS,
    experiment: Experiment | None = None,
    position_scale_m: float = 5e-8,
    command_scale_v: float = 0.004,
) -> OutputErrorFit:
    """Output-error identification by closed-loop simulation: bounded least squares on the
    measured position (in encoder counts) and command (in units of the controller
    emulation's 0.004 V rms) against the simulation, starting from ``system`` (default: the
    authors' symmetric model). Standard errors from the Jacobian, inflated by the residual's
    integrated autocorrelation time."""
    from ..diagnosis.objective import autocorrelation_time

    base = system or presets.emps()
    e = experiment or data.experiment
    assert e.command_v is not None
    command = e.command_v
    names = [p[0] for p in parameters]
    x0 = np.array([float(get_path(base, n)) for n in names])
    lo = np.array([p[1] for p in parameters])
    hi = np.array([p[2] for p in parameters])
    x0 = np.clip(x0, lo, hi)
    width = hi - lo
    n = len(e.time_s)
    count = [0]

    def physical(u: FloatArray) -> FloatArray:
        # Normalised coordinates in [1, 2] (so that relative finite-difference steps are
        # fractions of each parameter's range).
        out: FloatArray = lo + (u - 1.0) * width
        return out

    def build(u: FloatArray) -> System:
        values = {k: float(v) for k, v in zip(names, physical(u), strict=True)}
        p = base.plant
        if isinstance(p, ForceDrivePlant) and "plant.friction.coulomb_force_n" in values:
            fc = values["plant.friction.coulomb_force_n"]
            extra = p.friction.static_force_n - p.friction.coulomb_force_n
            values["plant.friction.static_force_n"] = fc + extra
        built: System = replace_paths(base, values)
        return built

    def residual(u: FloatArray) -> FloatArray:
        count[0] += 1
        tr = simulate_experiment(build(u), e)
        # The true (unquantised) simulated position minus half a count keeps the residual
        # smooth in the parameters; the command stays quantisation-driven, so the finite
        # differences use 1 % steps.
        rx = (e.position_m - (tr.motor_position_m - 0.5 * position_scale_m)) / position_scale_m
        ru = (command - tr.command) / command_scale_v
        return np.concatenate([rx, ru]) / math.sqrt(n)

    sol = least_squares(
        residual,
        1.0 + (x0 - lo) / width,
        bounds=(1.0, 2.0),
        method="trf",
        diff_step=2e-3,
        max_nfev=60,
    )
    jac = sol.jac
    dof = max(len(sol.fun) - len(names), 1)
    s2 = 2.0 * sol.cost / dof * autocorrelation_time(np.asarray(sol.fun))
    cov = np.linalg.pinv(jac.T @ jac) * s2
    std = np.sqrt(np.clip(np.diag(cov), 0.0, None)) * width
    values = {k: float(v) for k, v in zip(names, physical(sol.x), strict=True)}
    return OutputErrorFit(
        values=values,
        std_errors={k: float(s) for k, s in zip(names, std, strict=True)},
        system=build(sol.x),
        cost=float(sol.cost),
        n_evaluations=count[0],
    )


#: Fewest samples the study accepts (0.1 s at 1 kHz).
MIN_STUDY_SAMPLES = 100
#: Largest rms difference between the logged command and the cascade controller law on the
#: logged positions, as a fraction of the command's rms (DATA_EMPS: 0.24 %). Positions in
#: millimetres, or a different controller, give 100 % or more.
MAX_CONTROLLER_MISMATCH = 0.1


def check_study_data(data: EmpsData) -> None:
    """Check that the data suit the study: enough samples, and a logged command that the
    documented cascade controller reproduces from the logged positions (which also catches
    positions in millimetres: the law would be 1000 times too strong).

    Raises
    ------
    ValueError
        Naming the file, the value and the limit.
    """
    e = data.experiment
    src = e.source or e.name
    if e.n_samples < MIN_STUDY_SAMPLES:
        raise ValueError(
            f"{src}: {e.n_samples} samples, the EMPS study needs at least {MIN_STUDY_SAMPLES}"
        )
    command_rms = float(np.sqrt(np.mean(data.command_v**2)))
    fit = controller_fit(data)
    if not (command_rms > 0.0 and fit.rms_v <= MAX_CONTROLLER_MISMATCH * command_rms):
        raise ValueError(
            f"{src}: the logged command vir (rms {command_rms:.4g} V) differs from the cascade "
            f"controller law on qg and qm by {fit.rms_v:.4g} V rms, more than "
            f"{MAX_CONTROLLER_MISMATCH:.0%} of it: are qg and qm in metres (values in "
            "millimetres make the law 1000 times too strong) and kp, kv the controller's gains?"
        )


def emps_study(out_dir: str | Path, *, mat_path: str | None = None) -> dict[str, Any]:
    """The EMPS study: authors' models and the output-error model against the data
    (yardstick), written to ``out_dir/emps.json``; the identified (output-error) model
    to ``out_dir/model.toml`` (docs/model-file.md), with the standard errors and bounds of
    its fitted parameters and the data file and fit statistics as provenance.

    ``out_dir`` and the data (:func:`~nanostage.studies.emps.load_emps`, :func:`check_study_data`)
    are checked before any work; the folder is written whole or not at all
    (:func:`nanostage.output.staged_output`)."""
    check_output_dir(out_dir)
    data = load_emps(mat_path)
    check_study_data(data)
    results: dict[str, Any] = {"source": data.experiment.source}
    results["authors_reference"] = {"position": 0.00014, "force": 0.058, "velocity": 0.0023}
    results["authors_symmetric"] = yardstick(presets.emps(), data).to_dict()
    results["authors_asymmetric"] = yardstick(presets.emps(asymmetric=True), data).to_dict()
    oe = output_error_fit(data)
    oe_yardstick = yardstick(oe.system, data).to_dict()
    results["output_error"] = {
        "values": oe.values,
        "std_errors": oe.std_errors,
        "yardstick": oe_yardstick,
        "evaluations": oe.n_evaluations,
    }
    results["model_file"] = MODEL_FILE
    bounds = {name: (lo, hi) for name, lo, hi in OE_PARAMETERS}
    with staged_output(out_dir, "emps") as folder:
        write_json(results, folder / "emps.json", indent=1)
        save_model(
            oe.system,
            folder / MODEL_FILE,
            provenance={
                "command": "nanostage emps",
                "nanostage_version": __version__,
                "data": str(data.experiment.source),
                "method": "output-error identification by closed-loop simulation",
                "cost": oe.cost,
                "evaluations": oe.n_evaluations,
                "relative_error": oe_yardstick,
            },
            identified={
                name: IdentifiedParameter(
                    std_error=oe.std_errors[name], lower=bounds[name][0], upper=bounds[name][1]
                )
                for name in oe.values
            },
        )
    return results


#: Time windows of DATA_EMPS that start at reversals of the reference (where the axis is
#: nearly at rest, so a simulation starting at rest is a fair start), s.
WINDOWS_S: tuple[tuple[float, float], ...] = (
    (0.0, 6.224),
    (6.224, 12.464),
    (12.464, 18.704),
    (18.704, 24.84),
)


def write_manifest(
    path: str | Path,
    *,
    preset: str,
    free: Mapping[str, tuple[float, float]],
    mat_path: str | Path,
    candidates: str | Sequence[str] = "all",
) -> Path:
    """A diagnosis manifest over DATA_EMPS cut into the four windows of :data:`WINDOWS_S`:
    windows 1 and 3 train, 2 and 4 validate. A manifest's trace files must lie inside its
    folder, so the data file is copied there unless it already is."""
    p = Path(path)
    data = p.parent / Path(mat_path).name
    cand = (
        f'"{candidates}"'
        if isinstance(candidates, str)
        else "[" + ", ".join(f'"{c}"' for c in candidates) + "]"
    )
    lines = [
        "[model]",
        f'preset = "{preset}"',
        "free = [" + ", ".join(f'"{k}"' for k in free) + "]",
        "",
        "[model.bounds]",
        *[f'"{k}" = [{lo}, {hi}]' for k, (lo, hi) in free.items()],
        "",
        "[diagnosis]",
        f"candidates = {cand}",
        "",
    ]
    for i, (a, b) in enumerate(WINDOWS_S):
        lines += [
            "[[experiment]]",
            f'name = "window{i + 1}"',
            f'file = "{data.name}"',
            f'role = "{"train" if i % 2 == 0 else "validate"}"',
            'columns = { time_s = "t", reference_m = "qg", position_m = "qm", command_v = "vir" }',
            f"window_s = [{a}, {b}]",
            "",
        ]
    p.parent.mkdir(parents=True, exist_ok=True)
    if not (data.exists() and data.samefile(mat_path)):
        shutil.copyfile(mat_path, data)
    p.write_text("\n".join(lines), encoding="utf-8")
    return p
