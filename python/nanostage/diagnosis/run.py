"""``nanostage diagnose``: read a manifest, run the engine, write the report.

The report (``report.json``; schema in docs/diagnosis.md) has at least

``gap_before``
    the validation gap of the calibrated nominal model: ``total_rms_m``, ``by_segment``
    (phase → RMS and share of the total sum of squares) and the full gap analysis;
``candidates``
    every candidate of the first round, best first (by ``ranking``: ``"relative"``, the
    geometric mean of the per-experiment gaps, or ``"pooled"``, the pooled RMS gap):
    ``effect``, ``validation_rms_m``, ``validation_geometric_rms_m``, ``shrink``
    (fraction of the validation RMS gap removed), ``significant``,
    ``parameters`` (value, standard error, unit), ``p_value`` and ``why``;
``selected``
    the effects kept by forward selection (possibly empty);
``gap_after``
    the validation gap with the selected effects (same form as ``gap_before``);
``model_file``
    with an output folder: ``model.toml``, the model file (docs/model-file.md) of the
    selected model, the one behind ``gap_after`` (with one fold, simulating it on the
    validation experiments gives ``gap_after`` to the last bit);

plus ``indistinguishable`` (selected effect → candidates the validation data cannot tell
from it), ``crossfit`` (the shrink when each validation experiment is judged by the nominal
and the selected model refitted on all the other experiments), ``gap_best_single``,
``noise_floor_rms_m``, ``forward_selection``, ``evidence``, ``advice``, ``skipped``,
``nominal_parameters``, ``selected_model_parameters``, ``unexplained_rms_m``,
``unexplained`` (with nothing selected above the floor: the gap and its best partial
explanations), ``calibration_at_bounds`` (free parameters the nominal calibration and the
selected model left at their bounds), ``warnings`` (about the measured commands, and the
parameters at their bounds) and ``timing_s``.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from .._core import ConfigError, __version__
from ..config import System, field_paths, get_path, replace_paths
from ..experiment import Experiment
from ..model_file import IdentifiedParameter, save_model
from ..output import check_output_dir, staged_output
from .candidates import CANDIDATES, Candidate, Param, applicable_candidates
from .fit import Fit, at_bounds
from .gap import analyse_gap
from .loop import crossfit_models, diagnose_experiments, experiment_class, experiment_scale
from .manifest import Manifest, load_manifest
from .objective import (
    MICRO_STEP_MAX_COUNTS,
    SimulationCache,
    align_holds,
    command_problems,
    reading_quantum,
    simulate_readings_and_commands,
)
from .report import write_report
from .segments import segment
from .select import CandidateResult, indistinguishable, too_few_to_test
from .settings import DiagnosisSettings, print_progress
from .signatures import SIGNATURE_UNITS, Feature, SignatureJudge
from .signatures import distance as signature_distance
from .signatures import misses as signature_misses

__all__ = [
    "DISTINGUISHING_EXPERIMENT",
    "MODEL_FILE",
    "Diagnosis",
    "diagnose",
    "experiment_advice",
    "indistinguishable",
    "model_gap",
    "readings_gap",
    "ties_of_selected",
    "unexplained_gap",
]

#: For pairs of effects that leave similar signatures: the experiment that separates them.
DISTINGUISHING_EXPERIMENT: dict[frozenset[str], str] = {
    frozenset({"asymmetric_friction", "offset_force"}): "micro-steps of a few counts and "
    "large steps, each in both directions: an offset force shifts the breakaway (static) "
    "and the sliding force by the same amount, asymmetric friction by amounts proportional "
    "to the static and the Coulomb level. Where that difference, a·(Fs − Fc), is a few per "
    "cent of the breakaway force (the seed axis), the position readings cannot resolve it "
    "and the logged command adds nothing (the controller computes it from the readings): "
    "measure the drive force directly, with the loop open, in both directions and "
    "repeated: slow voltage ramps to breakaway and constant-speed slides. The + − "
    "difference of the breakaway voltages equals that of the sliding voltages for an "
    "offset force and exceeds it by Fs/Fc for asymmetric friction; an offset force larger "
    "than the static friction makes the unpowered axis drift",
    frozenset({"backlash", "drive_compliance"}): "a slow reversal: backlash gives lost "
    "motion of a fixed width, a compliance a deflection proportional to the force",
    frozenset({"lead_periodic_friction", "position_random_friction"}): "the same move at "
    "start positions spaced by a quarter of the screw lead over several leads",
    frozenset({"dwell_static_friction", "stribeck"}): "the same move after dwells of "
    "0.05 s, 0.5 s and 5 s (best: a micro-step of a few counts under integral-only control, "
    "one step per record, so the breakaway delay measures the breakaway force): only rising "
    "static friction depends on the dwell",
    frozenset({"frictional_memory", "stribeck"}): "moves with different accelerations to "
    "the same speed: only frictional memory depends on the rate of change of velocity",
    frozenset({"sensor_delay", "computation_delay"}): "log the controller output: a "
    "sensor delay shifts the command against the reading, a computation delay the motion "
    "against the command",
    frozenset({"lugre", "gms"}): "small reversals inside a larger one (minor loops): only "
    "GMS returns to the outer branch (non-local memory)",
    frozenset({"amplifier_dynamics", "computation_delay"}): "a step of the command with "
    "the loop open: a delay shifts, a finite bandwidth rounds the response",
    frozenset({"drive_compliance", "computation_delay"}): "known pulses added to the "
    "command (as in the EMPS validation run): a delay shifts the response, a flexibility "
    "filters it and rings at its resonance",
    frozenset({"backlash", "computation_delay"}): "a slow reversal and micro-steps in both "
    "directions: backlash loses a fixed motion at each reversal and hunts with an amplitude "
    "of its width, a delay loses nothing at a reversal and rings at a frequency set by the "
    "loop gain and the delay, whatever the direction",
    frozenset({"backlash", "sensor_delay"}): "a slow reversal: backlash loses a fixed motion "
    "at each reversal, a sensor delay loses none; the logged command leads the reading by "
    "the delay",
    frozenset({"backlash", "amplifier_dynamics"}): "a slow reversal and a step of the "
    "command with the loop open: backlash loses motion at a reversal, a finite amplifier "
    "bandwidth rounds the response to the step in either direction alike",
    frozenset({"drive_compliance", "amplifier_dynamics"}): "a step of the command with the "
    "loop open, and known pulses added to the command: a compliance rings at its resonance "
    "and deflects with the force, an amplifier lag rounds the response without ringing",
    frozenset({"sensor_delay", "amplifier_dynamics"}): "a step of the command with the loop "
    "open, logged: a delay shifts the response by whole samples, a bandwidth rounds it",
    frozenset({"drive_compliance", "sensor_delay"}): "known pulses added to the command: a "
    "delay shifts the response, a flexibility filters it and rings at its resonance",
    frozenset({"asymmetric_friction", "lugre"}): "the same slow ramps in both directions: "
    "asymmetric friction differs by direction at every speed, a LuGre law is symmetric",
    frozenset({"asymmetric_friction", "stribeck"}): "the same slow ramps in both directions: "
    "asymmetric friction differs by direction at every speed, a Stribeck curve is symmetric "
    "and changes with the speed",
    frozenset({"offset_force", "coulomb_viscous"}): "the command at rest after moves in both "
    "directions and constant-speed ramps at several speeds: an offset force shifts both "
    "directions the same way, friction opposes the motion",
    frozenset({"dwell_static_friction", "lugre"}): "the same micro-step after dwells of "
    "0.05 s, 0.5 s and 5 s: only rising static friction depends on the dwell",
}


#: The model file ``diagnose`` writes into its output folder.
MODEL_FILE = "model.toml"


def _moves(e: Experiment) -> list[tuple[int, float, float]]:
    """(start index, dwell before it in s, signed size in m) of each reference change."""
    ref = np.asarray(e.reference_m)
    idx = np.flatnonzero(np.diff(ref) != 0) + 1
    out: list[tuple[int, float, float]] = []
    prev = 0
    for k in idx:
        if k - 1 > prev or not out:
            out.append((int(k), float(e.time_s[k] - e.time_s[prev]), float(ref[k] - ref[k - 1])))
        prev = int(k)
    return out


def ties_of_selected(
    rounds: Sequence[Sequence[CandidateResult]], selected: Sequence[str], ranking: str
) -> dict[str, list[str]]:
    """For each selected effect, the significant candidates of its round that the
    validation data cannot tell from it (:func:`indistinguishable`): the selection between
    them is then a coin toss, and the report says so."""
    out: dict[str, list[str]] = {}
    for rnd, name in zip(rounds, selected, strict=False):
        win = next(r for r in rnd if r.effect == name)
        out[name] = [
            r.effect
            for r in rnd
            if r.effect != name and r.significant and indistinguishable(win, r, ranking)
        ]
    return out


def best_single(
    first_round: Sequence[CandidateResult], selected: Sequence[str]
) -> CandidateResult | None:
    """The report's best single effect: the round-1 fit of the effect selected first (in a
    tie decided by the Occam factor, not always the smallest validation gap); with nothing
    selected, the first round-1 candidate (``first_round`` is sorted best first by the
    ranking); None without candidates."""
    if selected:
        hit = next((r for r in first_round if r.effect == selected[0]), None)
        if hit is not None:
            return hit
    return first_round[0] if first_round else None


#: Below this share of the validation experiments' reference samples inside the positions
#: their training experiments covered, a friction that varies irregularly with position
#: cannot be judged (:func:`experiment_advice`).
MIN_POSITION_COVERAGE = 0.5
#: Above this share of the validation gap before (its sum of squares) in one validation
#: experiment, the candidates are judged on that experiment alone (:func:`experiment_advice`).
MAX_VALIDATION_SHARE = 0.8


def position_coverage(
    folds: Sequence[tuple[Sequence[Experiment], Sequence[Experiment]]],
) -> float | None:
    """The share of the validation experiments' reference samples (all folds) that lie
    within the position range, widened by one reading quantum, of some training experiment
    of their fold; None without validation samples."""
    inside = total = 0
    for train, validate in folds:
        spans = []
        for e in train:
            ref = np.asarray(e.reference_m, dtype=np.float64)
            q = reading_quantum(e.position_m)
            spans.append((float(np.min(ref)) - q, float(np.max(ref)) + q))
        for e in validate:
            ref = np.asarray(e.reference_m, dtype=np.float64)
            hit = np.zeros(ref.size, dtype=bool)
            for lo, hi in spans:
                hit |= (ref >= lo) & (ref <= hi)
            inside += int(np.count_nonzero(hit))
            total += ref.size
    return inside / total if total else None


#: The largest experiment of a kind is "alone at its size" when the next largest of that
#: kind asks for a motion smaller by more than this factor (:func:`lone_largest`).
LONE_LARGEST_FACTOR = 2.0


def _length(x_m: float) -> str:
    """A length in mm from 1 mm up, else in µm (three significant digits)."""
    return f"{x_m * 1e3:.3g} mm" if x_m >= 1e-3 else f"{x_m * 1e6:.3g} µm"


#: Names of the kinds of :func:`~.loop.experiment_class`.
_KIND_NAMES = {0: "ramp", 1: "micro-step", 2: "step"}


def lone_largest(
    experiments: Sequence[Experiment], count_m: float
) -> list[tuple[Experiment, str, str, float]]:
    """The experiments alone at the largest size of their kind (:func:`~.loop.experiment_class`,
    of two or more that move; the size is :func:`~.loop.experiment_scale`): the next largest
    of the kind
    asks for a motion smaller by more than :data:`LONE_LARGEST_FACTOR`. Each with its kind's
    name, its size in words (a ramp's speed, a move's largest step) and the factor.
    Cross-judging holds each experiment out once (:func:`~.loop.cross_judge_split`), so such
    an experiment is predicted by models refitted on smaller motions only."""
    kinds: dict[int, list[tuple[float, Experiment]]] = {}
    for e in experiments:
        scale = experiment_scale(e.reference_m)
        if scale > 0.0:  # a reference that never moves is of no kind
            k = experiment_class(e.reference_m, count_m)
            kinds.setdefault(k, []).append((scale, e))
    out = []
    for k, members in sorted(kinds.items()):
        if len(members) < 2:
            continue
        members.sort(key=lambda m: -m[0])
        (top, e), (nxt, _) = members[0], members[1]
        if top <= LONE_LARGEST_FACTOR * nxt:
            continue
        if k == 0:
            dt = float(np.median(np.diff(e.time_s))) if len(e.time_s) > 1 else 0.0
            size = _length(top / dt) + "/s" if dt > 0.0 else _length(top) + " per sample"
        else:
            size = _length(top)
        out.append((e, _KIND_NAMES[k], size, top / nxt))
    return out


def experiment_advice(
    experiments: Sequence[Experiment],
    lead_m: float | None,
    results: Sequence[CandidateResult],
    penalty: float,
    folds: Sequence[tuple[Sequence[Experiment], Sequence[Experiment]]] | None = None,
    *,
    level_floors: Mapping[str, float] | None = None,
    validation_gap_m2: Mapping[str, float] | None = None,
    ranking: str = "relative",
    selected: Sequence[CandidateResult] = (),
    p_value: float = 0.05,
    cross_judged_count_m: float | None = None,
) -> list[dict[str, Any]]:
    """What the experiments cannot reveal, and which experiment would. With ``folds``, also
    whether the validation experiments revisit positions their training experiments
    covered (:func:`position_coverage`). With ``level_floors`` (by experiment name: how
    many noise floors a 1 % run-to-run friction level change moves it,
    :func:`~nanostage.diagnosis.scatter.level_floors`), the advice on repeats names the
    experiments whose gap such scatter can dominate. With ``validation_gap_m2`` (by
    validation experiment: the sum of squares of its gap before), whether one experiment
    holds more than :data:`MAX_VALIDATION_SHARE` of it, so that the candidates
    (``results``, best first) are judged on that experiment alone. With ``selected`` (the
    selected effects' results, each from its round), whether an effect's relative
    significance rests on too few validation experiments above their noise floors for any
    test over them to reach the level it was judged at (its ``p_level``, at most ``p_value``:
    :func:`~nanostage.diagnosis.select.too_few_to_test`). With ``cross_judged_count_m`` (the
    rounds were judged on every experiment, their kinds told with this encoder count), the
    experiments alone at the largest size of their kind (:func:`lone_largest`)."""
    advice: list[dict[str, Any]] = []
    level = {id(r): min(r.p_level, p_value) for r in selected}
    few = [
        r
        for r in selected
        if r.informative_experiments is not None
        and 0.0 < level[id(r)] < 1.0
        and too_few_to_test(r.informative_experiments, level[id(r)])
    ]
    if few:
        p_value = min(level[id(r)] for r in few)
        # The fewest experiments with 2⁻ⁿ ≤ p_value.
        need = max(1, math.ceil(math.log2(1.0 / p_value)))
        advice.append(
            {
                "effects": [r.effect for r in few],
                "issue": "the significance of "
                + ", ".join(
                    f"{r.effect} rests on {r.informative_experiments} validation "
                    f"experiment(s) with a gap above their noise floor (bootstrap p = "
                    f"{r.p_value:.3f})"
                    for r in few
                )
                + f": a bootstrap over so few gives p = 0 whenever all of them improve, and "
                f"no test over them can reach p < {p_value:g} (an exact sign-flip test "
                f"gives at least 2⁻ⁿ), so the selection is weak evidence of a consistent "
                "improvement",
                "experiment": f"validate on at least {need} experiments whose gap lies above "
                "the noise floor (one of each kind the training has: step, ramp, "
                "micro-step, reversal, dwell), so that the improvement can show as "
                "consistent",
            }
        )
    total_m2 = sum((validation_gap_m2 or {}).values())
    if validation_gap_m2 and len(validation_gap_m2) > 1 and total_m2 > 0.0:
        name, top_m2 = max(validation_gap_m2.items(), key=lambda kv: kv[1])
        if top_m2 > MAX_VALIDATION_SHARE * total_m2:
            advice.append(
                {
                    "effects": [r.effect for r in results[:3]],
                    "issue": f"{name} holds {top_m2 / total_m2:.0%} of the validation gap "
                    f"before (of {len(validation_gap_m2)} validation experiments): the "
                    "candidates are ranked and tested on that one experiment, so its "
                    "run-to-run scatter and its own conditions (a slew at the amplifier's "
                    "limit, say) decide between them",
                    "experiment": "validate on more experiments with gaps of their own (one "
                    "of each kind the training has: step, ramp, micro-step, reversal), and "
                    f"repeat {name} 3–5 times",
                }
            )
    moves = [m for e in experiments for m in _moves(e)]
    signs = {math.copysign(1.0, m[2]) for m in moves if m[2] != 0}
    if len(signs) <= 1:
        advice.append(
            {
                "effects": ["backlash", "asymmetric_friction", "offset_force"],
                "issue": "all moves go in one direction: there is no reversal, so backlash "
                "cannot show, and direction-dependent friction cannot be told from an offset "
                "force",
                "experiment": "add moves in the opposite direction and reversals (e.g. "
                "+100 µm, −100 µm, +1 mm, −1 mm)",
            }
        )
    dwells = [m[1] for m in moves if m[1] > 0]
    if dwells and max(dwells) < 2.0 * min(dwells):
        advice.append(
            {
                "effects": ["dwell_static_friction"],
                "issue": f"all dwell times before moves lie within a factor 2 "
                f"({min(dwells):.3g}–{max(dwells):.3g} s): rising static friction cannot be "
                "seen",
                "experiment": "repeat one move after dwells of 0.05 s, 0.5 s and 5 s, "
                "best a micro-step of a few counts under integral-only control, one step "
                "per record",
            }
        )
    span = max(float(np.ptp(e.position_m)) for e in experiments)
    lo = min(float(np.min(e.position_m)) for e in experiments)
    hi = max(float(np.max(e.position_m)) for e in experiments)
    if lead_m is not None and hi - lo < 2.0 * lead_m:
        advice.append(
            {
                "effects": ["lead_periodic_friction", "position_random_friction"],
                "issue": f"the experiments cover {(hi - lo) * 1e3:.3g} mm, less than two "
                f"screw leads ({2 * lead_m * 1e3:g} mm): position-periodic friction cannot be "
                "resolved",
                "experiment": "the same move at start positions spread over at least three leads",
            }
        )
    del span
    coverage = position_coverage(folds) if folds else None
    if coverage is not None and coverage < MIN_POSITION_COVERAGE:
        advice.append(
            {
                "effects": ["position_random_friction"],
                "issue": f"only {coverage:.0%} of the validation experiments' samples lie at "
                "positions a training experiment covered: a friction that varies irregularly "
                "along the travel can be fitted where the training experiments ran but not "
                "predicted elsewhere, so it cannot be judged (a screw-lead periodic friction "
                "can)",
                "experiment": "repeat moves at the positions of other experiments (a "
                "training and a validation experiment over the same stretch of travel), "
                "wherever position-dependent friction matters",
            }
        )
    refs: dict[tuple[int, int], int] = {}
    for e in experiments:
        travel_nm = round(float(np.sum(np.abs(np.diff(e.reference_m)))) * 1e9)
        key = (len(e.reference_m), travel_nm)
        refs[key] = refs.get(key, 0) + 1
    if max(refs.values()) < 2:
        moved = sorted(((v, n) for n, v in (level_floors or {}).items() if v > 1.0), reverse=True)
        issue = (
            "no experiment is repeated: the trial-to-trial scatter (noise floor) is only "
            "estimated from quantisation and sensor noise"
        )
        experiment = "repeat one experiment 3–5 times"
        if moved:
            v, n = moved[0]
            others = len(moved) - 1
            issue += (
                f"; yet a 1 % run-to-run change of the friction levels moves {n} by "
                f"{v:.3g} noise floors (RMS)"
                + (f", and {others} other experiment(s) by more than one" if others else "")
                + ": gaps and differences between candidates of that size there can be "
                "scatter, not an effect (the fits allow for level_scatter, 1 % unless given: "
                "give the machine's if it is known)"
            )
            experiment = f"repeat {n} 3–5 times (the repeats measure the scatter)"
        advice.append(
            {
                "effects": ["stochastic_friction"],
                "issue": issue,
                "experiment": experiment,
            }
        )
    if all(e.command_v is None for e in experiments):
        advice.append(
            {
                "effects": [
                    "stribeck",
                    "lugre",
                    "gms",
                    "dwell_static_friction",
                    "asymmetric_friction",
                    "offset_force",
                ],
                "issue": "no experiment has the controller's output (command_v): in a stiff "
                "position loop friction-law effects move the encoder reading by a fraction of "
                "a count but the command clearly, and the command at rest in each direction "
                "tells an offset force from asymmetric friction",
                "experiment": "log the controller output with the position (command_v, in volts)",
            }
        )
    speeds = [s for e in experiments for s in _ramp_speeds(e)]
    if not speeds or max(speeds) < 3.0 * min(speeds):
        advice.append(
            {
                "effects": ["stribeck", "lugre", "coulomb_viscous", "asymmetric_friction"],
                "issue": "no constant-velocity ramps at several speeds"
                + (
                    f" (ramps at {min(speeds) * 1e6:.3g}–{max(speeds) * 1e6:.3g} µm/s only)"
                    if speeds
                    else ""
                )
                + ": the friction curve against speed is not seen",
                "experiment": "slow ramps out and back (a reversal) at three speeds from tens "
                "of µm/s to about 1 mm/s, with the command logged",
            }
        )
    sizes = [abs(m[2]) for m in moves if m[2] != 0]
    count = _count(experiments)
    if count is not None and (not sizes or min(sizes) > MICRO_STEP_MAX_COUNTS * count):
        advice.append(
            {
                "effects": ["dwell_static_friction", "lugre", "gms", "dahl"],
                "issue": "no micro-step of a few encoder counts: breakaway and presliding "
                "are not seen",
                "experiment": "micro-steps of 3–5 counts after dwells of 0.05 s, 0.3 s and "
                "1.5 s, in both directions",
            }
        )
    if cross_judged_count_m is not None:
        for e, kind, size, factor in lone_largest(experiments, cross_judged_count_m):
            advice.append(
                {
                    "effects": ["backlash", "drive_compliance", "amplifier_dynamics"],
                    "issue": f"{e.name} is the only {kind} at {size}, the next largest "
                    f"{kind} asks for {factor:.3g} times less: judged on every experiment, "
                    f"each candidate is refitted without {e.name} and predicts it from "
                    f"smaller {kind}s alone, so a refit that does not extrapolate to its size "
                    "(a dead band or a lag hunting where it never trained) counts against its "
                    "effect there",
                    "experiment": f"repeat {e.name}, or add a second {kind} at {size}, so "
                    f"that the models that judge it have trained on a {kind} of its size",
                }
            )
    good = [r for r in results if r.shrink > penalty]
    for i, a in enumerate(good):
        for b in good[i + 1 :]:
            if indistinguishable(a, b, ranking):
                pair = frozenset({a.effect, b.effect})
                advice.append(
                    {
                        "effects": sorted(pair),
                        "issue": f"{a.effect} and {b.effect} fit the validation data equally "
                        f"well ({a.validation_rms_m * 1e9:.0f} vs "
                        f"{b.validation_rms_m * 1e9:.0f} nm)",
                        "experiment": DISTINGUISHING_EXPERIMENT.get(
                            pair,
                            "an experiment that exercises one effect and not the other "
                            "(see their signatures)",
                        ),
                    }
                )
    return advice


def _ramp_speeds(e: Experiment, min_samples: int = 20) -> list[float]:
    """Speeds of the constant-velocity stretches of the reference (at least ``min_samples``
    samples of the same non-zero increment, to 1 ppm), m/s."""
    d = np.diff(np.asarray(e.reference_m, dtype=np.float64))
    out = []
    k = 0
    while k < len(d):
        j = k
        while j + 1 < len(d) and d[k] != 0.0 and abs(d[j + 1] - d[k]) <= 1e-6 * abs(d[k]):
            j += 1
        if d[k] != 0.0 and j - k + 1 >= min_samples:
            out.append(abs(float(d[k])) / e.sample_period_s)
        k = j + 1
    return out


def _count(experiments: Sequence[Experiment]) -> float | None:
    """The encoder count from the readings (:func:`~.objective.reading_quantum`, the median
    over experiments), None if no reading changes."""
    q = [reading_quantum(e.position_m) for e in experiments]
    q = [v for v in q if v > 0.0]
    return float(np.median(q)) if q else None


def _gap(
    experiments: Sequence[Experiment], simulated: Sequence[np.ndarray], lead_m: float | None
) -> dict[str, Any]:
    ga = analyse_gap(experiments, simulated, lead_m=lead_m)
    d = ga.to_dict()
    phases = ga.overall.partitions.get("phase", {})
    d["total_rms_m"] = ga.overall.rms_m
    d["by_segment"] = {k: {"rms_m": g.rms_m, "share": g.share} for k, g in phases.items()}
    return d


@dataclass(frozen=True, slots=True, kw_only=True)
class Diagnosis:
    """What :func:`diagnose` returns: the report dict and where it was written."""

    report: dict[str, Any]
    out_dir: Path | None
    #: The model with the selected effects at their fitted values (first fold's fit).
    model: System


def _lead(system: System) -> float | None:
    screw = getattr(system.plant, "screw", None)
    return float(screw.lead_m) if screw is not None else None


@dataclass(frozen=True, slots=True)
class _Setup:
    """What the manifest gives the engine: the nominal model, its free parameters, the
    folds, and how a model is set up for one experiment (its controller) and for values of
    the free parameters."""

    manifest: Manifest
    nominal: System
    free: list[tuple[str, Param]]
    folds: list[tuple[list[Experiment], list[Experiment]]]
    adapt: Callable[[System, Experiment], System]
    set_free: Callable[[System, Mapping[str, float]], System]
    #: Warnings about the measured commands, by experiment name (:func:`command_problems`).
    warnings: Mapping[str, str]


def _setup(manifest: str | Path | Manifest) -> _Setup:
    """Load and check the manifest and its traces (every input error is raised here)."""
    m = manifest if isinstance(manifest, Manifest) else load_manifest(manifest)
    pairs = m.experiments()
    by_name = {spec.name: exp for spec, exp in pairs}
    specs = {spec.name: spec for spec, _ in pairs}
    nominal = m.system()
    for name, e in by_name.items():
        t = nominal.sample_period_s
        if abs(e.sample_period_s - t) > 1e-3 * t:
            raise ValueError(
                f"{m.path}: experiment {name!r} ({e.source}) is sampled every "
                f"{e.sample_period_s:g} s but the controller runs every {t:g} s"
            )
    systems = {n: m.system(specs[n]) for n in by_name}
    gains = {
        n: {k: get_path(systems[n], k) for k in _controller_paths(systems[n])} for n in by_name
    }

    def adapt(system: System, e: Experiment) -> System:
        g = gains.get(e.name)
        return replace_paths(system, g) if g else system

    free = [
        (
            path,
            Param(
                name=path,
                unit="",
                lower=m.model.bounds[path][0],
                upper=m.model.bounds[path][1],
                initial=m.model.initial[path],
                log=m.model.bounds[path][0] > 0
                and m.model.bounds[path][1] >= 10 * m.model.bounds[path][0],
            ),
        )
        for path in m.model.free
    ]

    # A free Coulomb force of a Coulomb + viscous map (Fs = Fc in the nominal model) carries
    # the static force with it, so that the map stays Coulomb + viscous (Fs ≥ Fc holds).
    tied = {
        path: path[: -len("coulomb_force_n")] + "static_force_n"
        for path in m.model.free
        if path.endswith(".coulomb_force_n")
        and _is_coulomb_viscous(nominal, path[: -len(".coulomb_force_n")])
    }

    # In SI units a DC motor's torque constant (N·m/A) and back-EMF constant (V·s/rad) are
    # one motor constant: a free torque constant carries the back-EMF constant with it when
    # the nominal model has them equal and the back-EMF constant is not free itself.
    for kt_path in [p for p in m.model.free if p.endswith(".torque_constant_nm_per_a")]:
        ke_path = kt_path[: -len("torque_constant_nm_per_a")] + "back_emf_v_s_per_rad"
        if ke_path not in m.model.free and get_path(nominal, kt_path) == get_path(nominal, ke_path):
            tied[kt_path] = ke_path

    def set_free(system: System, values: Mapping[str, float]) -> System:
        if not values:
            return system
        v = dict(values)
        for fc_path, fs_path in tied.items():
            if fc_path in v:
                v[fs_path] = v[fc_path]
        out: System = replace_paths(system, v)
        return out

    folds = [([by_name[n] for n in f.train], [by_name[n] for n in f.validate]) for f in m.splits()]
    errors, warnings = command_problems(
        list(by_name.values()), {n: adapt(nominal, e) for n, e in by_name.items()}
    )
    if errors:
        raise ConfigError(f"{m.path}: " + "; ".join(errors))
    return _Setup(m, nominal, free, folds, adapt, set_free, warnings)


def diagnose(
    manifest: str | Path | Manifest,
    out_dir: str | Path | None = None,
    *,
    settings: DiagnosisSettings | None = None,
    progress: bool = True,
    figures: bool = True,
    manifest_path: str | Path | None = None,
    executor: Any = None,
) -> Diagnosis:
    """Diagnose the gap between a nominal model and measured experiments (see the module
    docstring for the report). All input errors are raised before any fitting, and so is
    an unusable ``out_dir`` (:func:`nanostage.output.check_output_dir`); the folder is
    written whole or not at all (:func:`nanostage.output.staged_output`).
    ``manifest_path``: the manifest's path the report gives (default: where it was read;
    a caller that reads it from a staging folder names its final place). ``executor``: a
    :class:`concurrent.futures.Executor` or a ``dask.distributed.Client`` on which the
    candidate fits of each round run (:func:`~nanostage.diagnosis.loop.diagnose_experiments`;
    the report is bit-identical to a local run)."""
    if out_dir is not None:
        check_output_dir(out_dir)
    setup = _setup(manifest)
    m, nominal, free, folds = setup.manifest, setup.nominal, setup.free, setup.folds
    adapt = setup.adapt
    st = settings or DiagnosisSettings(
        seed=m.diagnosis.seed, level_scatter=m.diagnosis.level_scatter
    )
    names = [c for c in m.diagnosis.candidates if c in CANDIDATES]
    cands, _ = applicable_candidates(nominal, names)
    for w in setup.warnings.values():
        print_progress(f"warning: {w}", progress)
    out = diagnose_experiments(
        nominal,
        free,
        setup.set_free,
        folds,
        adapt=adapt,
        candidates=names,
        settings=st,
        progress=progress,
        executor=executor,
    )
    clock = out["phases"]
    report = assemble_report(out, folds, adapt, _lead(nominal), st, [c.name for c in cands])
    clock.lap("report")
    report["crossfit"] = _crossfit(setup, out, st, _lead(nominal), progress)
    if report["crossfit"] is not None:
        clock.lap("cross-fit")
    report["phases"] = [dict(e) for e in clock.entries]
    report["manifest"] = str(m.path if manifest_path is None else manifest_path)
    report["calibration_at_bounds"] = {
        "nominal": at_bounds(out["nominal"], free),
        "selected_model": at_bounds(out["final"], free) if out["selected"] else [],
    }
    report["warnings"] = (
        list(setup.warnings.values())
        + bound_warnings(
            report["calibration_at_bounds"]["nominal"],
            report["calibration_at_bounds"]["selected_model"],
        )
        + widened_gap_warnings(
            float(report["gap_before"]["total_rms_m"]),
            float(report["gap_after"]["total_rms_m"]),
            report["selected"],
        )
    )
    written = None
    if out_dir is not None:
        val = _validation_order(folds)
        sims = [
            reading
            for reading, _ in _simulated_pairs([f.system for f in out["final_fits"]], folds, adapt)
        ]
        gap_exps = [
            {
                "name": e.name,
                "time_s": e.time_s,
                "reference_m": e.reference_m,
                "measured_m": e.position_m,
                "simulated_m": s,
                "intervals": segment(e).intervals(),
            }
            for e, s in zip(val, sims, strict=True)
        ]
        report["model_file"] = MODEL_FILE
        with staged_output(out_dir, "diagnose") as folder:
            write_report(report, folder, gap_experiments=gap_exps, figures=figures)
            save_model(
                out["final"].system,
                folder / MODEL_FILE,
                provenance=_model_provenance(report, len(folds)),
                identified=_identified(setup, out),
            )
        written = Path(out_dir)
    return Diagnosis(report=report, out_dir=written, model=out["final"].system)


def _model_provenance(report: Mapping[str, Any], n_folds: int) -> dict[str, Any]:
    """The ``[provenance]`` of the diagnosis's model file."""
    prov: dict[str, Any] = {
        "command": "nanostage diagnose",
        "nanostage_version": __version__,
        "manifest": str(report["manifest"]),
        "selected_effects": list(report["selected"]),
        "gap_before_rms_m": float(report["gap_before"]["total_rms_m"]),
        "gap_after_rms_m": float(report["gap_after"]["total_rms_m"]),
        "folds": n_folds,
    }
    if n_folds > 1:
        prov["note"] = (
            f"the fit of the first of {n_folds} folds; gap_after judges each fold's "
            "validation experiments by that fold's own fit"
        )
    return prov


