"""Tests of the positioning test cycles (nanostage.cycles).

ISO 230-2 standard test cycle: docs/DOMAIN.md section 1.4. Step cycle: docs/SEED.md ("The
experiments": repeated unidirectional steps from the same start position).
"""

from __future__ import annotations

import csv
import dataclasses
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import example, given
from hypothesis import strategies as st

# isort: split
import nanostage
from nanostage import iso230_2
from nanostage.cycles import (
    MAX_N_TARGETS,
    Cycle,
    MoveProfile,
    min_targets,
    standard_test_cycle,
    step_cycle,
)

T = 1e-3  # the seed loop's control period [s]
UM = 1e-6

STEP = MoveProfile()
TRAPEZOID = MoveProfile(kind="trapezoid", max_velocity_m_per_s=5e-3, acceleration_m_per_s2=0.05)


def standard(**overrides: Any) -> Cycle:
    kwargs: dict[str, Any] = {
        "travel_m": 0.02,
        "overrun_m": 1e-3,
        "dwell_s": 0.05,
        "move": STEP,
        "sample_period_s": T,
        "seed": 7,
    }
    kwargs.update(overrides)
    return standard_test_cycle(**kwargs)


def steps(**overrides: Any) -> Cycle:
    kwargs: dict[str, Any] = {
        "step_m": 100 * UM,
        "repeats": 5,
        "dwell_s": 0.2,
        "return_s": 0.1,
        "sample_period_s": T,
    }
    kwargs.update(overrides)
    return step_cycle(**kwargs)


def dwell_samples(cycle: Cycle, dwell_s: float) -> int:
    return round(dwell_s / cycle.sample_period_s)


def last_different(reference: np.ndarray, index: int, value: float) -> float:
    """The last reference value before ``index`` that differs from ``value``."""
    before = reference[:index]
    diff = np.nonzero(before != value)[0]
    assert diff.shape[0] > 0, "the reference never differs from the target before it"
    return float(before[diff[-1]])


def check_measurements(cycle: Cycle, dwell_s: float) -> None:
    """Dwell, measurement at its end and approach side for every measurement."""
    ref = cycle.reference_m
    n_dwell = dwell_samples(cycle, dwell_s)
    for m, target, d in zip(cycle.measure_index, cycle.target_m, cycle.direction, strict=True):
        # The reference has been at the target for the whole dwell ...
        assert np.all(ref[m - n_dwell : m + 1] == target)
        # ... and leaves it right after the measurement (measured at the end of the dwell).
        assert m + 1 < ref.shape[0]
        assert ref[m + 1] != target
        # Approach side: from below for +1, from above for -1.
        prev = last_different(ref, m - n_dwell, target)
        assert (prev < target) if d > 0 else (prev > target)


# --------------------------------------------------------------------------------------------
# Standard test cycle: targets
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("travel_m", "expected"),
    [(1e-3, 5), (0.02, 5), (0.5, 5), (1.0, 5), (1.01, 6), (1.2, 6), (1.6, 8), (2.0, 10)],
)
def test_default_target_count_is_the_iso_minimum(travel_m: float, expected: int) -> None:
    assert min_targets(travel_m) == expected
    cycle = standard(travel_m=travel_m, overrun_m=min(1e-3, travel_m))
    n = cycle.targets_m.shape[0]
    assert n == expected
    assert n >= 5
    assert n >= 5 * travel_m - 1e-9  # at least 5 per metre


def test_target_count_below_the_minimum_is_rejected() -> None:
    with pytest.raises(nanostage.ConfigError, match=r"n_targets = 5 is outside \[6, 10000\]"):
        standard(travel_m=1.2, n_targets=5)
    with pytest.raises(nanostage.ConfigError, match=r"n_targets = 4 is outside \[5, "):
        standard(n_targets=4)
    with pytest.raises(nanostage.ConfigError, match="n_targets"):
        standard(n_targets=MAX_N_TARGETS + 1)
    assert standard(n_targets=12).targets_m.shape == (12,)


