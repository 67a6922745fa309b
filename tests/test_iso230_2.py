"""Tests of the ISO 230-2 evaluator (nanostage.iso230_2).

Formulas and invariants: docs/DOMAIN.md section 1 (k = coverage factor, default 2).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
from pathlib import Path

import hypothesis.extra.numpy as hnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

# isort: split
# (keeps the import sorting stable whether or not ruff is told that nanostage is first-party)
from nanostage import iso230_2
from nanostage.iso230_2 import Iso230InputError

UM = 1e-6  # one micrometre in metres

# --------------------------------------------------------------------------------------------
# Hand-computed example (values in µm, targets 0 mm and 10 mm, 3 runs per direction, k = 2)
# --------------------------------------------------------------------------------------------
#
# target 0 mm:   ↑ 1, 2, 3      x̄↑ = 2,  s↑ = sqrt((1 + 0 + 1) / 2) = 1
#                ↓ -1, 0, 1     x̄↓ = 0,  s↓ = 1
#                x̄ = (2 + 0) / 2 = 1,  B = 2 - 0 = 2
#                R↑ = 4·1 = 4, R↓ = 4,  R = max(2·1 + 2·1 + |2|, 4, 4) = 6
# target 10 mm:  ↑ 4, 6, 8      x̄↑ = 6,  s↑ = sqrt((4 + 0 + 4) / 2) = 2
#                ↓ 3, 5, 7      x̄↓ = 5,  s↓ = 2
#                x̄ = 5.5,  B = 1
#                R↑ = 8, R↓ = 8,  R = max(2·2 + 2·2 + 1, 8, 8) = 9
# axis:  E↑ = 6 - 2 = 4;  E↓ = 5 - 0 = 5;  E = max(2, 6, 0, 5) - min(2, 6, 0, 5) = 6 - 0 = 6
#        M = 5.5 - 1 = 4.5;  B = max(|2|, |1|) = 2;  B̄ = (2 + 1) / 2 = 1.5
#        R↑ = 8;  R↓ = 8;  R = max(6, 9) = 9
#        A↑ = max(2 + 2, 6 + 4) - min(2 - 2, 6 - 4) = 10 - 0 = 10
#        A↓ = max(0 + 2, 5 + 4) - min(0 - 2, 5 - 4) = 9 - (-2) = 11
#        A  = max(4, 10, 2, 9) - min(0, 2, -2, 1) = 10 - (-2) = 12
HAND_TARGETS_M = np.array([0.0, 0.010])
HAND_UP_M = np.array([[1.0, 2.0, 3.0], [4.0, 6.0, 8.0]]) * UM
HAND_DOWN_M = np.array([[-1.0, 0.0, 1.0], [3.0, 5.0, 7.0]]) * UM
HAND_AXIS_UM = {
    "systematic_deviation_up_m": 4.0,
    "systematic_deviation_down_m": 5.0,
    "systematic_deviation_m": 6.0,
    "mean_deviation_range_m": 4.5,
    "repeatability_up_m": 8.0,
    "repeatability_down_m": 8.0,
    "repeatability_m": 9.0,
    "reversal_m": 2.0,
    "mean_reversal_m": 1.5,
    "accuracy_up_m": 10.0,
    "accuracy_down_m": 11.0,
    "accuracy_m": 12.0,
}

# --------------------------------------------------------------------------------------------
# Reference vector: ecmc report, paulscherrerinstitute/ecmccfg,
# examples/test/fat_sat/report.md (commit 072a917e6c0a20132b75f29ce7be50c99f6d34cc).
# Targets [mm] and the tables "x(i,j) = reference position - target position [mm]",
# copied verbatim; 5 targets x 5 runs per direction.
# --------------------------------------------------------------------------------------------
ECMC_TARGETS_MM = [-10.0, -4.88, 0.24, 5.36, 10.48]
ECMC_UP_MM = [
    [-8.102e-05, -0.00010202, -8.702e-05, -9.202e-05, -0.00010002],
    [-8.702e-05, -9.702e-05, -9.702e-05, -9.502e-05, -8.202e-05],
    [-7.202e-05, -9.002e-05, -8.802e-05, -8.702e-05, -8.702e-05],
    [-0.00010202, -8.602e-05, -8.602e-05, -9.302e-05, -7.802e-05],
    [-0.00010002, -0.00011202, -0.00012902, -0.00010902, -9.702e-05],
]
ECMC_DOWN_MM = [
    [-9.902e-05, -9.402e-05, -8.202e-05, -9.102e-05, -9.402e-05],
    [-0.00010302, -0.00010402, -9.502e-05, -0.00011102, -9.302e-05],
    [-8.602e-05, -0.00010202, -9.102e-05, -7.602e-05, -9.902e-05],
    [-7.202e-05, -9.202e-05, -9.502e-05, -0.00010302, -8.102e-05],
    [-0.00010402, -0.00012602, -0.00013002, -0.00014102, -0.00010702],
]
# Recomputed with ISO 230-2 formulas (DOMAIN.md §1.3), µm, 4 decimals. NB the ecmc report
# itself prints E = 0.0246 µm (= E↑, impossible since E >= E↓) and R = 0.0629 µm
# (= max(R↑, R↓) instead of maxᵢ Rᵢ); both are wrong and must not be reproduced.
ECMC_AXIS_UM = {
    "systematic_deviation_up_m": 0.0246,
    "systematic_deviation_down_m": 0.0330,
    "systematic_deviation_m": 0.0368,
    "mean_deviation_range_m": 0.0277,
    "repeatability_up_m": 0.0503,
    "repeatability_down_m": 0.0629,
    "repeatability_m": 0.0688,
    "reversal_m": 0.0122,
    "mean_reversal_m": 0.0054,
    "accuracy_up_m": 0.0643,
    "accuracy_down_m": 0.0888,
    "accuracy_m": 0.0888,
}
# Per-target values printed by the report (mm): x_avg↑, x_avg↓, B(i), S_fwd, S_bwd, R(i).
ECMC_MEAN_UP_MM = [-9.242e-05, -9.162e-05, -8.482e-05, -8.902e-05, -0.00010942]
ECMC_MEAN_DOWN_MM = [-9.202e-05, -0.00010122, -9.082e-05, -8.862e-05, -0.00012162]
ECMC_REVERSAL_MM = [-4e-07, 9.6e-06, 6e-06, -4e-07, 1.22e-05]
ECMC_S_UP_MM = [8.79e-06, 6.77e-06, 7.26e-06, 9e-06, 1.258e-05]
ECMC_S_DOWN_MM = [6.28e-06, 7.29e-06, 1.043e-05, 1.218e-05, 1.573e-05]
ECMC_R_I_MM = [3.517e-05, 3.772e-05, 4.17e-05, 4.871e-05, 6.882e-05]  # per target: correct


def ecmc_result(coverage_factor: float = 2.0) -> iso230_2.Iso230Result:
    return iso230_2.evaluate(
        np.array(ECMC_TARGETS_MM) * 1e-3,
        np.array(ECMC_UP_MM) * 1e-3,
        np.array(ECMC_DOWN_MM) * 1e-3,
        coverage_factor=coverage_factor,
    )


def hand_result() -> iso230_2.Iso230Result:
    return iso230_2.evaluate(HAND_TARGETS_M, HAND_UP_M, HAND_DOWN_M)


def flatten(
    targets_m: np.ndarray, up_m: np.ndarray, down_m: np.ndarray | None
) -> tuple[list[float], list[str], list[int], list[float]]:
    """Matrices -> flat records (target, direction, run, actual = target + deviation)."""
    t: list[float] = []
    d: list[str] = []
    r: list[int] = []
    a: list[float] = []
    for sign, mat in (("+", up_m), ("-", down_m)):
        if mat is None:
            continue
        for i, target in enumerate(targets_m):
            for j, dev in enumerate(mat[i]):
                t.append(float(target))
                d.append(sign)
                r.append(j + 1)
                a.append(float(target) + float(dev))
    return t, d, r, a


# --------------------------------------------------------------------------------------------
# Hand-computed values
# --------------------------------------------------------------------------------------------


def test_hand_example_axis_parameters() -> None:
    res = hand_result()
    for key, expected_um in HAND_AXIS_UM.items():
        assert getattr(res, key) == pytest.approx(expected_um * UM, rel=1e-12, abs=1e-18), key


def test_hand_example_per_target() -> None:
    res = hand_result()
    np.testing.assert_allclose(res.targets_m, HAND_TARGETS_M)
    np.testing.assert_allclose(res.mean_deviation_up_m, [2 * UM, 6 * UM], rtol=1e-12)
    np.testing.assert_allclose(res.mean_deviation_down_m, [0.0, 5 * UM], rtol=1e-12, atol=1e-18)
    np.testing.assert_allclose(res.mean_bidirectional_deviation_m, [UM, 5.5 * UM], rtol=1e-12)
    np.testing.assert_allclose(res.reversal_at_target_m, [2 * UM, UM], rtol=1e-12)
    np.testing.assert_allclose(res.std_up_m, [UM, 2 * UM], rtol=1e-12)
    np.testing.assert_allclose(res.std_down_m, [UM, 2 * UM], rtol=1e-12)
    np.testing.assert_allclose(res.repeatability_at_target_up_m, [4 * UM, 8 * UM], rtol=1e-12)
    np.testing.assert_allclose(res.repeatability_at_target_down_m, [4 * UM, 8 * UM], rtol=1e-12)
    np.testing.assert_allclose(res.repeatability_at_target_m, [6 * UM, 9 * UM], rtol=1e-12)
    np.testing.assert_array_equal(res.n_runs_up, [3, 3])
    np.testing.assert_array_equal(res.n_runs_down, [3, 3])
    assert res.bidirectional
    assert res.n_targets == 2
    assert res.coverage_factor == 2.0


def test_hand_example_legacy_coverage_factor_3() -> None:
    # k = 3: Rᵢ↑ = 6 s = 6 and 12;  R₁ = max(3 + 3 + 2, 6, 6) = 8;  R₂ = max(6 + 6 + 1, 12) = 13
    # A↑ = max(2 + 3, 6 + 6) - min(2 - 3, 6 - 6) = 12 + 1 = 13;  E is independent of k.
    res = iso230_2.evaluate(HAND_TARGETS_M, HAND_UP_M, HAND_DOWN_M, coverage_factor=3.0)
    assert res.repeatability_up_m == pytest.approx(12 * UM, rel=1e-12)
    np.testing.assert_allclose(res.repeatability_at_target_m, [8 * UM, 13 * UM], rtol=1e-12)
    assert res.accuracy_up_m == pytest.approx(13 * UM, rel=1e-12)
    assert res.systematic_deviation_m == pytest.approx(6 * UM, rel=1e-12)


def test_ecmc_reference_vector_axis() -> None:
    res = ecmc_result()
    for key, expected_um in ECMC_AXIS_UM.items():
        value = getattr(res, key)
        assert value is not None
        assert round(value / UM, 4) == pytest.approx(expected_um, abs=1e-9), key
    # The two values the ecmc report prints wrongly:
    assert res.systematic_deviation_m is not None
    assert res.systematic_deviation_m > res.systematic_deviation_up_m
    assert res.repeatability_m is not None
    assert res.repeatability_m > 0.0629 * UM


def test_ecmc_reference_vector_per_target() -> None:
    res = ecmc_result()
    mm = 1e-3
    # the report prints 4 significant digits
    np.testing.assert_allclose(res.mean_deviation_up_m, np.array(ECMC_MEAN_UP_MM) * mm, rtol=1e-9)
    np.testing.assert_allclose(
        res.mean_deviation_down_m, np.array(ECMC_MEAN_DOWN_MM) * mm, rtol=1e-9
    )
    np.testing.assert_allclose(
        res.reversal_at_target_m, np.array(ECMC_REVERSAL_MM) * mm, rtol=1e-6, atol=1e-15
    )
    np.testing.assert_allclose(res.std_up_m, np.array(ECMC_S_UP_MM) * mm, rtol=5e-3)
    np.testing.assert_allclose(res.std_down_m, np.array(ECMC_S_DOWN_MM) * mm, rtol=5e-3)
    np.testing.assert_allclose(res.repeatability_at_target_m, np.array(ECMC_R_I_MM) * mm, rtol=1e-3)


def test_unidirectional_only() -> None:
    uni = iso230_2.evaluate(HAND_TARGETS_M, HAND_UP_M)
    bi = hand_result()
    assert not uni.bidirectional
    for name in (
        "deviations_down_m",
        "mean_deviation_down_m",
        "mean_bidirectional_deviation_m",
        "reversal_at_target_m",
        "std_down_m",
        "repeatability_at_target_down_m",
        "repeatability_at_target_m",
        "systematic_deviation_down_m",
        "systematic_deviation_m",
        "mean_deviation_range_m",
        "repeatability_down_m",
        "repeatability_m",
        "reversal_m",
        "mean_reversal_m",
        "accuracy_down_m",
        "accuracy_m",
    ):
        assert getattr(uni, name) is None, name
    assert uni.n_runs_down is None
    for name in ("systematic_deviation_up_m", "repeatability_up_m", "accuracy_up_m"):
        assert getattr(uni, name) == getattr(bi, name)
    np.testing.assert_array_equal(uni.std_up_m, bi.std_up_m)
    table = uni.summary_table_markdown()
    assert "| E | Bidirectional systematic positional deviation | — |" in table
    assert "| E↑ | Unidirectional systematic positional deviation (↑) | 4.0000 |" in table
    json.dumps(uni.to_dict(), allow_nan=False)


def test_targets_are_sorted_and_runs_may_differ_between_directions() -> None:
    res = iso230_2.evaluate(
        HAND_TARGETS_M[::-1], HAND_UP_M[::-1], np.hstack([HAND_DOWN_M, HAND_DOWN_M])[::-1]
    )
    np.testing.assert_array_equal(res.targets_m, HAND_TARGETS_M)
    np.testing.assert_array_equal(res.n_runs_down, [6, 6])
    assert res.systematic_deviation_m == pytest.approx(6 * UM, rel=1e-12)


def test_result_is_immutable_and_json_ready() -> None:
    res = hand_result()
    with pytest.raises(dataclasses.FrozenInstanceError):
        res.accuracy_m = 0.0  # type: ignore[misc]
    with pytest.raises(ValueError, match="read-only"):
        res.mean_deviation_up_m[0] = 1.0
    with pytest.raises(ValueError, match="read-only"):
        res.deviations_up_m[0][0] = 1.0
    d = res.to_dict()
    text = json.dumps(d, allow_nan=False)
    back = json.loads(text)
    assert back["units"] == "m"
    assert back["standard"] == "ISO 230-2"
    assert back["axis"]["accuracy_m"] == pytest.approx(12 * UM)
    assert back["symbols"]["systematic_deviation_m"] == "E"
    assert back["per_target"][1]["repeatability_at_target_m"] == pytest.approx(9 * UM)
    assert back["per_target"][0]["n_runs_down"] == 3
    assert back["deviations_down_m"][0] == pytest.approx([-UM, 0.0, UM])
    assert set(back["axis"]) == {key for _, key, _ in iso230_2.AXIS_PARAMETERS}


def test_summary_table_in_micrometres() -> None:
    table = ecmc_result().summary_table_markdown()
    assert table.splitlines()[0] == "| Symbol | Parameter | Value [µm] |"
    assert "| E | Bidirectional systematic positional deviation | 0.0368 |" in table
    assert "| R | Bidirectional repeatability of positioning | 0.0688 |" in table
    assert "| B̄ | Mean reversal value of the axis (signed) | 0.0054 |" in table
    assert len(table.strip().splitlines()) == 2 + len(iso230_2.AXIS_PARAMETERS)
    per_target = ecmc_result().per_target_table_markdown()
    assert "| 5 | 10.48 | 5 | 5 |" in per_target


@pytest.mark.parametrize(
    ("kwargs", "column", "fragment"),
    [
        ({"targets_m": [0.0, 0.01, 0.02]}, "deviations_up_m", "shape"),
        ({"deviations_up_m": HAND_UP_M[:, :1]}, "deviations_up_m", "at least 2 runs"),
        ({"deviations_down_m": HAND_DOWN_M[:1]}, "deviations_down_m", "shape"),
        ({"deviations_up_m": np.where(HAND_UP_M > 5 * UM, np.nan, HAND_UP_M)}, "", "non-finite"),
        ({"targets_m": [0.01, 0.01]}, "targets_m", "duplicate target"),
        ({"targets_m": [[0.0, 0.01]]}, "targets_m", "1-D"),
        ({"coverage_factor": 0.0}, "coverage_factor", "> 0"),
        ({"coverage_factor": math.nan}, "coverage_factor", "> 0"),
    ],
)
def test_evaluate_rejects_bad_input(kwargs: dict[str, object], column: str, fragment: str) -> None:
    args: dict[str, object] = {
        "targets_m": HAND_TARGETS_M,
        "deviations_up_m": HAND_UP_M,
        "deviations_down_m": HAND_DOWN_M,
    }
    args.update(kwargs)
    with pytest.raises(Iso230InputError, match=fragment) as info:
        iso230_2.evaluate(**args)  # type: ignore[arg-type]
    assert isinstance(info.value, ValueError)
    assert column in str(info.value)


# --------------------------------------------------------------------------------------------
# Properties (hypothesis)
# --------------------------------------------------------------------------------------------

_DEV = st.floats(-1e-5, 1e-5, allow_nan=False, allow_infinity=False, allow_subnormal=False)


@st.composite
def datasets(draw: st.DrawFn) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Random bidirectional tests: 1-6 targets in ±0.5 m, 2-6 runs per direction."""
    m = draw(st.integers(1, 6))
    targets_mm = draw(st.lists(st.integers(-500, 500), min_size=m, max_size=m, unique=True))
    targets = np.array(targets_mm, dtype=np.float64) * 1e-3
    n_up = draw(st.integers(2, 6))
    n_down = draw(st.integers(2, 6))
    up = draw(hnp.arrays(np.float64, (m, n_up), elements=_DEV))
    down = draw(hnp.arrays(np.float64, (m, n_down), elements=_DEV))
    return targets, up, down