def _identified(setup: _Setup, out: Mapping[str, Any]) -> dict[str, IdentifiedParameter]:
    """Standard error and bounds of the selected model's fitted parameters, by dotted path:
    the free nominal parameters (refitted with the selected effects) and the continuous
    parameters of the selected effects (from the round that selected each)."""
    final: Fit = out["final"]
    ident: dict[str, IdentifiedParameter] = {}
    for path, p in setup.free:
        ident[path] = IdentifiedParameter(
            std_error=final.std_errors.get(path), lower=p.lower, upper=p.upper
        )
    rounds: Sequence[Sequence[CandidateResult]] = out["rounds"]
    for rnd, (cand, values) in zip(rounds, out["selected_effects"], strict=False):
        if cand.discrete:
            continue
        won = next((r for r in rnd if r.effect == cand.name), None)
        paths = _effect_paths(cand, values, final.system)
        for q, where in zip(cand.params, paths, strict=True):
            if where is None or where in ident:
                continue
            se = won.fit.std_errors.get(f"{cand.name}.{q.name}") if won is not None else None
            ident[where] = IdentifiedParameter(std_error=se, lower=q.lower, upper=q.upper)
    return ident


def _effect_paths(cand: Candidate, values: Sequence[float], system: System) -> list[str | None]:
    """The dotted path of the model that holds each parameter of an applied effect (None
    where it is not one field holding the value as fitted): the one field that changes
    when that parameter alone is moved to one of its bounds."""
    numeric = field_paths(system)
    out: list[str | None] = []
    for i, p in enumerate(cand.params):
        alt = list(values)
        alt[i] = p.lower if values[i] != p.lower else p.upper
        try:
            moved = cand.apply(system, alt)
            changed = [q for q in numeric if repr(get_path(moved, q)) != repr(get_path(system, q))]
        except (ValueError, TypeError, KeyError, AttributeError, ConfigError):
            out.append(None)
            continue
        hit = len(changed) == 1 and get_path(system, changed[0]) == values[i]
        out.append(changed[0] if hit else None)
    return out