@pytest.mark.parametrize("seed", [0, 1, 2, 3, 12345])
@pytest.mark.parametrize("n_targets", [5, 9, 40])
def test_targets_are_within_the_travel_with_unequal_intervals(seed: int, n_targets: int) -> None:
    start, travel = -0.003, 0.02
    cycle = standard(start_m=start, travel_m=travel, n_targets=n_targets, seed=seed)
    targets = cycle.targets_m
    assert targets.shape == (n_targets,)
    assert np.all(targets >= start)
    assert np.all(targets <= start + travel)
    intervals = np.diff(targets)
    p = travel / (n_targets - 1)
    # offset_fraction = 0.25: every interval within p·(1 ± 0.5), strictly increasing targets
    assert np.all(intervals >= 0.5 * p * (1 - 1e-12))
    assert np.all(intervals <= 1.5 * p * (1 + 1e-12))
    # pairwise different intervals (no periodic sampling)
    assert np.unique(intervals).shape == intervals.shape
    assert float(np.min(np.diff(np.sort(intervals)))) > 1e-9 * p
    # the offsets are real: the targets are not the uniform grid
    assert np.max(np.abs(targets - (start + np.arange(n_targets) * p))) > 0.01 * p


def test_offset_fraction_bounds_the_offsets() -> None:
    cycle = standard(n_targets=30, offset_fraction=0.05, seed=3)
    p = 0.02 / 29
    offsets = cycle.targets_m - np.arange(30) * p
    assert np.all(np.abs(offsets) <= 0.05 * p * (1 + 1e-9))
    assert offsets[0] >= 0.0
    assert offsets[-1] <= 0.0
    for bad in (0.0, 0.5, -0.1, math.nan):
        with pytest.raises(
            nanostage.ConfigError, match=r"offset_fraction = .* is outside \(0, 0.5\)"
        ):
            standard(offset_fraction=bad)


def test_same_seed_same_cycle_different_seed_different_targets() -> None:
    a = standard(seed=42, move=TRAPEZOID)
    b = standard(seed=42, move=TRAPEZOID)
    c = standard(seed=43, move=TRAPEZOID)
    for name in ("reference_m", "measure_index", "target_m", "direction", "run"):
        assert np.array_equal(getattr(a, name), getattr(b, name)), name
    assert not np.array_equal(a.targets_m, c.targets_m)
    assert not np.any(a.targets_m[1:-1] == c.targets_m[1:-1])


# --------------------------------------------------------------------------------------------
# Standard test cycle: approaches, overrun, dwell
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("move", [STEP, TRAPEZOID], ids=["step", "trapezoid"])
def test_five_approaches_per_direction_and_target(move: MoveProfile) -> None:
    cycle = standard(move=move)
    assert cycle.n_measurements == 2 * 5 * cycle.targets_m.shape[0]
    for target in cycle.targets_m:
        for d in (+1, -1):
            sel = (cycle.target_m == target) & (cycle.direction == d)
            assert sorted(cycle.run[sel].tolist()) == [1, 2, 3, 4, 5]
    assert set(cycle.run.tolist()) == {1, 2, 3, 4, 5}


@pytest.mark.parametrize("runs", [2, 3, 7])
def test_runs_parameter(runs: int) -> None:
    cycle = standard(runs=runs)
    m = cycle.targets_m.shape[0]
    assert cycle.n_measurements == 2 * runs * m
    assert np.array_equal(np.bincount(cycle.run)[1:], np.full(runs, 2 * m))


def test_linear_cycle_order() -> None:
    """Each run: up through all targets in order, then down through all in reverse."""
    cycle = standard(runs=3)
    targets = cycle.targets_m
    m = targets.shape[0]
    for j in (1, 2, 3):
        sel = cycle.run == j
        assert np.array_equal(cycle.direction[sel], np.repeat([1, -1], m))
        assert np.array_equal(cycle.target_m[sel], np.concatenate([targets, targets[::-1]]))
    assert np.all(np.diff(cycle.measure_index) > 0)
    assert np.array_equal(cycle.target_m, cycle.reference_m[cycle.measure_index])


@pytest.mark.parametrize("move", [STEP, TRAPEZOID], ids=["step", "trapezoid"])
def test_overrun_past_both_ends_before_every_reversal(move: MoveProfile) -> None:
    overrun = 0.7e-3
    cycle = standard(move=move, overrun_m=overrun)
    ref = cycle.reference_m
    first, last = float(cycle.targets_m[0]), float(cycle.targets_m[-1])
    low, high = first - overrun, last + overrun
    # the reference starts at start_m = 0, goes to the lower reversal point and stays within
    # [low, high] from then on
    reached_low = np.nonzero(ref == low)[0]
    assert reached_low.shape[0] > 0
    assert 0 < reached_low[0] < cycle.measure_index[0]  # before the first ↑ approach
    assert float(np.min(ref[reached_low[0] :])) == low
    assert float(np.max(ref)) == high
    idx, d = cycle.measure_index, cycle.direction
    for k in range(1, idx.shape[0]):
        if d[k] == d[k - 1]:
            continue
        between = ref[idx[k - 1] + 1 : idx[k]]
        if d[k] < 0:  # reversal at the top: past the last target
            assert float(np.max(between)) == high
        else:  # reversal at the bottom: past the first target
            assert float(np.min(between)) == low
    # the reversal point is held (overrun_dwell_s defaults to dwell_s)
    assert np.count_nonzero(ref == np.max(ref)) >= 5 * dwell_samples(cycle, 0.05)


