"""The diagnosis engine: the gap metric, the noise floor, significance, and small end-to-end
runs on synthetic data with a known hidden effect (the full blind benchmark is
``nanostage diagnose-benchmark``; see docs/benchmarks.md)."""

from __future__ import annotations

import dataclasses as dc
import json
import math
import os
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace
from typing import Any, cast

import numpy as np
import pytest
from diagnosis_cases import (
    candidate_result,
    friction_problems,
    simulated_experiment,
    step_case,
)
from hypothesis import given, settings
from hypothesis import strategies as st_h

import nanostage as ns
from nanostage import presets
from nanostage.config import System, get_path, replace_paths
from nanostage.diagnosis.benchmark import (
    BREAKAWAY_GAINS,
    DESIGN,
    MID_COUNT_M,
    MOVE_S,
    _hidden,
    design_reference,
    draw_truth,
    median_phase_seconds,
    oracle_model,
    run_benchmark,
    truth_starts,
)
from nanostage.diagnosis.candidates import (
    CANDIDATES,
    NOT_CANDIDATES,
    Param,
    applicable_candidates,
    gms_spread,
    motor_static_force_n,
)
from nanostage.diagnosis.fit import AT_BOUND, Fit, FitProblem, at_bounds
from nanostage.diagnosis.loop import (
    BIAS_ALIASES,
    BIAS_MARKS,
    BREAKAWAY_MARKS,
    FRICTION_MODELS,
    LAG_FAMILY,
    _Ctx,
    _judge,
    _judged_holm,
    _refit_control,
    _verdict,
    candidate_seed,
    cross_judge_split,
    crossfit_folds,
    crossfit_models,
    experiment_class,
    experiment_scale,
    hopeless_lag_refits,
    mark_effects,
    refine_names,
)
from nanostage.diagnosis.manifest import load_manifest
from nanostage.diagnosis.objective import (
    SimulationCache,
    _best_shift,
    apply_gap_plan,
    autocorrelation_time,
    command_plan,
    experiment_floors_m,
    experiment_kind,
    gap_plan,
    gap_residual,
    hold_intervals,
    hunting_ramps,
    move_units,
    noise_floor_m,
    rms_of,
    simulate_readings_and_commands,
)
from nanostage.diagnosis.report import _extra_refit_lines, markdown_report
from nanostage.diagnosis.run import (
    best_single,
    bound_warnings,
    diagnose,
    experiment_advice,
    indistinguishable,
    model_gap,
    readings_gap,
    selecting_results,
    ties_of_selected,
    widened_gap_warnings,
)
from nanostage.diagnosis.select import (
    CandidateResult,
    holm_levels,
    log_occam_factor,
    null_test_p,
    pick_winner,
    rank_key,
    relative_terms,
    significance_mode,
    too_few_to_test,
    turned_down,
    without_unsupported,
)
from nanostage.diagnosis.settings import (
    RANKINGS,
    DiagnosisSettings,
    PhaseClock,
    phase_totals,
    with_starts,
)
from nanostage.diagnosis.signatures import SIGNATURE_UNITS
from nanostage.effects import (
    EFFECT_NAMES,
    Backlash,
    DwellStaticFriction,
    Effects,
    EncoderErrors,
    FrictionModifiers,
    StochasticFriction,
)
from nanostage.experiment import Experiment
from nanostage.simulate import simulate


def test_every_effect_name_is_a_candidate_or_explained() -> None:
    assert set(CANDIDATES) | set(NOT_CANDIDATES) == set(EFFECT_NAMES)
    cands, skipped = applicable_candidates(ns.presets.seed())
    names = {c.name for c in cands}
    assert "dahl" in skipped and "backlash" in names
    cands, skipped = applicable_candidates(ns.presets.emps())
    assert "backlash" in skipped and "a force drive has no gearhead" in skipped["backlash"]
    with pytest.raises(ValueError, match="unknown effect 'nope'"):
        applicable_candidates(ns.presets.seed(), ["nope"])


def test_candidate_parameters_round_trip_and_stay_valid() -> None:
    """Every candidate's parameters map to [0, 1] and back, and its system builds (the Rust
    core validates) at the bounds and at the start values."""
    for system in (ns.presets.seed(), ns.presets.emps(), ns.presets.emps_naive()):
        cands, _ = applicable_candidates(system)
        for c in cands:
            for p in c.params:
                for v in (p.lower, p.initial, p.upper):
                    assert p.from_unit(p.to_unit(v)) == pytest.approx(v, rel=1e-9, abs=1e-15)
            for u in (0.0, 0.5, 1.0):
                vals = [p.from_unit(u) for p in c.params] or [1]
                c.apply(system, vals)


@pytest.mark.parametrize(
    ("preset", "paths"),
    [
        (
            "seed",
            (
                "plant.table.mass_kg",
                "plant.dahl.coulomb_force_n",
                "plant.motor_friction.static_torque_nm",
            ),
        ),
        ("emps", ("plant.mass_kg", "plant.friction.viscous_n_s_per_m")),
    ],
)
def test_candidates_keep_the_free_parameters_they_are_given(
    preset: str, paths: tuple[str, ...]
) -> None:
    """A candidate augments the system it is *given* (which carries the fitted free nominal
    parameters): applying it must not restore the nominal values it was made from. (The
    offset-force and inductance candidates used to rebuild the nominal plant, so the fit
    could not move the free parameters while judging them.)"""
    nominal = ns.presets.seed(1e-3) if preset == "seed" else ns.presets.emps()
    cands, _ = applicable_candidates(nominal)
    assert {"offset_force"} <= {c.name for c in cands}
    for c in cands:
        vals = [p.initial for p in c.params] if not c.discrete else [c.discrete[0]]
        for path in paths:
            changed = replace_paths(nominal, {path: get_path(nominal, path) * 1.1})
            out = c.apply(changed, vals)
            if c.name in FRICTION_MODELS and path.split(".")[1] in ("dahl", "friction"):
                continue  # a friction-model candidate replaces that friction model
            assert get_path(out, path) == get_path(changed, path), (c.name, path)


def test_an_invalid_parameter_region_is_a_bad_fit_not_the_best(tmp_path: Path) -> None:
    """Parameter sets whose model is invalid (here: a Coulomb torque above the static one)
    are charged a huge gap, so a start in that region can never beat a valid fit."""
    m = _case(tmp_path, Effects(), seed=6)
    text = m.read_text(encoding="utf-8").replace(
        'free = ["plant.dahl.coulomb_force_n"]',
        'free = ["plant.dahl.coulomb_force_n", "plant.motor_friction.coulomb_torque_nm"]\n'
        '[model.bounds]\n"plant.motor_friction.coulomb_torque_nm" = [5e-5, 2e-4]',
    )
    m.write_text(text)
    man = load_manifest(m)
    exps = [e for _, e in man.experiments()]
    free = [
        ("plant.dahl.coulomb_force_n", Param(name="f", unit="N", lower=20, upper=40, initial=30.4)),
        (
            "plant.motor_friction.coulomb_torque_nm",
            Param(name="t", unit="N·m", lower=5e-5, upper=2e-4, initial=1e-4),
        ),
    ]
    nominal = man.system()
    prob = FitProblem(
        free,
        lambda v: replace_paths(nominal, {n: x for (n, _), x in zip(free, v, strict=True)}),
        exps[:2],
        2,
        lambda s, e: s,
    )
    prob.scale_m = 1e-7
    bad = prob._vector(np.array([1.5, 1.9]))  # Coulomb 1.7e-4 N·m > static 1.2e-4 N·m
    good = prob._vector(np.array([1.5, 1.3]))
    assert np.sum(bad**2) > 1e6 * np.sum(good**2)
    fit = prob.fit(3, FAST, seed=0)
    assert fit.values["plant.motor_friction.coulomb_torque_nm"] <= 1.2e-4
    # The covariance in normalised coordinates (bounds span 1) is the standard errors'
    # source: symmetric, positive semi-definite, its diagonal the errors over the widths.
    cov = fit.unit_covariance
    assert cov.shape == (2, 2) and np.array_equal(cov, cov.T)
    assert np.all(np.linalg.eigvalsh(cov) >= -1e-12 * np.max(np.abs(cov)))
    for i, (n, p) in enumerate(free):
        assert fit.std_errors[n] == pytest.approx((p.upper - p.lower) * np.sqrt(cov[i, i]))


