"""``nanostage diagnose-benchmark``: a blind check of the diagnosis on synthetic data.

Each case draws a truth model: the seed axis with its uncertain friction levels perturbed,
one hidden effect (or none) with random plausible parameters, trial-to-trial stochastic
friction, encoder noise before quantisation, and a much finer integrator tolerance. It
simulates a designed set of experiments (several step sizes and start positions, both
directions, reversals, two dwell times, six repeated experiments, integral-only breakaway
tests of one micro-step after dwells of 0.05 to 1.5 s), writes them as CSV traces
with a manifest, and runs the diagnosis on the files alone.

Avoiding the inverse crime: a hidden LuGre-like presliding effect is simulated with a
six-element GMS of a different shape (the candidates are LuGre and a three-element GMS);
the hidden backlash has a contact stiffness and damping different from the candidate's
fixed values; delays are whole samples in the truth and in the candidate alike (an exact
model of the FPGA timing), but the truth adds noise, quantisation and scatter.

Scores: top-1 identification over the cases with an effect, the false-alarm rate over the
no-effect cases, the median validation-gap shrink of the selected model over the cases
with an effect, and a confusion matrix (hidden → first selected). Beside them, per case:
the shrink of the truth's own deterministic model (:func:`oracle_model`, nothing fitted:
what the drawn data allow; for the independent family :func:`independent_oracles`, which
also measures how far the hidden effect shrinks that model's gap) and the truth-started
check (is the effect detectable at all).
"""

from __future__ import annotations

import dataclasses as dc
import math
import os
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any, Final

import numpy as np

from .. import presets
from .._core import ConfigError
from ..config import Plant, System
from ..effects import (
    Backlash,
    DwellStaticFriction,
    Effects,
    EncoderErrors,
    FrictionModifiers,
    Gms,
    StochasticFriction,
    lead_periodic_friction,
)
from ..experiment import Experiment
from ..output import check_output_dir, staged_output, write_json
from ..simulate import simulate
from . import independent_truth
from .candidates import motor_static_force_n
from .case_manifest import case_manifest_head
from .manifest import load_manifest
from .run import diagnose, model_gap, readings_gap
from .scatter import MAX_LEVEL_SCATTER
from .settings import DEFAULT_LEVEL_SCATTER, DiagnosisSettings, phase_totals
from .traces import write_trace_csv

__all__ = [
    "DESIGN",
    "HIDDEN_EFFECTS",
    "MAX_CASES",
    "MAX_SEED",
    "SPEED_DESIGN",
    "TRUTH_FAMILIES",
    "design_reference",
    "draw_truth",
    "generate_case",
    "independent_oracles",
    "median_phase_seconds",
    "oracle_model",
    "run_benchmark",
    "truth_starts",
]

#: Most cases of one benchmark run.
MAX_CASES: Final[int] = 10_000
#: Largest seed of the case draws (a case's seeds are derived from it).
MAX_SEED: Final[int] = 2**32 - 1

#: Hidden effects drawn by the benchmark ("none": the nominal structure is right).
HIDDEN_EFFECTS: tuple[str, ...] = (
    "none",
    "asymmetric_friction",
    "dwell_static_friction",
    "lead_periodic_friction",
    "backlash",
    "computation_delay",
    "offset_force",
    "presliding_gms",
)

#: Which diagnosed names count as finding each hidden effect.
ACCEPT: dict[str, set[str]] = {
    "presliding_gms": {"gms", "lugre"},
}

#: The truth families a benchmark draws its cases from: ``own`` (nanostage's own core and
#: effect formulations, this module) and ``independent`` (a simulator written without
#: nanostage's models, :mod:`nanostage.diagnosis.independent_truth`).
TRUTH_FAMILIES: tuple[str, ...] = ("own", "independent")

#: Contact stiffness of the hidden backlash (the candidate's default is 5e7 N/m, its
#: damping fixed at another value than the truth's 800 N·s/m).
TRUTH_BACKLASH_STIFFNESS_N_PER_M = 2.5e7

#: Time after the last move (and between moves where no dwell is given), s.
MOVE_S = 0.3
#: Every experiment's reference starts this far into an encoder count (the truth starts at
#: a random point of the middle half of that count). A start exactly on a count edge (a
#: round start position) lets the sensor noise flicker the reading during the first dwell;
#: the integrator then preloads the drive by an amount no model of the mean reading can
#: know, and a micro-step breaks away at once, whatever the dwell (no dwell signature).
MID_COUNT_M = 30e-9

#: Integral-only PID gains (kp, ki, kd) of the breakaway tests: with no proportional or
#: derivative term the drive voltage after a small step ramps at a known rate until the axis
#: breaks away, so the breakaway delay measures the breakaway force. With the Table 1 gains
#: the proportional term of a three-count error already exceeds most breakaway levels, and
#: the response after a dwell is itself chaotic. Measured on one-step tests after dwells of
#: 0.05, 0.3 and 1.5 s (rise 3× the static level, 0.3 s): the dwell signature is 53–58 nm
#: against a scatter of up to 34 nm RMS between two friction draws with the Table 1 gains,
#: 74 nm against 21 nm under integral-only control.
BREAKAWAY_GAINS: tuple[float, float, float] = (0.0, 2.0, 0.0)
#: Hold after a breakaway test's step, s: long enough for the latest breakaway.
BREAKAWAY_HOLD_S = 0.8