def _is_coulomb_viscous(system: System, parent: str) -> bool:
    try:
        obj = get_path(system, parent)
    except (KeyError, AttributeError, ValueError):
        return False
    fs = getattr(obj, "static_force_n", None)
    return fs is not None and fs == getattr(obj, "coulomb_force_n", None)


def _controller_paths(system: System) -> list[str]:
    ctl = system.controller
    names = ("kp", "ki", "kd") if hasattr(ctl, "kd") else ("kp_per_s", "kv_v_s_per_m")
    return [f"controller.{n}" for n in names]


def _validation_order(
    folds: Sequence[tuple[Sequence[Experiment], Sequence[Experiment]]],
) -> list[Experiment]:
    return [e for _, v in folds for e in v]


def _simulated_pairs(
    systems: Sequence[System],
    folds: Sequence[tuple[Sequence[Experiment], Sequence[Experiment]]],
    adapt: Any,
    cache: SimulationCache | None = None,
) -> list[tuple[np.ndarray, np.ndarray]]:
    """Simulated (mean reading, command) of the validation experiments, each fold's by its
    system, all in one batch of the core (pairs the diagnosis already simulated looked up in
    its ``cache``)."""
    pairs = [(adapt(s, e), e) for s, (_, v) in zip(systems, folds, strict=True) for e in v]
    simulate = simulate_readings_and_commands if cache is None else cache.simulate
    return simulate([a for a, _ in pairs], [e for _, e in pairs])