PROPS = settings(max_examples=150, deadline=None)


@PROPS
@given(datasets())
def test_iso_invariants(data: tuple[np.ndarray, np.ndarray, np.ndarray]) -> None:
    res = iso230_2.evaluate(*data)
    e, e_up = res.systematic_deviation_m, res.systematic_deviation_up_m
    e_down = res.systematic_deviation_down_m
    a, a_up, a_down = res.accuracy_m, res.accuracy_up_m, res.accuracy_down_m
    r, r_up, r_down = res.repeatability_m, res.repeatability_up_m, res.repeatability_down_m
    m_range, b = res.mean_deviation_range_m, res.reversal_m
    assert e is not None and e_down is not None and m_range is not None
    assert a is not None and a_down is not None and r is not None and r_down is not None
    assert b is not None
    assert e >= max(e_up, e_down)
    assert m_range <= e
    assert a >= max(a_up, a_down)
    assert a >= e
    assert r >= max(r_up, r_down)
    assert res.repeatability_at_target_m is not None and res.reversal_at_target_m is not None
    assert np.all(res.repeatability_at_target_m >= np.abs(res.reversal_at_target_m))
    assert np.all(res.repeatability_at_target_m >= res.repeatability_at_target_up_m)
    for value in (e, e_up, e_down, m_range, a, a_up, a_down, r, r_up, r_down, b):
        assert value >= 0.0
    assert res.mean_reversal_m is not None
    assert abs(res.mean_reversal_m) <= b * (1 + 1e-12)  # a mean can round up by an ulp


