"""Off-line PID tuning: the robust figures against an independent computation on full traces,
reproducibility, the search space, the Pareto front, bad input and the CLI."""

from __future__ import annotations

import json
import math
import pickle
from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace

import numpy as np
import pytest

import nanostage as ns
from nanostage import presets
from nanostage.cli import main
from nanostage.config import CascadeController
from nanostage.tune import (
    Candidate,
    GainSpace,
    Objective,
    RobustMetrics,
    _dense,
    _Evaluator,
    evaluate_gains,
    pareto_front,
    tune,
    tuning_cycle,
    with_friction_spread,
)

STEP_M = 100e-6


def _hand_figures(system: ns.System, cycle, band_counts: int) -> dict[str, list[float]]:
    """Settling time, overshoot and final error of every approach from one full trace,
    written directly from the definitions (loops, no shared code with nanostage.tune)."""
    tr = ns.simulate(system, cycle.reference_m, seed=0)
    count = system.encoder.count_m
    t_s = cycle.sample_period_s
    settle, over, final = [], [], []
    ref = cycle.reference_m
    for m, k_meas in enumerate(cycle.measure_index.tolist()):
        target = float(cycle.target_m[m])
        a = k_meas
        while a > 0 and ref[a - 1] == target:
            a -= 1
        ref_counts = round(target / count)
        last_outside = None
        for k in range(a, k_meas + 1):
            if abs(ref_counts - int(tr.encoder_counts[k])) > band_counts:
                last_outside = k
        n = k_meas + 1 - a
        if last_outside is None:
            settle.append(0.0)
        elif last_outside == k_meas:
            settle.append(2.0 * n * t_s)
        else:
            settle.append((last_outside + 1 - a) * t_s)
        sgn = int(cycle.direction[m])
        over.append(
            max(0.0, max((float(tr.position_m[k]) - target) * sgn for k in range(a, k_meas + 1)))
        )
        final.append(abs(target - float(tr.position_m[k_meas])))
    return {"settle": settle, "over": over, "final": final}


def test_figures_match_a_full_trace_computed_by_hand() -> None:
    system = presets.seed(STEP_M)  # no random effect: every trial is the same run
    cycle = tuning_cycle(STEP_M, repeats=3, dwell_s=0.2, return_s=0.05)
    hand = _hand_figures(system, cycle, band_counts=1)
    for stat, reduce in (("max", max), ("mean", lambda v: sum(v) / len(v))):
        obj = Objective(settling_weight_per_s=1.0, statistic=stat)  # type: ignore[arg-type]
        c = evaluate_gains(system, cycle, objective=obj, n_trials=3, seed=5)
        m = c.metrics
        assert m.n_failed == 0
        assert m.settling_time_s == pytest.approx(reduce(hand["settle"]), abs=1e-12)
        assert m.overshoot_m == pytest.approx(reduce(hand["over"]), abs=1e-15)
        assert m.final_error_m == pytest.approx(reduce(hand["final"]), abs=1e-15)
        assert m.objective == pytest.approx(m.settling_time_s, rel=1e-12)
    # Table 1 at 100 µm overshoots by about 28 µm and settles within the window.
    assert 20e-6 < max(hand["over"]) < 35e-6
    # Identical trials: pooled A↑ is 4·s over identical final positions per run = the spread
    # of the repeats alone; it is finite and below one count plus the overshoot scale.
    assert math.isfinite(m.accuracy_up_m) and m.accuracy_up_m >= 0.0