Design = tuple[
    tuple[float, ...], float, tuple[float, ...], str, tuple[float, float, float] | None, float
]

# (steps in m, start in m, dwell before each step in s, role, gains or None for the Table 1
# gains of the nearest step size, hold after the last step in s). The breakaway tests are
# one micro-step of three counts each under integral-only control, after a dwell of 0.05 s
# to 1.5 s, in both directions, in the training and the validation set. One step per test:
# in a chain of micro-steps each breakaway starts from where the last one landed (which
# scatters by a count or more), and the gap of a dwell model was a needle a few per cent
# wide around the true rise and time constant, amid peaks; with one step per test it is a
# plateau below the true rise, a valley at it and a steady rise above, which a scan finds.
DESIGN: tuple[Design, ...] = (
    ((100e-6,), 2.0e-3 + MID_COUNT_M, (0.02,), "train", None, MOVE_S),
    ((-100e-6,), 4.5e-3 + MID_COUNT_M, (0.5,), "validate", None, MOVE_S),
    ((500e-6,), 7.0e-3 + MID_COUNT_M, (0.5,), "validate", None, MOVE_S),
    ((-500e-6,), 9.3e-3 + MID_COUNT_M, (0.02,), "train", None, MOVE_S),
    ((1e-3,), 12.0e-3 + MID_COUNT_M, (0.02,), "train", None, MOVE_S),
    ((-1e-3,), 15.1e-3 + MID_COUNT_M, (0.5,), "validate", None, MOVE_S),
    ((200e-6, -200e-6), 17.0e-3 + MID_COUNT_M, (0.02, MOVE_S), "train", None, MOVE_S),
    ((-200e-6, 200e-6), 19.6e-3 + MID_COUNT_M, (0.5, MOVE_S), "validate", None, MOVE_S),
    ((100e-6,), 5.0e-3 + MID_COUNT_M, (0.02,), "train", None, MOVE_S),
    ((100e-6,), 5.0e-3 + MID_COUNT_M, (0.02,), "validate", None, MOVE_S),
    # Repeats of training steps of every kind, validation only (cheap), so that the noise
    # floor is the mean of repeat pairs covering the quiet and the noisy experiments
    # (with the 1 mm step and the reversal left out, the floor was about half the no-effect
    # gap and position-dependent candidates passed for effects on two of six null cases).
    ((-500e-6,), 9.3e-3 + MID_COUNT_M, (0.02,), "validate", None, MOVE_S),
    ((-100e-6,), 4.5e-3 + MID_COUNT_M, (0.5,), "validate", None, MOVE_S),
    ((1e-3,), 12.0e-3 + MID_COUNT_M, (0.02,), "validate", None, MOVE_S),
    ((200e-6, -200e-6), 17.0e-3 + MID_COUNT_M, (0.02, MOVE_S), "validate", None, MOVE_S),
    # Breakaway tests.
    ((300e-9,), 22.3e-3 + MID_COUNT_M, (0.05,), "train", BREAKAWAY_GAINS, BREAKAWAY_HOLD_S),
    ((300e-9,), 22.3e-3 + MID_COUNT_M, (0.3,), "train", BREAKAWAY_GAINS, BREAKAWAY_HOLD_S),
    ((300e-9,), 22.3e-3 + MID_COUNT_M, (1.5,), "train", BREAKAWAY_GAINS, BREAKAWAY_HOLD_S),
    # Its repeat (validation only), so that the noise floor sees the breakaway scatter.
    ((300e-9,), 22.3e-3 + MID_COUNT_M, (1.5,), "validate", BREAKAWAY_GAINS, BREAKAWAY_HOLD_S),
    ((300e-9,), 22.3e-3 + MID_COUNT_M, (0.8,), "validate", BREAKAWAY_GAINS, BREAKAWAY_HOLD_S),
    ((-300e-9,), 23.9e-3 + MID_COUNT_M, (0.1,), "validate", BREAKAWAY_GAINS, BREAKAWAY_HOLD_S),
    ((-300e-9,), 23.9e-3 + MID_COUNT_M, (0.8,), "validate", BREAKAWAY_GAINS, BREAKAWAY_HOLD_S),
)

#: The 10 experiments of the speed benchmark (the issue's "about 10 experiments"): four
#: training steps of three sizes in both directions, a reversal, two breakaway tests, and
#: for validation steps of three sizes and a breakaway repeat (the noise floor).
SPEED_DESIGN: tuple[Design, ...] = tuple(DESIGN[i] for i in (0, 3, 4, 6, 14, 16, 1, 2, 5, 17))