@PROPS
@given(datasets(), st.floats(-1e-4, 1e-4, allow_nan=False, allow_subnormal=False))
def test_translation_invariance(
    data: tuple[np.ndarray, np.ndarray, np.ndarray], shift_m: float
) -> None:
    targets, up, down = data
    base = iso230_2.evaluate(targets, up, down)
    moved = iso230_2.evaluate(targets, up + shift_m, down + shift_m)
    for key in (
        "systematic_deviation_up_m",
        "systematic_deviation_down_m",
        "systematic_deviation_m",
        "mean_deviation_range_m",
        "repeatability_up_m",
        "repeatability_down_m",
        "repeatability_m",
        "reversal_m",
        "mean_reversal_m",
        "accuracy_up_m",
        "accuracy_down_m",
        "accuracy_m",
    ):
        assert getattr(moved, key) == pytest.approx(getattr(base, key), abs=1e-15), key
    np.testing.assert_allclose(
        moved.mean_deviation_up_m, base.mean_deviation_up_m + shift_m, atol=1e-15
    )


@PROPS
@given(datasets(), st.floats(0.5, 4.0), st.floats(1.0, 5.0))
def test_coverage_factor_scaling(
    data: tuple[np.ndarray, np.ndarray, np.ndarray], k: float, factor: float
) -> None:
    targets, up, down = data
    base = iso230_2.evaluate(targets, up, down, coverage_factor=k)
    scaled = iso230_2.evaluate(targets, up, down, coverage_factor=k * factor)
    # Unidirectional repeatability 2k·s is linear in k ...
    assert scaled.repeatability_up_m == pytest.approx(factor * base.repeatability_up_m, rel=1e-12)
    assert base.repeatability_down_m is not None
    assert scaled.repeatability_down_m == pytest.approx(
        factor * base.repeatability_down_m, rel=1e-12
    )
    # ... the bidirectional R = max(k s↑ + k s↓ + |B|, ...) is not (|B| does not scale with k):
    # it grows with k but at most linearly.
    assert base.repeatability_m is not None and scaled.repeatability_m is not None
    assert scaled.repeatability_m >= base.repeatability_m * (1 - 1e-12)
    assert scaled.repeatability_m <= factor * base.repeatability_m * (1 + 1e-12) + 1e-21
    # E, M, B do not depend on k.
    assert scaled.systematic_deviation_m == base.systematic_deviation_m
    assert scaled.mean_deviation_range_m == base.mean_deviation_range_m
    assert scaled.reversal_m == base.reversal_m