@pytest.mark.parametrize("move", [STEP, TRAPEZOID], ids=["step", "trapezoid"])
def test_approach_sides_and_dwell(move: MoveProfile) -> None:
    cycle = standard(move=move, dwell_s=0.03)
    check_measurements(cycle, 0.03)


def test_step_approach_is_from_the_previous_point() -> None:
    """With steps the sample just before the dwell is the previous target or reversal."""
    cycle = standard(dwell_s=0.02)
    n_dwell = dwell_samples(cycle, 0.02)
    ref = cycle.reference_m
    for m, target, d in zip(cycle.measure_index, cycle.target_m, cycle.direction, strict=True):
        before = ref[m - n_dwell - 1]
        assert (before < target) if d > 0 else (before > target)
        assert ref[m - n_dwell] == target


def test_trapezoid_approach_is_monotone() -> None:
    """The move into each target never goes past it (no overshoot of the reference)."""
    cycle = standard(move=TRAPEZOID)
    n_dwell = dwell_samples(cycle, 0.05)
    ref = cycle.reference_m
    starts = np.concatenate([[0], cycle.measure_index[:-1] + 1])
    for s, m, target, d in zip(
        starts, cycle.measure_index, cycle.target_m, cycle.direction, strict=True
    ):
        arrival = m - n_dwell
        # the previous stop (target or reversal) is held before the move starts
        seg = ref[s : arrival + 1]
        rest = np.nonzero(np.diff(seg) != 0)[0]
        move_part = seg[rest[-1] :] if rest.shape[0] else seg
        steps_ = np.diff(move_part)
        assert np.all(steps_ * d >= 0)
        assert np.all((move_part - target) * d <= 0)


def test_dwell_rounding_and_overrun_dwell() -> None:
    cycle = standard(dwell_s=0.0304, overrun_dwell_s=0.2)
    n_dwell = 30
    ref = cycle.reference_m
    for m, target in zip(cycle.measure_index, cycle.target_m, strict=True):
        assert np.all(ref[m - n_dwell : m + 1] == target)
        assert ref[m - n_dwell - 1] != target
    top = float(np.max(ref))
    runs_at_top = np.diff(np.nonzero(np.diff((ref == top).astype(np.int8)))[0])
    assert runs_at_top[0] == 200  # samples at the reversal point = overrun_dwell_s / T


def test_unidirectional_standard_cycle() -> None:
    cycle = standard(bidirectional=False, runs=4)
    assert np.all(cycle.direction == 1)
    assert cycle.n_measurements == 4 * cycle.targets_m.shape[0]
    check_measurements(cycle, 0.05)
    # it still goes down between runs, below the first target by the overrun
    first = float(cycle.targets_m[0])
    assert float(np.min(cycle.reference_m)) == pytest.approx(first - 1e-3, abs=1e-15)
    result = cycle.evaluate(cycle.target_m + 1 * UM)
    assert not result.bidirectional
    assert result.n_targets == cycle.targets_m.shape[0]


def test_cycle_starts_at_the_start_position() -> None:
    cycle = standard(start_m=0.004)
    assert cycle.reference_m[0] == 0.004
    assert np.all(cycle.reference_m[:50] == 0.004)  # one dwell at rest at the start
    assert cycle.duration_s == pytest.approx(cycle.n_samples * T)
    assert cycle.time_s[-1] == pytest.approx((cycle.n_samples - 1) * T)
    assert np.allclose(cycle.measure_time_s, cycle.measure_index * T)


def test_bidirectional_evaluation_recovers_known_deviations() -> None:
    """Synthetic measurements: +1.5 µm on the way up, -0.5 µm down, run-dependent scatter."""
    cycle = standard(runs=5)
    scatter = 0.1 * UM * (cycle.run - 3)
    actual = cycle.target_m + np.where(cycle.direction > 0, 1.5 * UM, -0.5 * UM) + scatter
    result = cycle.evaluate(actual)
    assert result.bidirectional
    assert np.allclose(result.targets_m, cycle.targets_m, rtol=0, atol=1e-15)
    assert result.mean_reversal_m == pytest.approx(2.0 * UM, abs=1e-12)
    assert result.reversal_m == pytest.approx(2.0 * UM, abs=1e-12)
    s = float(np.std(0.1 * UM * np.arange(-2, 3), ddof=1))
    assert result.repeatability_up_m == pytest.approx(4 * s, rel=1e-6)
    assert result.systematic_deviation_m == pytest.approx(2.0 * UM, abs=1e-12)