def _simulated(
    fits: Sequence[Fit | System],
    folds: Sequence[tuple[Sequence[Experiment], Sequence[Experiment]]],
    adapt: Any,
    cache: SimulationCache | None = None,
) -> list[np.ndarray]:
    """Simulated mean readings of the validation experiments (each fold's by its fit's
    system, or the given system), hold windows rank-aligned to the measurement (so that
    measured − simulated is the engine's gap residual)."""
    systems = [f.system if isinstance(f, Fit) else f for f in fits]
    return _aligned(
        _validation_order(folds),
        [reading for reading, _ in _simulated_pairs(systems, folds, adapt, cache)],
    )


def _aligned(experiments: Sequence[Experiment], readings: Sequence[np.ndarray]) -> list[np.ndarray]:
    """Each simulated mean reading with its hold windows rank-aligned to its experiment's
    measurement (so that measured − aligned is the engine's gap residual)."""
    return [
        align_holds(e.position_m, r, e.reference_m)
        for e, r in zip(experiments, readings, strict=True)
    ]


def _crossfit(
    setup: _Setup,
    out: Mapping[str, Any],
    st: DiagnosisSettings,
    lead_m: float | None,
    progress: bool,
) -> dict[str, Any] | None:
    """The report's ``crossfit``: the validation gap of the nominal and of the selected
    model when each validation experiment is judged by models refitted on all the other
    experiments (:func:`~nanostage.diagnosis.loop.crossfit_models`); None when it is off,
    nothing was selected (the shrink is 0) or the manifest has several folds (then every
    fold already trains on all but its validation experiments)."""
    if st.crossfit_folds <= 0 or not out["selected"] or len(setup.folds) != 1:
        return None
    print_progress(
        f"diagnosis: cross-fitting the nominal and the selected model "
        f"({st.crossfit_folds} folds of the validation experiments)",
        progress,
    )
    train, validate = setup.folds[0]
    models = crossfit_models(
        setup.nominal,
        setup.free,
        setup.set_free,
        train,
        validate,
        out["selected_effects"],
        {n: out["nominal_fits"][0].values[n] for n, _ in setup.free},
        {n: out["final_fits"][0].values[n] for n, _ in setup.free},
        k=st.crossfit_folds,
        adapt=setup.adapt,
        settings=st,
        cache=out["cache"],
        command_weights_m_per_v=out["command_weights_m_per_v"],
        level_directions=out["level_directions"],
    )
    # Both models of every fold in one batch: the judged experiments once with the nominal
    # refit, once with the selected one.
    folds: list[tuple[Sequence[Experiment], Sequence[Experiment]]] = [
        ([], judged) for judged, _, _ in models for _ in range(2)
    ]
    sims = iter(_simulated([m for _, b, a in models for m in (b, a)], folds, setup.adapt))
    sim_b: dict[str, np.ndarray] = {}
    sim_a: dict[str, np.ndarray] = {}
    for judged, _, _ in models:
        sim_b.update({e.name: next(sims) for e in judged})
        sim_a.update({e.name: next(sims) for e in judged})
    gap_b = _gap(validate, [sim_b[e.name] for e in validate], lead_m)
    gap_a = _gap(validate, [sim_a[e.name] for e in validate], lead_m)
    rb, ra = float(gap_b["total_rms_m"]), float(gap_a["total_rms_m"])
    return {
        "folds": len(models),
        "judged": [[e.name for e in judged] for judged, _, _ in models],
        "gap_before_rms_m": rb,
        "gap_after_rms_m": ra,
        "shrink": 1.0 - ra / rb if rb > 0 else 0.0,
        "by_segment_before": gap_b["by_segment"],
        "by_segment_after": gap_a["by_segment"],
    }