@PROPS
@given(datasets(), st.floats(0.5, 4.0), st.floats(1.0, 5.0))
def test_bidirectional_repeatability_linear_in_k_without_reversal(
    data: tuple[np.ndarray, np.ndarray, np.ndarray], k: float, factor: float
) -> None:
    targets, up, _ = data
    down = up[:, ::-1]  # same runs in reverse order: Bᵢ = 0 (up to rounding)
    base = iso230_2.evaluate(targets, up, down, coverage_factor=k)
    scaled = iso230_2.evaluate(targets, up, down, coverage_factor=k * factor)
    assert base.repeatability_m is not None and scaled.repeatability_m is not None
    assert scaled.repeatability_m == pytest.approx(
        factor * base.repeatability_m, rel=1e-9, abs=1e-18
    )


@PROPS
@given(datasets(), st.randoms(use_true_random=False))
def test_order_of_targets_and_records_does_not_matter(
    data: tuple[np.ndarray, np.ndarray, np.ndarray], rnd: object
) -> None:
    targets, up, down = data
    base = iso230_2.evaluate(targets, up, down)
    perm = np.argsort(-targets)
    flipped = iso230_2.evaluate(targets[perm], up[perm], down[perm])
    assert flipped.to_dict() == base.to_dict()
    # flat records in any order give the same result as the matrices
    t, d, r, a = flatten(targets, up, down)
    order = list(range(len(t)))
    rnd.shuffle(order)  # type: ignore[attr-defined]
    rec = iso230_2.evaluate_records(
        [t[i] for i in order], [d[i] for i in order], [r[i] for i in order], [a[i] for i in order]
    )
    for key, value in base.axis_parameters().items():
        assert rec.axis_parameters()[key] == pytest.approx(value, rel=1e-9, abs=1e-15), key