def _hidden(name: str, rng: np.random.Generator, base: System) -> tuple[System, dict[str, Any]]:
    fx = base.effects
    info: dict[str, Any] = {}
    if name == "asymmetric_friction":
        a = float(rng.uniform(0.15, 0.4) * rng.choice([-1, 1]))
        fx = dc.replace(fx, motor_friction=FrictionModifiers(asymmetry=a))
        info["asymmetry"] = a
    elif name == "dwell_static_friction":
        rise = float(rng.uniform(2.0, 5.0))  # relative to the motor-side static force
        tau = float(rng.uniform(0.05, 0.5))
        fs = motor_static_force_n(base)
        fx = dc.replace(
            fx,
            motor_friction=FrictionModifiers(
                dwell=DwellStaticFriction(rise_n=rise * fs, time_constant_s=tau)
            ),
        )
        info |= {"rise_n": rise * fs, "time_constant_s": tau}
    elif name == "lead_periodic_friction":
        amp = float(rng.uniform(0.15, 0.35))
        ph = float(rng.uniform(-math.pi, math.pi))
        fx = dc.replace(
            fx,
            position_friction=(
                lead_periodic_friction(
                    side="motor", lead_m=2e-3, amplitudes=(amp,), phases_rad=(ph,)
                ),
            ),
        )
        info |= {"amplitude": amp, "phase_rad": ph}
    elif name == "backlash":
        w = float(rng.uniform(5e-6, 30e-6))
        fx = dc.replace(
            fx,
            backlash=Backlash(
                width_m=w,
                contact_stiffness_n_per_m=TRUTH_BACKLASH_STIFFNESS_N_PER_M,
                damping_n_s_per_m=800.0,
            ),
        )
        info["width_m"] = w
    elif name == "computation_delay":
        d = int(rng.integers(1, 3))
        fx = dc.replace(fx, computation_delay_samples=d)
        info["samples"] = d
    elif name == "offset_force":
        f = float(rng.uniform(3.0, 10.0) * rng.choice([-1, 1]))
        p = base.plant
        assert isinstance(p, Plant)
        table = dc.replace(p.table, external_force_n=f)
        base = dc.replace(base, plant=dc.replace(p, table=table))
        info["external_force_n"] = f
    elif name == "presliding_gms":
        p = base.plant
        assert isinstance(p, Plant)
        fc = p.dahl.coulomb_force_n
        k = float(rng.uniform(0.5, 2.0)) * p.dahl.stiffness_n_per_m
        weights = (0.05, 0.1, 0.15, 0.2, 0.2, 0.3)
        ratios = (1.0, 0.6, 0.35, 0.2, 0.1, 0.05)
        fs = fc * float(rng.uniform(1.3, 1.8))
        fx = dc.replace(
            fx,
            table_friction=Gms(
                stiffness_n_per_m=tuple(k * r / sum(ratios) for r in ratios),
                weights=weights,
                coulomb_force_n=fc,
                static_force_n=fs,
                stribeck_velocity_m_per_s=float(rng.uniform(2e-4, 2e-3)),
            ),
        )
        info |= {"stiffness_n_per_m": k, "static_force_n": fs}
    elif name != "none":
        raise ValueError(f"unknown hidden effect {name!r}; valid: {', '.join(HIDDEN_EFFECTS)}")
    return dc.replace(base, effects=fx), info


def truth_starts(hidden: str, parameters: dict[str, Any]) -> dict[str, dict[str, float]]:
    """The candidate parameter values that reproduce a hidden effect's truth (the start
    values of the truth-started check; empty where the candidate has no parameters or none
    maps: delays are discrete and tried in full, GMS truth is not a candidate's shape)."""
    if hidden == "asymmetric_friction":
        return {hidden: {"asymmetry": parameters["asymmetry"]}}
    if hidden == "dwell_static_friction":
        return {
            hidden: {
                "rise_n": parameters["rise_n"],
                "time_constant_s": parameters["time_constant_s"],
            }
        }
    if hidden == "lead_periodic_friction":
        # The truth's term is a·cos(κx + φ); the candidate's c·cos κx + s·sin κx.
        a, ph = parameters["amplitude"], parameters["phase_rad"]
        return {hidden: {"cos_amplitude": a * math.cos(ph), "sin_amplitude": -a * math.sin(ph)}}
    if hidden == "backlash":
        return {
            hidden: {
                "width_m": parameters["width_m"],
                "contact_stiffness_n_per_m": TRUTH_BACKLASH_STIFFNESS_N_PER_M,
            }
        }
    if hidden == "offset_force":
        return {hidden: {"external_force_n": parameters["external_force_n"]}}
    return {}


def _gains(step_m: float) -> tuple[float, float, float]:
    """Table 1 gains of the nearest Table 1 step size (log distance)."""
    sizes = (100e-6, 500e-6, 1e-3, 10e-3)
    best = min(sizes, key=lambda s: abs(math.log(s / step_m)))
    return presets.table1_gains(best)


def design_reference(
    steps: Sequence[float],
    start_m: float,
    dwells_s: Sequence[float],
    sample_period_s: float = 1e-3,
    hold_s: float = MOVE_S,
) -> np.ndarray:
    """A step sequence: rest at ``start_m`` for ``dwells_s[0]``, step by ``steps[0]``, rest
    for ``dwells_s[1]``, …, and hold the last position for ``hold_s``."""
    if len(steps) != len(dwells_s):
        raise ValueError(f"{len(steps)} steps need {len(steps)} dwells, got {len(dwells_s)}")
    parts = []
    x = start_m
    for s, d in zip(steps, dwells_s, strict=True):
        parts.append(np.full(round(d / sample_period_s), x))
        x += s
    parts.append(np.full(round(hold_s / sample_period_s), x))
    return np.concatenate(parts)