def test_figures_on_a_bidirectional_standard_cycle() -> None:
    """A whole ISO test cycle (both directions, overrun moves between approaches)."""
    from nanostage.cycles import MoveProfile, standard_test_cycle

    system = presets.seed(1e-3)
    cycle = standard_test_cycle(
        travel_m=2e-3,
        n_targets=5,
        runs=2,
        overrun_m=0.3e-3,
        dwell_s=0.25,
        move=MoveProfile(),
        sample_period_s=1e-3,
        seed=3,
    )
    assert set(cycle.direction.tolist()) == {-1, 1}
    hand = _hand_figures(system, cycle, band_counts=2)
    obj = Objective(settling_weight_per_s=1.0, band_counts=2, statistic="max")
    m = evaluate_gains(system, cycle, objective=obj, n_trials=1, seed=0, per_trial=True).metrics
    assert m.settling_time_s == pytest.approx(max(hand["settle"]), abs=1e-12)
    assert m.overshoot_m == pytest.approx(max(hand["over"]), abs=1e-15)
    assert m.final_error_m == pytest.approx(max(hand["final"]), abs=1e-15)
    # Two runs per trial: the per-trial ISO figures exist and equal the pooled ones here.
    assert m.accuracy_up_trial_mean_m == pytest.approx(m.accuracy_up_m, rel=1e-12)
    assert m.accuracy_up_m >= m.repeatability_up_m >= 0.0


def test_band_counts_and_overshoot_bound_change_the_objective() -> None:
    system = presets.seed(STEP_M)
    cycle = tuning_cycle(STEP_M, repeats=2, dwell_s=0.2, return_s=0.05)
    wide = evaluate_gains(
        system, cycle, objective=Objective.settling(band_counts=20), n_trials=1, seed=0
    ).metrics
    tight = evaluate_gains(
        system, cycle, objective=Objective.settling(band_counts=1), n_trials=1, seed=0
    ).metrics
    assert wide.settling_time_s < tight.settling_time_s
    bounded = evaluate_gains(
        system, cycle, objective=Objective.settling(overshoot_max_m=10e-6), n_trials=1, seed=0
    ).metrics
    # The 28 µm overshoot violates a 10 µm bound: penalty 1e3 · (o/bound − 1).
    expected = tight.settling_time_s + 1e3 * (tight.overshoot_m / 10e-6 - 1.0)
    assert bounded.objective == pytest.approx(expected, rel=1e-12)


def test_common_random_numbers_and_spread() -> None:
    system = with_friction_spread(presets.seed(STEP_M), 0.3)
    cycle = tuning_cycle(STEP_M, repeats=2, dwell_s=0.15, return_s=0.05)
    obj = Objective.mix()
    a = evaluate_gains(system, cycle, objective=obj, n_trials=16, seed=3)
    b = evaluate_gains(system, cycle, objective=obj, n_trials=16, seed=3, threads=1)
    assert a.metrics == b.metrics  # bit-identical whatever the thread count
    c = evaluate_gains(system, cycle, objective=obj, n_trials=16, seed=4)
    assert c.metrics != a.metrics  # other draws give other figures
    # The friction spread makes trials differ: the pooled repeatability exceeds that of the
    # system without spread on the same seed.
    plain = evaluate_gains(presets.seed(STEP_M), cycle, objective=obj, n_trials=16, seed=3)
    assert a.metrics.repeatability_up_m > plain.metrics.repeatability_up_m


def _small_tune(**kw: object):
    system = with_friction_spread(presets.seed(STEP_M), 0.2)
    cycle = tuning_cycle(STEP_M, repeats=2, dwell_s=0.15, return_s=0.05)
    args = {
        "objective": Objective.mix(),
        "n_trials": 4,
        "seed": 11,
        "popsize": 4,
        "maxiter": 2,
        "progress": False,
    }
    args.update(kw)
    return system, cycle, tune(system, cycle, **args)  # type: ignore[arg-type]