# --------------------------------------------------------------------------------------------
# Move profiles
# --------------------------------------------------------------------------------------------


def limits_hold(ref: np.ndarray, v: float, a: float, period_s: float) -> tuple[bool, bool]:
    # Each sample is from_m plus a profile offset, rounded (a few ulps of the position); a
    # second difference combines three of them: up to about 4 × 2 ulps of rounding, so 16
    # ulps (8 let a hypothesis example at 0.027 m with a 1e-10 m second difference fail
    # by 0.4 ulp).
    ulp = 16.0 * np.spacing(float(np.max(np.abs(ref))) + 1e-300)
    vel_ok = bool(np.all(np.abs(np.diff(ref)) <= v * period_s * (1 + 1e-12) + ulp))
    acc_ok = bool(np.all(np.abs(np.diff(ref, 2)) <= a * period_s**2 * (1 + 1e-12) + ulp))
    return vel_ok, acc_ok


def test_trapezoid_limits_respected_and_reached() -> None:
    v, a = TRAPEZOID.max_velocity_m_per_s, TRAPEZOID.acceleration_m_per_s2
    assert v is not None and a is not None
    cycle = standard(move=TRAPEZOID)
    ref = cycle.reference_m
    assert limits_hold(ref, v, a, T) == (True, True)
    # the limits are actually used (intervals of ≥ 2.5 mm reach the 5 mm/s cruise)
    assert float(np.max(np.abs(np.diff(ref)))) >= 0.999 * v * T
    assert float(np.max(np.abs(np.diff(ref, 2)))) >= 0.9 * a * T**2
    # the same cycle with steps breaks both limits: the check can fail
    assert limits_hold(standard(move=STEP).reference_m, v, a, T) == (False, False)


def test_trapezoid_move_timing() -> None:
    move = MoveProfile(kind="trapezoid", max_velocity_m_per_s=0.01, acceleration_m_per_s2=0.1)
    # long move: 0.1 s accel (0.5 mm), 0.4 s cruise (4 mm), 0.1 s decel (0.5 mm) = 0.6 s
    assert move.move_samples(5e-3, T) == 600
    # short move: triangular, t = 2·sqrt(d/a) = 2·sqrt(1e-4 / 0.1) ≈ 63.2 ms
    assert move.move_samples(-1e-4, T) == math.ceil(2 * math.sqrt(1e-3) / T)
    assert move.move_samples(0.0, T) == 1
    assert STEP.move_samples(5e-3, T) == 1
    s = move.samples(1e-3, 6e-3, T)
    assert s.shape == (600,)
    assert s[-1] == 6e-3
    assert s[0] == pytest.approx(1e-3 + 0.5 * 0.1 * T**2, rel=1e-12)
    assert s[299] == pytest.approx(3.5e-3, rel=1e-12)  # the middle of the move at t = 0.3 s
    assert np.all(np.diff(s) > 0)
    down = move.samples(6e-3, 1e-3, T)
    assert np.allclose(down[:-1], 7e-3 - s[:-1], rtol=0, atol=1e-15)  # mirror image
    assert np.array_equal(STEP.samples(1e-3, 6e-3, T), [6e-3])


@given(
    from_m=st.floats(-0.05, 0.05),
    to_m=st.floats(-0.05, 0.05),
    v=st.floats(1e-3, 0.05),
    a=st.floats(1e-2, 10.0),
    period_s=st.sampled_from([1e-4, 5e-4, 1e-3]),
)
# rounding at the cruise/deceleration join once made these step back by one ulp
@example(from_m=0.01, to_m=0.001, v=0.001, a=1.0, period_s=1e-4)
@example(from_m=-0.01, to_m=-0.001, v=0.001, a=1.0, period_s=1e-4)
@example(from_m=0.001, to_m=0.01, v=0.001, a=1.0, period_s=1e-4)
@example(from_m=0.02734375, to_m=-0.02734375, v=0.03125, a=0.01, period_s=1e-4)
def test_trapezoid_samples_property(
    from_m: float, to_m: float, v: float, a: float, period_s: float
) -> None:
    move = MoveProfile(kind="trapezoid", max_velocity_m_per_s=v, acceleration_m_per_s2=a)
    s = move.samples(from_m, to_m, period_s)
    assert s.shape == (move.move_samples(to_m - from_m, period_s),)
    assert s[-1] == to_m
    path = np.concatenate([[from_m, from_m], s, [to_m, to_m]])  # at rest before and after
    assert limits_hold(path, v, a, period_s) == (True, True)
    sign = 1.0 if to_m >= from_m else -1.0
    assert np.all(np.diff(path) * sign >= 0)