# --------------------------------------------------------------------------------------------
# Flat records
# --------------------------------------------------------------------------------------------


def test_evaluate_records_matches_matrix_evaluation_and_allows_ragged_runs() -> None:
    t, d, r, a = flatten(HAND_TARGETS_M, HAND_UP_M, HAND_DOWN_M)
    rec = iso230_2.evaluate_records(t, d, r, a)
    for key, expected_um in HAND_AXIS_UM.items():
        assert getattr(rec, key) == pytest.approx(expected_um * UM, rel=1e-9, abs=1e-15), key
    # drop run 3 of target 0 in '+': 2 runs there, 3 elsewhere -> still valid
    keep = [i for i in range(len(t)) if not (t[i] == 0.0 and d[i] == "+" and r[i] == 3)]
    ragged = iso230_2.evaluate_records(
        [t[i] for i in keep], [d[i] for i in keep], [r[i] for i in keep], [a[i] for i in keep]
    )
    np.testing.assert_array_equal(ragged.n_runs_up, [2, 3])
    assert ragged.mean_deviation_up_m[0] == pytest.approx(1.5 * UM, rel=1e-9)
    # unidirectional records
    up_only = [i for i in range(len(t)) if d[i] == "+"]
    uni = iso230_2.evaluate_records(
        [t[i] for i in up_only],
        ["+"] * len(up_only),
        [r[i] for i in up_only],
        [a[i] for i in up_only],
    )
    assert not uni.bidirectional
    assert uni.accuracy_up_m == pytest.approx(10 * UM, rel=1e-9)