def model_gap(manifest: str | Path | Manifest, system: System) -> dict[str, Any]:
    """The validation gap of a given model, nothing fitted: the measure of the report's
    ``gap_before`` and ``gap_after`` (the same validation experiments, each with its
    manifest controller, the same hold alignment), e.g. to judge a model from elsewhere on
    the data. Returns the same form (``total_rms_m``, ``by_segment``, the full analysis)."""
    setup = _setup(manifest)
    val = _validation_order(setup.folds)
    sims = _simulated([system] * len(setup.folds), setup.folds, setup.adapt)
    return _gap(val, sims, _lead(setup.nominal))


def readings_gap(
    manifest: str | Path | Manifest, readings: Mapping[str, npt.ArrayLike]
) -> dict[str, Any]:
    """:func:`model_gap` of mean readings simulated elsewhere (true position − half a count,
    as the engine simulates them; e.g. by the independent truth family's own model,
    :func:`~nanostage.diagnosis.independent_truth.oracle_readings`): ``readings`` by
    validation experiment name, one value per sample of that experiment."""
    setup = _setup(manifest)
    val = _validation_order(setup.folds)
    missing = [e.name for e in val if e.name not in readings]
    if missing:
        raise ValueError(f"readings: no reading for validation experiment(s) {', '.join(missing)}")
    sims = [np.asarray(readings[e.name], dtype=np.float64) for e in val]
    for e, r in zip(val, sims, strict=True):
        if r.shape != e.position_m.shape:
            raise ValueError(
                f"readings[{e.name!r}]: {r.size} values for an experiment of "
                f"{e.position_m.size} samples"
            )
    return _gap(val, _aligned(val, sims), _lead(setup.nominal))


