"""Run-to-run friction scatter in the diagnosis's gap: the level factor, the level
directions and the fit residuals whitened by one level draw per run."""

from __future__ import annotations

import dataclasses as dc
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from diagnosis_cases import simulated_experiment, step_case
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from nanostage import presets
from nanostage.config import get_path, replace_paths
from nanostage.diagnosis.candidates import Param
from nanostage.diagnosis.fit import FitProblem
from nanostage.diagnosis.loop import command_weights
from nanostage.diagnosis.objective import experiment_floors_m, simulate_readings_and_commands
from nanostage.diagnosis.run import diagnose, experiment_advice
from nanostage.diagnosis.scatter import (
    LEVEL_STEP,
    MAX_LEVEL_SCATTER,
    SMOOTHING_SAMPLES,
    _smoothed,
    discount_level,
    level_floors,
    level_scatter_directions,
    level_sensitivities,
    with_friction_level,
)
from nanostage.diagnosis.settings import DEFAULT_LEVEL_SCATTER, DiagnosisSettings
from nanostage.effects import Effects, FrictionModifiers, PositionFriction
from nanostage.experiment import Experiment

Q = 1e-7
LEVELS = (
    "plant.dahl.coulomb_force_n",
    "plant.motor_friction.static_torque_nm",
    "plant.motor_friction.coulomb_torque_nm",
)


def _step(
    system: Any, step_m: float, name: str, start_m: float = 2e-3, seed: int = 1
) -> Experiment:
    """A step after a rest of 20 samples, held 300 samples, simulated by nanostage with its
    command."""
    x0 = start_m + Q / 3
    ref = np.concatenate([np.full(20, x0), np.full(300, x0 + step_m)])
    return simulated_experiment(system, ref, name, seed, x0)


def test_friction_level_factor_scales_every_level_as_the_parameters_do() -> None:
    s = presets.seed(500e-6)
    e = _step(s, 500e-6, "a")
    raised = with_friction_level(s, 1.05)
    scaled = replace_paths(s, {p: 1.05 * get_path(s, p) for p in LEVELS})
    (r0, _), (r1, c1), (r2, c2) = simulate_readings_and_commands([s, raised, scaled], [e] * 3)
    # The same trace up to rounding (the factor multiplies inside the core, the parameters
    # outside), and a different one from the unscaled model.
    assert np.max(np.abs(r1 - r2)) < 1e-3 * Q and np.max(np.abs(c1 - c2)) < 1e-6
    assert np.max(np.abs(r1 - r0)) > 10 * Q
    assert with_friction_level(s, 1.0) is s
    for bad in (0.99, 1.91, float("nan")):
        with pytest.raises(ValueError, match="factor"):
            with_friction_level(s, bad)


def test_level_directions_are_the_unit_sensitivities_with_their_discount() -> None:
    s = presets.seed(1e-3)
    long_step = _step(s, 1e-3, "long")
    small = _step(s, 100e-6, "small", start_m=5e-3)
    rep_a = _step(s, 500e-6, "rep_a", start_m=10e-3, seed=2)
    rep_b = _step(s, 500e-6, "rep_b", start_m=10e-3, seed=3)
    exps = [long_step, small, rep_a, rep_b]
    floors = experiment_floors_m(exps, Q)
    cw = {n: 1e-4 for n in floors}
    systems = {e.name: s for e in exps}
    sens = level_sensitivities(exps, systems)
    sc = level_scatter_directions(exps, sens, floors, cw, Q, 0.03)
    assert sc.spread == 0.03
    # The repeated pair is left as it is: its floor holds the scatter already.
    assert sorted(sc.repeated) == ["rep_a", "rep_b"]
    assert set(sc.directions) == {"long", "small"}
    # By hand: u stacks J of the reading and the weighted J of the command, J the change
    # per unit of relative level averaged over SMOOTHING_SAMPLES; s = σ·|u|/f.
    ((r0, c0), (r1, c1)) = simulate_readings_and_commands(
        [s, with_friction_level(s, 1.0 + LEVEL_STEP)], [long_step] * 2
    )
    u = np.concatenate(
        [_smoothed((r1 - r0) / LEVEL_STEP), 1e-4 * _smoothed((c1 - c0) / LEVEL_STEP)]
    )
    unit, keep = sc.directions["long"]
    assert len(unit) == 2 * len(long_step.time_s)
    assert np.allclose(unit, u / np.linalg.norm(u), rtol=0.0, atol=1e-12)
    s_long = 0.03 * float(np.linalg.norm(u)) / floors["long"]
    assert sc.scatter_floors["long"] == pytest.approx(s_long, rel=1e-12)
    assert keep == pytest.approx(1.0 / np.sqrt(1.0 + s_long**2), rel=1e-12)
    # A 3 % level moves the slew of a 1 mm step by many floors: its component is nearly
    # all discounted; a larger scatter discounts every experiment at least as much.
    assert keep < 0.05
    wider = level_scatter_directions(exps, sens, floors, cw, Q, 0.1)
    for n, (_, k) in sc.directions.items():
        assert wider.directions[n][1] < k
    # Without the command in the gap the direction is the reading's alone.
    pos_only = level_scatter_directions(exps, sens, floors, {}, Q, 0.03)
    assert len(pos_only.directions["long"][0]) == len(long_step.time_s)
    d = sc.to_dict()
    assert d["spread"] == 0.03 and d["repeated"] == ["rep_a", "rep_b"]
    assert d["discounted"]["long"] == {"scatter_floors": s_long, "kept": keep}  # type: ignore[index]
    for bad in (0.0, -0.01, MAX_LEVEL_SCATTER * 1.01, float("nan")):
        with pytest.raises(ValueError, match="level_scatter"):
            level_scatter_directions(exps, sens, floors, cw, Q, bad)