def test_evaluate_records_groups_targets_within_tolerance() -> None:
    t, d, r, a = flatten(HAND_TARGETS_M, HAND_UP_M, HAND_DOWN_M)
    t_noisy = [x + (1e-12 if k % 2 else 0.0) for k, x in enumerate(t)]
    res = iso230_2.evaluate_records(t_noisy, d, r, a)
    assert res.n_targets == 2


@pytest.mark.parametrize(
    ("mutate", "record", "column", "fragment"),
    [
        (lambda t, d, r, a: d.__setitem__(3, "up"), 3, "direction", "unknown direction"),
        (lambda t, d, r, a: a.__setitem__(2, math.nan), 2, "actual_m", "not a finite"),
        (lambda t, d, r, a: t.__setitem__(1, math.inf), 1, "target_m", "not a finite"),
        (lambda t, d, r, a: r.__setitem__(1, 1), 1, "run", "duplicate run"),
        (lambda t, d, r, a: r.__setitem__(0, 1.5), 0, "run", "not an integer"),
    ],
)
def test_evaluate_records_errors_name_record_and_column(
    mutate: object, record: int, column: str, fragment: str
) -> None:
    t, d, r, a = flatten(HAND_TARGETS_M, HAND_UP_M, HAND_DOWN_M)
    r_any: list[float] = list(r)
    mutate(t, d, r_any, a)  # type: ignore[operator]
    with pytest.raises(Iso230InputError, match=fragment) as info:
        iso230_2.evaluate_records(t, d, r_any, a)
    assert f"record {record}" in str(info.value)
    assert f"column '{column}'" in str(info.value)
    assert info.value.record == record
    assert info.value.column == column


def test_evaluate_records_needs_two_runs_and_plus_direction() -> None:
    t, d, r, a = flatten(HAND_TARGETS_M, HAND_UP_M, HAND_DOWN_M)
    # records 6..8: target 0, '-', runs 1..3; keep only run 1 (record 6)
    keep = [i for i in range(len(t)) if not (d[i] == "-" and t[i] == 0.0 and r[i] > 1)]
    sub = [[seq[i] for i in keep] for seq in (t, d, r, a)]
    with pytest.raises(Iso230InputError, match="1 run") as info:
        iso230_2.evaluate_records(*sub)
    assert "record 6" in str(info.value) and "column 'run'" in str(info.value)
    minus = [i for i in range(len(t)) if d[i] == "-"]
    with pytest.raises(Iso230InputError, match="no '\\+' records"):
        iso230_2.evaluate_records(*[[seq[i] for i in minus] for seq in (t, d, r, a)])
    with pytest.raises(Iso230InputError, match="differ in length"):
        iso230_2.evaluate_records(t, d, r, a[:-1])
    with pytest.raises(Iso230InputError, match="no measurement records"):
        iso230_2.evaluate_records([], [], [], [])


# --------------------------------------------------------------------------------------------
# CSV files
# --------------------------------------------------------------------------------------------

GOOD_CSV_LINES = [
    "target_m,direction,run,actual_m",  # line 1
    "0.0,+,1,1e-6",  # line 2
    "0.0,+,2,2e-6",  # line 3
    "0.0,-,1,-1e-6",  # line 4
    "0.0,-,2,0.0",  # line 5
    "0.01,+,1,0.010004",  # line 6
    "0.01,+,2,0.010006",  # line 7
    "0.01,-,1,0.010003",  # line 8
    "0.01,-,2,0.010005",  # line 9
]


def write_lines(path: Path, lines: list[str]) -> Path:
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


def test_csv_round_trip(tmp_path: Path) -> None:
    targets = np.array(ECMC_TARGETS_MM) * 1e-3
    t, d, r, a = flatten(targets, np.array(ECMC_UP_MM) * 1e-3, np.array(ECMC_DOWN_MM) * 1e-3)
    path = iso230_2.write_measurement_csv(tmp_path / "meas.csv", t, d, r, a)
    records = iso230_2.read_measurement_csv(path)
    assert len(records) == 50
    assert records.source == str(path)
    np.testing.assert_array_equal(records.target_m, t)
    np.testing.assert_array_equal(records.actual_m, a)
    np.testing.assert_array_equal(records.run, r)
    assert list(records.direction) == d
    np.testing.assert_array_equal(records.line, np.arange(2, 52))
    from_file = records.evaluate()
    direct = iso230_2.evaluate_records(t, d, r, a)
    assert from_file.to_dict() == direct.to_dict()
    for key, expected_um in ECMC_AXIS_UM.items():
        assert round(getattr(from_file, key) / UM, 4) == pytest.approx(expected_um, abs=1e-9)
    via_function = iso230_2.evaluate_records(
        records.target_m, records.direction, records.run, records.actual_m
    )
    assert via_function.to_dict() == direct.to_dict()