def test_batched_evaluations_equal_one_at_a_time(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The finite-difference points of each Jacobian (scipy's ``workers`` hook) and the
    scan's points are simulated as one batch: every point's residuals are bit for bit those
    of evaluating it alone, an invalid point among them is still the failed gap, and a whole
    fit takes the same path as with scipy's own one-at-a-time evaluation."""
    import nanostage.diagnosis.fit as eng

    problem = friction_problems(
        _case(tmp_path, Effects(), seed=6),
        force_initial_n=30.4,
        torque_upper_nm=2e-4,
        torque_initial_nm=1e-4,
    )
    prob = problem()
    points = [np.array([1.5, 1.3]), np.array([1.5, 1.9]), np.array([1.2, 1.05])]  # 2nd invalid
    batch = prob._batch_map(lambda u: u, iter(points))
    one = [prob._vector(u) for u in points]
    assert prob.n_evaluations == 6
    assert all(np.array_equal(a, b) for a, b in zip(batch, one, strict=True))
    assert np.sum(batch[1] ** 2) > 1e6 * np.sum(batch[0] ** 2)

    batched = problem().fit(2, FAST, seed=0, scan=4)
    real = eng.least_squares

    def one_at_a_time(fun: Any, x0: np.ndarray, **kw: Any) -> Any:
        kw.pop("workers")
        return real(fun, x0, **kw)

    monkeypatch.setattr(eng, "least_squares", one_at_a_time)
    alone = problem().fit(2, FAST, seed=0, scan=4)
    assert batched.values == alone.values
    assert batched.train_rms_m == alone.train_rms_m
    assert batched.n_evaluations == alone.n_evaluations


COULOMB = "plant.dahl.coulomb_force_n"


def _coulomb_ctx(manifest: Path, st: DiagnosisSettings) -> tuple[_Ctx, list[Experiment]]:
    """A diagnosis context on a step case with the table's Coulomb force free (20–40 N,
    prior 30.4 N) and calibrated, bent, to 27 N; two experiments train, the rest validate."""
    man = load_manifest(manifest)
    exps = [e for _, e in man.experiments()]
    free = [(COULOMB, Param(name="f", unit="N", lower=20, upper=40, initial=30.4))]
    ctx = _Ctx(
        free=free,
        set_free=lambda s, v: replace_paths(s, dict(v)),
        folds=[(exps[:2], exps[2:])],
        floor=1e-8,
        st=st,
        adapt=lambda s, e: s,
        nominal=man.system(),
        warm=[{COULOMB: 27.0}],
    )
    return ctx, exps


def test_screening_fits_only_the_discrete_setting_that_starts_best(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A discrete candidate (a delay) is screened by fitting only the setting whose model at
    the fits' starts (the warm and the manifest's free values) has the smallest training
    gap; refining fits every setting. On data with a hidden two-sample computation delay the
    setting chosen at the start is 2, the one-at-a-time start gaps agree, and the screened
    result has the refined result's setting. When every start fails to simulate, every
    setting is fitted (and reports why)."""
    m = _case(tmp_path, Effects(computation_delay_samples=2), seed=5)
    ctx, exps = _coulomb_ctx(m, FAST)
    nominal, free, name = ctx.nominal, ctx.free, COULOMB
    (cand,), _ = applicable_candidates(nominal, ["computation_delay"])
    assert cand.discrete == (1, 2, 3)
    chosen = ctx.best_start_setting(nominal, cand)

    def start_ms(k: int, f: float) -> float:
        s = cand.apply(replace_paths(nominal, {name: f}), [k])
        prob = FitProblem(free, lambda v: s, exps[:2], 1, lambda s, e: s)
        return float(np.mean([np.mean(r**2) for r in prob.residuals(s, exps[:2])]))

    costs = {k: min(start_ms(k, 27.0), start_ms(k, 30.4)) for k in cand.discrete}
    assert chosen == (min(costs, key=costs.__getitem__),) == (2,)

    calls: list[int] = []
    real = _Ctx.fit_and_validate

    def counting(self: _Ctx, *args: Any, **kw: Any) -> Any:
        calls.append(1)
        return real(self, *args, **kw)

    monkeypatch.setattr(_Ctx, "fit_and_validate", counting)
    base_ms = np.ones(2) * 1e-12
    screened = _judge(cand, nominal, base_ms, [None, None], None, ctx, screen=True)
    assert len(calls) == 1 and screened.setting == 2
    calls.clear()
    refined = _judge(cand, nominal, base_ms, [None, None], None, ctx, screen=False)
    assert len(calls) == 3 and refined.setting == 2

    def fail(*_: object) -> None:
        raise RuntimeError("integrator failed")

    monkeypatch.setattr(FitProblem, "residuals_of", fail)
    assert ctx.best_start_setting(nominal, cand) == (1, 2, 3)


def test_refine_the_best_friction_model_outside_the_best_four() -> None:
    """The refits of a round: the best four screened candidates, and the best-screened
    friction-model candidate outside them (one at most; none without one, or when turned
    off)."""

    def ranked(*names: str) -> list[CandidateResult]:
        return [cast(CandidateResult, SimpleNamespace(effect=n, shrink=0.0)) for n in names]

    st = DiagnosisSettings()
    order = ranked(
        "backlash",
        "lugre",
        "drive_compliance",
        "computation_delay",
        "sensor_delay",
        "gms",
        "coulomb_viscous",
    )
    top4 = ["backlash", "lugre", "drive_compliance", "computation_delay"]
    assert refine_names(order, st) == [*top4, "gms"]
    assert refine_names(order, dc.replace(st, refine_best_friction_model=False)) == top4
    assert refine_names(order[:5], st) == top4
    assert refine_names(ranked("gms", "offset_force"), st) == ["gms", "offset_force"]


def test_a_refined_offset_or_asymmetry_refines_its_alias() -> None:
    """An offset force and an asymmetric friction are refined together: the one outside
    the best four joins when the other is among them (in either role), after the usual
    refits and once; neither joins when neither is refined, or when turned off."""

    def ranked(*names: str) -> list[CandidateResult]:
        return [cast(CandidateResult, SimpleNamespace(effect=n, shrink=0.0)) for n in names]

    st = DiagnosisSettings()
    rest = ["lugre", "drive_compliance", "backlash", "lead_periodic_friction", "sensor_delay"]
    order = ranked("offset_force", *rest[:3], "asymmetric_friction", *rest[3:])
    usual = ["offset_force", *rest[:3]]
    assert refine_names(order, st) == [*usual, "asymmetric_friction"]
    flipped = ranked("asymmetric_friction", *rest[:3], "offset_force", *rest[3:])
    assert refine_names(flipped, st) == ["asymmetric_friction", *rest[:3], "offset_force"]
    both = ranked("offset_force", "asymmetric_friction", *rest)
    assert refine_names(both, st) == ["offset_force", "asymmetric_friction", *rest[:2]]
    neither = ranked(*rest, "offset_force", "asymmetric_friction")
    assert refine_names(neither, st) == rest[:4]
    off = dc.replace(st, refine_bias_aliases=False)
    assert refine_names(order, off) == usual
    assert set(BIAS_ALIASES) <= set(CANDIDATES)


def test_a_calibration_at_its_bounds_refines_the_whole_lag_family() -> None:
    """With a free parameter of the model before at its bound, every lag-family candidate
    is refined too (after the usual ones, in screening order, none twice); without, or
    turned off, the refits are the usual ones."""

    def ranked(*names: str) -> list[CandidateResult]:
        return [cast(CandidateResult, SimpleNamespace(effect=n, shrink=0.0)) for n in names]

    order = ranked(
        "offset_force",
        "lugre",
        "drive_compliance",
        "dwell_static_friction",
        "stribeck",
        "amplifier_dynamics",
        "position_random_friction",
        "backlash",
        "computation_delay",
    )
    st = DiagnosisSettings()
    usual = ["offset_force", "lugre", "drive_compliance", "dwell_static_friction", "stribeck"]
    assert refine_names(order, st) == usual
    assert refine_names(order, st, lag_family=True) == [
        *usual,
        "amplifier_dynamics",
        "backlash",
        "computation_delay",
    ]
    off = dc.replace(st, refine_lag_family_at_bounds=False)
    assert refine_names(order, off, lag_family=True) == usual
    # A missed mark that a lag makes (or a calibration bent for one) triggers the same
    # refits, by its own switch.
    lag_marks = ["ramp_level_v"]
    assert refine_names(order, off, missed_marks=lag_marks) == refine_names(
        order, st, lag_family=True
    )
    no_marks = dc.replace(st, refine_on_missed_marks=False)
    assert refine_names(order, no_marks, missed_marks=lag_marks) == usual
    assert refine_names(order, no_marks, lag_family=True, missed_marks=lag_marks) == refine_names(
        order, st, lag_family=True
    )
    assert set(LAG_FAMILY) <= set(CANDIDATES)


def test_a_missed_mark_refines_the_effects_that_make_it() -> None:
    """Each missed mark calls for the candidates that make it: the mean command of the
    two directions (ramps, rest) for the offset force and the friction asymmetry, not the
    lag family; the rise of breakaway with rest for the dwell-dependent friction; the
    limit cycle, the ramps' level and the lost motion for the lag family. Every candidate
    named exists, and only candidates outside the usual refits are added, in screening
    order."""

    def ranked(*names: str) -> list[CandidateResult]:
        return [cast(CandidateResult, SimpleNamespace(effect=n, shrink=0.0)) for n in names]

    st = DiagnosisSettings(refine_top=2, refine_best_friction_model=False)
    order = ranked(
        "lugre",
        "stribeck",
        "amplifier_dynamics",
        "asymmetric_friction",
        "dwell_static_friction",
        "backlash",
        "offset_force",
    )
    usual = ["lugre", "stribeck"]
    for bias in BIAS_MARKS:
        assert mark_effects(bias) == BIAS_ALIASES
        assert refine_names(order, st, missed_marks=[bias]) == [
            *usual,
            "asymmetric_friction",
            "offset_force",
        ]
    assert mark_effects("breakaway_per_decade_v") == ("dwell_static_friction",)
    assert refine_names(order, st, missed_marks=["breakaway_per_decade_v"]) == [
        *usual,
        "dwell_static_friction",
    ]
    for lag_mark in ("hold_amplitude_m", "hold_frequency_hz", "ramp_level_v", "reversal_lag_m"):
        assert mark_effects(lag_mark) == LAG_FAMILY
    both = refine_names(order, st, missed_marks=["ramp_bias_v", "hold_amplitude_m"])
    assert both == [*usual, "amplifier_dynamics", "asymmetric_friction", "backlash", "offset_force"]
    # The same candidate for two marks is refitted once; at a bound the lag family joins.
    assert refine_names(order, st, lag_family=True, missed_marks=["ramp_bias_v"]) == both
    assert (
        refine_names(
            order, dc.replace(st, refine_on_missed_marks=False), missed_marks=["ramp_bias_v"]
        )
        == usual
    )
    # Every mark the signatures measure has its effects, and they are candidates.
    for mark in SIGNATURE_UNITS:
        assert set(mark_effects(mark)) <= set(CANDIDATES)
    assert set(BIAS_MARKS) | set(BREAKAWAY_MARKS) <= set(SIGNATURE_UNITS)


def test_the_lag_family_leaves_out_members_that_multiply_the_gap() -> None:
    """The lag family's extra refits leave out a member whose screened pooled validation
    gap is more than ``lag_refit_max_gap_ratio`` times the model before's (pooled shrink
    below 1 − ratio); the usual refits are never left out; ``inf`` refits every one; the
    report says which were left out."""

    def res(name: str, shrink: float) -> CandidateResult:
        return cast(CandidateResult, SimpleNamespace(effect=name, shrink=shrink))

    st = DiagnosisSettings(refine_top=2)
    order = [
        res("offset_force", 0.3),
        res("sensor_delay", -25.0),  # a usual refit: kept however bad
        res("amplifier_dynamics", -0.4),
        res("backlash", -1.9),  # 2.9× the gap before: within 3×
        res("computation_delay", -2.1),  # 3.1×: left out
        res("lugre", -30.0),  # no lag-family member
    ]
    assert hopeless_lag_refits(order, st) == ["computation_delay"]
    assert refine_names(order, st, missed_marks=["hold_amplitude_m"]) == [
        "offset_force",
        "sensor_delay",
        "lugre",
        "amplifier_dynamics",
        "backlash",
    ]
    every = dc.replace(st, lag_refit_max_gap_ratio=math.inf)
    assert hopeless_lag_refits(order, every) == []
    assert "computation_delay" in refine_names(order, every, lag_family=True)
    # Without a trigger the lag family is not refitted at all.
    assert refine_names(order, st) == ["offset_force", "sensor_delay", "lugre"]
    lines = _extra_refit_lines(
        [
            {
                "round": 1,
                "at_bounds": [],
                "missed_marks": ["ramp_level_v"],
                "refined": ["backlash"],
                "not_refined": ["computation_delay"],
            }
        ]
    )
    assert lines == [
        "Round 1: the model before misses the marks `ramp_level_v` (see *Signatures*), so the "
        "effects that make them were refitted with the free parameters too: `backlash` (not "
        "`computation_delay`: screened far worse than the model before).\n"
    ]


def test_benchmark_design_reference() -> None:
    """The benchmark's step sequences: a rest of each dwell before each step, then the hold;
    micro-steps start inside an encoder count."""
    ref = design_reference((3e-7, -3e-7), 1e-3 + MID_COUNT_M, (0.5, 0.05))
    assert len(ref) == 500 + 50 + round(MOVE_S / 1e-3)
    assert np.all(ref[:500] == 1e-3 + MID_COUNT_M)
    assert ref[500] == pytest.approx(1e-3 + MID_COUNT_M + 3e-7, abs=1e-15)
    assert np.all(ref[550:] == ref[0])
    with pytest.raises(ValueError, match="2 steps need 2 dwells"):
        design_reference((1e-6, 1e-6), 0.0, (0.1,))
    assert len(design_reference((3e-7,), 0.0, (0.5,), hold_s=0.8)) == 500 + 800
    for steps, x0, dwells, _role, gains, hold in DESIGN:
        assert len(steps) == len(dwells)
        assert 0.1 < (x0 / 1e-7) % 1.0 < 0.9  # mid-count starts
        if max(abs(s) for s in steps) < 1e-6:  # micro-steps: one per breakaway test
            assert gains == BREAKAWAY_GAINS and len(steps) == 1 and hold >= 0.5
    # Breakaway tests after at least three different dwells, in both directions.
    micro = [(d[0], s[0] > 0) for s, _x, d, _r, g, _h in DESIGN if g == BREAKAWAY_GAINS]
    assert len({d for d, _ in micro}) >= 3 and {up for _, up in micro} == {True, False}
    assert BREAKAWAY_GAINS[0] == 0.0 and BREAKAWAY_GAINS[2] == 0.0 < BREAKAWAY_GAINS[1]


def test_breakaway_tests_carry_the_dwell_signature_above_the_scatter() -> None:
    """The benchmark's integral-only micro-steps: a static friction rising with the dwell
    changes the response several times more than two stochastic friction draws differ, and
    the ratio is far better than under the Table 1 gains (whose response with a dwell is
    itself chaotic)."""
    base = presets.seed(1e-3)
    fs = motor_static_force_n(base)
    noisy = dc.replace(
        base,
        effects=Effects(
            stochastic=StochasticFriction(level_spread=0.005),
            encoder_errors=EncoderErrors(noise_std_m=5e-9),
        ),
    )
    dwell = dc.replace(
        noisy,
        effects=dc.replace(
            noisy.effects,
            motor_friction=FrictionModifiers(
                dwell=DwellStaticFriction(rise_n=3 * fs, time_constant_s=0.3)
            ),
        ),
    )
    x0 = 22.3e-3 + MID_COUNT_M
    refs = [design_reference((3e-7,), x0, (d,), hold_s=0.8) for d in (0.05, 0.3, 1.5)]

    def runs(s: System, gains: tuple[float, float, float], seed: int) -> np.ndarray:
        g = presets.with_gains(s, kp=gains[0], ki=gains[1], kd=gains[2])
        return np.concatenate(
            [simulate(g, r, seed=seed, initial_position_m=x0).encoder_position_m for r in refs]
        )

    def rms(a: np.ndarray, b: np.ndarray) -> float:
        return float(np.sqrt(np.mean((a - b) ** 2)))

    # Signal over scatter, the scatter of two friction draws with and without the dwell.
    ratio = {}
    for gains in (BREAKAWAY_GAINS, presets.table1_gains(100e-6)):
        scatter = max(
            rms(runs(noisy, gains, 1), runs(noisy, gains, 2)),
            rms(runs(dwell, gains, 1), runs(dwell, gains, 2)),
        )
        ratio[gains] = rms(runs(dwell, gains, 1), runs(noisy, gains, 1)) / scatter
    assert ratio[BREAKAWAY_GAINS] > 3.0
    assert ratio[BREAKAWAY_GAINS] > 1.5 * ratio[presets.table1_gains(100e-6)]


def test_one_step_breakaway_tests_make_the_dwell_gap_a_valley() -> None:
    """With one micro-step per breakaway test, the gap of a dwell model over its rise is a
    plateau below the truth's, a valley at it and a steady rise above (in a chain of steps
    each breakaway starts where the last landed, and the gap was a needle a few per cent
    wide amid peaks)."""
    base = presets.seed(1e-3)
    fs = motor_static_force_n(base)
    g = BREAKAWAY_GAINS
    x0 = 22.3e-3 + MID_COUNT_M
    q = base.encoder.count_m

    def with_dwell(s: System, rise_n: float) -> System:
        fx = dc.replace(
            s.effects,
            motor_friction=FrictionModifiers(
                dwell=DwellStaticFriction(rise_n=rise_n, time_constant_s=0.3)
            ),
        )
        return presets.with_gains(dc.replace(s, effects=fx), kp=g[0], ki=g[1], kd=g[2])

    truth = with_dwell(
        dc.replace(base, effects=Effects(encoder_errors=EncoderErrors(noise_std_m=5e-9))), 3 * fs
    )
    refs = [design_reference((3e-7,), x0, (d,), hold_s=0.8) for d in (0.05, 0.3, 1.5)]
    measured = [simulate(truth, r, seed=3, initial_position_m=x0).encoder_position_m for r in refs]

    def gap(rise_n: float) -> float:
        s = with_dwell(base, rise_n)
        res = [
            # Measured against the mean reading (half a count below the true position).
            gap_residual(m, simulate(s, r, initial_position_m=x0).position_m - q / 2, r)
            for m, r in zip(measured, refs, strict=True)
        ]
        return float(np.sqrt(np.mean([np.mean(x**2) for x in res])))

    below = [gap(f * 3 * fs) for f in (0.3, 0.6, 0.8, 0.9)]
    above = [gap(f * 3 * fs) for f in (1.1, 1.25, 1.5, 2.0)]
    at = gap(3 * fs)
    # A plateau below (too little rise changes little), a valley at the truth, a steady rise
    # above (every breakaway too late).
    assert all(b > 2 * at for b in below)
    assert at < above[0] < above[1] < above[2] < above[3]
    assert above[0] > 2 * at


def test_hold_intervals_and_phase_insensitive_gap() -> None:
    ref = np.zeros(400)
    ref[50:] = 1e-4
    assert hold_intervals(ref) == [(0, 50), (50, 400)]
    t = np.arange(400)
    # A limit cycle around the target, measured and simulated with different phases.
    meas = np.where(t >= 80, 1e-4 + 2e-6 * np.sin(2 * np.pi * t / 40), t / 80 * 1e-4)
    sim = np.where(t >= 80, 1e-4 + 2e-6 * np.sin(2 * np.pi * t / 40 + 1.3), t / 80 * 1e-4)
    r = gap_residual(meas, sim, ref)
    assert np.sqrt(np.mean((meas - sim)[200:] ** 2)) > 1e-6  # sample by sample: large
    assert np.max(np.abs(r[200:])) < 1e-7  # as distributions: equal
    # A different amplitude is still seen.
    r2 = gap_residual(meas, np.where(t >= 80, 1e-4 + 1e-6 * np.sin(2 * np.pi * t / 40), sim), ref)
    assert np.sqrt(np.mean(r2[200:] ** 2)) > 5e-7


def test_a_hunting_ramp_compares_its_tracking_errors_as_distributions() -> None:
    """A slow ramp (20 µm/s over 1 s) whose tracking error hunts by ±20 counts: the same
    hunting in another phase leaves under a count RMS on the ramp (sorted tracking errors), a model
    that tracks without hunting leaves the cycle's RMS, and a cycle half as large shows.
    A ramp whose error does not hunt (a steady lag of 3 counts, reading noise of one
    count; a ringing that dies out) is compared sample by sample."""
    q = 1e-7
    t = np.arange(1100)
    ref = np.where(t < 50, 0.0, np.minimum(t - 49, 1000) * 2e-8)
    assert hunting_ramps(ref, ref, q) == []

    def hunting(amplitude_m: float, phase: float) -> np.ndarray:
        e = np.where((t >= 60) & (t < 1050), amplitude_m * np.sin(2 * np.pi * t / 25 + phase), 0)
        return np.round((ref + e) / q) * q

    meas = hunting(2e-6, 0.0)
    assert hunting_ramps(meas, ref, q) == [(50, 1050)]
    r = gap_residual(meas, hunting(2e-6, 2.0), ref)
    plain = hunting(2e-6, 2.0)
    assert np.sqrt(np.mean((meas - plain)[60:1050] ** 2)) > 1.5e-6  # sample by sample
    assert np.sqrt(np.mean(r[60:1050] ** 2)) < q  # as distributions: equal within a count
    tracking = np.round(ref / q) * q
    assert np.sqrt(np.mean(gap_residual(meas, tracking, ref)[60:1050] ** 2)) > 1.3e-6
    half = gap_residual(meas, hunting(1e-6, 2.0), ref)
    assert np.sqrt(np.mean(half[60:1050] ** 2)) > 6e-7
    rng = np.random.default_rng(4)
    lagging = np.round((ref - 3 * q + q * rng.integers(-1, 2, t.size)) / q) * q
    assert hunting_ramps(lagging, ref, q) == []
    # A ringing of ±8 counts after the ramp's start that dies out (time constant 400
    # samples) is a transient, compared sample by sample.
    ring = np.where(t >= 50, 8e-7 * np.exp(-(t - 50) / 400) * np.sin(2 * np.pi * t / 25), 0)
    assert hunting_ramps(np.round((ref + ring) / q) * q, ref, q) == []
    assert np.array_equal(gap_residual(lagging, tracking, ref), lagging - tracking)


def test_the_hold_after_a_hunting_ramp_is_compared_about_its_own_level() -> None:
    """A ramp whose tracking error hunts (±20 counts) stops where the cycle left the axis:
    in the hold after it, a model that sticks 7 counts higher, with the same creep, leaves
    no gap there (each signal less its own mean over the hold), while a creep twice as
    large shows. After a ramp that tracks without hunting, the same offset is a gap: that
    hold is compared as before (its sorted values, level included)."""
    q = 1e-7
    t = np.arange(1400)
    ref = np.where(t < 50, 0.0, np.minimum(t - 49, 1000) * 2e-8)
    # The hold's first sample (1049) ends the ramp: the axis is stuck from there on.
    creep = np.where(t >= 1049, 2.4e-7 * (t - 1049) / 351, 0.0)

    def run(amplitude_m: float, stuck_m: float, creep_scale: float = 1.0) -> np.ndarray:
        e = np.where((t >= 60) & (t < 1049), amplitude_m * np.sin(2 * np.pi * t / 25), 0.0)
        e = e + np.where(t >= 1049, stuck_m + creep_scale * creep, 0.0)
        return np.round((ref + e) / q) * q

    meas = run(2e-6, 3e-7)
    assert hunting_ramps(meas, ref, q) == [(50, 1050)]
    hold = slice(1052, 1400)
    assert np.max(np.abs(gap_residual(meas, run(2e-6, 1e-6), ref)[hold])) < 1e-3 * q
    assert np.sqrt(np.mean(gap_residual(meas, run(2e-6, 3e-7, 3.0), ref)[hold] ** 2)) > 0.8 * q
    # The hold's level still counts after a ramp that does not hunt.
    smooth = run(0.0, 3e-7)
    assert hunting_ramps(smooth, ref, q) == []
    offset = gap_residual(smooth, run(0.0, 1e-6), ref)[hold]
    assert np.sqrt(np.mean(offset**2)) > 6e-7
    # The command's plan carries the same treatment: a command held at another level
    # after the hunting ramp leaves no gap in that hold.
    cmd = np.where(t >= 1049, 0.4, 0.0) + 0.01 * np.sin(t / 7.0)
    cplan = command_plan(gap_plan(meas, ref), cmd)
    assert (
        np.max(np.abs(apply_gap_plan(cplan, cmd, cmd + np.where(t >= 1049, -0.3, 0.0))[hold]))
        < 1e-12
    )


def test_best_shift_is_the_cheapest_clamped_shift() -> None:
    """The time shift of a move out of a hunting hold (vectorised over the shifts) against
    the definition, one shift at a time: the clamped shift of least squared difference;
    no shift wins a tie, then the most negative one. Records with exact ties (quantised,
    noise-free copies) included."""
    rng = np.random.default_rng(3)
    for trial in range(400):
        n = int(rng.integers(20, 800))
        a = int(rng.integers(0, n - 1))
        h = int(rng.integers(a + 1, n + 1))
        s = np.round(np.cumsum(rng.normal(size=n)) * 3) * 1e-8
        m = np.roll(s, int(rng.integers(-60, 60))) + (0 if trial % 2 else 1e-9) * rng.normal(size=n)
        w = int(rng.integers(0, 60))
        best, best_cost = s[a:h], float(np.sum((m[a:h] - s[a:h]) ** 2))
        for shift in range(-w, w + 1):
            cand = s[np.clip(np.arange(a, h) + shift, 0, n - 1)]
            cost = float(np.sum((m[a:h] - cand) ** 2))
            if cost < best_cost:
                best, best_cost = cand, cost
        assert np.array_equal(_best_shift(m, s, a, h, w), best), trial


def test_a_move_out_of_a_hunting_hold_is_compared_at_its_best_phase() -> None:
    """After a hold that ends unsettled (hunting by many counts), the next move starts from
    the phase of the oscillation: its transient is compared after the best small time
    shift. After a settled hold the same delay is a gap."""
    q = 1e-7
    n = 600
    t = np.arange(n)
    ref = np.where(t < 20, 0.0, np.where(t < 300, 2e-4, 0.0))

    def response(delay: int, hunting_m: float) -> np.ndarray:
        # Rise to 200 µm, hunt until the move back starts (``delay`` samples after the
        # reference), fall in 20 samples, rest.
        rise = np.clip((t - 20) / 20, 0.0, 1.0) * 2e-4
        fall = 2e-4 * (1.0 - np.clip((t - 300 - delay) / 20, 0.0, 1.0))
        x = np.where(t < 300 + delay, rise, fall)
        hunt = (t >= 60) & (t < 300 + delay)
        x[hunt] += hunting_m * np.sin(2 * np.pi * t[hunt] / 20)
        return np.round(x / q) * q

    for hunting_m in (1.6e-5, 0.0):
        meas = response(7, hunting_m)
        sim = response(0, hunting_m)
        r = gap_residual(meas, sim, ref)
        move = float(np.sqrt(np.mean(r[300:330] ** 2)))
        plain = float(np.sqrt(np.mean((meas - sim)[300:330] ** 2)))
        if hunting_m > 0:
            assert move < 0.3 * plain  # aligned: left, the hunting over the 7 samples
        else:
            assert move == plain > 2e-5  # settled: a delay of seven samples is a gap
    # A reference that never moves (an open-loop pulse test): sample by sample throughout.
    flat = np.zeros(n)
    meas, sim = response(7, 1.6e-5), response(0, 1.6e-5)
    assert np.array_equal(gap_residual(meas, sim, flat), meas - sim)


def test_move_units_cut_an_experiment_into_its_moves() -> None:
    """The bootstrap's units: one per move (the rest before the first move belongs to it);
    a reference that never settles anew is one unit; the units' shares sum to the mean
    square."""
    ref = design_reference((1e-4, -1e-4, 3e-7), 0.0, (0.05, 0.3, 0.3))
    units = move_units(ref)
    assert units == [(0, 350), (350, 650), (650, len(ref))]
    assert move_units(np.zeros(100)) == [(0, 100)]
    ramp = np.r_[np.linspace(0.0, 1e-4, 200), np.full(100, 1e-4)]
    assert move_units(ramp) == [(0, 300)]
    r = np.random.default_rng(1).normal(size=len(ref))
    shares = [float(np.sum(r[a:b] ** 2)) / len(r) for a, b in units]
    assert sum(shares) == pytest.approx(float(np.mean(r**2)), rel=1e-12)


def test_noise_floor_sees_quantisation_noise_and_repeats() -> None:
    q = 1e-7
    ref = np.zeros(500)
    ref[100:] = 1e-4
    t = np.arange(500) * 1e-3
    rng = np.random.default_rng(0)
    clean = Experiment(name="a", time_s=t, reference_m=ref, position_m=np.floor(ref / q) * q)
    assert noise_floor_m([clean], q) == pytest.approx(q / np.sqrt(12))
    noisy = [
        Experiment(
            name=f"n{i}",
            time_s=t,
            reference_m=ref,
            position_m=ref + rng.normal(0, 2e-7, 500),
        )
        for i in range(2)
    ]
    floor = noise_floor_m(noisy, q)
    assert 2e-7 < floor < 4e-7  # white noise 2e-7, repeats differ by √2·2e-7
    # The same step elsewhere on the travel is not a repeat (position-dependent friction
    # makes it differ): two runs that differ by a slow drift count only at the same place.
    drift = 3e-7 * np.sin(np.arange(500) / 40)
    here = Experiment(name="h", time_s=t, reference_m=ref, position_m=np.floor(ref / q) * q)
    there = Experiment(
        name="t", time_s=t, reference_m=ref + 5e-3, position_m=np.floor((ref + drift) / q) * q
    )
    again = Experiment(
        name="r", time_s=t, reference_m=ref, position_m=np.floor((ref + drift) / q) * q
    )
    assert noise_floor_m([here, there], q) == pytest.approx(q / np.sqrt(12))
    assert noise_floor_m([here, again], q) > 3 * q / np.sqrt(12)
    # Several pairs: the mean of their spreads (mean squares), as the gap averages.
    quiet = [
        Experiment(name=f"q{i}", time_s=t, reference_m=ref + 9e-3, position_m=ref + 9e-3)
        for i in range(2)
    ]
    one = noise_floor_m([here, again], q) ** 2
    assert noise_floor_m([here, again, *quiet], q) ** 2 == pytest.approx(
        max(q**2 / 12, one / 2), rel=1e-9
    )


def test_noise_floor_ignores_the_phase_of_a_limit_cycle_in_repeats() -> None:
    """Two repeats that hunt around the target with the same amplitude but another phase are
    not scattered in the gap's sense (holds are compared as sorted values), so the floor
    stays at the quantisation level; a different amplitude still counts."""
    q = 1e-7
    t = np.arange(600)
    ref = np.where(t >= 100, 1e-4, 0.0)
    ramp = np.clip((t - 100) / 50, 0, 1) * 1e-4

    def run(phase: float, amp: float) -> Experiment:
        hunt = np.where(t >= 150, amp * np.sign(np.sin(2 * np.pi * t / 30 + phase)), 0.0)
        x = np.floor((ramp + hunt) / q) * q
        return Experiment(name=f"r{phase}", time_s=t * 1e-3, reference_m=ref, position_m=x)

    same = noise_floor_m([run(0.0, 4e-7), run(1.7, 4e-7)], q)
    # Sample by sample the two differ by 8e-7 m in about half the hold: ≈ 3.5e-7 m of
    # scatter. As distributions they differ only in the few samples the phase shifts
    # between the ends of the hold.
    assert same < 0.6e-7
    other = noise_floor_m([run(0.0, 4e-7), run(1.7, 1e-6)], q)
    assert other > 2e-7


def _case(tmp_path: Path, effects: Effects, seed: int) -> Path:
    """Four seed-axis experiments (both directions), two train, two validate."""
    return step_case(tmp_path, effects, seed)


FAST = DiagnosisSettings(n_starts_nominal=1, n_starts_candidate=1, forward_rounds=2)


def test_diagnosis_finds_a_hidden_asymmetry(tmp_path: Path) -> None:
    # An offset force is left out: on these few large steps it mimics the asymmetry (an
    # offset shifts the static and the sliding level by the same force, the asymmetry by
    # 0.3 of each, which differ by 20 %), and which of the two wins is a coin toss.
    m = _case(tmp_path, Effects(motor_friction=FrictionModifiers(asymmetry=0.3)), seed=3)
    m.write_text(m.read_text(encoding="utf-8").replace('"offset_force", ', ""))
    d = diagnose(m, tmp_path / "out", settings=FAST, progress=False, figures=False)
    r = d.report
    assert r["selected"] == ["asymmetric_friction"]
    best = r["candidates"][0]
    assert best["effect"] == "asymmetric_friction" and best["significant"]
    assert best["shrink"] > 0.5
    # The candidate has an asymmetry of the motor map and one of the table's Dahl law. Large
    # steps alone show what they do together while sliding: a force bias of a_m·F_m + a_t·F_t
    # at the table (F_m the motor map's Coulomb torque there, F_t the Dahl level), which
    # the truth has as 0.3·F_m (its asymmetry sits in the motor map).
    nominal = ns.presets.seed(1e-3)
    plant = nominal.plant
    f_m = (
        plant.gearhead.efficiency
        * plant.screw.efficiency
        * plant.motor_friction.coulomb_torque_nm
        / plant.transmission_m_per_rad
    )
    f_t = plant.dahl.coulomb_force_n
    a_m = best["parameters"]["asymmetric_friction.asymmetry"]["value"]
    a_t = best["parameters"]["asymmetric_friction.table_asymmetry"]["value"]
    assert a_m * f_m + a_t * f_t == pytest.approx(0.3 * f_m, rel=0.25)
    # Its Occam factor (the tie-break): at most 1, and 1 only if the data pinned nothing.
    assert best["log_occam_factor"] < 0.0
    assert r["gap_after"]["total_rms_m"] < 0.5 * r["gap_before"]["total_rms_m"]
    # The gap of a given model, nothing fitted, is the report's measure: the selected model
    # (one fold) gives gap_after exactly; the truth itself leaves only the noise.
    assert model_gap(m, d.model)["total_rms_m"] == r["gap_after"]["total_rms_m"]
    truth = dc.replace(
        ns.presets.seed(1e-3), effects=Effects(motor_friction=FrictionModifiers(asymmetry=0.3))
    )
    assert model_gap(m, truth)["total_rms_m"] < 0.5 * r["gap_before"]["total_rms_m"]
    # The same measure of mean readings simulated elsewhere (readings_gap, for a truth that
    # is not a nanostage model): the truth's readings of the validation experiments, each
    # with its own controller, give model_gap's value to the last bit.
    mm = load_manifest(m)
    val = [(spec, e) for spec, e in mm.experiments() if spec.role == "validate"]
    sims = simulate_readings_and_commands(
        [dc.replace(mm.system(spec), effects=truth.effects) for spec, _ in val],
        [e for _, e in val],
    )
    readings = {e.name: reading for (_, e), (reading, _) in zip(val, sims, strict=True)}
    assert readings_gap(m, readings)["total_rms_m"] == model_gap(m, truth)["total_rms_m"]
    name = val[0][1].name
    with pytest.raises(ValueError, match=f"no reading for validation experiment.*{name}"):
        readings_gap(m, {k: v for k, v in readings.items() if k != name})
    with pytest.raises(ValueError, match=f"readings\\['{name}'\\]: 3 values"):
        readings_gap(m, {**readings, name: np.zeros(3)})
    # The model file of the selected model: loaded and simulated on the validation
    # experiments, it gives gap_after to the last bit; it carries the selected effects.
    assert r["model_file"] == "model.toml"
    doc = ns.load_model_file(tmp_path / "out" / "model.toml")
    assert doc.system == d.model
    assert model_gap(m, doc.system)["total_rms_m"] == r["gap_after"]["total_rms_m"]
    assert doc.provenance["selected_effects"] == r["selected"]
    assert doc.provenance["gap_after_rms_m"] == r["gap_after"]["total_rms_m"]
    assert doc.provenance["gap_before_rms_m"] == r["gap_before"]["total_rms_m"]
    assert doc.provenance["command"] == "nanostage diagnose"
    assert doc.provenance["manifest"] == str(m)
    # Both asymmetries land in the model file at their fitted values, with their errors
    # and bounds.
    asym = doc.identified["effects.motor_friction.asymmetry"]
    table = doc.identified["plant.dahl.asymmetry"]
    assert doc.system.effects.motor_friction.asymmetry == a_m
    assert doc.system.plant.dahl.asymmetry == a_t
    assert asym.std_error is not None and asym.std_error > 0
    assert table.std_error is not None and table.std_error > 0
    assert (asym.lower, asym.upper) == (table.lower, table.upper) == (-0.6, 0.6)
    for path, par in r["selected_model_parameters"].items():
        assert get_path(doc.system, path) == par["value"]
        assert doc.identified[path].std_error == par["std_error"]
    # Cross-fit: every validation experiment judged once, by models that never saw it.
    cf = r["crossfit"]
    val_names = r["folds"][0]["validate"]
    assert sorted(n for judged in cf["judged"] for n in judged) == sorted(val_names)
    assert cf["folds"] == min(FAST.crossfit_folds, len(val_names))
    assert cf["gap_after_rms_m"] < 0.5 * cf["gap_before_rms_m"]
    assert cf["shrink"] == pytest.approx(1.0 - cf["gap_after_rms_m"] / cf["gap_before_rms_m"])
    on_disk = json.loads((tmp_path / "out" / "report.json").read_text(encoding="utf-8"))
    for key in ("gap_before", "candidates", "selected", "gap_after", "crossfit"):
        assert key in on_disk
    assert {"total_rms_m", "by_segment"} <= set(on_disk["gap_before"])
    md = (tmp_path / "out" / "report.md").read_text(encoding="utf-8")
    assert "asymmetric_friction" in md
    assert f"| shrink | {cf['shrink']:.1%} |" in md
    # Every candidate parameter has its unit; the evidence repeats the selected effect's
    # identified parameters (from its round's fit), and the readable report shows them.
    assert all(d["unit"] for c in r["candidates"] for d in c["parameters"].values()), r[
        "candidates"
    ]
    ev = r["evidence"][0]
    assert (ev["round"], ev["effect"]) == (1, "asymmetric_friction")
    assert ev["parameters"] == best["parameters"] and ev["shrink"] == best["shrink"]
    value = best["parameters"]["asymmetric_friction.asymmetry"]["value"]
    assert "### 1. `asymmetric_friction` (round 1)" in md
    # Its round was cross-judged and selected it by its results on every experiment: the
    # evidence says why in those terms first, then the validation experiments' alone.
    assert r["cross_judged"][0]["candidates"][0]["effect"] == "asymmetric_friction"
    assert ev["why"][0].startswith("judged on every experiment: validation gaps")
    assert any(w.startswith("on the validation experiments alone: ") for w in ev["why"])
    assert f"- {ev['why'][0]}" in md
    assert f"| `asymmetric_friction.asymmetry` | {value:.4g} |" in md
    assert "## Experiment advice" in md and "## Forward selection" in md
    # The free nominal parameters alone and refitted with the selected effect.
    assert set(r["selected_model_parameters"]) == set(r["nominal_parameters"]) != set()
    assert "| with the selected effects |" in md
    # Signatures: measured on all four experiments (no command: the hold features only),
    # simulated by the nominal, the selected model and the selected candidate's fit, whose
    # model is the selected one (one effect: the same system, the same features).
    sig = r["signatures"]
    assert sorted(sig["experiments"]) == ["e0", "e1", "e2", "e3"]
    assert set(sig["measured"]) == {"hunting_fraction"} | (
        {"hold_amplitude_m", "hold_frequency_hz"}
        if sig["measured"]["hunting_fraction"]["value"]
        else set()
    )
    rows = {(m["model"], m["effect"]): m for m in sig["models"]}
    assert set(rows) == {
        ("nominal", None),
        ("selected model", None),
        ("candidate", "asymmetric_friction"),
    }
    assert all(m["distance"] >= 0.0 for m in rows.values())
    assert "## Signatures, measured vs models" in md and "| χ² from measured | 0 |" in md


def test_indistinguishable_candidates_are_reported_as_ties() -> None:
    def res(name: str, ms: list[float], significant: bool = True) -> CandidateResult:
        a = np.array(ms)
        return cast(
            CandidateResult,
            SimpleNamespace(
                effect=name,
                validation_ms=a,
                log_ms=np.log(a),
                validation_rms_m=float(np.sqrt(a.mean())),
                significant=significant,
            ),
        )

    best = res("asymmetric_friction", [1.0e-14, 2.0e-14, 1.5e-14, 1.2e-14])
    same = res("offset_force", [1.2e-14, 1.8e-14, 1.6e-14, 1.1e-14])
    worse = res("backlash", [4.0e-14, 5.0e-14, 4.5e-14, 4.2e-14])
    noisy_but_insignificant = res("gms", [1.1e-14, 2.0e-14, 1.5e-14, 1.2e-14], False)
    rounds = [[best, same, noisy_but_insignificant, worse]]
    for ranking in RANKINGS:
        assert indistinguishable(best, same, ranking) and indistinguishable(same, best, ranking)
        assert not indistinguishable(best, worse, ranking)
        assert ties_of_selected(rounds, ["asymmetric_friction"], ranking) == {
            "asymmetric_friction": ["offset_force"]
        }
        assert ties_of_selected(rounds, [], ranking) == {}
    # The best single effect is the first selection's, also when another candidate of its
    # round has a smaller validation gap (a tie decided by the Occam factor); with nothing
    # selected, the smallest gap.
    rounds = [[same, best, worse]]
    assert best_single(rounds[0], ["asymmetric_friction", "backlash"]) is best
    assert best_single(rounds[0], []) is same
    assert best_single([], []) is None


def test_the_relative_ranking_counts_no_gap_below_its_floor() -> None:
    """A change of an experiment's gap below its noise floor neither ranks nor ties: with
    the floors known, two micro-steps at 5 and 25 nm under a 29 nm floor count alike, and
    the candidate that cuts the loud experiments tenfold ranks first and is told apart;
    without them, the fivefold change below the floor would have put it behind."""
    floor_ms = np.full(4, (29e-9) ** 2)

    def res(name: str, rms_nm: list[float], floors: np.ndarray | None) -> CandidateResult:
        ms = (np.asarray(rms_nm) * 1e-9) ** 2
        return candidate_result(name, list(ms), rms_m=float(np.sqrt(ms.mean())), floor_ms=floors)

    for floors in (floor_ms, None):
        cut = res("offset_force", [420.0, 25.0, 71.0, 26.0], floors)
        flat = res("voltage_saturation", [4238.0, 5.0, 115.0, 4.0], floors)
        key = rank_key("relative")
        if floors is not None:
            assert key(cut) < key(flat)
            assert not indistinguishable(cut, flat, "relative")
            # Both micro-steps at the floor: the geometric gap counts each as 29 nm.
            g = (420.0 * 29.0 * 71.0 * 29.0) ** 0.25 * 1e-9
            assert cut.geometric_rms_m == pytest.approx(g, rel=1e-12)
        else:
            assert key(cut) > key(flat)
    # Below the floor everywhere, two candidates are the same.
    a = res("a", [5.0, 6.0, 7.0, 8.0], floor_ms)
    b = res("b", [20.0, 25.0, 10.0, 28.0], floor_ms)
    assert a.mean_log_ms == b.mean_log_ms and indistinguishable(a, b, "relative")


def test_log_occam_factor_by_hand() -> None:
    """½ Σ log min(1, 2πλ) over the eigenvalues λ of the marginal covariance of the
    candidate's own parameters in normalised coordinates (bounds span 1), minus log of the
    settings of a discrete candidate: σ√(2π) per uncorrelated parameter, 2πσ₁σ₂√(1−ρ²) for
    two correlated ones; a parameter the data do not constrain (variance 0 or ∞) or a
    direction wider than the bounds costs nothing; the nominal parameters do not count."""
    r2pi = np.sqrt(2 * np.pi)
    s_f, s_w, s_n, rho = 0.015 / 60.0, 0.004, 0.02, -0.9
    cov = np.diag([s_n**2, s_f**2, s_w**2, 0.0, 4.0])
    cov[0, 1] = cov[1, 0] = 0.5 * s_n * s_f  # nominal ↔ f: marginalised away

    def fit_with(c: np.ndarray) -> Fit:
        return Fit(
            values={"nominal.k": 1.0, "x.f": 1.2, "x.w": 2e-5, "x.u": 0.3, "x.a": 0.1},
            std_errors={},
            train_rms_m=1e-8,
            n_evaluations=1,
            system=presets.seed(1e-3),
            unit_covariance=c,
        )

    fit = fit_with(cov)
    one = log_occam_factor(fit, ["x.f"])
    assert one == pytest.approx(np.log(s_f * r2pi))
    assert log_occam_factor(fit, ["x.w"]) == pytest.approx(np.log(s_w * r2pi))
    assert log_occam_factor(fit, ["x.u", "x.a"]) == 0.0
    assert log_occam_factor(fit, [], n_settings=4) == pytest.approx(-np.log(4))
    both = log_occam_factor(fit, ["x.f", "x.w", "x.u"])
    assert both == pytest.approx(one + np.log(s_w * r2pi))
    # Correlated: the posterior is thinner than its standard errors say.
    cor = cov.copy()
    cor[1, 2] = cor[2, 1] = rho * s_f * s_w
    both_cor = log_occam_factor(fit_with(cor), ["x.f", "x.w"])
    assert both_cor == pytest.approx(np.log(2 * np.pi * s_f * s_w * np.sqrt(1 - rho**2)))
    assert both_cor < both
    # A principal direction wider than the bounds counts as the whole range: a fully
    # correlated pair of wide parameters costs only its narrow direction.
    wide = np.diag([1.0, 0.5, 0.5, 0.0, 0.0])
    wide[1, 2] = wide[2, 1] = 0.5 - 1e-6  # eigenvalues 1 − 1e-6 and 1e-6
    assert log_occam_factor(fit_with(wide), ["x.f", "x.w"]) == pytest.approx(
        0.5 * np.log(2 * np.pi * 1e-6)
    )
    # No covariance (a failed inversion): nothing but the discrete settings.
    assert log_occam_factor(fit_with(np.zeros((0, 0))), ["x.f"], 3) == -np.log(3)


def test_a_tie_goes_to_the_candidate_with_the_larger_occam_factor() -> None:
    """Among significant candidates the validation data cannot tell apart the larger Occam
    factor wins, whatever the order of their gaps; a clearly better gap, an insignificant
    candidate and the setting turned off keep the first significant one."""

    def res(name: str, ms: list[float], occam: float, significant: bool = True) -> Any:
        a = np.array(ms)
        return SimpleNamespace(
            effect=name,
            validation_ms=a,
            log_ms=np.log(a),
            validation_rms_m=float(np.sqrt(a.mean())),
            significant=significant,
            log_occam=occam,
        )

    best = res("offset_force", [1.0e-14, 2.0e-14, 1.5e-14, 1.2e-14], -7.4)
    tied = res("asymmetric_friction", [1.2e-14, 1.8e-14, 1.6e-14, 1.1e-14], -4.9)
    far = res("backlash", [4.0e-14, 5.0e-14, 4.5e-14, 4.2e-14], -1.0)
    weak = res("gms", [1.1e-14, 2.0e-14, 1.5e-14, 1.2e-14], -0.5, significant=False)
    st = DiagnosisSettings()
    assert pick_winner([best, tied, far], st) is tied
    assert pick_winner([best, weak, far], st) is best
    assert pick_winner([weak, best, tied], st) is tied
    assert pick_winner([best, far], st) is best
    assert pick_winner([best, tied, far], dc.replace(st, occam_tie_break=False)) is best
    equal = res("stribeck", list(best.validation_ms), best.log_occam)
    assert pick_winner([best, equal], st) is best
    assert pick_winner([weak], st) is None


def test_refit_control_restarts_the_model_before_from_a_candidates_free_values() -> None:
    """Refitting alone: when the model before, refitted from a significant candidate's free
    values, fits the training data better and the validation data no worse, that fit is the
    new baseline; a better-training refit that predicts validation worse is recorded, not
    adopted. The warm starts are restored either way, and insignificant candidates are not
    used."""
    free = [("plant.dahl.coulomb_force_n", Param(name="f", unit="N", lower=1, upper=9, initial=5))]
    landscape = {5.0: 2e-8, 3.0: 1e-8, 7.0: 3e-8, 2.0: 0.5e-8}  # training RMS at a start
    # Validation RMS at a start: the 2.0 basin fits training best and validates worst.
    validation = {5.0: 2e-8, 3.0: 1e-8, 7.0: 3e-8, 2.0: 4e-8}

    def fit_of(v: float) -> Fit:
        return cast(Fit, SimpleNamespace(values={free[0][0]: v}, train_rms_m=landscape[v]))

    calls: list[float] = []

    def fit_and_validate(
        *_: object,
    ) -> tuple[list[Fit], np.ndarray, list[object], list[None], np.ndarray]:
        v = ctx.warm[0][free[0][0]]
        calls.append(v)
        ms = np.array([validation[v] ** 2])
        return [fit_of(v)], ms, [], [None], ms

    ctx = SimpleNamespace(
        st=DiagnosisSettings(refit_control_top=2),
        free=free,
        warm=[{free[0][0]: 5.0}],
        fit_and_validate=fit_and_validate,
        validation_weights=np.ones(1),
        n_validation=1,
        floor=1e-9,
    )

    def result(name: str, v: float, significant: bool) -> CandidateResult:
        return cast(
            CandidateResult,
            SimpleNamespace(effect=name, fold_fits=[fit_of(v)], significant=significant),
        )

    def control(results: list[CandidateResult], rnd: int = 1) -> tuple[Any, list[dict[str, Any]]]:
        return _refit_control(cast(Any, ctx), ns.presets.seed(), results, current, ms, rnd, False)

    current = [fit_of(5.0)]
    ms = np.array([4e-16])
    worse = [result("a", 7.0, True), result("b", 5.0, True)]
    assert control(worse, 0) == (None, [])
    assert ctx.warm == [{free[0][0]: 5.0}] and calls == [7.0, 5.0]
    calls.clear()
    mixed = [result("c", 3.0, False), result("d", 7.0, True), result("e", 3.0, True)]
    out, records = control(mixed)
    assert out is not None and calls == [7.0, 3.0]
    fits, new_ms, _, units = out
    assert units[0] == new_ms[0]
    assert fits[0].train_rms_m == 1e-8 and new_ms[0] == pytest.approx(1e-16)
    [record] = records
    assert record["restarted_from"] == "e" and record["round"] == 2 and record["adopted"]
    assert record["train_rms_after_m"] < record["train_rms_before_m"]
    assert record["validation_shrink"] == pytest.approx(0.5)
    assert ctx.warm == [{free[0][0]: 5.0}]
    # Better in training, worse in validation: recorded, not the baseline; a refit that is
    # better in both is adopted beside it, although it trains less well.
    out, records = control([result("p", 2.0, True)])
    assert out is None and [r["adopted"] for r in records] == [False]
    assert records[0]["validation_shrink"] == pytest.approx(-1.0)
    assert records[0]["validation_rms_after_m"] > records[0]["validation_rms_before_m"]
    out, records = control([result("p", 2.0, True), result("q", 3.0, True)])
    assert out is not None and out[0][0].train_rms_m == 1e-8
    assert [(r["restarted_from"], r["adopted"]) for r in records] == [("q", True), ("p", False)]
    # By default every significant candidate restarts it: the third one here finds the
    # better optimum, which the best two alone would miss.
    three = [result("f", 7.0, True), result("g", 5.0, True), result("h", 3.0, True)]
    calls.clear()
    assert control(three) == (None, [])
    assert calls == [7.0, 5.0]
    ctx.st = DiagnosisSettings()
    assert ctx.st.refit_control_top is None
    calls.clear()
    out, records = control(three)
    assert out is not None and records[0]["restarted_from"] == "h" and calls == [7.0, 5.0, 3.0]
    for off in (0, -1):
        ctx.st = DiagnosisSettings(refit_control_top=off)
        calls.clear()
        assert control(three) == (None, [])
        assert calls == []


def test_crossfit_folds_judge_each_validation_experiment_once_by_a_fit_without_it() -> None:
    for n_train, n_val, k in [(8, 13, 3), (2, 2, 3), (5, 1, 3), (3, 7, 1), (4, 6, 6)]:
        folds = crossfit_folds(n_train, n_val, k)
        assert len(folds) == min(k, n_val)
        judged = sorted(i for _, j in folds for i in j)
        assert judged == list(range(n_train, n_train + n_val))
        for train, j in folds:
            assert set(range(n_train)) <= set(train)  # the training experiments, always
            assert not set(train) & set(j)
            assert sorted(set(train) | set(j)) == list(range(n_train + n_val))
        sizes = [len(j) for _, j in folds]
        assert max(sizes) - min(sizes) <= 1


def test_crossfit_models_fit_on_everything_but_the_judged_experiments(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The refits of the cross-fit: per fold, the nominal and the selected model are fitted
    on exactly the experiments the fold does not judge, the selected model with the free
    parameters and the effect's own, warm-started at the given values."""
    import nanostage.diagnosis.fit as eng

    m = _case(tmp_path, Effects(), seed=6)
    man = load_manifest(m)
    exps = [e for _, e in man.experiments()]
    train, validate = exps[:2], exps[2:]
    free = [
        ("plant.dahl.coulomb_force_n", Param(name="f", unit="N", lower=20, upper=40, initial=30.4))
    ]
    seen: list[tuple[list[str], list[str]]] = []
    real = eng.FitProblem.fit

    def recording(self: FitProblem, *a: Any, **kw: Any) -> Fit:
        seen.append(([n for n, _ in self.params], [e.name for e in self.experiments]))
        return real(self, *a, **kw)

    monkeypatch.setattr(eng.FitProblem, "fit", recording)
    (offset,), _ = applicable_candidates(man.system(), ["offset_force"])
    out = crossfit_models(
        man.system(),
        free,
        lambda s, v: replace_paths(s, dict(v)),
        train,
        validate,
        [(offset, [0.5])],
        {"plant.dahl.coulomb_force_n": 30.0},
        {"plant.dahl.coulomb_force_n": 31.0},
        k=2,
        adapt=lambda s, e: s,
        settings=FAST,
    )
    assert len(out) == 2 and len(seen) == 4
    names = [e.name for e in exps]
    for judged, before, after in out:
        rest = [n for n in names if n not in {e.name for e in judged}]
        fits = [x for x in seen if sorted(x[1]) == sorted(rest)]
        coulomb = "plant.dahl.coulomb_force_n"
        assert sorted(p for p, _ in fits) == [[coulomb], [coulomb, "offset_force.external_force_n"]]
        # The selected model carries the offset force; the nominal one is the preset with
        # only its free parameter refitted.
        assert before == replace_paths(man.system(), {coulomb: get_path(before, coulomb)})
        assert after != replace_paths(man.system(), {coulomb: get_path(after, coulomb)})