def draw_truth(
    hidden: str, seed: int, *, level_spread: float = 0.005
) -> tuple[System, dict[str, Any], np.random.Generator]:
    """A case's truth model (the seed axis with its friction levels perturbed, the hidden
    effect, stochastic friction, encoder noise and a fine integrator tolerance), what was
    drawn, and the random generator after those draws (the experiments' start positions
    come next)."""
    rng = np.random.default_rng(seed)
    truth, fc, scale = _nominal_truth(rng, level_spread)
    truth, info = _hidden(hidden, rng, truth)
    info = {"parameters": info, "dahl_coulomb_force_n": fc, "motor_friction_scale": scale}
    return truth, info, rng


def _nominal_truth(rng: np.random.Generator, level_spread: float) -> tuple[System, float, float]:
    """A case's truth before its hidden effect (the first draws of its ``rng``), with the
    drawn Dahl level and motor friction scale."""
    base = presets.seed(1e-3)
    p = base.plant
    assert isinstance(p, Plant)
    fc = float(p.dahl.coulomb_force_n * rng.uniform(0.85, 1.15))
    mf = p.motor_friction
    scale = float(rng.uniform(0.85, 1.15))
    plant = dc.replace(
        p,
        dahl=dc.replace(p.dahl, coulomb_force_n=fc),
        motor_friction=dc.replace(
            mf,
            static_torque_nm=mf.static_torque_nm * scale,
            coulomb_torque_nm=mf.coulomb_torque_nm * scale,
        ),
    )
    truth = dc.replace(
        base,
        plant=plant,
        integrator=dc.replace(base.integrator, rtol=1e-9, atol_position_m=1e-13),
        effects=Effects(
            stochastic=StochasticFriction(level_spread=level_spread),
            encoder_errors=EncoderErrors(noise_std_m=5e-9),
        ),
    )
    return truth, fc, scale


def generate_case(
    hidden: str,
    seed: int,
    out_dir: Path,
    *,
    level_spread: float = 0.005,
    design: Sequence[Design] = DESIGN,
    level_scatter: float | None = None,
) -> tuple[Path, dict[str, Any]]:
    """Write one case's traces and manifest into ``out_dir``; returns the manifest path and
    the truth (hidden effect, its parameters, the perturbed nominal values). ``design``: the
    experiments (default `DESIGN`; ``benches/diagnosis_speed.py`` times a 10-experiment
    subset, `SPEED_DESIGN`); ``level_scatter``: the manifest's ``[diagnosis]`` setting (0:
    left out; None: not written, the diagnosis's default applies)."""
    truth, info, rng = draw_truth(hidden, seed, level_spread=level_spread)
    p = presets.seed(1e-3).plant
    assert isinstance(p, Plant)
    mf = p.motor_friction
    out_dir.mkdir(parents=True, exist_ok=True)
    fc0 = p.dahl.coulomb_force_n
    # The uncertain friction levels are free: the Dahl level and the motor map's static and
    # Coulomb torques (the truth perturbs all three). Where the bounds overlap, a Coulomb
    # torque above the static one is an invalid model, which the fit treats as a bad fit.
    tc0, ts0 = mf.coulomb_torque_nm, mf.static_torque_nm
    lines = case_manifest_head(fc0, ts0, tc0, seed, level_scatter=level_scatter)
    q = truth.encoder.count_m
    for i, (steps, x0, dwells, role, gains, hold) in enumerate(design):
        ref = design_reference(steps, x0, dwells, hold_s=hold)
        g = gains or _gains(max(abs(s) for s in steps))
        sys_i = presets.with_gains(truth, kp=g[0], ki=g[1], kd=g[2])
        # The axis rests anywhere in the reference's count (the controller sees counts
        # only), in its middle half: nearer an edge the sensor noise flickers the reading.
        start = math.floor(x0 / q) * q + float(rng.uniform(0.25, 0.75)) * q
        b = sys_i.effects.backlash
        if b is not None:
            # A backlash rests against the flank of the last move before the run, either
            # side (the runs come in no known order).
            flank = float(rng.choice([-1.0, 1.0]))
            fx = dc.replace(sys_i.effects, backlash=dc.replace(b, initial_flank=flank))
            sys_i = dc.replace(sys_i, effects=fx)
        tr = simulate(sys_i, ref, seed=seed * 1000 + i, initial_position_m=start)
        exp = Experiment(
            name=f"exp{i:02d}",
            time_s=tr.time_s,
            reference_m=ref,
            position_m=tr.encoder_position_m,
        )
        write_trace_csv(exp, out_dir / f"exp{i:02d}.csv")
        lines += [
            "[[experiment]]",
            f'name = "exp{i:02d}"',
            f'file = "exp{i:02d}.csv"',
            f'role = "{role}"',
            f"controller = {{ kp = {g[0]}, ki = {g[1]}, kd = {g[2]} }}",
            "",
        ]
    manifest = out_dir / "manifest.toml"
    manifest.write_text("\n".join(lines), encoding="utf-8")
    truth_info = {"hidden": hidden, **info, "seed": seed}
    write_json(truth_info, out_dir / "truth.json", indent=1)
    return manifest, truth_info