@given(
    st.lists(st.floats(-1.0, 1.0), min_size=3, max_size=12),
    st.floats(0.0, 50.0),
    st.integers(0, 2**32 - 1),
)
@settings(max_examples=60, deadline=None)
def test_discounting_the_level_whitens_by_one_level_draw(
    raw: list[float], s: float, seed: int
) -> None:
    """Its sum of squares is the gap's Mahalanobis norm under the covariance f²·I + σ²·u·uᵀ
    (times f²), computed here with a dense inverse; the components orthogonal to u stay."""
    u = np.asarray(raw)
    assume(float(np.linalg.norm(u)) > 1e-3)
    n = len(u)
    f = 2.0
    sigma = s * f / float(np.linalg.norm(u))
    unit, keep = u / np.linalg.norm(u), 1.0 / np.sqrt(1.0 + s * s)
    r = np.random.default_rng(seed).normal(size=n)
    w = discount_level(r, (unit, keep))
    cov = f**2 * np.eye(n) + sigma**2 * np.outer(u, u)
    assert float(w @ w) == pytest.approx(f**2 * float(r @ np.linalg.solve(cov, r)), rel=1e-9)
    ortho = r - float(unit @ r) * unit
    assert np.allclose(w - float(unit @ w) * unit, ortho, rtol=0.0, atol=1e-12)
    with pytest.raises(ValueError, match="samples"):
        discount_level(r[:-1], (unit, keep))


def test_smoothing_is_a_centred_moving_average_shrunk_at_the_ends() -> None:
    j = np.arange(100, dtype=float) ** 2
    out = _smoothed(j)
    h = SMOOTHING_SAMPLES // 2
    for i in (0, 3, h, 50, 99):
        lo, hi = max(i - h, 0), min(i + h + 1, 100)
        assert out[i] == pytest.approx(float(np.mean(j[lo:hi])), rel=1e-12)
    # A linear ramp away from the ends is left as it is.
    ramp = np.linspace(0.0, 1.0, 200)
    assert np.allclose(_smoothed(ramp)[h:-h], ramp[h:-h], rtol=0.0, atol=1e-12)


def test_fit_residuals_are_the_gap_with_its_level_component_discounted() -> None:
    s = presets.seed(500e-6)
    exps = [_step(s, 500e-6, "a"), _step(s, -500e-6, "b", start_m=4e-3, seed=2)]
    floors = experiment_floors_m(exps, Q)
    weights = command_weights(exps, {e.name: s for e in exps}, floors, Q, DiagnosisSettings())
    rng = np.random.default_rng(0)
    dirs = {}
    for e in exps:
        u = rng.normal(size=2 * len(e.time_s))
        dirs[e.name] = (u / np.linalg.norm(u), float(rng.uniform(0.05, 0.9)))
    name = "plant.dahl.coulomb_force_n"
    free = [(name, Param(name=name, unit="N", lower=20.0, upper=40.0, initial=30.4))]

    def build(v: Any) -> Any:
        return replace_paths(s, {name: v[0]})

    plain = FitProblem(free, build, exps, 1, lambda x, e: x, None, weights)
    level = FitProblem(free, build, exps, 1, lambda x, e: x, None, weights, dirs)
    other = build([33.0])
    for e, p, w in zip(
        exps, plain.residuals(other, exps), level.residuals(other, exps), strict=True
    ):
        unit, keep = dirs[e.name]
        assert np.allclose(w, p + (keep - 1.0) * float(unit @ p) * unit, rtol=0.0, atol=1e-20)
        assert float(w @ w) < float(p @ p)
    # An experiment without a direction keeps its gap to the last bit.
    only = FitProblem(free, build, exps, 1, lambda x, e: x, None, weights, {"a": dirs["a"]})
    assert np.array_equal(only.residuals(other, exps)[1], plain.residuals(other, exps)[1])