def test_diagnosis_calls_nothing_when_the_model_is_right(tmp_path: Path) -> None:
    """No effect, none called. The candidates fitted two at a time (the default) give the
    report of fitting them one at a time, to the last bit."""
    m = _case(tmp_path, Effects(), seed=4)
    d = diagnose(m, tmp_path / "out", settings=FAST, progress=False, figures=False)
    assert FAST.parallel_candidates == 2
    assert d.report["selected"] == [] and d.report["crossfit"] is None
    # Nothing selected: the model file is the nominal model as calibrated, the one behind
    # gap_after (which then equals gap_before).
    doc = ns.load_model_file(tmp_path / "out" / "model.toml")
    assert doc.provenance["selected_effects"] == []
    assert doc.system.effects == Effects()
    assert model_gap(m, doc.system)["total_rms_m"] == d.report["gap_after"]["total_rms_m"]
    assert d.report["gap_after"]["total_rms_m"] == d.report["gap_before"]["total_rms_m"]
    assert all(not c["significant"] for c in d.report["candidates"])
    assert d.report["ranking"] == d.report["significance"] == "relative"
    # Each candidate names the relative rule it failed.
    rules = ("geometric shrink", "(log ratios)", "nothing left to explain", "command")
    assert all(any(r in w for r in rules for w in c["why"]) for c in d.report["candidates"])
    # The right model needs no parameter bent to its bound, and the report says none is.
    assert d.report["calibration_at_bounds"] == {"nominal": [], "selected_model": []}
    assert not any("bound" in w for w in d.report["warnings"])
    one = diagnose(m, None, settings=dc.replace(FAST, parallel_candidates=1), progress=False)
    # Bookkeeping aside (time, and how many simulations were looked up: two candidates
    # fitted at once may both simulate a pair neither has stored yet).
    book = {"timing_s", "simulations", "phases", "model_file"}
    assert {k: v for k, v in one.report.items() if k not in book} == {
        k: v for k, v in d.report.items() if k not in book
    }