def _truth_check(
    hidden: str,
    manifest: Path,
    truth: dict[str, Any],
    settings: DiagnosisSettings | None,
    seed: int,
) -> dict[str, Any]:
    """Diagnose a case with only the candidates that find ``hidden``, started at the truth,
    one forward round; returns whether it selects one (``detectable``), its validation
    shrink and the seconds it took."""
    m = load_manifest(manifest)
    accepted = tuple(sorted(ACCEPT.get(hidden, {hidden})))
    m = dc.replace(m, diagnosis=dc.replace(m.diagnosis, candidates=accepted))
    st = dc.replace(
        settings or DiagnosisSettings(),
        seed=seed,
        candidate_starts=truth_starts(hidden, truth["parameters"]),
        forward_rounds=1,
    )
    t = time.perf_counter()
    rep = diagnose(m, None, settings=st, progress=False, figures=False).report
    best = rep["candidates"][0] if rep["candidates"] else None
    return {
        "detectable": bool(rep["selected"]),
        "effect": best["effect"] if best else None,
        "shrink": best["shrink"] if best else 0.0,
        "seconds": time.perf_counter() - t,
    }


def oracle_model(
    hidden: str, seed: int, *, level_spread: float = 0.005, without_hidden: bool = False
) -> System:
    """The deterministic part of a case's truth (:func:`draw_truth` without its stochastic
    friction and encoder noise, at the nominal model's integrator tolerance): the model no
    candidate can beat but by fitting noise. ``without_hidden``: the same without the hidden
    effect (the truth's nominal draws only)."""
    if without_hidden:
        draw_truth(hidden, seed, level_spread=level_spread)  # checks the name
        truth, _, _ = _nominal_truth(np.random.default_rng(seed), level_spread)
    else:
        truth, _, _ = draw_truth(hidden, seed, level_spread=level_spread)
    return dc.replace(
        truth,
        integrator=presets.seed(1e-3).integrator,
        effects=dc.replace(truth.effects, stochastic=None, encoder_errors=None),
    )


def independent_oracles(hidden: str, seed: int, manifest: Path) -> tuple[float, float]:
    """The validation gap (:func:`~.run.model_gap`'s measure) of an independent-family case's
    own deterministic model (:func:`~.independent_truth.oracle_readings`), with and without
    its hidden effect, m RMS."""
    names = [e.name for e in independent_truth.experiment_design() if e.role == "validate"]
    workers = os.cpu_count() or 1
    gaps = [
        readings_gap(
            manifest,
            independent_truth.oracle_readings(
                hidden, seed, names, without_hidden=without, workers=workers
            ),
        )["total_rms_m"]
        for without in (False, True)
    ]
    return float(gaps[0]), float(gaps[1])


def median_phase_seconds(rows: Sequence[dict[str, Any]]) -> dict[str, float]:
    """The median over the cases of each phase's seconds (``phase_seconds`` of the
    rows; a phase a case did not run counts 0), the phases in the order they first came."""
    names: dict[str, None] = {}
    for r in rows:
        names.update(dict.fromkeys(r.get("phase_seconds") or {}))
    return {
        n: float(np.median([(r.get("phase_seconds") or {}).get(n, 0.0) for r in rows]))
        for n in names
    }


def _check_cell(row: dict[str, Any]) -> str:
    c = row["truth_check"]
    if c is None:
        return "—"
    return f"{'' if c['detectable'] else 'not '}detectable ({c['effect']}, {c['shrink']:+.0%})"