def test_csv_accepts_comments_extra_columns_any_order_and_bom(tmp_path: Path) -> None:
    lines = [
        "# machine: nanostage sim",
        "",
        "run,actual_m,note,direction,target_m",
        "1, 1e-6 ,a,+,0.0",
        "2,2e-6,,+,0.0",
        "# a comment in the middle",
        "1,0.010004,,+,0.01",
        "2,0.010006,,+,0.01",
    ]
    path = tmp_path / "extra.csv"
    path.write_text("\ufeff" + "\n".join(lines) + "\n", encoding="utf-8")
    records = iso230_2.read_measurement_csv(path)
    np.testing.assert_array_equal(records.line, [4, 5, 7, 8])
    res = records.evaluate()
    assert not res.bidirectional
    assert res.systematic_deviation_up_m == pytest.approx(3.5 * UM, rel=1e-6)


def _replace(index: int, text: str) -> list[str]:
    lines = list(GOOD_CSV_LINES)
    lines[index] = text
    return lines


def _drop(*indices: int) -> list[str]:
    return [line for k, line in enumerate(GOOD_CSV_LINES) if k not in indices]


CSV_ERROR_CASES = [
    pytest.param(
        _replace(0, "target_m,direction,run,actual"), 1, "actual_m", "missing", id="missing-column"
    ),
    pytest.param(_replace(2, "0.0,+,2,nan"), 3, "actual_m", "not a finite", id="nan-actual"),
    pytest.param(_replace(5, "NaN,+,1,0.010004"), 6, "target_m", "not a finite", id="nan-target"),
    pytest.param(_replace(5, ",+,1,0.010004"), 6, "target_m", "empty", id="empty-target"),
    pytest.param(_replace(8, "0.01,-,2"), 9, "actual_m", "empty", id="short-row"),
    pytest.param(_replace(6, "0.01,+,two,0.010006"), 7, "run", "cannot parse", id="bad-run"),
    pytest.param(_replace(7, "0.01,-,1,0.01x"), 8, "actual_m", "cannot parse", id="bad-float"),
    pytest.param(_replace(3, "0.0,up,1,-1e-6"), 4, "direction", "unknown direction", id="dir"),
    pytest.param(_drop(4), 4, "run", "1 run", id="one-run-at-target"),
    pytest.param(_drop(3, 4), 2, "direction", "0 run", id="no-runs-at-target"),
    pytest.param(_replace(6, "0.01,+,1,0.010006"), 7, "run", "duplicate run", id="dup-run"),
    pytest.param(_replace(8, "0.01,-,2,10.005"), 9, "actual_m", "mixed units", id="mm-actual"),
    pytest.param(_replace(5, "10.5,+,1,10.500004"), 6, "target_m", "millimetres", id="mm-target"),
]


@pytest.mark.parametrize(("lines", "line", "column", "fragment"), CSV_ERROR_CASES)
def test_csv_errors_name_file_line_and_column(
    tmp_path: Path, lines: list[str], line: int, column: str, fragment: str
) -> None:
    path = write_lines(tmp_path / "bad.csv", lines)
    with pytest.raises(Iso230InputError, match=fragment) as info:
        iso230_2.read_measurement_csv(path)
    message = str(info.value)
    assert str(path) in message
    assert f"line {line}" in message
    assert f"column '{column}'" in message
    assert (info.value.source, info.value.line, info.value.column) == (str(path), line, column)
    assert isinstance(info.value, ValueError)


def test_csv_error_line_numbers_count_comment_lines(tmp_path: Path) -> None:
    lines = ["# header comment", "# another", *_replace(2, "0.0,+,2,oops")]
    path = write_lines(tmp_path / "c.csv", lines)
    with pytest.raises(Iso230InputError, match="line 5, column 'actual_m'"):
        iso230_2.read_measurement_csv(path)


def test_csv_unit_check_can_be_disabled(tmp_path: Path) -> None:
    # a whole file in millimetres: rejected by default, accepted with check_units=False
    lines = ["target_m,direction,run,actual_m"] + [
        f"{t},+,{j},{t + dev}" for t in (0.0, 10.5) for j, dev in ((1, 0.001), (2, 0.002))
    ]
    path = write_lines(tmp_path / "mm.csv", lines)
    with pytest.raises(Iso230InputError, match="millimetres"):
        iso230_2.read_measurement_csv(path)
    res = iso230_2.read_measurement_csv(path, check_units=False).evaluate()
    assert res.n_targets == 2


