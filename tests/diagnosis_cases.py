"""A small diagnosis case shared by the diagnosis tests: four seed-axis steps of ±0.5 mm (both
directions) with a hidden effect, two training and two validation experiments, the table's
Coulomb level free."""

from __future__ import annotations

import dataclasses as dc
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

import nanostage as ns
from nanostage.config import replace_paths
from nanostage.diagnosis.candidates import Param
from nanostage.diagnosis.fit import Fit, FitProblem
from nanostage.diagnosis.manifest import load_manifest
from nanostage.diagnosis.select import CandidateResult
from nanostage.diagnosis.traces import write_trace_csv
from nanostage.effects import Effects, StochasticFriction
from nanostage.experiment import Experiment


def simulated_experiment(
    system: ns.System, reference_m: np.ndarray, name: str, seed: int, start_m: float
) -> Experiment:
    """An experiment simulated by nanostage itself on ``reference_m`` from rest at
    ``start_m``, with its command (volts)."""
    tr = ns.simulate(system, reference_m, seed=seed, initial_position_m=start_m)
    return Experiment(
        name=name,
        time_s=tr.time_s,
        reference_m=reference_m,
        position_m=tr.encoder_position_m,
        command_v=tr.command * tr.output_unit_v,
    )


#: The candidates of the case's manifest unless given.
STEP_CASE_CANDIDATES = ("asymmetric_friction", "offset_force", "lead_periodic_friction")


def step_case(
    folder: Path,
    effects: Effects,
    seed: int,
    candidates: Sequence[str] = STEP_CASE_CANDIDATES,
    n_samples: int = 330,
) -> Path:
    """Write the case's traces and manifest into ``folder`` and return the manifest's path.
    The truth is the seed axis with ``effects`` and a small friction scatter; experiment
    ``i`` is simulated with seed ``10·seed + i`` (``n_samples`` samples, the step at 30)."""
    truth = dc.replace(
        ns.presets.seed(1e-3),
        effects=dc.replace(effects, stochastic=StochasticFriction(level_spread=0.003)),
    )
    names = ", ".join(f'"{c}"' for c in candidates)
    lines = [
        '[model]\npreset = "seed"\nfree = ["plant.dahl.coulomb_force_n"]\n',
        "[diagnosis]",
        f"candidates = [{names}]",
        f"seed = {seed}\n",
    ]
    design = [(5e-4, 1e-3, "train"), (-5e-4, 4e-3, "train"), (5e-4, 7e-3, "validate")]
    design += [(-5e-4, 9.5e-3, "validate")]
    for i, (step, x0, role) in enumerate(design):
        ref = np.full(n_samples, x0)
        ref[30:] = x0 + step
        g = ns.presets.table1_gains(abs(step))
        s = ns.presets.with_gains(truth, kp=g[0], ki=g[1], kd=g[2])
        tr = ns.simulate(s, ref, seed=seed * 10 + i)
        e = Experiment(
            name=f"e{i}", time_s=tr.time_s, reference_m=ref, position_m=tr.encoder_position_m
        )
        write_trace_csv(e, folder / f"e{i}.csv")
        lines += [
            "[[experiment]]",
            f'name = "e{i}"\nfile = "e{i}.csv"\nrole = "{role}"',
            f"controller = {{ kp = {g[0]}, ki = {g[1]}, kd = {g[2]} }}\n",
        ]
    (folder / "m.toml").write_text("\n".join(lines), encoding="utf-8")
    return folder / "m.toml"


def candidate_result(
    name: str,
    validation_ms: Sequence[float],
    *,
    rms_m: float,
    occam: float = 0.0,
    floor_ms: np.ndarray | None = None,
) -> CandidateResult:
    """A significant candidate result with the given per-experiment validation mean squares
    (m²), pooled RMS gap ``rms_m`` (also its training gap), Occam factor and floors, and
    nothing fitted: for the ranking, tie and tie-break rules."""
    fit = Fit(values={}, std_errors={}, train_rms_m=rms_m, n_evaluations=1, system=None)  # type: ignore[arg-type]
    ms = np.asarray(validation_ms, dtype=float)
    return CandidateResult(
        effect=name,
        fit=fit,
        fold_fits=[fit],
        validation_ms=ms,
        validation_command_ms=[None] * len(ms),
        command_ratio=None,
        validation_rms_m=rms_m,
        shrink=0.5,
        weighted_shrink=0.5,
        geometric_shrink=0.5,
        p_value=0.0,
        significant=True,
        reasons=[],
        log_occam=occam,
        validation_floor_ms=floor_ms,
    )


def friction_problems(
    manifest: Path,
    *,
    force_initial_n: float,
    torque_upper_nm: float,
    torque_initial_nm: float,
) -> Callable[[], FitProblem]:
    """New :class:`FitProblem` s on the first two experiments of ``manifest`` (no
    per-experiment adaptation, two simulation threads), each fitting the table's Dahl
    Coulomb force (20–40 N) and the motor's Coulomb torque (5e-5 N·m to
    ``torque_upper_nm``) of its nominal model from the given initial values."""
    man = load_manifest(manifest)
    exps = [e for _, e in man.experiments()][:2]
    free = [
        (
            "plant.dahl.coulomb_force_n",
            Param(name="f", unit="N", lower=20, upper=40, initial=force_initial_n),
        ),
        (
            "plant.motor_friction.coulomb_torque_nm",
            Param(
                name="t", unit="N·m", lower=5e-5, upper=torque_upper_nm, initial=torque_initial_nm
            ),
        ),
    ]
    nominal = man.system()

    def problem() -> FitProblem:
        return FitProblem(
            free,
            lambda v: replace_paths(nominal, {n: x for (n, _), x in zip(free, v, strict=True)}),
            exps,
            2,
            lambda s, e: s,
        )

    return problem