def test_tune_is_reproducible_and_respects_the_space() -> None:
    _, _, r1 = _small_tune()
    _, _, r2 = _small_tune(threads=1)
    assert [c.to_dict() for c in r1.history] == [c.to_dict() for c in r2.history]
    assert r1.best.to_dict() == r2.best.to_dict()
    # The baseline is the system's own Table 1 gains, evaluated first.
    assert (r1.start.kp, r1.start.ki, r1.start.kd) == (450.0, 2.0, 40.0)
    assert r1.history[0] is r1.start
    assert r1.best.objective == min(c.objective for c in r1.history)
    space = GainSpace()
    for c in r1.history[1:]:
        assert float(c.kp).is_integer() and float(c.ki).is_integer() and float(c.kd).is_integer()
        assert space.kp_bounds[0] <= c.kp <= space.kp_bounds[1]
        assert space.ki_bounds[0] <= c.ki <= space.ki_bounds[1]
        assert space.kd_bounds[0] <= c.kd <= space.kd_bounds[1]
    assert {c.anti_windup for c in r1.history} <= {"none", "clamp", "conditional"}
    assert len({c.anti_windup for c in r1.history}) > 1  # the option is searched
    # Distinct candidates only; calls include cache hits.
    keys = [(c.kp, c.ki, c.kd, c.anti_windup) for c in r1.history]
    assert len(keys) == len(set(keys)) and r1.n_evaluations >= len(keys)
    tuned = r1.system(presets.seed(STEP_M))
    assert isinstance(tuned.controller, ns.FpgaPid)
    assert tuned.controller.kp == r1.best.kp


def test_fixed_point_gains_and_one_anti_windup_option() -> None:
    space = GainSpace(
        kp_bounds=(300.0, 600.0),
        ki_bounds=(0.0, 5.0),
        kd_bounds=(10.0, 60.0),
        integer_gains=False,
        anti_windup=("clamp",),
    )
    _, _, r = _small_tune(space=space, maxiter=1)
    lsb = 2.0**-8  # the seed gain format <s, 24, 16>
    for c in r.history[1:]:
        assert c.anti_windup == "clamp"
        for g in (c.kp, c.ki, c.kd):
            assert (g / lsb).is_integer()
    assert any(not float(c.kp).is_integer() for c in r.history[1:])


def test_executor_gives_the_local_result() -> None:
    _, _, local = _small_tune(maxiter=1)
    with ThreadPoolExecutor(2) as ex:
        _, _, remote = _small_tune(maxiter=1, executor=ex)
    by_key = {(c.kp, c.ki, c.kd, c.anti_windup): c.metrics for c in local.history}
    # Both start from the Table 1 gains, so the comparison below is never empty.
    assert (450.0, 2.0, 40.0, "conditional") in by_key
    assert remote.start.metrics == by_key[(450.0, 2.0, 40.0, "conditional")]
    for c in remote.history:
        key = (c.kp, c.ki, c.kd, c.anti_windup)
        if key in by_key:
            assert by_key[key] == c.metrics
    # The evaluator pickles (what a process pool or dask sends to its workers).
    system = presets.seed(STEP_M)
    ev = _Evaluator(system, _dense(tuning_cycle(STEP_M)), Objective.mix(), 2, 0, 1)
    ev2 = pickle.loads(pickle.dumps(ev))
    assert (
        ev2((450.0, 2.0, 40.0, "conditional")).metrics
        == ev((450.0, 2.0, 40.0, "conditional")).metrics
    )


def _cand(t: float, a: float, failed: int = 0) -> Candidate:
    m = RobustMetrics(
        settling_time_s=t,
        settling_time_mean_s=t,
        settled_fraction=1.0,
        overshoot_m=0.0,
        overshoot_mean_m=0.0,
        final_error_m=0.0,
        final_error_mean_m=0.0,
        accuracy_up_m=a,
        repeatability_up_m=a,
        n_trials=1,
        n_failed=failed,
        objective=t + a,
    )
    return Candidate(kp=t, ki=a, kd=0.0, anti_windup="none", metrics=m)


def test_pareto_front_by_hand() -> None:
    pts = [
        _cand(1.0, 5.0),
        _cand(2.0, 3.0),
        _cand(2.5, 4.0),  # dominated by (2, 3)
        _cand(3.0, 1.0),
        _cand(4.0, 1.0),  # dominated by (3, 1)
        _cand(0.5, 9.0),
        _cand(0.1, 0.1, failed=1),  # failed: left out
        _cand(math.nan, 0.0),  # no figure: left out
    ]
    front = pareto_front(pts)
    assert [(c.kp, c.ki) for c in front] == [(0.5, 9.0), (1.0, 5.0), (2.0, 3.0), (3.0, 1.0)]