def selecting_results(
    rounds: Sequence[Sequence[CandidateResult]],
    cross_judged: Sequence[Sequence[CandidateResult]],
    selected: Sequence[str],
) -> list[CandidateResult]:
    """Each selected effect's result in the terms its round selected it by: its result
    judged on every experiment where the round was cross-judged
    (:attr:`DiagnosisSettings.cross_judge_folds`), else its validation result."""
    out = []
    for i, name in enumerate(selected):
        pools = [cross_judged[i]] if i < len(cross_judged) else []
        pools.append(rounds[i])
        out.append(next(r for pool in pools for r in pool if r.effect == name))
    return out


def assemble_report(
    out: Mapping[str, Any],
    folds: Sequence[tuple[Sequence[Experiment], Sequence[Experiment]]],
    adapt: Any,
    lead_m: float | None,
    st: DiagnosisSettings,
    candidate_names: Sequence[str],
) -> dict[str, Any]:
    """The report dict from the engine's output."""
    val = _validation_order(folds)
    rounds: list[list[CandidateResult]] = out["rounds"]
    first = rounds[0] if rounds else []
    # The engine simulated every one of these fits on the validation experiments already.
    cache: SimulationCache | None = out.get("cache")
    before = _gap(val, _simulated(out["nominal_fits"], folds, adapt, cache), lead_m)
    after = _gap(val, _simulated(out["final_fits"], folds, adapt, cache), lead_m)
    single_best = best_single(first, out["selected"])
    single = (
        _gap(val, _simulated(single_best.fold_fits, folds, adapt, cache), lead_m)
        if single_best
        else None
    )
    candidates = [r.to_dict() for r in first]
    selecting = selecting_results(rounds, out.get("cross_judged") or [], out["selected"])
    evidence = []
    previous = before
    for i, (rnd, name) in enumerate(zip(rounds, out["selected"], strict=False)):
        r = next(x for x in rnd if x.effect == name)
        ev, previous = _evidence(r, previous, val, folds, adapt, lead_m, cache)
        if selecting[i] is not r:
            # Selected by its results on every experiment: those say why; the validation
            # experiments' alone follow, labelled.
            ev["why"] = [f"judged on every experiment: {w}" for w in selecting[i].reasons] + [
                f"on the validation experiments alone: {w}" for w in r.reasons
            ]
        ev["why"] = list(ev.get("why") or []) + [
            f"named on the gap as measured {d['every_experiment']}; on the validation "
            f"experiments alone {d['validation']}"
            for d in out.get("measured_on_every") or []
            if d["round"] == i + 1 and d["effect"] == name
        ]
        evidence.append({"round": i + 1} | ev)
    floor = float(out["floor_rms_m"])
    total_after = float(after["total_rms_m"])
    penalty = st.penalty(1)
    return {
        "gap_before": before,
        "candidates": candidates,
        "selected": list(out["selected"]),
        # With the cross-judging, the ties of the results the rounds selected by.
        "indistinguishable": ties_of_selected(
            out.get("cross_judged") or rounds, out["selected"], st.ranking
        ),
        "cross_judged": [
            {
                "round": i + 1,
                "folds": st.cross_judge_folds,
                "candidates": [r.to_dict() for r in rnd],
            }
            for i, rnd in enumerate(out.get("cross_judged") or [])
        ],
        "ranking": st.ranking,
        "significance": st.significance,
        "tie_break": "occam_factor" if st.occam_tie_break else "validation_gap",
        # Per round with a tie: the signature χ² of each tied candidate (the judge's) and
        # the margin within which a candidate stayed in the tie.
        "tie_signatures": [
            {
                "round": i + 1,
                "distances": dict(d),
                "margin": st.signature_margin,
                "marks": list(marks),
            }
            for i, (d, marks) in enumerate(
                zip(
                    out.get("signature_distances") or [],
                    out.get("signature_marks") or itertools.repeat([]),
                    strict=False,
                )
            )
            if d
        ],
        # Per round whose lag family was refitted beyond the usual refits: why.
        "extra_refits": [dict(d) for d in out.get("extra_refits") or []],
        # Per round whose friction laws put right the ramp marks the model before misses:
        # each such law and the share of those marks' χ² it removes.
        "speed_mark_support": [dict(d) for d in out.get("speed_mark_support") or []],
        # Per round whose pick was named on the gap as measured over every experiment (its
        # own fit left the validation experiments' measured gap): both measures.
        "measured_on_every": [dict(d) for d in out.get("measured_on_every") or []],
        "gap_after": after,
        "gap_best_single": single,
        "best_single_effect": single_best.effect if single_best else None,
        "noise_floor_rms_m": floor,
        "experiment_noise_floors_m": dict(out["experiment_floors_m"]),
        "kind_floors": bool(out["kind_floors"]),
        "unexplained_rms_m": math.sqrt(max(total_after**2 - floor**2, 0.0)),
        "unexplained": unexplained_gap(
            before["total_rms_m"],
            floor,
            out["selected"],
            first,
            st,
            judged_round=(out.get("cross_judged") or [[]])[0],
        ),
        "explained_fraction": _explained(before["total_rms_m"], total_after, floor),
        "forward_selection": [
            {
                "round": i + 1,
                "candidates": [
                    {
                        "effect": r.effect,
                        "validation_rms_m": r.validation_rms_m,
                        "shrink": r.shrink,
                        "significant": r.significant,
                    }
                    for r in rnd
                ],
            }
            for i, rnd in enumerate(rounds)
        ],
        "evidence": evidence,
        "advice": experiment_advice(
            val + [e for t, _ in folds for e in t],
            lead_m,
            first,
            penalty,
            folds,
            level_floors=out.get("level_floors"),
            validation_gap_m2={
                n: float(v["sum_sq_m2"]) for n, v in before["per_experiment"].items()
            },
            ranking=st.ranking,
            selected=selecting,
            p_value=st.p_value,
            cross_judged_count_m=(
                out["nominal"].system.encoder.count_m if out.get("cross_judged") else None
            ),
        ),
        "level_scatter": out.get("level_scatter"),
        "level_floors": dict(out.get("level_floors") or {}),
        "skipped": dict(out["skipped"]),
        "refit_control": list(out.get("refit_control", [])),
        "nominal_parameters": _free_parameters(out["nominal"], out["nominal"]),
        # The free nominal parameters as refitted with the selected effects (they move when
        # an effect takes up part of what they fitted before).
        "selected_model_parameters": _free_parameters(out["final_fits"][0], out["nominal"]),
        "folds": [
            {"train": [e.name for e in t], "validate": [e.name for e in v]} for t, v in folds
        ],
        "timing_s": out["timing_s"],
        "simulations": dict(out["simulations"]),
        "signatures": signature_comparison(out, first, st.ranking),
    }