def test_a_missed_mark_of_the_model_before_refines_the_lag_family(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """The round compares the model before's simulated marks with the measured ones
    (:func:`~nanostage.diagnosis.signatures.misses`); a miss refits every lag-family
    candidate with the free parameters, and the progress line names the mark. Turned off,
    the same miss refits only the usual ones."""
    import nanostage.diagnosis.loop as loop_mod

    m = step_case(tmp_path, Effects(), seed=4, candidates=("offset_force", "computation_delay"))
    seen: list[tuple[dict[str, Any], dict[str, Any]]] = []

    def fake_misses(measured: dict[str, Any], simulated: dict[str, Any]) -> list[dict[str, Any]]:
        seen.append((measured, simulated))
        return [{"feature": "ramp_level_v", "measured": 1.0, "simulated": 0.5, "z": 9.0}]

    monkeypatch.setattr(loop_mod, "misses", fake_misses)
    judged: list[System] = []
    simulated = loop_mod.SignatureJudge.simulated

    def recording(self: Any, system: System) -> Any:
        judged.append(system)
        return simulated(self, system)

    monkeypatch.setattr(loop_mod.SignatureJudge, "simulated", recording)
    # No usual refits: the lag family's are the only ones. A one-sample delay added to
    # this loop multiplies the gap more than tenfold: every member is refitted here
    # (``inf``), and left out with the default ratio (below).
    st = dc.replace(
        FAST,
        forward_rounds=1,
        refine_top=0,
        crossfit_folds=0,
        lag_refit_max_gap_ratio=math.inf,
    )
    d = diagnose(m, tmp_path / "out", settings=st, progress=True, figures=False)
    err = capsys.readouterr().err
    assert d.report["extra_refits"] == [
        {
            "round": 1,
            "at_bounds": [],
            "missed_marks": ["ramp_level_v"],
            "refined": ["computation_delay"],
            "not_refined": [],
        }
    ]
    md = (tmp_path / "out" / "report.md").read_text(encoding="utf-8")
    assert "misses the marks `ramp_level_v`" in md and "too: `computation_delay`." in md
    assert seen and "marks missed (ramp_level_v)" in err
    # The marks judged are the calibrated model's (the free Coulomb force as fitted), not
    # the manifest's model before calibration.
    fitted = d.report["nominal_parameters"]["plant.dahl.coulomb_force_n"]["value"]
    assert fitted != presets.seed(1e-3).plant.dahl.coulomb_force_n
    assert get_path(judged[0], "plant.dahl.coulomb_force_n") == fitted
    assert "refining the effects that make them too (computation_delay)" in err
    assert "refit computation_delay" in err and "refit offset_force" not in err
    # The default ratio: the delay screened at more than ten times the gap before.
    d10 = diagnose(m, None, settings=dc.replace(st, lag_refit_max_gap_ratio=10.0), progress=True)
    err = capsys.readouterr().err
    delay = next(r for r in d10.report["candidates"] if r["effect"] == "computation_delay")
    assert delay["shrink"] < -9.0
    assert d10.report["extra_refits"][0]["refined"] == []
    assert d10.report["extra_refits"][0]["not_refined"] == ["computation_delay"]
    assert "not computation_delay: screened at more than 10× the gap before" in err
    assert "refit computation_delay" not in err
    off = dc.replace(st, refine_on_missed_marks=False)
    d_off = diagnose(m, None, settings=off, progress=True)
    assert "marks missed" not in capsys.readouterr().err
    assert d_off.report["extra_refits"] == []


def test_reused_simulations_leave_the_report_unchanged(tmp_path: Path) -> None:
    """The simulation cache changes no result: the report without it is the same to the last
    bit, and with it some simulations were looked up (a refit repeats its screening's
    starts) and fewer were run."""
    m = _case(tmp_path, Effects(motor_friction=FrictionModifiers(asymmetry=0.3)), seed=3)
    st = dc.replace(FAST, n_starts_candidate=2)
    cached = diagnose(m, None, settings=st, progress=False).report
    plain = diagnose(
        m, None, settings=dc.replace(st, simulation_cache_mb=0.0), progress=False
    ).report
    book = {"timing_s", "simulations", "phases"}
    assert {k: v for k, v in cached.items() if k not in book} == {
        k: v for k, v in plain.items() if k not in book
    }
    assert plain["simulations"] == {"simulated": None, "reused": 0}
    assert cached["simulations"]["reused"] > 0 and cached["simulations"]["simulated"] > 0
    # Where the time went: every simulation the loop ran falls in one of its phases, in
    # the order they ran; the report's own phases come after (the cross-fit only when
    # something was selected). Without the cache nothing counts them.
    phases = cached["phases"]
    loop_phases = [e for e in phases if e["phase"] not in ("report", "cross-fit")]
    assert sum(e["simulated"] for e in loop_phases) == cached["simulations"]["simulated"]
    assert [(e["phase"], e["round"]) for e in phases[:3]] == [
        ("calibration", None),
        ("screening", 1),
        ("refinement", 1),
    ]
    assert [e["phase"] for e in phases[-2:]] == ["report", "cross-fit"] and cached["selected"]
    assert all(e["seconds"] >= 0.0 and e["simulated"] >= 0 for e in phases)
    assert sum(e["seconds"] for e in loop_phases) <= cached["timing_s"]
    assert all(e["simulated"] is None for e in plain["phases"])
    assert [(e["phase"], e["round"]) for e in plain["phases"]] == [
        (e["phase"], e["round"]) for e in phases
    ]
    with pytest.raises(ValueError, match=r"simulation_cache_mb = -1.0: must be ≥ 0"):
        diagnose(m, None, settings=dc.replace(st, simulation_cache_mb=-1.0), progress=False)
    for ratio in (0.5, float("nan")):
        with pytest.raises(ValueError, match=r"lag_refit_max_gap_ratio = .*must be ≥ 1"):
            bad = dc.replace(st, lag_refit_max_gap_ratio=ratio)
            diagnose(m, None, settings=bad, progress=False)
    for share in (-0.1, 1.5, float("nan")):
        with pytest.raises(ValueError, match=r"friction_model_share = .*must be in \[0, 1\]"):
            diagnose(m, None, settings=dc.replace(st, friction_model_share=share), progress=False)
        with pytest.raises(ValueError, match=r"speed_mark_share = .*must be in \[0, 1\]"):
            diagnose(m, None, settings=dc.replace(st, speed_mark_share=share), progress=False)


def test_phase_clock_charges_each_lap_to_its_phase_and_round() -> None:
    """A lap charges the time and the simulations since the last lap; the same phase in the
    same round adds up, another round has its own entry; the totals sum over the rounds and
    the benchmark's medians count a phase a case did not run as 0; the report shows them."""
    clock_s = iter([10.0, 11.5, 12.0, 14.0, 14.25, 20.0, 25.75])
    count = iter([3, 7, 7, 20, 21])
    clock = PhaseClock(lambda: next(count), lambda: next(clock_s))
    clock.lap("calibration")  # 1.5 s, 4 simulations
    clock.lap("screening", 1)  # 0.5 s, 0
    clock.lap("screening", 2)  # 2 s, 13
    clock.lap("screening", 1)  # 0.25 s, 1: added to round 1's
    assert clock.entries == [
        {"phase": "calibration", "round": None, "seconds": 1.5, "simulated": 4},
        {"phase": "screening", "round": 1, "seconds": 0.75, "simulated": 1},
        {"phase": "screening", "round": 2, "seconds": 2.0, "simulated": 13},
    ]
    assert phase_totals(clock.entries) == {"calibration": 1.5, "screening": 2.75}
    bare = PhaseClock(now=lambda: next(clock_s))
    bare.lap("report")
    assert bare.entries == [{"phase": "report", "round": None, "seconds": 5.75, "simulated": None}]
    rows = [
        {"phase_seconds": {"calibration": 1.0, "screening": 4.0}},
        {"phase_seconds": {"calibration": 3.0}},
        {"phase_seconds": {"calibration": 2.0, "screening": 6.0, "cross-fit": 9.0}},
    ]
    assert median_phase_seconds(rows) == {"calibration": 2.0, "screening": 4.0, "cross-fit": 0.0}
    assert median_phase_seconds([]) == {}
    md = markdown_report({"candidates": [], "timing_s": 3.0, "phases": clock.entries})
    assert "- **Time:** 4.2 s (see *Where the time went*)" in md
    assert "| screening | 2 | 2.0 | 47% | 13 |" in md
    assert "| calibration | — | 1.5 | 35% | 4 |" in md
    assert "- **Time:** 3.0 s\n" in markdown_report({"candidates": [], "timing_s": 3.0})
    assert "Where the time went" not in markdown_report({"candidates": [], "phases": "x"})


def test_simulation_cache_looks_up_repeats_and_drops_the_least_recently_used() -> None:
    base = ns.presets.seed(1e-3)
    ref = np.r_[np.zeros(20), np.full(180, 5e-5)]
    t = np.arange(200) * base.sample_period_s
    exps = [
        Experiment(name=f"c{i}", time_s=t, reference_m=ref + i * 1e-3, position_m=ref + i * 1e-3)
        for i in range(2)
    ]
    kp, ki, kd = presets.table1_gains(5e-5)
    other = presets.with_gains(base, kp=2.0 * kp, ki=ki, kd=kd)
    direct = simulate_readings_and_commands([base, other, base], [exps[0], exps[0], exps[1]])
    one = 2 * 200 * 8  # bytes of one (reading, command) pair
    cache = SimulationCache(2.5 * one)
    got = cache.simulate([base, other, base, base], [exps[0], exps[0], exps[1], exps[0]])
    # A pair repeated within a call is simulated once; the results are the direct ones.
    assert (cache.misses, cache.hits, len(cache)) == (3, 1, 2)
    for (r, c), (r0, c0) in zip(got, [*direct, direct[0]], strict=True):
        assert np.array_equal(r, r0) and np.array_equal(c, c0)
        assert not r.flags.writeable and not c.flags.writeable
    # Two pairs fit in 2.5 pairs' bytes: (base, c0), stored first, was dropped.
    assert cache.n_bytes == 2 * one
    cache.simulate([base], [exps[1]])  # a hit, now the most recently used
    assert (cache.misses, cache.hits) == (3, 2)
    cache.simulate([base], [exps[0]])  # simulated again; drops (other, c0)
    assert (cache.misses, cache.hits, len(cache)) == (4, 2, 2)
    cache.simulate([other, base], [exps[0], exps[1]])
    assert (cache.misses, cache.hits) == (5, 3)
    # Equal systems are one key, whichever object: a rebuilt copy is a hit.
    cache.simulate([dc.replace(base)], [exps[1]])
    assert cache.hits == 4
    with pytest.raises(ValueError, match="max_bytes"):
        SimulationCache(-1.0)


def _tau_by_definition(r: np.ndarray, max_lag: int = 500) -> float:
    """``1 + 2·Σρ(k)`` with one dot product per lag, summed while ρ > 0."""
    x = r - r.mean()
    var = float(x @ x)
    tau = 1.0
    for k in range(1, min(max_lag, len(x) // 2)):
        rho = float(x[:-k] @ x[k:]) / var
        if rho <= 0.0:
            break
        tau += 2.0 * rho
    return tau


@settings(max_examples=40, deadline=None)
@given(
    n=st_h.integers(min_value=4, max_value=3000),
    phi=st_h.floats(min_value=-0.9, max_value=0.999),
    seed=st_h.integers(min_value=0, max_value=2**31),
    max_lag=st_h.sampled_from([2, 3, 50, 500]),
)
def test_autocorrelation_time_is_the_sum_of_its_definition(
    n: int, phi: float, seed: int, max_lag: int
) -> None:
    """The FFT's lag products give the integrated autocorrelation time of one dot product
    per lag, summed to the first lag where ρ ≤ 0, on AR(1) residuals of any memory."""
    e = np.random.default_rng(seed).normal(size=n)
    x = np.empty(n)
    x[0] = e[0]
    for i in range(1, n):
        x[i] = phi * x[i - 1] + e[i]
    assert autocorrelation_time(x, max_lag) == pytest.approx(
        _tau_by_definition(x, max_lag), rel=1e-9, abs=1e-9
    )


def test_autocorrelation_time_of_ar1_noise_and_degenerate_residuals() -> None:
    """AR(1) with coefficient φ has ρ(k) = φᵏ, so τ = (1 + φ)/(1 − φ) (all lags kept); white
    noise stops at its first negative ρ (τ ≈ 1); a constant or too short residual is 1."""
    rng = np.random.default_rng(7)
    n, phi = 400_000, 0.8
    e = rng.normal(size=n)
    x = np.empty(n)
    x[0] = e[0] / math.sqrt(1.0 - phi**2)
    for i in range(1, n):
        x[i] = phi * x[i - 1] + e[i]
    assert autocorrelation_time(x) == pytest.approx((1 + phi) / (1 - phi), rel=0.05)
    assert autocorrelation_time(rng.normal(size=n)) == pytest.approx(1.0, abs=0.02)
    assert autocorrelation_time(np.full(100, 3.0)) == 1.0
    assert autocorrelation_time(np.array([1.0, 2.0, 3.0])) == 1.0


def test_a_backlash_of_open_flank_starts_against_the_flank_that_fits_the_trace() -> None:
    """A dead band rests against the flank of the last move before a run, which a trace
    does not record: with ``initial_flank`` None each experiment is simulated from both
    flanks and the one whose reading is closer to the measured one is kept, bit for bit
    that flank's simulation; a flank the model sets is simulated as set."""
    base = presets.seed(1e-3)

    def with_flank(flank: float | None) -> System:
        fx = Effects(backlash=Backlash(width_m=15e-6, initial_flank=flank))
        return dc.replace(base, effects=fx)

    ref = np.r_[np.zeros(20), np.full(280, 1e-4)] + 2e-3
    t = np.arange(ref.size) * base.sample_period_s
    sims = {}
    for flank in (1.0, -1.0):
        dummy = Experiment(name="d", time_s=t, reference_m=ref, position_m=ref.copy())
        sims[flank] = simulate_readings_and_commands([with_flank(flank)], [dummy])[0]
    # The two flanks give different first moves (the full dead band crossed, or none).
    assert float(np.max(np.abs(sims[1.0][0] - sims[-1.0][0]))) > 5e-6
    for flank in (1.0, -1.0):
        measured = Experiment(
            name=f"m{flank}", time_s=t, reference_m=ref, position_m=sims[flank][0]
        )
        ((reading, command),) = simulate_readings_and_commands([with_flank(None)], [measured])
        assert np.array_equal(reading, sims[flank][0])
        assert np.array_equal(command, sims[flank][1])
        # A set flank is simulated as set, whatever the trace.
        ((fixed, _),) = simulate_readings_and_commands([with_flank(-flank)], [measured])
        assert np.array_equal(fixed, sims[-flank][0])


def test_cli_rejects_an_unknown_effect_before_fitting(tmp_path: Path) -> None:
    m = _case(tmp_path, Effects(), seed=5)
    m.write_text(m.read_text(encoding="utf-8").replace('"offset_force"', '"offset_farce"'))
    p = subprocess.run(
        [sys.executable, "-m", "nanostage.cli", "diagnose", str(m), "--out", str(tmp_path / "o")],
        stdin=subprocess.DEVNULL,
        capture_output=True,
        encoding="utf-8",
        env={**os.environ, "PYTHONIOENCODING": "utf-8"},
        timeout=600,
        check=False,
    )
    assert p.returncode == 2
    assert "offset_farce" in p.stderr and "m.toml" in p.stderr
    assert not (tmp_path / "o").exists()


def _judge_one_parameter(
    ms: np.ndarray,
    base_ms: np.ndarray,
    floor_m: float,
    weights: np.ndarray,
    st: DiagnosisSettings,
    family: int = 1,
    fit: Fit | None = None,
    null_params: tuple[tuple[str, Param], ...] = (),
) -> CandidateResult:
    """``_verdict`` of a one-parameter candidate with validation mean squares ``ms`` against
    ``base_ms`` (no command channel, units: the experiments) among ``family`` candidates,
    fitted as ``fit`` with the parameters ``null_params`` that have a null value."""
    n = len(ms)
    ctx = SimpleNamespace(
        st=st,
        floor=floor_m,
        n_validation=n,
        validation_weights=weights,
        family=family,
        p_level=st.p_value / family if st.multiple_testing else st.p_value,
    )
    return _verdict(
        "x",
        [cast(Any, fit)],
        ms,
        [None] * n,
        None,
        1,
        base_ms,
        [None] * n,
        cast(Any, ctx),
        0,
        null_params=null_params,
    )


def test_holm_levels_by_hand() -> None:
    """Holm's step-down by hand, family of 8 at 0.05: p = 0, 0 pass at 0.05/8 and 0.05/7,
    0.007 passes at 0.05/6 = 0.0083 (Bonferroni's 0.00625 would fail it), and 0.2 fails at
    0.05/5; a p after the first failure is judged at the failing level. Ties keep the given
    order; a family larger than the p's given counts the missing ones."""
    assert holm_levels([0.0, 0.007, 0.0, 0.2], 0.05, 8) == [8, 6, 7, 5]
    # 0.03 fails at 0.05/2 = 0.025: everything larger is judged there too.
    assert holm_levels([0.03, 0.04, 0.001], 0.05, 3) == [2, 2, 3]
    assert holm_levels([0.01, 0.01], 0.05, 2) == [2, 1]
    assert holm_levels([0.02], 0.05, 4) == [4]
    assert holm_levels([], 0.05, 3) == []
    # The smallest p's candidate fails another rule: the step-down stops there, and the
    # rest stay at Bonferroni's level.
    assert holm_levels([0.0, 0.007, 0.0], 0.05, 8, [True, True, False]) == [8, 7, 7]
    assert holm_levels([0.0, 0.007, 0.0], 0.05, 8, [False, True, True]) == [8, 8, 8]
    with pytest.raises(ValueError, match="others_pass has 1 entries"):
        holm_levels([0.0, 0.1], 0.05, 2, [True])


@settings(max_examples=300, deadline=None)
@given(
    st_h.lists(st_h.tuples(st_h.floats(0.0, 1.0), st_h.booleans()), min_size=1, max_size=12),
    st_h.integers(0, 6),
    st_h.sampled_from([0.01, 0.05, 0.1]),
)
def test_holm_is_the_step_down_and_never_weaker_than_bonferroni(
    drawn: list[tuple[float, bool]], extra: int, alpha: float
) -> None:
    """Against the definition: in ascending order of p (ties in the given order), the k-th
    p is judged at ``alpha`` over the family size less k up to the first step that fails
    (its p at or above that level or, with the other rules given, its candidate failing
    them), and every later one at that step's level. Every p Bonferroni passes (``alpha``
    over the family) passes, and with nothing significant by Bonferroni (its level and the
    other rules) nothing is by Holm."""
    p = [x for x, _ in drawn]
    ok = [o for _, o in drawn]
    m = len(p) + extra
    order = sorted(range(len(p)), key=lambda i: (p[i], i))
    for others in (None, ok):
        div = holm_levels(p, alpha, m, others)
        stop = next(
            (
                k
                for k, i in enumerate(order)
                if not (p[i] < alpha / (m - k) and (others is None or others[i]))
            ),
            len(p),
        )
        for k, i in enumerate(order):
            assert div[i] == m - min(k, stop)
            if p[i] < alpha / m:
                assert p[i] < alpha / div[i]
    div = holm_levels(p, alpha, m, ok)
    if not any(x < alpha / m and o for x, o in drawn):
        assert not any(x < alpha / d and o for (x, o), d in zip(drawn, div, strict=True))


def test_holm_passes_a_candidate_that_bonferroni_passes_over() -> None:
    """Two candidates judged together on 8 validation experiments: one cuts every gap by
    e (p = 0), the other cuts six by e and widens two by e^0.8 (bootstrap p = 0.03, between
    0.05/2 and 0.05). Bonferroni judges both at 0.025 and passes only the first; Holm judges
    the second at 0.05 once the first passed, and passes it too, saying so. With nothing
    passing Bonferroni (the first alone at p = 0.03), Holm passes nothing."""
    st = DiagnosisSettings(significance="relative")
    n = 8
    base = np.full(n, 1e-12)
    ctx = SimpleNamespace(
        st=st,
        floor=1e-9,
        n_validation=n,
        validation_weights=np.ones(n),
        family=2,
        p_level=st.p_value / 2,
    )
    fit = cast(Any, None)

    def judged(d: np.ndarray, index: int) -> CandidateResult:
        return _verdict(
            f"c{index}",
            [fit],
            base * np.exp(-d),
            [None] * n,
            None,
            1,
            base,
            [None] * n,
            cast(Any, ctx),
            index,
        )

    clear = judged(np.ones(n), 0)
    mixed = judged(np.array([1.0] * 6 + [-0.8] * 2), 1)
    assert clear.p_value == 0.0 and clear.significant
    assert 0.025 <= mixed.p_value < 0.05 and not mixed.significant
    holm = _judged_holm(cast(Any, ctx), [clear, mixed], base, [None] * n, None)
    assert holm[0] is clear
    assert holm[1].significant and holm[1].p_level == pytest.approx(0.05)
    assert holm[1].geometric_shrink == mixed.geometric_shrink
    # Alone at p = 0.03 in a family of two: its level stays Bonferroni's, and it fails.
    alone = _judged_holm(cast(Any, ctx), [mixed], base, [None] * n, None)
    assert not alone[0].significant and alone[0].p_level == pytest.approx(0.025)
    off = _judged_holm(
        cast(Any, SimpleNamespace(**{**vars(ctx), "st": dc.replace(st, multiple_testing=False)})),
        [clear, mixed],
        base,
        [None] * n,
        None,
    )
    assert off == [clear, mixed]


def _offset_fit(value_n: float, std_error_n: float, span_n: float = 20.0) -> Fit:
    """A fit of a free nominal parameter and an offset force (bounds ±span/2, null 0) of
    ``value_n`` ± ``std_error_n``, the two correlated by 0.5, in normalised coordinates."""
    su = std_error_n / span_n
    cov = np.array([[1e-4, 0.5 * 1e-2 * su], [0.5 * 1e-2 * su, su**2]])
    return Fit(
        values={"nominal.mass_kg": 1.0, "x.external_force_n": value_n},
        std_errors={"nominal.mass_kg": 0.1, "x.external_force_n": std_error_n},
        train_rms_m=0.0,
        n_evaluations=1,
        system=cast(Any, None),
        unit_covariance=cov,
    )


_OFFSET = Param(name="external_force_n", unit="N", lower=-10.0, upper=10.0, initial=0.0, null=0.0)


def test_null_test_by_hand() -> None:
    """The Wald test of a candidate's parameters against their nulls, by hand: one
    parameter at 1.5 standard errors from 0 gives W = 2.25 and p = 2(1 − Φ(1.5)) = 0.1336;
    the free nominal parameter's correlation does not enter the marginal test. Two
    parameters each one standard error from 0 and correlated by 0.5 give W = δᵀΣ⁻¹δ = 2/1.5
    and p = exp(−W/2) (χ² with 2 degrees of freedom). A parameter the data leave
    unconstrained (variance 0) says nothing: with only it, p = 1. No parameter with a null:
    no test (None); a null on a log parameter or outside the bounds is refused."""
    p = null_test_p(_offset_fit(0.12, 0.08), [("x.external_force_n", _OFFSET)])
    assert p == pytest.approx(0.133614, abs=1e-6)
    assert null_test_p(_offset_fit(-0.6, 0.08), [("x.external_force_n", _OFFSET)]) < 1e-12
    a = Param(name="a", unit="-", lower=-1.0, upper=1.0, initial=0.0, null=0.0)
    b = Param(name="b", unit="-", lower=-1.0, upper=3.0, initial=0.0, null=1.0)
    s = 0.01
    two = Fit(
        values={"y.a": -1.0 + 2 * (0.5 + s), "y.b": -1.0 + 4 * (0.5 + s)},
        std_errors={},
        train_rms_m=0.0,
        n_evaluations=1,
        system=cast(Any, None),
        unit_covariance=np.array([[s**2, 0.5 * s**2], [0.5 * s**2, s**2]]),
    )
    got = null_test_p(two, [("y.a", a), ("y.b", b)])
    assert got == pytest.approx(math.exp(-0.5 * 2.0 / 1.5), rel=1e-9)
    loose = dc.replace(two, unit_covariance=np.array([[0.0, 0.0], [0.0, s**2]]))
    assert null_test_p(loose, [("y.a", a)]) == 1.0
    assert null_test_p(loose, [("y.a", a), ("y.b", b)]) == pytest.approx(math.erfc(1 / 2**0.5))
    assert null_test_p(two, [("y.a", dc.replace(a, null=None))]) is None
    assert null_test_p(dc.replace(two, unit_covariance=np.zeros((0, 0))), [("y.a", a)]) is None
    with pytest.raises(ValueError, match=r"null = 1\.0 is invalid"):
        Param(name="w", unit="m", lower=0.1, upper=10.0, initial=1.0, log=True, null=1.0)
    with pytest.raises(ValueError, match=r"null = 2\.0 is invalid"):
        Param(name="c", unit="-", lower=-1.0, upper=1.0, initial=0.0, null=2.0)


def test_an_effect_whose_fitted_size_does_not_differ_from_none_is_not_named() -> None:
    """A consistent held-out improvement (p = 0) by an offset of 0.12 ± 0.08 N: the gap
    test passes, the Wald test against 0 N does not (p = 0.13), so the candidate is not
    significant and the reason gives the size. The same improvement by 0.12 ± 0.01 N is
    significant, and so is the first with the rule off, or where the explained gap is
    large (the large-explained-gap rule overrides it, as it does the bootstrap)."""
    base_ms = np.full(12, (100e-9) ** 2)  # 5 floors: not a large gap
    ms = base_ms * 0.7**2
    st = DiagnosisSettings()
    assert st.null_test
    nulls = (("x.external_force_n", _OFFSET),)

    def judged(
        fit: Fit, settings: DiagnosisSettings = st, base: np.ndarray = base_ms, cut: float = 0.7
    ) -> Any:
        after = base * cut**2
        return _judge_one_parameter(after, base, 20e-9, np.ones(12), settings, 1, fit, nulls)

    weak = judged(_offset_fit(0.12, 0.08))
    assert weak.p_value == 0.0 and not weak.significant and weak.null_failed
    assert weak.null_p_value == pytest.approx(0.1336, abs=1e-4)
    assert any(
        "does not differ from none (external_force_n = 0.12 ± 0.08 N (none: 0))" in w
        and "Wald p = 0.134 ≥ 0.05" in w
        for w in weak.reasons
    )
    assert weak.to_dict()["null_p_value"] == pytest.approx(0.1336, abs=1e-4)
    strong = judged(_offset_fit(0.12, 0.01))
    assert strong.significant and strong.null_p_value < 1e-12 and not strong.null_failed
    off = judged(_offset_fit(0.12, 0.08), dc.replace(st, null_test=False))
    assert off.significant and not off.null_failed
    # 100 floors before, 70 % removed: a large explained gap.
    large = judged(_offset_fit(0.12, 0.08), st, np.full(12, (2000e-9) ** 2), 0.3)
    assert large.significant and large.null_p_value == pytest.approx(0.1336, abs=1e-4)
    assert not large.null_failed
    # Without parameters that have a null (a log-scaled size), no test and no reason.
    plain = _judge_one_parameter(ms, base_ms, 20e-9, np.ones(12), st, 1, _offset_fit(0.1, 1.0))
    assert plain.significant and plain.null_p_value is None


def test_judged_on_every_experiment_an_effect_whose_own_fit_widens_the_gap_is_not_named() -> None:
    """A candidate significant when judged on every experiment whose own fit (the one a
    selection carries) widens the round's pooled validation gap by more than
    ``max_pooled_widening`` is marked not significant with the reason (a consumed
    independent no-effect case: an encoder cyclic error 11 % better judged on every
    experiment, its own fit 16.5 % worse on the pooled validation gap, was selected and
    left the selected model's gap 57 % wider); the next significant candidate is picked.
    Within the bound, or with the rule off (the default), the judging stands."""
    judged = [
        candidate_result("encoder_cyclic_error", [1.0, 1.0], rms_m=1e-7),
        candidate_result("backlash", [2.0, 2.0], rms_m=2e-7),
    ]
    own = {
        "encoder_cyclic_error": dc.replace(judged[0], shrink=-0.165),
        "backlash": dc.replace(judged[1], shrink=-0.04),
    }
    out = without_unsupported(judged, own, 0.05)
    assert [r.significant for r in out] == [False, True]
    assert out[0].reasons[0] == (
        "its fit on the training experiments, which a selection carries, widens the pooled "
        "validation gap (shrink -16%, beyond −5%)"
    )
    assert out[1] is judged[1]
    pick = pick_winner(out, dc.replace(DiagnosisSettings(), occam_tie_break=False))
    assert pick is not None and pick.effect == "backlash"
    assert all(r.significant for r in without_unsupported(judged, own))
    assert all(r.significant for r in without_unsupported(judged, own, 0.2))


def test_judged_on_every_experiment_an_effect_absent_from_its_own_fit_is_not_named() -> None:
    """Judged on every experiment, each candidate is refitted on folds that hold validation
    experiments too; the selection carries the round's own fit (training experiments). An
    offset significant on the folds whose own fit does not differ from none (a consumed
    independent dwell case: 0.72 ± 0.04 N on the folds, 0.025 ± 0.04 N on the training
    experiments) is marked not significant, with the reason, and the round picks the next
    significant candidate, or none; a candidate whose own fit passes, or that has no own
    fit of the round, is left as judged."""
    judged = [
        candidate_result("offset_force", [1.0, 1.0], rms_m=1e-7),
        candidate_result("backlash", [2.0, 2.0], rms_m=2e-7),
        candidate_result("gms", [3.0, 3.0], rms_m=3e-7),
    ]
    own = {
        "offset_force": dc.replace(judged[0], null_failed=True, null_p_value=0.534),
        "backlash": judged[1],
    }
    out = without_unsupported(judged, own)
    assert [r.effect for r in out] == ["offset_force", "backlash", "gms"]
    assert [r.significant for r in out] == [False, True, True]
    why = out[0].reasons[0]
    assert why.startswith("its fit on the training experiments, which a selection carries")
    assert "does not differ from none (Wald p = 0.534)" in why
    assert out[1] is judged[1] and out[2] is judged[2]
    st = dc.replace(DiagnosisSettings(), occam_tie_break=False)
    pick = pick_winner(out, st)
    assert pick is not None and pick.effect == "backlash"
    alone = without_unsupported(judged[:1], own)
    assert pick_winner(alone, st) is None
    assert without_unsupported(judged[:1], {})[0].significant
    # report.md's cross-judged table says why a candidate was not significant.
    from nanostage.diagnosis.report import _cross_judged_table

    table = _cross_judged_table(
        [{"round": 1, "candidates": [{**r.to_dict(), "why": r.reasons} for r in out]}]
    )
    rows = [line for line in table.splitlines() if line.startswith("| 1 | `")]
    assert len(rows) == 3 and "| no | its fit on the training experiments" in rows[0]
    assert rows[1].endswith("| yes | — |")


@pytest.mark.parametrize("preset", ["seed", "seed_biased", "emps"])
def test_a_candidate_at_its_nulls_is_the_nominal_model(preset: str) -> None:
    """The null values are where the effect is absent: every candidate whose parameters all
    have one, applied at them, moves as the nominal model (a move out and back): the same
    encoder counts and command bit for bit, the position within 1 nm (a zero-amplitude
    friction term still takes the integrator through other roundings). A tenth of the range
    below one of them (a lower voltage limit: a higher one changes nothing until the move
    reaches it), the position differs by more than 10 nm. The nulls are the model's own
    values: the EMPS model's offset of −3.2 N, and a seed model given an offset and both
    asymmetries."""
    nominal = ns.presets.emps() if preset == "emps" else ns.presets.seed(1e-3)
    if preset == "seed_biased":
        nominal = replace_paths(
            nominal,
            {
                "plant.table.external_force_n": 1.5,
                "plant.dahl.asymmetry": 0.05,
                "effects.motor_friction.asymmetry": -0.1,
            },
        )
        cands = {c.name: c for c in applicable_candidates(nominal)[0]}
        assert cands["offset_force"].params[0].null == 1.5
        assert [p.null for p in cands["asymmetric_friction"].params] == [-0.1, 0.05]
    period = nominal.controller.sample_period_s
    n = round(0.3 / period)
    ref = np.where(np.arange(n) < n // 2, 2e-2 if preset == "emps" else 2e-4, 0.0)
    ref[: n // 10] = 0.0
    tested = 0
    before = ns.simulate(nominal, ref)
    for c in applicable_candidates(nominal)[0]:
        if not c.params or any(p.null is None for p in c.params):
            continue
        tested += 1
        nulls = [float(p.null) for p in c.params if p.null is not None]
        at = ns.simulate(c.apply(nominal, nulls), ref)
        np.testing.assert_array_equal(at.encoder_counts, before.encoder_counts, err_msg=c.name)
        np.testing.assert_array_equal(at.command, before.command, err_msg=c.name)
        np.testing.assert_allclose(at.position_m, before.position_m, rtol=0, atol=1e-9)
        p0 = c.params[0]
        u0 = p0.to_unit(nulls[0])
        moved = [p0.from_unit(u0 + (0.1 if u0 < 0.1 else -0.1)), *nulls[1:]]
        away = ns.simulate(c.apply(nominal, moved), ref)
        assert float(np.max(np.abs(away.position_m - before.position_m))) > 1e-8, c.name
    assert tested >= 4


def test_too_few_informative_experiments_are_counted_and_advised() -> None:
    """A bootstrap over the experiments above their floors gives p = 0 whenever all of
    them improve, however few: two experiments above a 20 nm floor (of four; the other two
    are below it before and after, log ratio 0) both improved make the relative test
    significant at p = 0, and the result records that two experiments carried it. No test
    over fewer than five experiments can reach p < 0.05 (an exact sign-flip test gives at
    least 2⁻ⁿ, 1/16 for four), so the experiment advice says the selection is weak evidence
    and asks for five; with five informative experiments, or the pooled significance
    (which resamples moves and counts no experiments), it says nothing of the kind."""
    assert too_few_to_test(4, 0.05) and not too_few_to_test(5, 0.05)
    assert too_few_to_test(1, 0.4) and not too_few_to_test(1, 0.6)
    st = DiagnosisSettings()
    base_ms = np.array([(400e-9) ** 2, (10e-9) ** 2, (300e-9) ** 2, (12e-9) ** 2])
    ms = np.array([(200e-9) ** 2, (9e-9) ** 2, (150e-9) ** 2, (11e-9) ** 2])
    r = _judge_one_parameter(ms, base_ms, 20e-9, np.ones(4), st)
    assert r.significant and r.p_value == 0.0
    assert r.informative_experiments == 2
    fitted = Fit(values={}, std_errors={}, train_rms_m=0.0, n_evaluations=1, system=cast(Any, None))
    assert dc.replace(r, fit=fitted).to_dict()["informative_validation_experiments"] == 2
    pooled = _judge_one_parameter(
        ms, base_ms, 20e-9, np.ones(4), DiagnosisSettings(significance="pooled")
    )
    assert pooled.informative_experiments is None

    t = np.arange(400) * 1e-4
    ref = np.where(t < 0.01, 0.0, np.where(t < 0.02, 1e-4, np.where(t < 0.03, 0.0, 1e-3)))
    exps = [Experiment(name="e", time_s=t, reference_m=ref, position_m=ref)]

    def weak_advice(result: CandidateResult) -> list[dict[str, Any]]:
        out = experiment_advice(exps, None, [result], 0.05, selected=[result], p_value=0.05)
        return [a for a in out if "weak evidence" in a["issue"]]

    (advice,) = weak_advice(r)
    assert advice["effects"] == ["x"]
    assert "x rests on 2 validation experiment(s)" in advice["issue"]
    assert "at least 5 experiments" in advice["experiment"]
    assert weak_advice(dc.replace(r, informative_experiments=5)) == []
    # Judged among six candidates (level 0.05/6), five experiments are too few as well: an
    # exact test needs seven (2⁻⁷ ≤ 0.0083).
    (among_six,) = weak_advice(dc.replace(r, informative_experiments=5, p_level=0.05 / 6))
    assert "at least 7 experiments" in among_six["experiment"]
    assert weak_advice(dc.replace(r, informative_experiments=7, p_level=0.05 / 6)) == []
    assert weak_advice(pooled) == []
    # Nothing selected: nothing to advise on.
    assert not any("weak evidence" in a["issue"] for a in experiment_advice(exps, None, [r], 0.05))
    # A round that was cross-judged selected by its results on every experiment: the advice
    # judges those (found on fresh independent case 1180006: the report called a selection
    # weak evidence from the two informative validation experiments, while the cross-judged
    # result that selected it had improved all eight of its informative experiments).
    judged = dc.replace(r, informative_experiments=8)
    other = dc.replace(r, effect="y")
    assert selecting_results([[other, r]], [[judged, other]], ["x"]) == [judged]
    assert selecting_results([[other, r]], [], ["x"]) == [r]
    assert selecting_results([[r], [other]], [[judged]], ["x", "y"]) == [judged, other]
    assert weak_advice(selecting_results([[r]], [[judged]], ["x"])[0]) == []


def test_a_round_judges_its_candidates_at_the_level_over_their_number() -> None:
    """Bonferroni: a round selects the best of the candidates it judges together, so each is
    judged at ``p_value`` over their number. A candidate that cuts nine of twelve gaps by
    30 % and raises three by 30–50 % has bootstrap p = 0.023: significant alone or among
    two (0.025), not among six (0.0083), and significant again with the correction off. A
    consistent improvement (p = 0) passes among any number; the level is recorded and the
    reason names it."""
    base_ms = np.full(12, (100e-9) ** 2)  # 5 floors: not a large explained gap
    factor = np.array([0.7] * 9 + [1.3, 1.4, 1.5])
    ms = base_ms * factor**2
    st = DiagnosisSettings()
    assert st.multiple_testing and st.p_value == 0.05

    def judged(family: int, settings: DiagnosisSettings = st, after: np.ndarray = ms) -> Any:
        return _judge_one_parameter(after, base_ms, 20e-9, np.ones(12), settings, family)

    alone = judged(1)
    assert alone.p_value == pytest.approx(0.0228) and alone.geometric_shrink > 0.1
    assert alone.significant and alone.p_level == 0.05
    assert judged(2).significant and judged(2).p_level == pytest.approx(0.025)
    six = judged(6)
    assert not six.significant and six.p_level == pytest.approx(0.05 / 6)
    assert any("p = 0.023 ≥ 0.0083 (0.05 over 6 candidates)" in w for w in six.reasons)
    fitted = Fit(values={}, std_errors={}, train_rms_m=0.0, n_evaluations=1, system=cast(Any, None))
    assert dc.replace(six, fit=fitted).to_dict()["p_level"] == pytest.approx(0.05 / 6)
    off = judged(6, dc.replace(st, multiple_testing=False))
    assert off.significant and off.p_level == 0.05
    consistent = judged(17, after=base_ms * 0.7**2)
    assert consistent.significant and consistent.p_value == 0.0
    # The engine's context: the level is p_value over its family, or p_value when off.
    ctx = _Ctx(
        free=[],
        set_free=lambda s, v: s,
        folds=[],
        floor=20e-9,
        st=st,
        adapt=lambda s, e: s,
        nominal=cast(Any, None),
        family=7,
    )
    assert ctx.p_level == pytest.approx(0.05 / 7)
    assert dc.replace(ctx, st=dc.replace(st, multiple_testing=False)).p_level == 0.05
    assert dc.replace(ctx, family=0).p_level == 0.05


def test_floor_rule_rejects_a_gain_on_a_gap_at_the_noise_floor() -> None:
    """A clear, consistent reduction is significant when the gap before is well above the
    noise floor; the same reduction on a gap within 1.5 floors is not ("nothing left to
    explain"), unless the rule is turned off (``explainable_factor = 0``)."""
    rng = np.random.default_rng(0)
    base_ms = np.full(12, (60e-9) ** 2)
    ms = base_ms * (0.5 + 0.02 * rng.random(12))  # every experiment better: shrink ~29 %

    def judge(floor_m: float, factor: float) -> bool:
        st = DiagnosisSettings(explainable_factor=factor)
        return _judge_one_parameter(ms, base_ms, floor_m, np.ones(12), st).significant

    assert judge(20e-9, 1.5)
    assert not judge(45e-9, 1.5)  # 60 nm ≤ 1.5 × 45 nm
    assert judge(45e-9, 0.0)


def test_relative_terms_by_hand() -> None:
    """Log ratios of the mean squares before and after, each clamped at its floor: 4 → 1
    floors² gives log 4; a cut below the floor counts to the floor only (100 → 0.01 floors²
    as 100 → 1); a gap at its floor before and after gives 0. The geometric shrink is
    1 − exp(−mean/2)."""
    f2 = np.array([1.0, 4.0, 9.0]) * 1e-16
    before = np.array([4.0, 100.0, 9.0]) * 1e-16 * np.array([1.0, 4.0, 1.0])
    after = np.array([1.0, 0.01, 1.0]) * 1e-16 * np.array([1.0, 4.0, 1.0])
    d, shrink = relative_terms(before, after, f2)
    assert d == pytest.approx([np.log(4.0), np.log(100.0), 0.0], rel=1e-12)
    assert shrink == pytest.approx(1.0 - np.exp(-0.5 * np.log(400.0) / 3.0), rel=1e-12)
    assert relative_terms(np.zeros(0), np.zeros(0), np.zeros(0))[1] == 0.0
    with pytest.raises(ValueError, match="expected the same"):
        relative_terms(before, after[:2], f2)


@settings(max_examples=60, deadline=None)
@given(
    st_h.lists(
        st_h.tuples(
            st_h.floats(0.1, 1e3), st_h.floats(0.1, 1e3), st_h.floats(0.5, 5.0), st_h.floats(-6, 6)
        ),
        min_size=1,
        max_size=12,
    )
)
def test_relative_terms_do_not_depend_on_any_experiments_scale(rows: list) -> None:
    """Scaling one experiment's gaps before and after and its floor by the same factor (a
    loud step against a micro-step) changes nothing; a worse gap gives a negative ratio."""
    table = np.array(rows)
    before, after, floor = (table[:, j] * 1e-16 for j in range(3))
    scale = 10.0 ** table[:, 3]
    d0, s0 = relative_terms(before, after, floor)
    d1, s1 = relative_terms(before * scale, after * scale, floor * scale)
    assert d1 == pytest.approx(d0, abs=1e-9)
    assert s1 == pytest.approx(s0, abs=1e-9)
    assert np.all((d0 < 0) <= (after > np.maximum(before, floor)))


def test_relative_significance_counts_each_experiment_by_its_own_factor() -> None:
    """Nine quiet validation experiments cut threefold and three loud ones 40 % worse (RMS),
    all with the same floor (the sensor's): the pooled gap rises, so the pooled rules reject
    the candidate, and the relative terms accept it (geometric shrink about 50 %) when the
    pooled gap may widen (``max_pooled_widening`` off); by default its 25 % widening rejects
    it. Each experiment's gap counts against its own floor: a cut from 2 floors to 0.1
    floor is a cut to the floor. Every experiment a few per cent better is below the
    complexity penalty either way."""
    overall = 30e-9
    w = np.ones(12)
    base_ms = np.array([(1000e-9) ** 2] * 3 + [(300e-9) ** 2] * 9)
    ms = base_ms * np.r_[[1.4**2] * 3, [1 / 9] * 9]

    def judge(after: np.ndarray, mode: str, widening: float = -1.0) -> CandidateResult:
        return _judge_one_parameter(
            after,
            base_ms,
            overall,
            w,
            DiagnosisSettings(significance=mode, max_pooled_widening=widening),
        )

    pooled, relative = judge(ms, "pooled"), judge(ms, "relative")
    assert pooled.shrink < 0 and not pooled.significant
    assert relative.significant, relative.reasons
    wider = judge(ms, "relative", DiagnosisSettings().max_pooled_widening)
    assert wider.shrink == pytest.approx(relative.shrink, rel=1e-12)
    assert wider.shrink < -0.05
    assert not wider.significant
    assert wider.reasons == [
        "the pooled validation gap widens (563 → 705 nm, shrink -25%, beyond −5%): the "
        "effect trades one experiment's residual for another's"
    ]
    assert relative.geometric_shrink == pytest.approx(
        1 - np.exp(-0.5 * np.mean(np.log(base_ms / ms))), rel=1e-12
    )
    assert "geometric shrink" in relative.reasons[-1]
    # Below the floor counts as the floor.
    quiet = np.r_[[0], [1] * 11].astype(bool)
    b2 = np.where(quiet, (2 * overall) ** 2, base_ms)
    a_floor = np.where(quiet, overall**2, base_ms)
    a_below = np.where(quiet, (0.1 * overall) ** 2, base_ms)
    g_floor = _judge_one_parameter(a_floor, b2, overall, w, DiagnosisSettings())
    g_below = _judge_one_parameter(a_below, b2, overall, w, DiagnosisSettings())
    assert g_below.geometric_shrink == g_floor.geometric_shrink > 0
    small = base_ms * 0.97**2
    for mode in ("pooled", "relative"):
        r = judge(small, mode)
        assert not r.significant
        assert any("complexity penalty" in why for why in r.reasons)
    with pytest.raises(ValueError, match=r"significance = 'geometric'.*relative, pooled"):
        significance_mode("geometric")


def test_experiments_at_their_floor_before_and_after_say_nothing() -> None:
    """Four validation experiments: a step and a ramp whose gaps a candidate cuts two- and
    threefold, and two micro-steps at their floor before and after. The micro-steps' log
    ratios are 0 and are left out of the bootstrap (kept, p would be about 1/16 whatever
    the step and the ramp show): significant, p = 0. A candidate that changes only
    experiments at their floor has no evidence left: p = 1."""
    floor = 30e-9
    base_ms = np.array([1270e-9, 25e-9, 560e-9, 28e-9]) ** 2
    ms = np.array([480e-9, 10e-9, 300e-9, 12e-9]) ** 2
    r = _judge_one_parameter(ms, base_ms, floor, np.ones(4), DiagnosisSettings())
    assert r.significant and r.p_value == 0.0, r.reasons
    d, shrink = relative_terms(base_ms, ms, np.full(4, floor**2))
    assert d[1] == d[3] == 0.0 and r.geometric_shrink == shrink
    only_floor = np.array([1270e-9, 5e-9, 560e-9, 5e-9]) ** 2
    quiet = _judge_one_parameter(
        np.r_[base_ms[0], only_floor[1], base_ms[2], only_floor[3]],
        base_ms,
        floor,
        np.ones(4),
        DiagnosisSettings(),
    )
    assert quiet.p_value == 1.0 and not quiet.significant


def test_each_experiment_kind_gets_the_floor_of_its_own_repeats() -> None:
    """Floors per kind (the step sizes, whatever the direction and the start): a quiet kind
    (three-count steps scattering by 20 nm) and a loud one (1 mm steps scattering by
    300 nm) each get their own repeat spread; a kind without repeats gets the overall
    floor; no floor is below the sensor floor."""
    q = 1e-7
    t = np.arange(600) * 1e-3
    rng = np.random.default_rng(3)

    def run(name: str, start_m: float, step_m: float, scatter_m: float) -> Experiment:
        ref = np.full(600, start_m)
        ref[100:] += step_m
        # A run-to-run different final error after the step (friction scatter), quantised.
        dev = np.where(np.arange(600) >= 100, scatter_m * rng.standard_normal(), 0.0)
        return Experiment(
            name=name, time_s=t, reference_m=ref, position_m=np.floor((ref + dev) / q) * q
        )

    assert experiment_kind(run("a", 0.0, 3e-7, 0).reference_m, q) == (3,)
    assert experiment_kind(run("b", 7e-3, -3e-7, 0).reference_m, q) == (3,)
    assert experiment_kind(run("c", 0.0, 1e-3, 0).reference_m, q) == (10_000,)
    quiet = [run("q1", 1e-3, 3e-7, 4e-8), run("q2", 1e-3, 3e-7, 4e-8)]
    loud = [run("l1", 5e-3, 1e-3, 6e-7), run("l2", 5e-3, 1e-3, 6e-7)]
    other_quiet = run("q3", 9e-3, -3e-7, 4e-8)  # same kind, elsewhere: not a repeat
    lone = run("m", 2e-2, 5e-4, 1e-7)  # a kind without repeats
    every = [*quiet, *loud, other_quiet, lone]
    floors = experiment_floors_m(every, q)
    overall = noise_floor_m(every, q)

    def spread(a: Experiment, b: Experiment) -> float:
        r = gap_residual(a.position_m, b.position_m, a.reference_m)
        return float(np.sqrt(np.mean(r**2) / 2))

    assert floors["q1"] == floors["q2"] == floors["q3"]
    assert floors["q1"] == pytest.approx(max(spread(*quiet), q / np.sqrt(12)), rel=1e-12)
    assert floors["l1"] == floors["l2"] == pytest.approx(spread(*loud), rel=1e-12)
    assert floors["l1"] > 5 * floors["q1"]
    assert floors["m"] == overall
    assert min(floors.values()) >= q / np.sqrt(12) * (1 - 1e-12)


def test_kind_floors_let_a_fix_of_the_quiet_experiments_count() -> None:
    """Three quiet validation experiments (floor 25 nm) with a gap of 100 nm, nine loud ones
    (floor 300 nm) at their floor. A candidate that brings the quiet ones to 30 nm removes
    all there is to explain, but the unweighted gap (264 nm) is within 1.5 overall floors
    (213 nm) and its RMS shrinks by 3 %: rejected with one floor for all, significant with
    each experiment judged against its own floor. A change of the loud ones by a fraction
    of their floor is not significant either way."""
    quiet_f, loud_f = 25e-9, 300e-9
    floors = np.array([loud_f] * 9 + [quiet_f] * 3)
    overall = float(np.sqrt(np.mean([loud_f**2, quiet_f**2])))
    base_ms = np.array([loud_f**2] * 9 + [(100e-9) ** 2] * 3)
    fixed = np.array([loud_f**2] * 9 + [(30e-9) ** 2] * 3)
    rng = np.random.default_rng(1)
    jitter = base_ms * np.r_[1 + 0.1 * rng.standard_normal(9), np.ones(3)]

    def judge(ms: np.ndarray, weighted: bool) -> CandidateResult:
        w = (overall / floors) ** 2 if weighted else np.ones(12)
        return _judge_one_parameter(ms, base_ms, overall, w, DiagnosisSettings())

    one_floor = judge(fixed, weighted=False)
    assert not one_floor.significant
    assert one_floor.shrink == pytest.approx(1 - np.sqrt(np.mean(fixed) / np.mean(base_ms)))
    own = judge(fixed, weighted=True)
    assert own.significant, own.reasons
    assert own.shrink == one_floor.shrink  # the reported shrink stays the plain one
    assert own.weighted_shrink > 0.4
    assert not judge(jitter, weighted=True).significant


def test_friction_model_candidates_are_screened_from_two_starts_and_refitted_from_six() -> None:
    """A friction-model candidate (it replaces the table friction, so its warm start is not
    the model before) is screened with a local fit from the warm start and one from the
    scan's best point; other candidates with the better of the two only. Found on a
    presliding case of the benchmark: screened from one start the GMS and LuGre fits ended
    worse than the nominal model, ranked twelfth, and an encoder cyclic error was selected;
    from two starts LuGre was found with a 46 % shrink."""
    seen: dict[str, int] = {}
    shaped: dict[str, tuple[str, ...]] = {}
    base = presets.seed(1e-3)

    def fit_and_validate(*args: Any, **kwargs: Any) -> Any:
        # (base, params, apply, n_starts, seed, screen, scan_points, screen_starts,
        # scan_starts)
        shaped[args[1][0][0].split(".")[0]] = tuple(kwargs["scan_only"])
        raise _Seen(args[-2], args[-1], args[3])

    class _Seen(Exception):
        pass

    ctx = SimpleNamespace(
        st=DiagnosisSettings(), fit_and_validate=fit_and_validate, selected_effects=[]
    )
    cands, _ = applicable_candidates(
        base, ["gms", "lugre", "offset_force", "backlash", "dwell_static_friction"]
    )
    scan: dict[str, int] = {}
    for cand in cands:
        try:
            _judge(cand, base, np.ones(1), [None], None, cast(Any, ctx), screen=True)
        except _Seen as s:
            seen[cand.name], scan[cand.name], _ = s.args
    assert seen == {
        "gms": 2,
        "lugre": 2,
        "offset_force": 1,
        "backlash": 1,
        "dwell_static_friction": 1,
    }
    # The dwell gap's basin is narrow: local fits from the four best scanned points; the
    # laws that fall with speed scan their shape only, and fit from its three best points.
    assert scan == {"dwell_static_friction": 4, "gms": 3, "lugre": 3} | {
        k: 1 for k in ("offset_force", "backlash")
    }
    shape = ("static_excess_n", "stribeck_velocity_m_per_s")
    assert shaped == {
        "gms": tuple(f"gms.{n}" for n in (*shape, "presliding_spread")),
        "lugre": tuple(f"lugre.{n}" for n in shape),
        "offset_force": (),
        "backlash": (),
        "dwell_static_friction": (),
    }
    st = DiagnosisSettings(screen_starts_friction_models=1)
    ctx = SimpleNamespace(st=st, fit_and_validate=fit_and_validate, selected_effects=[])
    with pytest.raises(_Seen) as one:
        _judge(cands[0], base, np.ones(1), [None], None, cast(Any, ctx), screen=True)
    assert one.value.args[0] == 1
    # Refits: a friction model from six starts (its gap has many basins), others from three.
    ctx = SimpleNamespace(
        st=DiagnosisSettings(), fit_and_validate=fit_and_validate, selected_effects=[]
    )
    refit: dict[str, int] = {}
    for cand in cands:
        try:
            _judge(cand, base, np.ones(1), [None], None, cast(Any, ctx), screen=False)
        except _Seen as s:
            refit[cand.name] = s.args[2]
    assert refit == {k: 6 if k in ("gms", "lugre") else 3 for k in seen}
    # In later rounds (on top of a selected effect) every candidate from three.
    ctx.selected_effects = [(cands[3], [1e-5, 5e7])]
    with pytest.raises(_Seen) as later:
        _judge(cands[0], base, np.ones(1), [None], None, cast(Any, ctx), screen=False)
    assert later.value.args[2] == 3


def test_a_candidates_fits_are_seeded_by_its_name_not_its_place_in_the_list() -> None:
    """A candidate's starts and scans draw from the diagnosis's seed and its own name: the
    same fit whether a diagnosis has every candidate or only a few. Found on consumed
    independent case 1180003 (a drive compliance): seeded by its place in the list, the
    compliance refitted alone and among all candidates landed in different basins of the
    rugged gap (damping 23 against 1.4 N·s/m; validation shrink 84 % against 67 %)."""
    base = presets.seed(1e-3)

    class _Seen(Exception):
        pass

    def fit_and_validate(*args: Any, **kwargs: Any) -> Any:
        raise _Seen(args[4])  # (base, params, apply, n_starts, seed, ...)

    def seeds(names: list[str], seed: int) -> dict[str, int]:
        ctx = SimpleNamespace(
            st=DiagnosisSettings(seed=seed), fit_and_validate=fit_and_validate, selected_effects=[]
        )
        cands, _ = applicable_candidates(base, names)
        out = {}
        for cand in cands:
            for screen in (True, False):
                with pytest.raises(_Seen) as s:
                    _judge(cand, base, np.ones(1), [None], None, cast(Any, ctx), screen=screen)
                out[cand.name, screen] = s.value.args[0]
        return out

    every = ["gms", "offset_force", "backlash", "drive_compliance", "amplifier_dynamics"]
    full = seeds(every, 7)
    few = seeds(["drive_compliance", "offset_force"], 7)
    assert few == {k: v for k, v in full.items() if k[0] in ("drive_compliance", "offset_force")}
    assert full == {k: 7 + candidate_seed(k[0]) for k in full}
    assert len({candidate_seed(n) for n in every}) == len(every)
    # The diagnosis's seed still moves every candidate's draws.
    assert seeds(every, 8) == {k: v + 1 for k, v in full.items()}


@pytest.mark.parametrize(
    "hidden",
    [
        "asymmetric_friction",
        "dwell_static_friction",
        "lead_periodic_friction",
        "backlash",
        "offset_force",
    ],
)
def test_truth_starts_rebuild_the_hidden_effect(hidden: str) -> None:
    """The truth-started check starts the candidate at values that rebuild the benchmark's
    hidden effect: the same friction modifiers, position term (amplitude, wavenumber, phase),
    dead band and contact stiffness, or offset force (backlash damping is the candidate's own
    by design: not the inverse crime)."""
    base = presets.seed(1e-3)
    truth, info = _hidden(hidden, np.random.default_rng(7), base)
    (cand,) = with_starts(applicable_candidates(base, [hidden])[0], truth_starts(hidden, info))
    model = cand.apply(base, [p.initial for p in cand.params])
    if hidden == "lead_periodic_friction":
        ((a, k, ph),) = model.effects.position_friction[0].terms
        ((a0, k0, ph0),) = truth.effects.position_friction[0].terms
        assert (a, k) == pytest.approx((a0, k0), rel=1e-12)
        assert np.cos(ph - ph0) == pytest.approx(1.0, abs=1e-12)
        assert model.effects.position_friction[0].side == truth.effects.position_friction[0].side
    elif hidden == "backlash":
        b, b0 = model.effects.backlash, truth.effects.backlash
        assert b is not None and b0 is not None
        assert (b.width_m, b.contact_stiffness_n_per_m) == (
            b0.width_m,
            b0.contact_stiffness_n_per_m,
        )
    elif hidden == "offset_force":
        assert get_path(model, "plant.table.external_force_n") == info["external_force_n"]
    else:
        assert model.effects.motor_friction == truth.effects.motor_friction


@pytest.mark.parametrize("spread", [1.0, 4.0, 100.0])
def test_gms_candidate_spreads_its_slip_displacements(spread: float) -> None:
    """The GMS candidate's elements: equal weights, stiffnesses summing to the presliding
    stiffness at the origin, slip displacements (weight·Fc/k) in geometric steps from the
    first to `spread` times it."""
    g = gms_spread(30.0, 40.0, 7.5e7, 5e-4, spread)
    assert sum(g.stiffness_n_per_m) == pytest.approx(7.5e7, rel=1e-12)
    assert g.weights == pytest.approx((1 / 3, 1 / 3, 1 / 3))
    slip = [w * g.coulomb_force_n / k for w, k in zip(g.weights, g.stiffness_n_per_m, strict=True)]
    assert slip[2] / slip[0] == pytest.approx(spread, rel=1e-12)
    assert slip[1] / slip[0] == pytest.approx(np.sqrt(spread), rel=1e-12)
    (cand,) = applicable_candidates(presets.seed(1e-3), ["gms"])[0]
    assert cand.params[-1].name == "presliding_spread"
    model = cand.apply(presets.seed(1e-3), [30.0, 10.0, 7.5e7, 5e-4, spread])
    assert model.effects.table_friction == g
    with pytest.raises(ValueError, match=r"presliding_spread = 0\.5"):
        gms_spread(30.0, 40.0, 7.5e7, 5e-4, 0.5)


@pytest.mark.parametrize("hidden", ["presliding_gms", "offset_force"])
def test_oracle_model_is_the_truth_without_its_noise(hidden: str) -> None:
    """The benchmark's ceiling model: the drawn truth (same hidden effect, same perturbed
    friction levels) without stochastic friction and encoder noise, at the nominal
    integrator tolerance; the same seed draws the same truth."""
    truth, info, _ = draw_truth(hidden, 12345)
    oracle = oracle_model(hidden, 12345)
    assert truth.effects.stochastic is not None and truth.effects.encoder_errors is not None
    assert oracle.effects.stochastic is None and oracle.effects.encoder_errors is None
    assert oracle.integrator == presets.seed(1e-3).integrator != truth.integrator
    assert oracle.plant == truth.plant
    assert oracle.effects.table_friction == truth.effects.table_friction
    assert info["parameters"] == draw_truth(hidden, 12345)[1]["parameters"]
    assert info["parameters"] != draw_truth(hidden, 12346)[1]["parameters"]
    # Without its hidden effect: the same drawn nominal truth, the no-effect case's of the
    # same seed (whose draws start alike), and not the model with the effect.
    bare = oracle_model(hidden, 12345, without_hidden=True)
    assert bare == oracle_model("none", 12345) != oracle
    assert bare.plant.dahl == oracle.plant.dahl  # type: ignore[union-attr]
    with pytest.raises(ValueError):
        oracle_model("gremlins", 1, without_hidden=True)


def test_candidate_starts_are_clipped_and_checked_before_fitting(tmp_path: Path) -> None:
    base = presets.seed(1e-3)
    cands, _ = applicable_candidates(base, ["offset_force", "computation_delay"])
    out = with_starts(cands, {"offset_force": {"external_force_n": 1e6}})
    (p,) = out[0].params
    assert p.initial == p.upper
    assert out[1] is cands[1] or out[1] == cands[1]
    with pytest.raises(
        ValueError, match=r"unknown parameter\(s\) force_n; valid: external_force_n"
    ):
        with_starts(cands, {"offset_force": {"force_n": 1.0}})
    m = _case(tmp_path, Effects(), seed=4)
    for starts, msg in (
        ({"offset_force": {"force_n": 1.0}}, "unknown parameter"),
        ({"backlash": {"width_m": 1e-6}}, "'backlash', not among the candidates"),
    ):
        st = dc.replace(FAST, candidate_starts=starts)
        # Raised before any fitting: the nominal calibration alone takes longer than this.
        with pytest.raises(ValueError, match=msg):
            diagnose(m, None, settings=st, progress=False)


def test_scan_starts_fit_from_the_next_best_scanned_points(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """With ``scan_starts`` = 3 the local fits start from the warm start and the three best
    scanned points that beat it (best first); with 1, from the best only. The gap here is a
    synthetic bowl (no simulation), so the scan's costs are known exactly."""
    import nanostage.diagnosis.fit as eng

    seed_system = presets.seed(1e-3)
    target = np.array([1.2, 1.7])

    class Bowl(FitProblem):
        def _vectors(self, us: Any) -> list[np.ndarray]:
            self.n_evaluations += len(us)
            return [np.asarray(u, dtype=float) - target for u in us]

    params = [
        ("a", Param(name="a", unit="-", lower=0.0, upper=1.0, initial=0.9)),
        ("b", Param(name="b", unit="-", lower=0.0, upper=1.0, initial=0.1)),
    ]
    x0s: list[np.ndarray] = []
    real = eng.least_squares

    def recording(fun: Any, x0: np.ndarray, **kw: Any) -> Any:
        x0s.append(np.array(x0))
        return real(fun, x0, **kw)

    monkeypatch.setattr(eng, "least_squares", recording)
    st = DiagnosisSettings()
    for k in (1, 3):
        x0s.clear()
        prob = Bowl(params, lambda v: seed_system, [cast(Experiment, None)], 1, lambda s, e: s)
        fit = prob.fit(2, st, seed=5, scan=32, scan_starts=k)
        assert fit.values["a"] == pytest.approx(0.2, abs=1e-3)
        # The scanned points, as fit() draws them, ranked by their cost.
        rows = 1.0 + qmc_rows(32, seed=5 + 7919)
        cost = np.sum((rows - target) ** 2, axis=1)
        warm = np.array([1.9, 1.1])
        better = [rows[i] for i in np.argsort(cost) if cost[i] < np.sum((warm - target) ** 2)]
        assert np.allclose(x0s[0], warm)
        assert len(x0s) == 1 + min(k, len(better))
        for got, want in zip(x0s[1:], better, strict=False):
            assert np.allclose(got, want)


def test_scan_only_draws_the_flagged_parameters_and_keeps_the_others() -> None:
    """With ``scan_only`` the scan draws only the flagged parameters (a 2-D Latin hypercube
    over them, as without flags over two parameters) and every scanned point keeps the
    unflagged one at its start value; the local fit then frees them all and reaches the
    bowl's bottom. The gap is a synthetic bowl (no simulation)."""
    seed_system = presets.seed(1e-3)
    target = np.array([1.5, 1.2, 1.7])
    seen: list[np.ndarray] = []

    class Bowl(FitProblem):
        def _vectors(self, us: Any) -> list[np.ndarray]:
            self.n_evaluations += len(us)
            seen.extend(np.asarray(u, dtype=float) for u in us)
            return [np.asarray(u, dtype=float) - target for u in us]

    params = [
        (n, Param(name=n, unit="-", lower=0.0, upper=1.0, initial=x))
        for n, x in (("level", 0.3), ("a", 0.9), ("b", 0.1))
    ]
    prob = Bowl(params, lambda v: seed_system, [cast(Experiment, None)], 1, lambda s, e: s)
    fit = prob.fit(1, DiagnosisSettings(), seed=5, scan=32, scan_only=[False, True, True])
    assert fit.values["level"] == pytest.approx(0.5, abs=1e-3)
    assert fit.values["b"] == pytest.approx(0.7, abs=1e-3)
    # The start, then the 32 scanned points: the level held at its start, (a, b) on the
    # hypercube the scan draws for two parameters.
    scanned = np.array(seen[1:33])
    assert np.all(scanned[:, 0] == 1.3)
    assert np.allclose(scanned[:, 1:], 1.0 + qmc_rows(32, seed=5 + 7919))
    assert not np.allclose(scanned[:, 1:], scanned[0, 1:])


def test_the_scan_only_names_of_every_candidate_are_its_parameters() -> None:
    """A misspelt name would silently give the scan back every parameter: each name a
    candidate's scan is limited to is one of its parameters, and the laws that fall with
    speed scan their shape only."""
    for system in (presets.seed(1e-3), presets.emps()):
        cands, _ = applicable_candidates(system, None)
        for c in cands:
            assert set(c.scan_only) <= {p.name for p in c.params}, c.name
        limited = {c.name for c in cands if c.scan_only}
        assert {"lugre", "gms", "stribeck"} <= limited


def qmc_rows(n: int, seed: int) -> np.ndarray:
    from scipy.stats import qmc

    return np.asarray(qmc.LatinHypercube(d=2, seed=seed).random(n))


def test_benchmark_scores_a_case_against_the_truths_own_model(tmp_path: Path) -> None:
    """One blind case end to end (a hidden offset force, the full design, fast settings,
    an assumed run-to-run level scatter): the row and the summary carry the shrink of the
    truth's deterministic model, which for a large effect removes nearly all the gap, and
    the files are written; the scatter is in the case's manifest and the diagnosis used it."""
    s = run_benchmark(
        tmp_path,
        cases=1,
        seed=3,
        hidden=["offset_force"],
        settings=dc.replace(FAST, forward_rounds=1),
        progress=False,
        truth_check=False,
        level_scatter=0.01,
    )
    assert s["level_scatter"] == 0.01
    case = tmp_path / "case00_offset_force"
    assert "level_scatter = 0.01\n" in (case / "manifest.toml").read_text(encoding="utf-8")
    report = json.loads((case / "report" / "report.json").read_text(encoding="utf-8"))
    assert report["level_scatter"]["spread"] == 0.01
    (row,) = s["rows"]
    assert row["hidden"] == "offset_force"
    assert row["oracle_rms_m"] < 0.2 * row["gap_before_rms_m"]
    assert row["oracle_shrink"] == pytest.approx(1 - row["oracle_rms_m"] / row["gap_before_rms_m"])
    assert s["median_oracle_shrink"] == row["oracle_shrink"]
    assert (
        json.loads((tmp_path / "benchmark.json").read_text(encoding="utf-8"))[
            "median_oracle_shrink"
        ]
        == (row["oracle_shrink"])
    )
    # The same model without the offset leaves most of the gap: the effect's own shrink.
    m = case / "manifest.toml"
    assert (
        row["oracle_without_effect_rms_m"]
        == (model_gap(m, oracle_model("offset_force", 30_000, without_hidden=True))["total_rms_m"])
    )
    assert row["effect_shrink"] == 1.0 - row["oracle_rms_m"] / row["oracle_without_effect_rms_m"]
    assert row["effect_shrink"] > 0.8
    md = (tmp_path / "benchmark.md").read_text(encoding="utf-8")
    assert "truth's shrink" in md and "its effect's shrink" in md
    assert "Without its hidden effect the truth's own model" in md
    assert "seed 3, diagnosed with a run-to-run friction level scatter of 0.01." in md
    # The case's seconds per phase are its report's, summed over the rounds; one case, so
    # the medians are its own.
    assert row["phase_seconds"] == phase_totals(report["phases"])
    assert list(row["phase_seconds"])[:3] == ["calibration", "screening", "refinement"]
    assert s["median_phase_seconds"] == row["phase_seconds"]
    assert sum(row["phase_seconds"].values()) <= row["seconds"]
    assert "Median seconds per case by phase of the diagnosis" in md


def test_parameters_at_their_bounds_are_found_and_named() -> None:
    free = [
        ("plant.mass_kg", Param(name="m", unit="kg", lower=0.2, upper=0.6, initial=0.4)),
        ("plant.k", Param(name="k", unit="N/m", lower=1e6, upper=1e9, initial=5e7, log=True)),
        ("plant.c", Param(name="c", unit="N", lower=10.0, upper=50.0, initial=30.0)),
    ]
    # Normalised: m at 0.9999 (upper), k at log(1.05e6/1e6)/log(1000) = 0.007 (lower), c at
    # 0.5; an effect's own parameter is not a free nominal one and is left out.
    values = {"plant.mass_kg": 0.59996, "plant.k": 1.05e6, "plant.c": 30.0, "backlash.w": 1e-9}
    fit = Fit(values=values, std_errors={}, train_rms_m=1e-7, n_evaluations=1, system=None)  # type: ignore[arg-type]
    rows = at_bounds(fit, free)
    assert rows == [
        {"parameter": "plant.mass_kg", "value": 0.59996, "bound": "upper", "limit": 0.6},
        {"parameter": "plant.k", "value": 1.05e6, "bound": "lower", "limit": 1e6},
    ]
    # Just inside the margin on the linear scale: not at the bound.
    inside = dict(values, **{"plant.mass_kg": 0.6 - 0.4 * AT_BOUND * 1.5})
    assert [r["parameter"] for r in at_bounds(dc.replace(fit, values=inside), free)] == ["plant.k"]
    warns = bound_warnings(rows, [])
    assert len(warns) == 1 and "plant.mass_kg = 0.6 at its upper bound 0.6" in warns[0]
    assert "plant.k = 1.05e+06 at its lower bound 1e+06" in warns[0]
    assert bound_warnings([], []) == []
    assert "still at their bounds" in bound_warnings([], rows[:1])[0]


def test_a_selection_that_widens_the_validation_gap_is_warned_about() -> None:
    (w,) = widened_gap_warnings(168.1e-9, 357.5e-9, ["lugre"])
    assert "(lugre)" in w and "357.5 nm against 168.1 nm" in w and "shrink -113%" in w
    assert widened_gap_warnings(168.1e-9, 100e-9, ["lugre"]) == []
    assert widened_gap_warnings(168.1e-9, 168.1e-9, ["lugre"]) == []
    assert widened_gap_warnings(168.1e-9, 357.5e-9, []) == []


def test_cross_judge_split_holds_out_every_experiment_once() -> None:
    for n in range(2, 14):
        for k in (0, 1, 2, 3, 5, 20):
            folds = cross_judge_split(n, k)
            assert len(folds) == max(2, min(k, n))
            assert sorted(i for f in folds for i in f) == list(range(n))
            assert all(f for f in folds)


@given(
    classes=st_h.lists(st_h.integers(0, 2), min_size=2, max_size=16),
    k=st_h.integers(0, 6),
)
@settings(max_examples=200, deadline=None)
def test_stratified_folds_spread_each_class(classes: list[int], k: int) -> None:
    """With classes, every experiment is still held out once in as many folds as without,
    the folds' sizes differ by one at most, and no fold holds out more than ⌈m/k⌉ of a
    class of m."""
    n = len(classes)
    folds = cross_judge_split(n, k, classes)
    kk = max(2, min(k, n))
    assert len(folds) == kk
    assert sorted(i for f in folds for i in f) == list(range(n))
    assert max(map(len, folds)) - min(map(len, folds)) <= 1
    for c in set(classes):
        m = classes.count(c)
        assert max(sum(classes[i] == c for i in f) for f in folds) <= -(-m // kk)


@given(
    classes=st_h.lists(st_h.integers(0, 2), min_size=2, max_size=16),
    k=st_h.integers(0, 6),
    data=st_h.data(),
)
@settings(max_examples=200, deadline=None)
def test_folds_dealt_largest_first_keep_the_largest_of_each_class_apart(
    classes: list[int], k: int, data: st_h.DataObject
) -> None:
    """With scales, each class is dealt largest first: the folds are stratified as without
    them (the same sizes per class and fold), and a class's ``k`` largest experiments are
    held out in ``k`` different folds, so every fold trains on one of the two largest."""
    n = len(classes)
    scales = data.draw(st_h.lists(st_h.floats(0.0, 1e-3, allow_nan=False), min_size=n, max_size=n))
    folds = cross_judge_split(n, k, classes, scales)
    kk = max(2, min(k, n))
    assert sorted(i for f in folds for i in f) == list(range(n))
    plain = cross_judge_split(n, k, classes)
    for c in set(classes):
        per_fold = sorted(sum(classes[i] == c for i in f) for f in folds)
        assert per_fold == sorted(sum(classes[i] == c for i in f) for f in plain)
        members = sorted((i for i in range(n) if classes[i] == c), key=lambda i: -scales[i])
        top = members[:kk]
        fold_of = {i: j for j, f in enumerate(folds) for i in f}
        assert len({fold_of[i] for i in top}) == len(top)


def test_experiment_scale_is_the_largest_reference_change_per_sample() -> None:
    assert experiment_scale([0.0, 0.0, 1e-4, 1e-4]) == pytest.approx(1e-4)  # a step
    ramp = np.concatenate([np.zeros(5), np.arange(1, 11) * 2e-7, np.full(5, 2e-6)])
    assert experiment_scale(ramp) == pytest.approx(2e-7)  # a ramp: speed × period
    assert experiment_scale([3e-3] * 4) == 0.0
    assert experiment_scale([1.0]) == 0.0


def test_the_independent_design_folds_hold_out_one_ramp_each() -> None:
    """The independent family's twelve experiments (training ones, then validation ones)
    fall into ramps, micro-steps and steps by their references alone, and each of the three
    stratified folds holds out one of the three ramps; round robin held out two ramps in
    one fold and trained it on the third."""
    from nanostage.diagnosis.independent_truth import SEED as TRUTH_SEED
    from nanostage.diagnosis.independent_truth import experiment_design

    design = experiment_design()
    exps = [e for e in design if e.role == "train"] + [e for e in design if e.role == "validate"]
    count_m = TRUTH_SEED["count_m"]
    classes = [experiment_class(e.reference_m, count_m) for e in exps]
    kinds = [e.name.split("_")[1] for e in exps]
    assert [c for c, k in zip(classes, kinds, strict=True) if k == "ramp"] == [0, 0, 0]
    assert {c for c, k in zip(classes, kinds, strict=True) if k == "micro"} == {1}
    assert {c for c, k in zip(classes, kinds, strict=True) if k in ("step", "reversal")} == {2}
    assert [sum(kinds[i] == "ramp" for i in f) for f in cross_judge_split(12, 3, classes)] == [
        1,
        1,
        1,
    ]
    assert max(sum(kinds[i] == "ramp" for i in f) for f in cross_judge_split(12, 3)) == 2
    # Dealt largest first, no fold holds out both large steps (1 mm and 0.5 mm) nor trains
    # without both of the two fastest ramps; by class alone one fold held out the 1 mm and
    # 0.5 mm steps and the 1 mm/s ramp, and its refits went unstable on that ramp.
    scales = [experiment_scale(e.reference_m) for e in exps]
    names = [e.name for e in exps]
    big_steps = {"exp01_step", "exp02_step"}
    fast_ramps = {"exp07_ramp", "exp08_ramp"}
    plain = [{names[i] for i in f} for f in cross_judge_split(12, 3, classes)]
    assert any(big_steps <= f for f in plain)
    for f in cross_judge_split(12, 3, classes, scales):
        held = {names[i] for i in f}
        assert not big_steps <= held and not fast_ramps <= held
    dealt = cross_judge_split(12, 3, classes, scales)
    assert [sum(kinds[i] == "ramp" for i in f) for f in dealt] == [1, 1, 1]


def test_cross_judging_refits_each_candidate_without_each_held_out_experiment(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """With ``cross_judge_folds``, each round's refitted candidates and the model before are
    refitted on all experiments but each fold's held-out ones (training experiments held
    out too), one local fit each; the round selects by these results, and the report lists
    them per round."""
    import nanostage.diagnosis.fit as eng

    m = _case(tmp_path, Effects(motor_friction=FrictionModifiers(asymmetry=0.3)), seed=3)
    m.write_text(m.read_text(encoding="utf-8").replace('"offset_force", ', ""))
    man = load_manifest(m)
    (fold,) = man.splits()
    order = [*fold.train, *fold.validate]
    refs = {spec.name: e.reference_m for spec, e in man.experiments()}
    count_m = presets.seed(1e-3).encoder.count_m
    classes = [experiment_class(refs[n], count_m) for n in order]
    scales = [experiment_scale(refs[n]) for n in order]
    held_out = [{order[i] for i in f} for f in cross_judge_split(len(order), 2, classes, scales)]
    names = set(order)
    fold_sets = [frozenset(names - h) for h in held_out]
    seen: list[tuple[frozenset[str], int]] = []
    real = eng.FitProblem.fit

    def recording(self: FitProblem, n_starts: int, *a: Any, **kw: Any) -> Fit:
        seen.append((frozenset(e.name for e in self.experiments), n_starts))
        return real(self, n_starts, *a, **kw)

    monkeypatch.setattr(eng.FitProblem, "fit", recording)
    st = dc.replace(FAST, cross_judge_folds=2, crossfit_folds=0)
    d = diagnose(m, None, settings=st, progress=False)
    r = d.report
    assert r["selected"] == ["asymmetric_friction"]
    cj = r["cross_judged"]
    assert [x["round"] for x in cj] == list(range(1, len(cj) + 1)) and cj
    # Round 1 judged every refitted candidate; the selection is its first significant one.
    first = [c["effect"] for c in cj[0]["candidates"]]
    assert "asymmetric_friction" in first
    best = next(c for c in cj[0]["candidates"] if c["significant"])
    assert best["effect"] == "asymmetric_friction"
    # Judged on every experiment (one mean square each), in the folds' order.
    assert len(best["validation_rms_by_experiment_m"]) == len(order)
    # Per round and fold: the model before and each judged candidate, one local fit each,
    # on exactly the experiments the fold does not hold out.
    for fs in fold_sets:
        fits = [n for s, n in seen if s == fs]
        assert set(fits) == {1}
        assert len(fits) == sum(1 + len(x["candidates"]) for x in cj)
    # report.md shows the cross-judged round as a table, one row per judged candidate.
    md = markdown_report(r)
    assert "## Judged on every experiment" in md
    section = md.split("## Judged on every experiment")[1].split("\n## ")[0]
    rows = [line for line in section.splitlines() if line.startswith("| 1 | `")]
    assert [x.split("`")[1] for x in rows] == first
    for bad in (2.5, True, "3"):
        with pytest.raises(ValueError, match=r"cross_judge_folds = .*must be an integer"):
            diagnose(m, None, settings=dc.replace(st, cross_judge_folds=bad), progress=False)
    off = diagnose(m, None, settings=dc.replace(st, cross_judge_folds=0), progress=False)
    assert off.report["cross_judged"] == []
    assert "## Judged on every experiment" not in markdown_report(off.report)


def test_a_cross_judged_tie_is_broken_on_the_rounds_own_fits(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Where the cross-judged candidates tie, the signature tie-break simulates the round's
    own fits (the ones the report's signature table shows), not the cross-judging folds'
    local refits, which leave out some experiments."""
    import nanostage.diagnosis.loop as lp
    from nanostage.diagnosis.signatures import SignatureJudge

    m = _case(tmp_path, Effects(motor_friction=FrictionModifiers(asymmetry=0.3)), seed=3)
    real = lp._cross_judge
    fold_systems: list[int] = []
    round_systems: list[int] = []

    lp_pools: list[Any] = []

    def all_tied(ctx: Any, current: Any, fits: Any, pool: Any) -> tuple[Any, Any]:
        round_systems.extend(id(r.fit.system) for _, r in pool)
        lp_pools.append(pool)
        out, terms = real(ctx, current, fits, pool)
        fold_systems.extend(id(r.fit.system) for r in out)
        first = out[0]
        # Every candidate significant and as good as the first: a tie of all.
        tied = [dc.replace(r, significant=True, validation_ms=first.validation_ms) for r in out]
        return tied, terms

    seen: list[list[int]] = []
    real_tie = SignatureJudge.tie_chi_squares

    bare: list[list[Any]] = []

    def record(
        self: SignatureJudge, systems: Any, without: Any = None
    ) -> tuple[list[tuple[float, int]], list[str]]:
        seen.append([id(x) for x in systems])
        bare.append(list(without))
        return real_tie(self, systems, without)

    monkeypatch.setattr(lp, "_cross_judge", all_tied)
    monkeypatch.setattr(SignatureJudge, "tie_chi_squares", record)
    st = dc.replace(FAST, cross_judge_folds=2, crossfit_folds=0, forward_rounds=1)
    d = diagnose(m, None, settings=st, progress=False)
    # The last tie-break is the cross-judged one (the round's own pick may break one first).
    assert d.report["selected"] and seen and len(seen[-1]) >= 2
    assert set(seen[-1]) <= set(round_systems)
    assert not set(seen[-1]) & set(fold_systems)
    # Each tied model is judged against itself with its effect taken out: the nominal
    # model (no effect, no asymmetry) at the candidate's own free values; the asymmetry's
    # own model has one.
    from nanostage.config import field_paths, get_path

    def asymmetries(system: Any) -> list[float]:
        return [get_path(system, p) for p in field_paths(system) if p.endswith("asymmetry")]

    tied_systems = {id(r.fit.system): r.fit.system for _, r in lp_pools[-1]}
    assert len(bare[-1]) == len(seen[-1])
    assert any(any(a != 0.0 for a in asymmetries(tied_systems[i])) for i in seen[-1])
    for b in bare[-1]:
        assert b.effects == Effects()
        assert asymmetries(b) and all(a == 0.0 for a in asymmetries(b))
    entry = d.report["tie_signatures"][-1]
    measured = d.report["signatures"]["measured"]
    assert isinstance(entry["marks"], list) and set(entry["marks"]) <= set(measured)


def test_the_round_selects_by_the_cross_judged_results(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Where the cross-judged results name another candidate than the validation
    experiments would, the round selects that one (with its own fit). The forced choice's
    own fit may widen the pooled validation gap, so that rule is off here (it has its own
    test)."""
    import nanostage.diagnosis.loop as lp

    m = _case(tmp_path, Effects(motor_friction=FrictionModifiers(asymmetry=0.3)), seed=3)
    m.write_text(m.read_text(encoding="utf-8").replace('"offset_force", ', ""))
    real = lp._cross_judge
    chosen: list[str] = []

    def other_wins(*a: Any, **kw: Any) -> tuple[Any, Any]:
        out, terms = real(*a, **kw)
        if not chosen:
            chosen.append(next(r.effect for r in out if r.effect != "asymmetric_friction"))
        return [dc.replace(r, significant=r.effect == chosen[0]) for r in out], terms

    monkeypatch.setattr(lp, "_cross_judge", other_wins)
    # Without the level scatter: with it, a candidate's validation RMS is that of the gaps
    # the scatter discounts, while the report's gap after stays in metres as measured.
    st = dc.replace(
        FAST,
        cross_judge_folds=2,
        crossfit_folds=0,
        forward_rounds=1,
        level_scatter=0.0,
        max_pooled_widening=-1.0,
        measured_shrink_rule=False,
    )
    d = diagnose(m, None, settings=st, progress=False)
    assert d.report["selected"] == chosen
    first = next(c for c in d.report["candidates"] if c["effect"] == chosen[0])
    assert d.report["gap_after"]["total_rms_m"] == pytest.approx(first["validation_rms_m"])


def test_the_rule_on_the_measured_gap_judges_the_headlines_gaps(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The measured-gap rule compares the pooled validation gap of the reading, as the
    report's headline gives it: its gap of the model before round 1 is the report's gap
    before, its gap of the selected pick the report's gap after (one round selects)."""
    import nanostage.diagnosis.loop as lp

    m = _case(tmp_path, Effects(motor_friction=FrictionModifiers(asymmetry=0.3)), seed=3)
    m.write_text(m.read_text(encoding="utf-8").replace('"offset_force", ', ""))
    real = lp._measured_rms
    seen: list[float] = []

    def recorded(ctx: Any, fits: Any) -> float:
        seen.append(real(ctx, fits))
        return seen[-1]

    monkeypatch.setattr(lp, "_measured_rms", recorded)
    st = dc.replace(FAST, crossfit_folds=0, forward_rounds=1)
    r = diagnose(m, None, settings=st, progress=False).report
    assert r["selected"] == ["asymmetric_friction"]
    # One pick, judged once: before and after.
    assert len(seen) == 2
    assert seen[0] == pytest.approx(r["gap_before"]["total_rms_m"], rel=1e-12)
    assert seen[1] == pytest.approx(r["gap_after"]["total_rms_m"], rel=1e-12)
    penalty = st.penalty_base + st.penalty_per_param * 2
    assert 1.0 - seen[1] / seen[0] > penalty


def _asymmetry_leaves_measured_gap(
    monkeypatch: pytest.MonkeyPatch, on_every: bool, factor: float = 1.0
) -> list[tuple[str, ...]]:
    """Make ``_measured_rms`` of fits with a motor asymmetry return the model before's value
    on the same folds (the measured gap left as it was; times ``factor``): on the
    validation experiments, and with ``on_every`` also judged on every experiment. Returns
    the folds' validation experiments of every call (one name tuple per call)."""
    import nanostage.diagnosis.loop as lp

    real = lp._measured_rms
    before: dict[tuple[tuple[str, ...], ...], float] = {}
    calls: list[tuple[str, ...]] = []

    def unchanged_by_asymmetry(ctx: Any, fits: Any) -> float:
        key = tuple(tuple(e.name for e in v) for _, v in ctx.folds)
        calls.append(tuple(n for k in key for n in k))
        asym = any(
            f.system.effects.motor_friction is not None
            and f.system.effects.motor_friction.asymmetry != 0.0
            for f in fits
        )
        if asym and key in before and (on_every or len(key) == 1):
            return before[key] * factor
        value = real(ctx, fits)
        before.setdefault(key, value)
        return value

    monkeypatch.setattr(lp, "_measured_rms", unchanged_by_asymmetry)
    return calls


def test_a_pick_that_leaves_the_measured_gap_is_turned_down(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A round's pick whose fit shrinks the measured pooled validation gap by no more than
    its complexity penalty is not named, whatever the judging found: it is marked not
    significant with the reason, and the round picks again (here the hidden asymmetry's
    candidate, made to leave the measured gap as it was, on the validation experiments and
    judged on every experiment). With the rule off it is named."""
    m = _case(tmp_path, Effects(motor_friction=FrictionModifiers(asymmetry=0.3)), seed=3)
    m.write_text(m.read_text(encoding="utf-8").replace('"offset_force", ', ""))
    _asymmetry_leaves_measured_gap(monkeypatch, on_every=True)
    st = dc.replace(FAST, crossfit_folds=0, forward_rounds=1)
    r = diagnose(m, None, settings=st, progress=False).report
    assert "asymmetric_friction" not in r["selected"]
    row = next(c for c in r["candidates"] if c["effect"] == "asymmetric_friction")
    assert not row["significant"]
    why = [w for w in row["why"] if w.startswith("the gap as measured")]
    assert len(why) == 1 and "shrink 0.0% ≤ complexity penalty 7%" in why[0], row["reasons"]
    # Picked on every experiment (the default judging), the rule judged that too.
    assert "; judged on every experiment, each held out once, the gap as measured goes" in why[0], (
        why[0]
    )
    assert why[0].count("shrink 0.0% ≤ complexity penalty 7%") == 2, why[0]
    # Whatever the round picked instead passed the rule on its own measured gap.
    for name in r["selected"]:
        other = next(c for c in r["candidates"] if c["effect"] == name)
        assert not any(w.startswith("the gap as measured") for w in other["why"])
    off = diagnose(
        m, None, settings=dc.replace(st, measured_shrink_rule=False), progress=False
    ).report
    assert off["selected"] == ["asymmetric_friction"]


def test_a_pick_judged_on_every_experiment_stands_when_its_folds_shrink_the_measured_gap(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A pick made on every experiment whose own fit leaves the measured gap of the
    validation experiments (one large step whose run-to-run level the judged gaps discount,
    say) is named all the same when its folds' fits shrink the gap as measured over every
    experiment, each held out once, by more than its complexity penalty: the rule judges
    it in the terms it was picked in too. Without the judging on every experiment, the
    validation experiments decide alone and it is turned down."""
    m = _case(tmp_path, Effects(motor_friction=FrictionModifiers(asymmetry=0.3)), seed=3)
    m.write_text(m.read_text(encoding="utf-8").replace('"offset_force", ', ""))
    calls = _asymmetry_leaves_measured_gap(monkeypatch, on_every=False)
    st = dc.replace(FAST, crossfit_folds=0, forward_rounds=1)
    r = diagnose(m, None, settings=st, progress=False).report
    assert r["selected"] == ["asymmetric_friction"]
    row = next(c for c in r["candidates"] if c["effect"] == "asymmetric_friction")
    assert not any(w.startswith("the gap as measured") for w in row["why"]), row["why"]
    # The report gives both measures: in the evidence and in report.json.
    (rec,) = r["measured_on_every"]
    assert rec["round"] == 1 and rec["effect"] == "asymmetric_friction"
    assert "> complexity penalty 7%" in rec["every_experiment"], rec
    assert "shrink 0.0% ≤ complexity penalty 7%" in rec["validation"], rec
    (ev,) = r["evidence"]
    assert any(
        w.startswith("named on the gap as measured judged on every experiment") for w in ev["why"]
    ), ev["why"]
    # Both measures were taken: the validation experiments' (before, pick) and every
    # experiment's, each held out once (before, pick).
    every = sorted(n for f in load_manifest(m).splits() for n in [*f.train, *f.validate])
    validation = [c for c in calls if len(c) < len(every)]
    on_every = [c for c in calls if sorted(c) == every]
    assert len(validation) == 2 and len(on_every) == 2, calls
    calls.clear()
    single = diagnose(m, None, settings=dc.replace(st, cross_judge_folds=0), progress=False).report
    assert "asymmetric_friction" not in single["selected"]
    assert single["measured_on_every"] == []
    assert all(len(c) < len(every) for c in calls), calls


def test_a_pick_whose_own_fit_widens_the_measured_gap_stays_turned_down(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The measure on every experiment does not rescue a pick whose own fit widens the
    validation experiments' measured gap at all: the model the report carries would widen
    the headline's gap by the effect it names. Here the asymmetry's own fit widens it by
    2 % (within the 5 % the pooled-widening rule tolerates) while its folds' fits shrink the
    gap over every experiment; it is turned down on the validation experiments' measure
    alone."""
    m = _case(tmp_path, Effects(motor_friction=FrictionModifiers(asymmetry=0.3)), seed=3)
    m.write_text(m.read_text(encoding="utf-8").replace('"offset_force", ', ""))
    _asymmetry_leaves_measured_gap(monkeypatch, on_every=False, factor=1.02)
    st = dc.replace(FAST, crossfit_folds=0, forward_rounds=1)
    r = diagnose(m, None, settings=st, progress=False).report
    assert "asymmetric_friction" not in r["selected"]
    assert r["measured_on_every"] == []
    row = next(c for c in r["candidates"] if c["effect"] == "asymmetric_friction")
    why = [w for w in row["why"] if w.startswith("the gap as measured")]
    assert len(why) == 1 and "shrink -2.0% ≤ complexity penalty 7%" in why[0], row["why"]
    assert "judged on every experiment" not in why[0]


def test_turned_down_marks_each_named_candidate_once() -> None:
    """The reason comes first, before the judging's words (here a pass), and only once."""
    a = dc.replace(candidate_result("a", [1e-14], rms_m=1e-7), reasons=["passed"])
    b = candidate_result("b", [1e-14], rms_m=1e-7)
    out = turned_down([a, b], {"a": "why"})
    assert [r.effect for r in out] == ["a", "b"]
    assert not out[0].significant and out[0].reasons == ["why", "passed"]
    assert out[1] is b
    again = turned_down(out, {"a": "why"})
    assert again[0].reasons.count("why") == 1 and not again[0].significant


def test_screening_moves_the_held_nominal_by_its_linearised_best(tmp_path: Path) -> None:
    """With ``screen_moves_nominal``, a held screening fit sees the training gap with the
    free nominal parameters' Jacobian projected out, and its model is the held one moved by
    the Gauss–Newton step: from a calibration bent to 27 N, on data whose Coulomb force is
    the preset's 30.4 N and which have no offset, the step brings the force within 0.5 N
    of it and the offset candidate to a smaller force than held; the fit's training gap is
    its model's and below the held one's. Off, the force stays where it was held."""
    m = _case(tmp_path, Effects(), seed=5)
    name = COULOMB
    fits = {}
    for moves in (False, True):
        ctx, exps = _coulomb_ctx(m, dc.replace(FAST, screen_moves_nominal=moves))
        nominal = ctx.nominal
        assert nominal.plant.dahl.coulomb_force_n == pytest.approx(30.4)
        (cand,), _ = applicable_candidates(nominal, ["offset_force"])
        extra = [(f"{cand.name}.{p.name}", p) for p in cand.params]
        f, prob = ctx._fit_held(nominal, extra, cand.apply, {name: 27.0}, exps[:2], 1, None, 1, 1)
        assert prob.projection is None  # taken off again after the fit
        assert f.train_rms_m == pytest.approx(rms_of(prob.residuals(f.system, exps[:2])), rel=1e-12)
        assert get_path(f.system, name) == f.values[name]
        fits[moves] = f
    held, moved = fits[False], fits[True]
    assert held.values[name] == 27.0
    assert moved.values[name] == pytest.approx(30.4, abs=0.5)
    off = "offset_force.external_force_n"
    assert abs(moved.values[off]) < abs(held.values[off])
    assert moved.train_rms_m < held.train_rms_m


@given(seed=st_h.integers(0, 2**32 - 1), k=st_h.integers(1, 3))
@settings(max_examples=20, deadline=None)
def test_a_projected_fit_problem_sees_no_residual_along_its_basis(seed: int, k: int) -> None:
    """Every residual vector a fit problem with a projection returns (failed simulations'
    included) is orthogonal to the basis; without one it is the plain scaled gap."""
    sys_ = ns.presets.seed(1e-3)
    ref = np.r_[np.full(30, 1e-3), np.full(200, 1.1e-3)]
    exps = [simulated_experiment(sys_, ref, "step", 1, 1e-3)]
    name = "plant.dahl.coulomb_force_n"
    free = [(name, Param(name="f", unit="N", lower=20, upper=40, initial=30.4))]
    prob = FitProblem(free, lambda v: replace_paths(sys_, {name: v[0]}), exps, 1, lambda s, e: s)
    plain = prob._vectors([np.array([1.3]), np.array([1.7])])
    rng = np.random.default_rng(seed)
    q, _ = np.linalg.qr(rng.standard_normal((plain[0].size, k)))
    prob.projection = q
    projected = prob._vectors([np.array([1.3]), np.array([1.7])])
    for v, p in zip(plain, projected, strict=True):
        assert np.abs(q.T @ p).max() <= 1e-9 * max(np.abs(v).max(), 1.0)
        assert p == pytest.approx(v - q @ (q.T @ v), abs=1e-12 * np.abs(v).max())