def test_level_scatter_setting_defaults_to_one_percent() -> None:
    assert DiagnosisSettings().level_scatter == DEFAULT_LEVEL_SCATTER == 0.01
    assert dc.replace(DiagnosisSettings(), level_scatter=0.0).level_scatter == 0.0
    assert dc.replace(DiagnosisSettings(), level_scatter=0.02).level_scatter == 0.02


def test_case_manifests_write_the_scatter_only_when_given() -> None:
    """A benchmark case's manifest says ``level_scatter = 0.0`` when the scatter is turned
    off (absent, the diagnosis's 1 % would apply) and nothing when none is given."""
    from nanostage.diagnosis.case_manifest import case_manifest_head

    def scatter_lines(**kw: float) -> list[str]:
        return [x for x in case_manifest_head(30.0, 1e-4, 8e-5, 1, **kw) if "scatter" in x]

    assert scatter_lines() == []
    assert scatter_lines(level_scatter=0.0) == ["level_scatter = 0.0"]
    assert scatter_lines(level_scatter=0.03) == ["level_scatter = 0.03"]


def test_repeat_advice_names_the_experiment_a_level_change_moves_most() -> None:
    s = presets.seed(1e-3)
    exps = [_step(s, 1e-3, "long"), _step(s, 100e-6, "small", start_m=5e-3)]
    floors = experiment_floors_m(exps, Q)
    sens = level_sensitivities(exps, {e.name: s for e in exps})
    lf = level_floors(sens, floors)
    # By hand: the RMS of 1 % of the sensitivity over the floor.
    jp = sens["long"][0]
    assert lf["long"] == pytest.approx(float(np.sqrt(np.mean((0.01 * jp) ** 2))) / floors["long"])
    assert lf["long"] > lf["small"] > 0.0 and lf["long"] > 1.0

    def repeat_advice(level: dict[str, float] | None) -> dict[str, Any]:
        out = experiment_advice(exps, 2e-3, [], 0.05, level_floors=level)
        return next(a for a in out if a["effects"] == ["stochastic_friction"])

    plain = repeat_advice(None)
    assert plain["experiment"] == "repeat one experiment 3–5 times"
    named = repeat_advice({"long": 19.04, "small": 2.5, "other": 0.4})
    assert "moves long by 19 noise floors" in named["issue"]
    assert "1 other experiment(s) by more than one" in named["issue"]
    assert named["experiment"].startswith("repeat long 3–5 times")
    # Below one floor everywhere: the plain advice.
    assert repeat_advice({"long": 0.9})["experiment"] == plain["experiment"]


def test_diagnosis_with_a_given_scatter_still_finds_the_asymmetry(tmp_path: Path) -> None:
    # The shared step case (its truth's levels scatter by 0.3 % from run to run) with the
    # scatter given: the long steps' slews count less, and the asymmetry is still found.
    m = step_case(tmp_path, Effects(motor_friction=FrictionModifiers(asymmetry=0.3)), seed=3)
    m.write_text(m.read_text(encoding="utf-8").replace('"offset_force", ', ""))
    fast = DiagnosisSettings(
        n_starts_nominal=1, n_starts_candidate=1, forward_rounds=2, level_scatter=0.003
    )
    d = diagnose(m, tmp_path / "out", settings=fast, progress=False, figures=False)
    r = d.report
    assert r["selected"] == ["asymmetric_friction"]
    assert r["level_scatter"]["spread"] == 0.003
    assert set(r["level_scatter"]["discounted"]) <= {"e0", "e1", "e2", "e3"}
    assert r["level_scatter"]["discounted"], "the 0.5 mm steps' slews are discounted"
    assert set(r["level_floors"]) == {"e0", "e1", "e2", "e3"}
    text = (tmp_path / "out" / "report.md").read_text(encoding="utf-8")
    assert "**Run-to-run friction scatter:** 0.003" in text


def test_a_model_without_room_for_the_level_factor_gets_no_sensitivity() -> None:
    s = presets.seed(1e-3)
    full = dc.replace(
        s,
        effects=dc.replace(
            s.effects,
            position_friction=(PositionFriction(side="table", terms=((0.895, 1e3, 0.0),)),),
        ),
    )
    with pytest.raises(ValueError, match="amplitude"):
        with_friction_level(full, 1.01)
    a, b = _step(s, 1e-3, "a"), _step(s, 1e-3, "b", start_m=5e-3)
    sens = level_sensitivities([a, b], {"a": s, "b": full})
    assert set(sens) == {"a"}
    floors = experiment_floors_m([a, b], Q)
    sc = level_scatter_directions([a, b], sens, floors, {}, Q, 0.03)
    assert set(sc.directions) == {"a"}
    assert level_sensitivities([b], {"b": full}) == {}