def _features(sig: Mapping[str, Feature]) -> dict[str, dict[str, Any]]:
    return {n: f.to_dict() | {"unit": SIGNATURE_UNITS.get(n, "")} for n, f in sorted(sig.items())}


def signature_comparison(
    out: Mapping[str, Any],
    first_round: Sequence[CandidateResult],
    ranking: str,
    top: int = 3,
) -> dict[str, Any] | None:
    """The report's ``signatures``: the measured signature of all experiments
    (:mod:`~nanostage.diagnosis.signatures`: limit cycles in holds, the command at rest
    and on ramps per direction, breakaway against rest) and the simulated one of the
    calibrated nominal model, the selected model, and the first round's candidates that
    matter for the choice (the first selected effect and those the validation data cannot
    tell from it; with nothing selected, the best ``top`` partial explanations), each with
    its χ² distance from the measured one and the features it misses by more than three
    standard errors (:func:`~nanostage.diagnosis.signatures.misses`). None when the traces
    have no signature feature. The judge is the engine's (``out["signature_judge"]``): the
    same measured signature, simulations and cache as its tie-breaks."""
    judge: SignatureJudge = out["signature_judge"]
    if not judge.measured:
        return None
    selected = list(out["selected"])
    models: list[tuple[str, str | None, System]] = [
        ("nominal", None, out["nominal_fits"][0].system)
    ]
    if selected:
        models.append(("selected model", None, out["final_fits"][0].system))
        ties = set(ties_of_selected([first_round], selected[:1], ranking).get(selected[0], []))
        picked = [r for r in first_round if r.effect == selected[0] or r.effect in ties]
    else:
        picked = [r for r in first_round if r.shrink > 0.0][:top]
    models += [("candidate", r.effect, r.fit.system) for r in picked]
    rows: list[dict[str, Any]] = []
    for kind, effect, system in models:
        try:
            sig = judge.simulated(system)
        except (RuntimeError, ValueError) as exc:
            rows.append({"model": kind, "effect": effect, "error": str(exc)})
            continue
        rows.append(
            {
                "model": kind,
                "effect": effect,
                "distance": signature_distance(judge.measured, sig),
                "misses": signature_misses(judge.measured, sig),
                "features": _features(sig),
            }
        )
    return {
        "experiments": [e.name for e in judge.experiments],
        "measured": _features(judge.measured),
        "models": rows,
    }