def run_benchmark(
    out_dir: str | Path,
    *,
    cases: int = 16,
    seed: int = 1,
    hidden: Sequence[str] | None = None,
    settings: DiagnosisSettings | None = None,
    progress: bool = True,
    truth_check: bool = True,
    truth: str = "own",
    level_scatter: float = DEFAULT_LEVEL_SCATTER,
) -> dict[str, Any]:
    """Generate ``cases`` cases (hidden effects cycled through ``hidden``, parameters random
    from ``seed``), diagnose each from its files alone, score, and write ``benchmark.json``
    and ``benchmark.md`` into ``out_dir``.

    ``truth`` chooses the family the cases come from (:data:`TRUTH_FAMILIES`): ``own``
    (nanostage's own core with its effects, this module's :func:`generate_case`) or
    ``independent`` (:func:`nanostage.diagnosis.independent_truth.write_case`: another
    integrator, other friction laws, effects written from their physics, ``command_v``
    recorded, a 12-experiment design; its experiments are simulated in one spawned process
    per CPU). The truth-started check exists for the own family only (the independent
    truth's effects are not nanostage candidates); the truth's own model of the independent
    family is its simulator's deterministic model, with and without the hidden effect
    (:func:`independent_oracles`: ``oracle_shrink`` and ``effect_shrink`` per row).

    ``level_scatter`` (relative, 1σ; default 1 %, 0 leaves it out) is written into every
    case's manifest as the diagnosis's run-to-run friction level scatter
    (:attr:`~nanostage.diagnosis.settings.DiagnosisSettings.level_scatter`), and replaces
    that of given ``settings``: the benchmark scores the diagnosis as a user who assumes
    that scatter would run it.

    With ``truth_check`` each case with an effect is also diagnosed with only the candidates
    that count as finding it, started from the truth's values (:func:`truth_starts`), one
    round: a case is *detectable* when that check selects it, i.e. when even knowing the
    answer the data show the effect above the noise floor by the same rules. It measures the
    information in the data, not the diagnosis; the scores over all cases stay the goal
    metrics.

    Every argument and ``out_dir`` are checked before any work; the folder (the cases'
    traces, manifests and reports, and the scores) is written whole or not at all
    (:func:`nanostage.output.staged_output`).

    Raises
    ------
    ConfigError
        ``cases`` not an integer in [1, :data:`MAX_CASES`], ``seed`` not one in
        [0, :data:`MAX_SEED`], an unknown ``truth`` family, a name in ``hidden`` that
        the family does not draw, or ``level_scatter`` not a number in
        [0, :data:`~nanostage.diagnosis.scatter.MAX_LEVEL_SCATTER`].
    OutputError
        ``out_dir`` cannot be used (an existing file, a folder of other files, not writable).
    """
    for name, value, lo, hi in (("cases", cases, 1, MAX_CASES), ("seed", seed, 0, MAX_SEED)):
        if isinstance(value, bool) or not isinstance(value, int) or not lo <= value <= hi:
            raise ConfigError(f"{name} = {value!r} is invalid: expected an integer in [{lo}, {hi}]")
    if (
        isinstance(level_scatter, bool)
        or not isinstance(level_scatter, int | float)
        or not 0.0 <= level_scatter <= MAX_LEVEL_SCATTER
    ):
        raise ConfigError(
            f"level_scatter = {level_scatter!r} is invalid: expected a relative friction "
            f"level scatter in [0, {MAX_LEVEL_SCATTER}] (0 leaves it out)"
        )
    if truth not in TRUTH_FAMILIES:
        raise ConfigError(
            f"truth = {truth!r} is invalid: expected one of {', '.join(TRUTH_FAMILIES)}"
        )
    family = HIDDEN_EFFECTS if truth == "own" else independent_truth.HIDDEN_EFFECTS
    names = list(family if hidden is None else hidden)
    unknown = [h for h in names if h not in family]
    if not names or unknown:
        raise ConfigError(
            f"hidden = {names!r} is invalid: expected a non-empty list of "
            f"{', '.join(family)} (truth family {truth!r})"
        )
    check_output_dir(out_dir)
    with staged_output(out_dir, "diagnose-benchmark") as folder:
        return _run_benchmark(
            folder,
            cases,
            seed,
            names,
            settings,
            progress=progress,
            truth_check=truth_check and truth == "own",
            final=Path(out_dir).expanduser().absolute(),
            truth=truth,
            level_scatter=float(level_scatter),
        )