def test_move_profile_validation() -> None:
    with pytest.raises(nanostage.ConfigError, match="max_velocity_m_per_s = None is invalid"):
        MoveProfile(kind="trapezoid", acceleration_m_per_s2=1.0)
    with pytest.raises(nanostage.ConfigError, match="acceleration_m_per_s2 = None is invalid"):
        MoveProfile(kind="trapezoid", max_velocity_m_per_s=1.0)
    with pytest.raises(
        nanostage.ConfigError, match=r"acceleration_m_per_s2 = -1.0 is outside \(0, inf\) m/s²"
    ):
        MoveProfile(kind="trapezoid", max_velocity_m_per_s=1.0, acceleration_m_per_s2=-1.0)
    with pytest.raises(nanostage.ConfigError, match="max_velocity_m_per_s = inf is outside"):
        MoveProfile(kind="trapezoid", max_velocity_m_per_s=math.inf, acceleration_m_per_s2=1.0)
    with pytest.raises(nanostage.ConfigError, match=r"max_velocity_m_per_s = 1\.0 is invalid for"):
        MoveProfile(max_velocity_m_per_s=1.0)
    with pytest.raises(nanostage.ConfigError, match="kind = 'ramp' is invalid"):
        MoveProfile(kind="ramp")  # type: ignore[arg-type]
    with pytest.raises(dataclasses.FrozenInstanceError):
        STEP.kind = "trapezoid"  # type: ignore[misc]


# --------------------------------------------------------------------------------------------
# Step cycle
# --------------------------------------------------------------------------------------------


def test_step_cycle_labels_and_timing() -> None:
    cycle = steps(step_m=100 * UM, repeats=4, start_m=0.002, dwell_s=0.2, return_s=0.1)
    target = 0.002 + 100 * UM
    assert np.array_equal(cycle.target_m, np.full(4, target))
    assert np.array_equal(cycle.targets_m, [target])
    assert np.array_equal(cycle.direction, np.ones(4, dtype=np.int64))
    assert np.array_equal(cycle.run, [1, 2, 3, 4])
    # 100 samples at the start, step, 200 samples dwell, measure, return, 100 at the start...
    assert np.array_equal(cycle.measure_index, 300 + 301 * np.arange(4))
    assert cycle.n_samples == 100 + 4 * 301
    ref = cycle.reference_m
    assert ref[0] == 0.002
    assert ref[-1] == 0.002
    assert set(np.unique(ref).tolist()) == {0.002, target}
    # exactly one step up per run
    assert np.count_nonzero(np.diff(ref) > 0) == 4
    check_measurements(cycle, 0.2)
    # every step starts from the start position, held for return_s
    for m in cycle.measure_index:
        assert np.all(ref[m - 200 - 100 : m - 200] == 0.002)


def test_step_cycle_negative_direction() -> None:
    cycle = steps(direction=-1, start_m=0.01, step_m=1e-3, repeats=3)
    assert np.allclose(cycle.target_m, 0.009, rtol=0, atol=1e-15)
    assert np.array_equal(cycle.direction, [-1, -1, -1])
    check_measurements(cycle, 0.2)
    records = cycle.records(cycle.target_m)
    assert records.direction.tolist() == ["-", "-", "-"]
    # the evaluator takes unidirectional data as ↑ only (documented limitation)
    with pytest.raises(iso230_2.Iso230InputError, match="no '\\+' records"):
        cycle.evaluate(cycle.target_m)


def test_step_cycle_with_trapezoid_moves() -> None:
    move = MoveProfile(kind="trapezoid", max_velocity_m_per_s=1e-3, acceleration_m_per_s2=0.02)
    cycle = steps(step_m=1e-3, repeats=3, move=move, dwell_s=0.1, return_s=0.1)
    assert limits_hold(cycle.reference_m, 1e-3, 0.02, T) == (True, True)
    check_measurements(cycle, 0.1)
    assert cycle.n_measurements == 3