def test_bad_input_is_a_clear_error_before_any_run() -> None:
    system = presets.seed(STEP_M)
    cycle = tuning_cycle(STEP_M)
    with pytest.raises(ns.ConfigError, match=r"kp_bounds.*gain format"):
        tune(
            system,
            cycle,
            objective=Objective.mix(),
            space=GainSpace(kp_bounds=(0.0, 1e6)),
            progress=False,
        )
    with pytest.raises(ns.ConfigError, match="at least one weight"):
        Objective()
    with pytest.raises(ns.ConfigError, match="settling_weight_per_s"):
        Objective(settling_weight_per_s=-1.0)
    with pytest.raises(ns.ConfigError, match="statistic"):
        Objective(settling_weight_per_s=1.0, statistic="median")  # type: ignore[arg-type]
    with pytest.raises(ns.ConfigError, match="kd_bounds"):
        GainSpace(kd_bounds=(5.0, 1.0))
    with pytest.raises(ns.ConfigError, match="anti_windup"):
        GainSpace(anti_windup=("sometimes",))  # type: ignore[arg-type]
    with pytest.raises(ns.ConfigError, match="n_trials = 0"):
        tune(system, cycle, objective=Objective.mix(), n_trials=0, progress=False)
    with pytest.raises(ns.ConfigError, match="popsize"):
        tune(system, cycle, objective=Objective.mix(), popsize=1, progress=False)
    emps = presets.emps()
    assert isinstance(emps.controller, CascadeController)
    with pytest.raises(ns.ConfigError, match="FpgaPid"):
        tune(emps, cycle, objective=Objective.mix(), progress=False)


def test_cli_writes_the_report(tmp_path, capsys) -> None:
    pytest.importorskip("matplotlib")
    out = tmp_path / "t"
    code = main(
        [
            "tune",
            "--step-um",
            "100",
            "--trials",
            "3",
            "--eval-trials",
            "3",
            "--popsize",
            "4",
            "--maxiter",
            "1",
            "--quiet",
            "--out",
            str(out),
        ]
    )
    assert code == 0
    rep = json.loads((out / "tune.json").read_text(encoding="utf-8"))
    row = rep["steps"][0]
    assert row["step_m"] == pytest.approx(STEP_M)
    assert (row["table1"]["kp"], row["table1"]["ki"], row["table1"]["kd"]) == (450, 2, 40)
    assert row["tuned"]["objective"] is not None
    assert row["pareto"] and len(row["history"]) >= len(row["pareto"])
    assert (out / "pareto.png").stat().st_size > 10_000
    text = (out / "tune.md").read_text(encoding="utf-8")
    assert "Table 1" in text and "tuned" in text
    assert "| 100 µm | Table 1 | 450, 2, 40 |" in capsys.readouterr().out
    assert main(["tune", "--step-um", "100", "--trials", "0", "--quiet", "--out", str(out)]) == 2
    assert "n_trials = 0" in capsys.readouterr().err


def test_tuning_cycle_dwell_scales_with_the_step() -> None:
    c1 = tuning_cycle(100e-6)
    c2 = tuning_cycle(10e-3, repeats=2)
    assert c1.n_measurements == 1 and c2.n_measurements == 2
    assert np.all(c1.target_m == 100e-6) and np.all(c2.target_m == 10e-3)
    # One step: rest 0.1 s, step, dwell; the cycle ends at the measurement.
    assert c1.n_samples == c1.measure_index[0] + 1 == 100 + 311
    assert np.all(c1.reference_m[:100] == 0.0) and np.all(c1.reference_m[100:] == 100e-6)
    with pytest.raises(ns.ConfigError, match="repeats"):
        tuning_cycle(100e-6, repeats=0)
    # 0.3 s + 100 s/m · step: 0.31 s and 1.3 s of dwell (one more sample to the measurement).
    w1 = _dense(c1).window_cols[0]
    w2 = _dense(c2).window_cols[0]
    assert w1[1] - w1[0] == 311 and w2[1] - w2[0] == 1301
    assert replace(Objective.mix(), statistic="mean").statistic == "mean"