def _run_benchmark(
    out: Path,
    cases: int,
    seed: int,
    names: list[str],
    settings: DiagnosisSettings | None,
    *,
    progress: bool,
    truth_check: bool,
    final: Path,
    truth: str = "own",
    level_scatter: float = DEFAULT_LEVEL_SCATTER,
) -> dict[str, Any]:
    """The cases, written into the staging folder ``out``; reports name the manifests at
    their place in the ``final`` folder."""
    own = truth == "own"
    accept: dict[str, set[str]] = (
        ACCEPT if own else {k: set(v) for k, v in independent_truth.ACCEPT.items()}
    )
    rows = []
    # Cases whose truth could not be simulated (the independent family's integrator gave
    # up): recorded with the reason and left out of the scores; the other cases go on.
    failed: list[dict[str, Any]] = []
    t0 = time.perf_counter()
    for c in range(cases):
        h = names[c % len(names)]
        case_dir = out / f"case{c:02d}_{h}"
        try:
            manifest, drawn = (
                generate_case(h, seed * 10_000 + c, case_dir, level_scatter=level_scatter)
                if own
                else independent_truth.write_case(
                    h,
                    seed * 10_000 + c,
                    case_dir,
                    workers=os.cpu_count() or 1,
                    level_scatter=level_scatter,
                )
            )
        except independent_truth.IntegrationStalled as e:
            failed.append(
                {"case": c, "hidden": h, "phase": "generating the traces", "error": str(e)}
            )
            if progress:
                print(
                    f"case {c + 1}/{cases} hidden {h:24s} NOT RUN: its truth could not be "
                    f"simulated ({e}); left out of the scores",
                    flush=True,
                )
            continue
        t = time.perf_counter()
        # Given settings keep the case's own random seed and scatter (the manifest's), as
        # the defaults do.
        st = (
            dc.replace(settings, seed=seed * 10_000 + c, level_scatter=level_scatter)
            if settings
            else None
        )
        d = diagnose(
            manifest,
            case_dir / "report",
            settings=st,
            progress=False,
            figures=False,
            manifest_path=final / manifest.relative_to(out),
        )
        rep = d.report
        found = rep["selected"][0] if rep["selected"] else "none"
        ok = found in accept.get(h, {h})
        # Found only up to a tie: the truth is among the candidates the report says the
        # validation data cannot tell from the first selection (not counted in top-1).
        tied = set(rep.get("indistinguishable", {}).get(found, [])) if found != "none" else set()
        ok_tie = ok or bool(tied & accept.get(h, {h}))
        seconds = time.perf_counter() - t
        check = (
            _truth_check(
                h,
                manifest,
                drawn,
                st or DiagnosisSettings(level_scatter=level_scatter),
                seed * 10_000 + c,
            )
            if truth_check and h != "none"
            else None
        )
        before = rep["gap_before"]["total_rms_m"]
        after = rep["gap_after"]["total_rms_m"]
        floor = rep["noise_floor_rms_m"]
        shrink = 1.0 - after / before if before > 0 else 0.0
        # Each validation experiment judged by models refitted on all the others (None
        # when the cross-fit is off; 0 when nothing was selected).
        cf = rep.get("crossfit")
        crossfit = cf["shrink"] if cf else (0.0 if not rep["selected"] else None)
        # The shrink the truth's own deterministic model gives: what the data allow (the
        # independent family's by its own simulator, with the gap its effect leaves).
        oracle: float | None = None
        bare: float | None = None
        if h != "none" and own:
            oracle, bare = (
                model_gap(manifest, oracle_model(h, seed * 10_000 + c, without_hidden=w))[
                    "total_rms_m"
                ]
                for w in (False, True)
            )
        elif h != "none":
            try:
                oracle, bare = independent_oracles(h, seed * 10_000 + c, manifest)
            except independent_truth.IntegrationStalled as e:
                # The diagnosis stands; only the truth's own model is missing from the row.
                failed.append(
                    {"case": c, "hidden": h, "phase": "the truth's own model", "error": str(e)}
                )
        rows.append(
            {
                "case": c,
                "hidden": h,
                "found": found,
                "selected": rep["selected"],
                "correct": ok,
                "correct_up_to_tie": ok_tie,
                "tied_with": sorted(tied),
                "gap_before_rms_m": before,
                "gap_after_rms_m": after,
                "noise_floor_rms_m": floor,
                "shrink": shrink,
                "crossfit_shrink": crossfit,
                "oracle_rms_m": oracle,
                "oracle_shrink": None if oracle is None or before <= 0 else 1.0 - oracle / before,
                "oracle_without_effect_rms_m": bare,
                "effect_shrink": None
                if oracle is None or bare is None or bare <= 0
                else 1.0 - oracle / bare,
                "explained_fraction": rep["explained_fraction"],
                "seconds": seconds,
                # The diagnosis's seconds per phase, summed over its rounds.
                "phase_seconds": phase_totals(rep.get("phases") or []),
                "truth": drawn["parameters"],
                "truth_check": check,
            }
        )
        if progress:
            print(
                f"case {c + 1}/{cases} hidden {h:24s} found {found:24s} "
                f"{'ok ' if ok else 'MISS'} gap {before * 1e9:7.0f} → {after * 1e9:7.0f} nm "
                f"({shrink:+.0%})  {seconds:.0f} s"
                + ("" if crossfit is None else f"  [cross-fit: {crossfit:+.0%}]")
                + ("" if oracle is None else f"  [truth's model: {1.0 - oracle / before:+.0%}]")
                + (
                    ""
                    if rows[-1]["effect_shrink"] is None
                    else f"  [its effect: {rows[-1]['effect_shrink']:+.0%}]"
                )
                + (
                    ""
                    if check is None
                    else f"  [truth-started: {'' if check['detectable'] else 'not '}"
                    f"detectable, shrink {check['shrink']:+.0%}]"
                ),
                flush=True,
            )
    eff = [r for r in rows if r["hidden"] != "none"]
    nulls = [r for r in rows if r["hidden"] == "none"]
    detectable = [r for r in eff if r["truth_check"] and r["truth_check"]["detectable"]]
    labels = sorted({r["hidden"] for r in rows} | {r["found"] for r in rows})
    confusion = {h: {f: 0 for f in labels} for h in labels}
    for r in rows:
        confusion[r["hidden"]][r["found"]] += 1
    oracles = [r["oracle_shrink"] for r in eff if r["oracle_shrink"] is not None]
    effect_shrinks = [r["effect_shrink"] for r in eff if r["effect_shrink"] is not None]
    phase_medians = median_phase_seconds(rows)
    summary = {
        "cases": cases,
        "seed": seed,
        "truth": truth,
        "level_scatter": level_scatter,
        "top1": float(np.mean([r["correct"] for r in eff])) if eff else math.nan,
        "top1_up_to_ties": float(np.mean([r["correct_up_to_tie"] for r in eff]))
        if eff
        else math.nan,
        "false_alarm_rate": float(np.mean([r["found"] != "none" for r in nulls]))
        if nulls
        else math.nan,
        "median_shrink": float(np.median([r["shrink"] for r in eff])) if eff else math.nan,
        "median_explained_fraction": float(np.median([r["explained_fraction"] or 0.0 for r in eff]))
        if eff
        else math.nan,
        "median_oracle_shrink": float(np.median(oracles)) if oracles else math.nan,
        "median_effect_shrink": float(np.median(effect_shrinks)) if effect_shrinks else None,
        "median_crossfit_shrink": float(np.median([r["crossfit_shrink"] for r in eff]))
        if eff and all(r["crossfit_shrink"] is not None for r in eff)
        else None,
        "median_seconds_per_case": float(np.median([r["seconds"] for r in rows]))
        if rows
        else math.nan,
        "median_phase_seconds": phase_medians,
        "detectable_cases": len(detectable) if truth_check else None,
        "top1_detectable": float(np.mean([r["correct"] for r in detectable]))
        if detectable
        else math.nan,
        "total_seconds": time.perf_counter() - t0,
        "truth_failures": failed,
        "confusion": confusion,
        "rows": rows,
    }
    write_json(summary, out / "benchmark.json", indent=1)
    skipped = [f for f in failed if f["phase"] == "generating the traces"]
    md = [
        "# Diagnosis blind benchmark",
        "",
        f"{cases} cases of the {truth} truth family, seed {seed}"
        + (
            f", diagnosed with a run-to-run friction level scatter of {level_scatter:.3g}"
            if level_scatter > 0.0
            else ""
        )
        + ". Top-1 "
        f"{summary['top1']:.0%} (counting a truth the report names as indistinguishable "
        f"from the first selection: "
        f"{summary['top1_up_to_ties']:.0%}), false alarms "
        f"{summary['false_alarm_rate']:.0%}, median shrink {summary['median_shrink']:.1%} "
        f"(of the gap above the noise floor: {summary['median_explained_fraction']:.0%}), "
        f"median {summary['median_seconds_per_case']:.0f} s per case.",
        "",
        *(
            [
                f"Shrink of the truth's own deterministic model (the hidden effect at its "
                f"true values, no noise; nothing fitted): median "
                f"{summary['median_oracle_shrink']:.1%}. No model can remove more of the "
                "gap than that but by fitting noise: it is what the drawn cases allow.",
                "",
            ]
            if oracles
            else []
        ),
        *(
            [
                (
                    ""
                    if own
                    else "The truth's own model is the independent simulator's, without "
                    "noise and with the run's friction level at its median. "
                )
                + "Without its hidden effect the truth's own model leaves a gap that the "
                f"effect shrinks by a median {summary['median_effect_shrink']:.1%}: an "
                "effect that leaves no mark on the validation experiments shrinks it by "
                "nothing, and no diagnosis can find it there.",
                "",
            ]
            if effect_shrinks
            else []
        ),
        *(
            []
            if summary["median_crossfit_shrink"] is None
            else [
                f"Cross-fitted shrink (each validation experiment judged by the nominal and "
                f"the selected model refitted on all the other experiments): median "
                f"{summary['median_crossfit_shrink']:.1%}.",
                "",
            ]
        ),
        *(
            []
            if summary["detectable_cases"] is None
            else [
                f"Truth-started check (only the candidates that find the hidden effect, "
                f"started at its true values): {summary['detectable_cases']} of {len(eff)} "
                f"cases detectable; top-1 over them {summary['top1_detectable']:.0%}.",
                "",
            ]
        ),
        *(
            [
                "Median seconds per case by phase of the diagnosis (a phase a case does "
                "not run counts 0): "
                + ", ".join(f"{k} {v:.0f}" for k, v in phase_medians.items())
                + ".",
                "",
            ]
            if phase_medians
            else []
        ),
        *(
            [
                f"{len(skipped)} case(s) not scored, their truth could not be simulated: "
                + "; ".join(f"case {f['case']} ({f['hidden']})" for f in skipped)
                + " (`benchmark.json` `truth_failures`).",
                "",
            ]
            if skipped
            else []
        ),
        "Confusion matrix (rows: hidden effect; columns: first selected effect):",
        "",
        "| hidden \\ found | " + " | ".join(labels) + " |",
        "|---" * (len(labels) + 1) + "|",
    ]
    for h in labels:
        md.append(f"| {h} | " + " | ".join(str(confusion[h][f]) for f in labels) + " |")
    md += [
        "",
        "| case | hidden | found | tied with | selected | gap before [nm] | after [nm] | "
        "floor [nm] | shrink | cross-fit shrink | truth's shrink | its effect's shrink | "
        "explained | time [s] | truth-started check |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        ex = r["explained_fraction"]
        oc = r["oracle_shrink"]
        cs = r["crossfit_shrink"]
        es = r["effect_shrink"]
        md.append(
            f"| {r['case']} | {r['hidden']} | {r['found']} | {', '.join(r['tied_with']) or '—'} "
            f"| {', '.join(r['selected']) or '—'} "
            f"| {r['gap_before_rms_m'] * 1e9:.0f} | {r['gap_after_rms_m'] * 1e9:.0f} "
            f"| {r['noise_floor_rms_m'] * 1e9:.0f} | {r['shrink']:.0%} "
            f"| {'—' if cs is None else f'{cs:.0%}'} "
            f"| {'—' if oc is None else f'{oc:.0%}'} "
            f"| {'—' if es is None else f'{es:.0%}'} "
            f"| {'—' if ex is None else f'{ex:.0%}'} | {r['seconds']:.0f} | {_check_cell(r)} |"
        )
    (out / "benchmark.md").write_text("\n".join(md) + "\n", encoding="utf-8")
    return summary