@given(
    step_m=st.floats(1e-7, 1e-2),
    repeats=st.integers(2, 8),
    start_m=st.floats(-0.1, 0.1),
    dwell_n=st.integers(1, 40),
    return_n=st.integers(1, 40),
    direction=st.sampled_from([1, -1]),
)
def test_step_cycle_property(
    step_m: float, repeats: int, start_m: float, dwell_n: int, return_n: int, direction: int
) -> None:
    cycle = steps(
        step_m=step_m,
        repeats=repeats,
        start_m=start_m,
        dwell_s=dwell_n * T,
        return_s=return_n * T,
        direction=direction,
    )
    assert cycle.n_samples == return_n + repeats * (dwell_n + 1 + return_n)
    assert cycle.reference_m[0] == start_m
    assert np.all(cycle.measure_index >= 0)
    assert np.all(cycle.measure_index < cycle.n_samples)
    assert np.array_equal(cycle.run, np.arange(1, repeats + 1))
    assert np.all(cycle.direction == direction)
    assert cycle.targets_m.shape == (1,)
    check_measurements(cycle, dwell_n * T)


# --------------------------------------------------------------------------------------------
# Hypothesis: standard cycle
# --------------------------------------------------------------------------------------------


@st.composite
def standard_kwargs(draw: st.DrawFn) -> dict[str, Any]:
    travel = draw(st.floats(1e-5, 0.01))
    n_min = min_targets(travel)
    kind = draw(st.sampled_from(["step", "trapezoid"]))
    move = (
        STEP
        if kind == "step"
        else MoveProfile(
            kind="trapezoid",
            max_velocity_m_per_s=draw(st.floats(0.01, 0.1)),
            acceleration_m_per_s2=draw(st.floats(0.1, 10.0)),
        )
    )
    period = draw(st.sampled_from([1e-3, 5e-4]))
    return {
        "travel_m": travel,
        "start_m": draw(st.floats(-0.05, 0.05)),
        "n_targets": draw(st.integers(n_min, n_min + 6)),
        "runs": draw(st.integers(2, 5)),
        "overrun_m": draw(st.floats(0.01, 1.0)) * travel,
        "dwell_s": draw(st.integers(1, 8)) * period,
        "move": move,
        "sample_period_s": period,
        "seed": draw(st.integers(0, 2**32)),
        "bidirectional": draw(st.booleans()),
        "offset_fraction": draw(st.floats(0.01, 0.49)),
    }


@given(kwargs=standard_kwargs())
def test_standard_cycle_property(kwargs: dict[str, Any]) -> None:
    cycle = standard_test_cycle(**kwargs)
    start, travel, n = kwargs["start_m"], kwargs["travel_m"], kwargs["n_targets"]
    targets = cycle.targets_m
    assert targets.shape == (n,)
    assert np.all(np.diff(targets) > 0)  # monotone, distinct
    assert targets[0] >= start
    assert targets[-1] <= start + travel
    assert np.unique(np.diff(targets)).shape == (n - 1,)  # unequal intervals
    assert np.all(cycle.measure_index >= 0)
    assert np.all(cycle.measure_index < cycle.n_samples)
    assert np.all(np.diff(cycle.measure_index) > 0)
    per_dir = 2 if kwargs["bidirectional"] else 1
    assert cycle.n_measurements == per_dir * kwargs["runs"] * n
    assert cycle.reference_m[0] == start
    check_measurements(cycle, kwargs["dwell_s"])
    move: MoveProfile = kwargs["move"]
    if move.kind == "trapezoid":
        assert move.max_velocity_m_per_s is not None and move.acceleration_m_per_s2 is not None
        limits = limits_hold(
            cycle.reference_m,
            move.max_velocity_m_per_s,
            move.acceleration_m_per_s2,
            kwargs["sample_period_s"],
        )
        assert limits == (True, True)


# --------------------------------------------------------------------------------------------
# Validation
# --------------------------------------------------------------------------------------------


def test_error_message_names_argument_value_and_range() -> None:
    with pytest.raises(
        nanostage.ConfigError, match=r"^dwell_s = -1 is outside \[sample_period_s = 0.001, 60\] s$"
    ):
        standard(dwell_s=-1)
    assert issubclass(nanostage.ConfigError, ValueError)


@pytest.mark.parametrize(
    ("name", "value", "valid"),
    [
        ("travel_m", 0.0, "[1e-06, 2] m"),
        ("travel_m", 2.5, "[1e-06, 2] m"),
        ("travel_m", math.nan, "[1e-06, 2] m"),
        ("start_m", 11.0, "[-10, 10] m"),
        ("runs", 1, "[2, 10000]"),
        ("overrun_m", 0.0, "(0, 0.02] m"),
        ("overrun_m", 0.03, "(0, 0.02] m"),
        ("dwell_s", 61.0, "[sample_period_s = 0.001, 60] s"),
        ("dwell_s", 1e-4, "[sample_period_s = 0.001, 60] s"),
        ("overrun_dwell_s", 0.0, "[sample_period_s = 0.001, 60] s"),
        ("sample_period_s", 0.0, "(0, 1] s"),
        ("sample_period_s", -1e-3, "(0, 1] s"),
        ("seed", -1, "[0, inf)"),
    ],
)
def test_standard_cycle_validation(name: str, value: object, valid: str) -> None:
    expected = f"{name} = {value!r} is outside {valid}"
    with pytest.raises(nanostage.ConfigError) as info:
        standard(**{name: value})
    assert str(info.value) == expected