def test_csv_without_data_or_header(tmp_path: Path) -> None:
    with pytest.raises(Iso230InputError, match="no header"):
        iso230_2.read_measurement_csv(write_lines(tmp_path / "empty.csv", ["# nothing"]))
    with pytest.raises(Iso230InputError, match="no data rows"):
        iso230_2.read_measurement_csv(write_lines(tmp_path / "h.csv", GOOD_CSV_LINES[:1]))


# --------------------------------------------------------------------------------------------
# Report
# --------------------------------------------------------------------------------------------


def _has_matplotlib() -> bool:
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        return False
    return True


def test_write_report(tmp_path: Path) -> None:
    res = ecmc_result()
    files = iso230_2.write_report(
        res, tmp_path / "out", title="ecmc fat_sat", conditions={"Instrument": "encoder"}
    )
    assert files.json == tmp_path / "out" / "iso230_2.json"
    assert files.markdown == tmp_path / "out" / "iso230_2.md"
    data = json.loads(files.json.read_text(encoding="utf-8"))
    assert data["title"] == "ecmc fat_sat"
    assert data["conditions"] == {"Instrument": "encoder"}
    assert data["axis"] == pytest.approx(res.to_dict()["axis"])
    assert data["axis"]["systematic_deviation_m"] == pytest.approx(0.0368 * UM, abs=1e-11)
    md = files.markdown.read_text(encoding="utf-8")
    assert md.startswith("# ecmc fat_sat")
    assert "| E | Bidirectional systematic positional deviation | 0.0368 |" in md
    assert "| A | Bidirectional accuracy of positioning | 0.0888 |" in md
    assert "| Instrument | encoder |" in md
    assert "x̄ᵢ↑ [µm]" in md
    assert "| 1 | -10 | -0.0810 | -0.1020 |" in md  # raw deviations table, µm
    if _has_matplotlib():
        assert files.png == tmp_path / "out" / "iso230_2.png"
        assert files.png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        assert "](iso230_2.png)" in md
    else:
        assert files.png is None


def test_write_report_unidirectional(tmp_path: Path) -> None:
    files = iso230_2.write_report(iso230_2.evaluate(HAND_TARGETS_M, HAND_UP_M), tmp_path)
    md = files.markdown.read_text(encoding="utf-8")
    assert "unidirectional" in md
    assert "negative direction" not in md
    assert json.loads(files.json.read_text(encoding="utf-8"))["deviations_down_m"] is None


def test_write_report_without_matplotlib(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "matplotlib", None)  # makes `import matplotlib` fail
    files = iso230_2.write_report(hand_result(), tmp_path)
    assert files.png is None
    assert not (tmp_path / "iso230_2.png").exists()
    md = files.markdown.read_text(encoding="utf-8")
    assert "Warning" in md and "matplotlib is not installed" in md
    assert files.json.exists()


def test_plot_into_existing_axes() -> None:
    pytest.importorskip("matplotlib")
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure()
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    assert iso230_2.plot(hand_result(), ax=ax, title="t") is ax
    assert ax.get_title() == "t"
    assert ax.get_xlabel() == "Target position [mm]"


# --------------------------------------------------------------------------------------------
# CLI helpers
# --------------------------------------------------------------------------------------------


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="nanostage")
    sub = parser.add_subparsers(dest="command", required=True)
    iso230_2.add_cli(sub)
    return parser


def test_cli_writes_report(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    csv_path = write_lines(tmp_path / "meas.csv", GOOD_CSV_LINES)
    out = tmp_path / "report"
    args = _parser().parse_args(
        ["iso230", str(csv_path), "--out", str(out), "--coverage-factor", "3"]
    )
    assert args.func is iso230_2.run_cli
    assert args.func(args) == 0
    data = json.loads((out / "iso230_2.json").read_text(encoding="utf-8"))
    assert data["coverage_factor"] == 3.0
    assert (out / "iso230_2.md").exists()
    captured = capsys.readouterr()
    assert "| Symbol | Parameter | Value [µm] |" in captured.out
    assert "iso230_2.json" in captured.out


def test_cli_default_out_dir(tmp_path: Path) -> None:
    csv_path = write_lines(tmp_path / "meas.csv", GOOD_CSV_LINES)
    args = _parser().parse_args(["iso230", str(csv_path)])
    assert iso230_2.run_cli(args) == 0
    assert (tmp_path / "meas_iso230_2" / "iso230_2.md").exists()


def test_cli_bad_input(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    csv_path = write_lines(tmp_path / "bad.csv", _replace(3, "0.0,x,1,-1e-6"))
    args = _parser().parse_args(["iso230", str(csv_path), "--out", str(tmp_path / "o")])
    assert iso230_2.run_cli(args) == 2
    err = capsys.readouterr().err
    assert str(csv_path) in err and "line 4" in err and "column 'direction'" in err
    assert not (tmp_path / "o").exists()
    missing = _parser().parse_args(["iso230", str(tmp_path / "nope.csv")])
    assert iso230_2.run_cli(missing) == 2
    bad_k = _parser().parse_args(
        ["iso230", str(write_lines(tmp_path / "g.csv", GOOD_CSV_LINES)), "--coverage-factor", "0"]
    )
    assert iso230_2.run_cli(bad_k) == 2