def unexplained_gap(
    before_rms_m: float,
    floor_rms_m: float,
    selected: Sequence[str],
    first_round: Sequence[CandidateResult],
    st: DiagnosisSettings,
    top: int = 3,
    judged_round: Sequence[CandidateResult] = (),
) -> dict[str, Any] | None:
    """With nothing selected while the validation gap is above
    :attr:`DiagnosisSettings.explainable_factor` noise floors: the gap, its ratio to the
    floor and the best ``top`` partial explanations (the round-1 candidates with a positive
    shrink of that gap, the largest first, each with its geometric shrink, by which the
    round ranked them, and why it was not selected); else None. The report says so
    plainly instead of "nothing found".

    With ``judged_round`` (round 1's refitted candidates judged on every experiment, by
    which the round selected nothing: :attr:`DiagnosisSettings.cross_judge_folds`) the
    partial explanations are those results (``judged``: ``"every experiment"``), else the
    validation results of ``first_round`` (``"validation experiments"``)."""
    if selected or not before_rms_m > st.explainable_factor * floor_rms_m:
        return None
    pool, judged = (
        (judged_round, "every experiment")
        if judged_round
        else (first_round, "validation experiments")
    )
    # Ordered by the share of the pooled gap each removes, the gap the sentence names
    # (the round's own order, by the geometric shrink, may put a candidate that removes
    # nothing of it before one that removes half).
    partial = [
        {
            "effect": r.effect,
            "shrink": r.shrink,
            "geometric_shrink": r.geometric_shrink,
            "why_not": r.reasons,
            "judged": judged,
        }
        for r in sorted((r for r in pool if r.shrink > 0.0), key=lambda r: -r.shrink)
    ][:top]
    return {
        "gap_rms_m": before_rms_m,
        "floor_ratio": before_rms_m / floor_rms_m if floor_rms_m > 0 else math.inf,
        "partial_explanations": partial,
    }


def bound_warnings(
    nominal: Sequence[Mapping[str, Any]], selected: Sequence[Mapping[str, Any]]
) -> list[str]:
    """The report's warnings about free parameters at their bounds (:func:`at_bounds`) in the
    nominal calibration (``nominal``) and with the selected effects (``selected``)."""

    def listed(rows: Sequence[Mapping[str, Any]]) -> str:
        return ", ".join(
            f"{r['parameter']} = {r['value']:.4g} at its {r['bound']} bound {r['limit']:.4g}"
            for r in rows
        )

    out = []
    if nominal:
        out.append(
            "the nominal calibration left free parameters at their bounds ("
            + listed(nominal)
            + "): the nominal model bends them to fit something it does not model, and the "
            "candidates are judged from this calibration, so an effect it has absorbed can "
            "be missed; widen the bounds in [model.bounds] where the datasheet allows, and "
            "read 'none' or a small shrink with care"
        )
    if selected:
        out.append(
            "with the selected effects, free parameters are still at their bounds ("
            + listed(selected)
            + "): the selected model may be compensating for a further effect"
        )
    return out


def widened_gap_warnings(
    before_rms_m: float, after_rms_m: float, selected: Sequence[str]
) -> list[str]:
    """The report's warning when the selected model's pooled validation gap is larger than
    the nominal model's: the selection then rests on the per-experiment (geometric) gaps or
    on the judging over every experiment (the training ones too), and its shrink is not
    confirmed on the pooled data the fit never saw."""
    if not selected or not after_rms_m > before_rms_m:
        return []
    return [
        f"the selected model ({', '.join(selected)}) leaves a larger validation gap than the "
        f"nominal model ({after_rms_m * 1e9:.1f} nm against {before_rms_m * 1e9:.1f} nm RMS, "
        f"shrink {1.0 - after_rms_m / before_rms_m:.0%}): the rules that selected it (the "
        "geometric gap per validation experiment, or the judging over every experiment) are "
        "not confirmed by the pooled validation gap; read the selection as a hypothesis and "
        "test it on further validation experiments of the kinds it improved (see "
        "*Candidates* and *Judged on every experiment*)"
    ]


def _free_parameters(fit: Fit, nominal: Fit) -> dict[str, dict[str, float | None]]:
    """The free nominal parameters (those of the nominal calibration ``nominal``) of
    ``fit``: value and standard error."""
    return {
        n: {"value": fit.values[n], "std_error": fit.std_errors.get(n)}
        for n in nominal.values
        if n in fit.values
    }


def _explained(before: float, after: float, floor: float) -> float | None:
    """Fraction of the gap above the noise floor that the model removed (mean squares)."""
    excess = before**2 - floor**2
    return (before**2 - after**2) / excess if excess > 0 else None


def _evidence(
    r: CandidateResult,
    before: Mapping[str, Any],
    val: Sequence[Experiment],
    folds: Any,
    adapt: Any,
    lead_m: float | None,
    cache: SimulationCache | None = None,
) -> tuple[dict[str, Any], dict[str, Any]]:
    """What the effect fixed relative to the model before it was added (and its gap)."""
    sims = _simulated(r.fold_fits, folds, adapt, cache)
    mine = _gap(val, sims, lead_m)
    seg_b = before["by_segment"]
    seg_a = mine["by_segment"]
    fixed = []
    for k, g in seg_b.items():
        rb, ra = g["rms_m"], seg_a.get(k, {}).get("rms_m")
        if rb and ra is not None and math.isfinite(rb) and math.isfinite(ra) and rb > 0:
            fixed.append((1.0 - ra / rb, k, rb, ra))
    fixed.sort(reverse=True)
    words = [f"{k}: {rb * 1e9:.0f} → {ra * 1e9:.0f} nm ({s:+.0%})" for s, k, rb, ra in fixed[:3]]
    lead_b, lead_a = before.get("lead_share"), mine.get("lead_share")
    return {
        "effect": r.effect,
        "shrink": r.shrink,
        "p_value": r.p_value,
        "parameters": r.to_dict()["parameters"],
        "segments_fixed": words,
        "lead_share_before": lead_b,
        "lead_share_after": lead_a,
        "why": r.reasons,
    }, mine