@pytest.mark.parametrize(
    ("name", "value", "valid"),
    [
        ("step_m", 0.0, "(0, 1] m"),
        ("step_m", -1e-4, "(0, 1] m"),
        ("repeats", 1, "[2, 16777216]"),
        ("return_s", 0.0, "[sample_period_s = 0.001, 60] s"),
        ("dwell_s", math.inf, "[sample_period_s = 0.001, 60] s"),
        ("direction", 0, "{+1, -1}"),
        ("direction", 2, "{+1, -1}"),
        ("start_m", -10.5, "[-10, 10] m"),
    ],
)
def test_step_cycle_validation(name: str, value: object, valid: str) -> None:
    with pytest.raises(nanostage.ConfigError) as info:
        steps(**{name: value})
    assert str(info.value) == f"{name} = {value!r} is outside {valid}"


def test_step_beyond_the_position_limit_is_rejected() -> None:
    with pytest.raises(nanostage.ConfigError, match=r"step_m = 0.5 is outside \(0, 0.2\] m"):
        steps(start_m=9.8, step_m=0.5)
    with pytest.raises(nanostage.ConfigError, match=r"travel_m = 1.0 is outside"):
        standard(start_m=9.5, travel_m=1.0)


@pytest.mark.parametrize(
    ("name", "value"),
    [("runs", 5.0), ("n_targets", "7"), ("seed", 1.5), ("move", "step"), ("bidirectional", 1)],
)
def test_wrong_types_raise_type_error(name: str, value: object) -> None:
    with pytest.raises(TypeError, match=name):
        standard(**{name: value})


def test_arguments_are_keyword_only() -> None:
    with pytest.raises(TypeError):
        step_cycle(1e-4, 5, 0.0, 0.1, 0.1, 1e-3)  # type: ignore[call-arg]
    with pytest.raises(TypeError):
        standard(unknown_argument=1)


def test_huge_cycles_are_rejected_with_the_sample_count() -> None:
    # 60000 + 100000 · (60000 + 1 + 60000) samples
    with pytest.raises(nanostage.ConfigError, match="would have 12000160000 samples, more than"):
        steps(repeats=100_000, dwell_s=60.0, return_s=60.0)
    with pytest.raises(nanostage.ConfigError, match=r"standard test cycle would have \d+ samples"):
        standard(runs=10_000, dwell_s=60.0)
    slow = MoveProfile(kind="trapezoid", max_velocity_m_per_s=1e-9, acceleration_m_per_s2=1.0)
    with pytest.raises(nanostage.ConfigError, match=r"would have \d+ samples, more than 2\*\*24"):
        standard(move=slow)
    # just under the limit is fine
    n_ok = steps(repeats=2, dwell_s=1.0, return_s=1.0).n_samples
    assert n_ok == 1000 + 2 * 2001


# --------------------------------------------------------------------------------------------
# Cycle object, records and CSV
# --------------------------------------------------------------------------------------------


def test_cycle_arrays_are_read_only_and_typed() -> None:
    cycle = standard()
    for name, dtype in [
        ("reference_m", np.float64),
        ("measure_index", np.int64),
        ("target_m", np.float64),
        ("direction", np.int64),
        ("run", np.int64),
    ]:
        arr = getattr(cycle, name)
        assert arr.dtype == dtype, name
        assert arr.ndim == 1
        assert not arr.flags.writeable, name
    with pytest.raises(dataclasses.FrozenInstanceError):
        cycle.sample_period_s = 2e-3  # type: ignore[misc]


def test_cycle_constructor_validation() -> None:
    ok: dict[str, Any] = {
        "reference_m": [0.0, 1.0, 1.0, 0.0],
        "sample_period_s": T,
        "measure_index": [2],
        "target_m": [1.0],
        "direction": [1],
        "run": [1],
    }
    assert Cycle(**ok).n_measurements == 1
    bad: list[tuple[dict[str, Any], str]] = [
        ({"measure_index": [4]}, "measure_index is invalid"),
        ({"measure_index": [-1]}, "measure_index is invalid"),
        ({"target_m": [0.5]}, "target_m is invalid"),
        ({"direction": [0]}, "direction is invalid"),
        ({"run": [0]}, "run is invalid"),
        ({"run": [1, 2]}, "run = array of shape"),
        ({"reference_m": [[0.0]]}, "reference_m = array of shape"),
        ({"reference_m": [0.0, math.nan, 1.0, 0.0]}, "non-finite"),
        ({"sample_period_s": 0.0}, "sample_period_s = 0.0 is outside"),
    ]
    for change, message in bad:
        with pytest.raises(nanostage.ConfigError, match=message):
            Cycle(**{**ok, **change})


def test_records_are_the_evaluator_input() -> None:
    cycle = standard(runs=3)
    rng = np.random.default_rng(0)
    actual = cycle.target_m + rng.normal(0.0, 0.3 * UM, cycle.n_measurements)
    records = cycle.records(actual)
    assert isinstance(records, iso230_2.MeasurementRecords)
    assert len(records) == cycle.n_measurements
    assert np.array_equal(records.target_m, cycle.target_m)
    assert np.array_equal(records.actual_m, actual)
    assert np.array_equal(records.run, cycle.run)
    assert records.direction.tolist() == ["+" if d > 0 else "-" for d in cycle.direction]
    via_cycle = cycle.evaluate(actual, coverage_factor=3.0)
    direct = iso230_2.evaluate_records(
        cycle.target_m, records.direction, cycle.run, actual, coverage_factor=3.0
    )
    assert via_cycle.to_dict() == direct.to_dict()
    assert via_cycle.n_targets == cycle.targets_m.shape[0]
    assert np.array_equal(via_cycle.n_runs_up, np.full(via_cycle.n_targets, 3))
    with pytest.raises(iso230_2.Iso230InputError, match="actual_m"):
        cycle.records(actual[:-1])
    with pytest.raises(nanostage.ConfigError, match="one value per sample"):
        cycle.at_measurements(actual)


def test_csv_rows_round_trip(tmp_path: Path) -> None:
    cycle = standard(runs=2)
    actual = cycle.target_m + 1e-7 * cycle.run * cycle.direction
    rows = cycle.to_csv_rows(actual)
    assert rows[0] == ("target_m", "direction", "run", "actual_m")
    assert len(rows) == cycle.n_measurements + 1
    path = tmp_path / "meas.csv"
    with path.open("w", newline="", encoding="utf-8") as fh:
        csv.writer(fh).writerows(rows)
    back = iso230_2.read_measurement_csv(path)
    assert np.array_equal(back.target_m, cycle.target_m)
    assert np.array_equal(back.actual_m, actual)
    assert np.array_equal(back.run, cycle.run)
    written = cycle.write_csv(tmp_path / "meas2.csv", actual)
    assert written.read_text(encoding="utf-8") == path.read_text(encoding="utf-8")
    assert back.evaluate().to_dict() == cycle.evaluate(actual).to_dict()


# --------------------------------------------------------------------------------------------
# End to end: the seed closed loop on the paper's 100 µm steps
# --------------------------------------------------------------------------------------------


def test_seed_closed_loop_step_cycle_end_to_end() -> None:
    step = 100 * UM
    system = nanostage.presets.seed(step_m=step)
    cycle = step_cycle(
        step_m=step,
        repeats=3,
        dwell_s=0.3,
        return_s=0.3,
        sample_period_s=system.controller.sample_period_s,
    )
    trace = nanostage.simulate(system, cycle.reference_m)
    assert np.array_equal(trace.reference_m, cycle.reference_m)
    actual = cycle.at_measurements(trace.position_m)
    result = cycle.evaluate(actual)
    assert result.n_targets == 1
    assert not result.bidirectional
    assert np.array_equal(result.targets_m, [step])
    final_error = trace.position_m[cycle.measure_index] - trace.reference_m[cycle.measure_index]
    assert np.allclose(result.deviations_up_m[0], final_error, rtol=0, atol=1e-18)
    # the loop has settled by the end of the dwell: sub-µm final errors, at rest
    assert np.all(np.abs(final_error) < 1 * UM)
    assert np.all(np.abs(trace.velocity_m_per_s[cycle.measure_index]) < 1e-5)
    # and the moves happened: halfway through each step the axis is near the target
    assert np.all(trace.position_m[cycle.measure_index - 150] > 0.5 * step)
    assert result.repeatability_up_m == pytest.approx(4 * np.std(final_error, ddof=1), rel=1e-9)
    assert result.accuracy_up_m >= result.repeatability_up_m / 2
