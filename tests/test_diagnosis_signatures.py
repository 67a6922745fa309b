"""Signature features of traces (limit cycles, rest and ramp commands, breakaway), checked
on synthetic traces whose features are known exactly, and their use in the choice between
candidates the gap cannot tell apart."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from diagnosis_cases import candidate_result
from hypothesis import given, settings
from hypothesis import strategies as st_h

from nanostage.diagnosis.select import indistinguishable, pick_winner, rank_key
from nanostage.diagnosis.settings import DiagnosisSettings
from nanostage.diagnosis.signatures import Feature, distance, signatures_of

T = 1e-3  # sample period, s
Q = 1e-7  # count, m


def _steps(targets_m: list[float], hold: int) -> np.ndarray:
    return np.concatenate([np.full(hold, t) for t in targets_m])


def test_hunting_amplitude_and_frequency_of_a_square_limit_cycle() -> None:
    hold = 200
    ref = _steps([0.0, 1e-4, 0.0, 1e-4], hold)
    period = 10  # samples: 100 Hz
    amp = 3e-6  # ± around the target: 6 µm peak to peak
    cycle = np.where((np.arange(ref.size) // (period // 2)) % 2 == 0, amp, -amp)
    pos = ref + cycle
    sig = signatures_of([(ref, pos, None)], T, Q)
    assert sig["hunting_fraction"].value == 1.0
    assert sig["hold_amplitude_m"].value == pytest.approx(2 * amp, rel=1e-12)
    # 50-sample tail: 10 half periods → 9 or 10 sign changes → 90–100 Hz.
    assert 90.0 <= sig["hold_frequency_hz"].value <= 100.0
    assert "rest_command_split_v" not in sig  # no command: no command features


def test_settled_holds_do_not_hunt_and_have_no_cycle_features() -> None:
    ref = _steps([0.0, 1e-4, 0.0], 200)
    pos = ref + np.where(np.arange(ref.size) % 2 == 0, Q, 0.0)  # one count of dither
    sig = signatures_of([(ref, pos, None)], T, Q)
    assert sig["hunting_fraction"].value == 0.0
    assert "hold_amplitude_m" not in sig and "hold_frequency_hz" not in sig


def test_rest_command_split_and_mean_are_exact() -> None:
    ref = _steps([0.0, 1e-4, 0.0, 1e-4, 0.0], 200)
    up, down = 0.7, -0.3
    cmd = np.zeros(ref.size)
    for k in range(1, 5):
        cmd[k * 200 : (k + 1) * 200] = up if k % 2 == 1 else down
    sig = signatures_of([(ref, ref.copy(), cmd)], T, Q)
    assert sig["rest_command_split_v"].value == pytest.approx((up - down) / 2)
    assert sig["rest_command_mean_v"].value == pytest.approx((up + down) / 2)


def _ramp(v_m_per_s: float, n: int, start_m: float) -> np.ndarray:
    return start_m + v_m_per_s * T * np.arange(1, n + 1)


def test_ramp_level_bias_and_slope_are_recovered() -> None:
    level, bias, slope = 0.4, 0.05, 300.0  # V, V, V·s/m
    refs, cmds = [], []
    for v in (2e-5, 1e-4, 5e-4):
        for d in (1.0, -1.0):
            ref = np.concatenate([np.zeros(30), _ramp(d * v, 400, 0.0)])
            c = np.zeros(ref.size)
            c[30:] = d * (level + slope * v) + bias
            refs.append(ref)
            cmds.append(c)
    sig = signatures_of([(r, r.copy(), c) for r, c in zip(refs, cmds, strict=True)], T, Q)
    assert sig["ramp_level_v"].value == pytest.approx(level, rel=1e-9)
    assert sig["ramp_bias_v"].value == pytest.approx(bias, rel=1e-9)
    assert sig["ramp_slope_v_s_per_m"].value == pytest.approx(slope, rel=1e-9)


def test_ramps_at_one_speed_give_levels_but_no_slope() -> None:
    refs = [np.concatenate([np.zeros(30), _ramp(d * 1e-4, 400, 0.0)]) for d in (1.0, -1.0)]
    cmds = [
        np.where(np.arange(r.size) >= 30, d * 0.5, 0.0) for r, d in zip(refs, (1, -1), strict=True)
    ]
    sig = signatures_of([(r, r.copy(), c) for r, c in zip(refs, cmds, strict=True)], T, Q)
    assert sig["ramp_level_v"].value == pytest.approx(0.5)
    assert "ramp_slope_v_s_per_m" not in sig


def test_breakaway_slope_per_decade_of_rest_within_equal_steps() -> None:
    beta, p0 = 0.2, 1.0  # V per decade, V at 1 s
    traces = []
    for rest in (50, 300, 1500):
        ref = np.concatenate([np.zeros(rest), np.full(300, 3 * Q)])
        cmd = np.zeros(ref.size)
        cmd[rest + 20] = p0 + beta * math.log10(rest * T)  # the breakaway peak
        traces.append((ref, ref.copy(), cmd))
    # A large step with a short rest and a saturated command: another group, which must
    # not bend the slope.
    big = np.concatenate([np.zeros(20), np.full(300, 1e-3)])
    traces.append((big, big.copy(), np.where(np.arange(big.size) >= 20, 6.0, 0.0)))
    sig = signatures_of(traces, T, Q)
    assert sig["breakaway_per_decade_v"].value == pytest.approx(beta, rel=1e-9)


def test_breakaway_needs_three_rests() -> None:
    traces = []
    for rest in (50, 300):
        ref = np.concatenate([np.zeros(rest), np.full(300, 3 * Q)])
        traces.append((ref, ref.copy(), np.where(np.arange(ref.size) == rest + 5, 1.0, 0.0)))
    assert "breakaway_per_decade_v" not in signatures_of(traces, T, Q)


def _out_and_back(v_m_per_s: float, n: int, hold: int = 50) -> np.ndarray:
    """A hold, a ramp out, a hold, the ramp back to the start, a hold."""
    out = _ramp(v_m_per_s, n, 0.0)
    back = _ramp(-v_m_per_s, n, float(out[-1]))
    return np.concatenate([np.zeros(hold), out, np.full(hold, out[-1]), back, np.zeros(hold)])


def test_reversal_lag_is_the_lost_motion_of_a_dead_band() -> None:
    """A table that waits at each reversal while the motor crosses a band of width b (its
    lag grows at the ramp speed up to b), then is pulled back onto the reference (the lag
    decays with 30 ms): the ramps that reverse the one before give b each, whatever the
    speed; the outward ramps (no ramp before them) count for nothing."""
    width = 4e-6
    traces = []
    for v in (2e-5, 2e-4, 1e-3):
        n = 400
        ref = _out_and_back(v, n)
        pos = ref.copy()
        a = 50 + n + 50  # the back ramp's first sample
        t = np.arange(ref.size - a) * T
        t_cross = width / v
        lag = np.where(t < t_cross, v * t, width * np.exp(-(t - t_cross) / 30e-3))
        pos[a:] = ref[a:] + lag  # moving in −: lagging behind is above the reference
        traces.append((ref, pos, None))
    sig = signatures_of(traces, T, Q)
    assert sig["reversal_lag_m"].value == pytest.approx(width, rel=1e-4)  # to a sample


def test_reversal_lag_of_a_delay_is_zero_and_needs_a_reversed_ramp() -> None:
    """A reading delayed by three samples lags by v·3T on every ramp, at the reversal as
    later: no lost motion. A trace whose ramps go one way only has no reversal lag."""
    ref = _out_and_back(2e-4, 400)
    pos = np.concatenate([np.zeros(3), ref[:-3]])
    sig = signatures_of([(ref, pos, None)], T, Q)
    assert abs(sig["reversal_lag_m"].value) < 1e-15
    one_way = np.concatenate([np.zeros(50), _ramp(2e-4, 400, 0.0)])
    two_out = np.concatenate([one_way, np.full(50, one_way[-1]), _ramp(2e-4, 400, one_way[-1])])
    assert "reversal_lag_m" not in signatures_of([(two_out, two_out.copy(), None)], T, Q)


def test_distance_is_the_chi_square_over_shared_features() -> None:
    m = {"a": Feature(1.0, 0.3), "b": Feature(2.0, 1.0), "only_measured": Feature(5.0, 1.0)}
    s = {"a": Feature(2.0, 0.4), "b": Feature(2.0, 0.5), "only_simulated": Feature(0.0, 1.0)}
    assert distance(m, s) == pytest.approx(1.0 / (0.09 + 0.16))
    assert distance(m, m) == 0.0


def _result(name: str, rms: float, ms: list[float], occam: float) -> object:
    return candidate_result(name, ms, rms_m=rms, occam=occam)


def test_signatures_narrow_a_tie_and_change_nothing_else() -> None:
    st = DiagnosisSettings()
    # Two candidates the validation gap cannot tell apart (same per-experiment gaps within
    # noise); "b" is the simpler by its Occam factor.
    a = _result("a", 1.0e-7, [1.0e-14, 1.1e-14, 0.9e-14], occam=-5.0)
    b = _result("b", 1.02e-7, [1.1e-14, 1.0e-14, 1.0e-14], occam=-1.0)
    results = [a, b]
    assert pick_winner(results, st) is b  # today's rule: the Occam factor

    def chi(table: dict[str, float]) -> object:
        return lambda tied: [(table[r.effect], 5) for r in tied]

    assert pick_winner(results, st, chi({"a": 0.0, "b": 0.0}), 4.0) is b  # equal: same
    assert pick_winner(results, st, chi({"a": 1.0, "b": 30.0}), 4.0) is a
    assert pick_winner(results, st, chi({"a": 1.0, "b": 30.0}), 0.0) is b  # margin 0: off
    assert pick_winner(results, st, chi({"a": 1.0, "b": 4.5}), 4.0) is b  # within margin
    no_occam = dataclasses.replace(st, occam_tie_break=False)
    assert pick_winner(results, no_occam) is a
    assert pick_winner(results, no_occam, chi({"a": 30.0, "b": 1.0}), 4.0) is b


def test_tie_chi_squares_scale_each_feature_by_its_closest_miss() -> None:
    from nanostage.diagnosis.signatures import tie_chi_squares

    measured = {
        "ramp_level_v": Feature(0.30, 0.001),
        "hunting_fraction": Feature(0.5, 0.1),
        "rest_command_mean_v": Feature(0.0, 0.01),
    }
    # Both models miss the ramp level by tens of errors (a shared friction-law mismatch);
    # only "a" reproduces the hunting; "b" has no rest feature.
    a = {
        "ramp_level_v": Feature(0.33, 0.0),
        "hunting_fraction": Feature(0.45, 0.0),
        "rest_command_mean_v": Feature(0.02, 0.0),
    }
    b = {"ramp_level_v": Feature(0.36, 0.0), "hunting_fraction": Feature(0.0, 0.0)}
    (xa, na), (xb, nb) = tie_chi_squares(measured, [a, b])
    # ramp level: terms 900 and 3600, the closest 900 → 1 and 4; hunting: 0.25 and 25,
    # the closest within its errors → unscaled; rest: 4 (only a has it) → 4/4 = 1.
    assert (na, nb) == (3, 2)
    assert xa == pytest.approx(1.0 + 0.25 + 1.0)
    assert xb == pytest.approx(4.0 + 25.0)
    # A plain χ² would have ranked them by the shared ramp miss alone (904 vs 3625), and
    # one Birge ratio for all (904/3 ≈ 301 per feature) would have buried the hunting:
    # (3625 − 904)/301 ≈ 9, at the margin; per feature it is 29 − 2.25, a clear mark.
    assert tie_chi_squares(measured, [a])[0][0] == pytest.approx(2.25)


def test_effect_marks_are_the_features_a_tied_effect_moves() -> None:
    from nanostage.diagnosis.signatures import effect_marks, tie_chi_squares

    errors = {"ramp_level_v": 0.001, "hold_amplitude_m": 2.0e-8, "reversal_lag_m": 1.0e-7}

    def sig(**values: float) -> dict[str, Feature]:
        """A signature of the given features (ramp level, hold amplitude, reversal lag)."""
        return {name: Feature(v, errors[name]) for name, v in values.items()}

    measured = sig(ramp_level_v=0.30, hold_amplitude_m=6.0e-7, reversal_lag_m=1.0e-6)
    # A backlash and an amplifier lag tied: each refit left the shared sliding friction at
    # another level (0.20 and 0.29 V), which neither effect moves (the same level with the
    # effect taken out); the backlash makes the measured hunting cycle (absent without it)
    # and a reversal lag (4σ from its bare model's); the lag moves nothing beyond 3σ and
    # hunts a little smaller than measured (4.2σ).
    backlash = sig(ramp_level_v=0.20, hold_amplitude_m=6.0e-7, reversal_lag_m=1.0e-6)
    backlash_bare = sig(ramp_level_v=0.20, reversal_lag_m=0.43e-6)
    lag = sig(ramp_level_v=0.29, hold_amplitude_m=4.8e-7, reversal_lag_m=1.0e-6)
    lag_bare = sig(ramp_level_v=0.29, hold_amplitude_m=4.7e-7, reversal_lag_m=0.9e-6)
    marks = effect_marks([backlash, lag], [backlash_bare, lag_bare])
    assert marks == ["hold_amplitude_m", "reversal_lag_m"]
    hunting = (1.2e-7 / math.hypot(2e-8, 2e-8)) ** 2  # 18: the lag's miss of the cycle
    # On all features the ramp level's coin toss decides: the backlash's refit missed it
    # by 100σ against the lag's 10σ (10 000 and 100, scaled by the closest: 100 and 1).
    (xb, _), (xl, _) = tie_chi_squares(measured, [backlash, lag])
    assert (xb, xl) == (pytest.approx(100.0), pytest.approx(1.0 + hunting))
    # On the marks the effects make, the cycle does: the backlash reproduces it.
    (xb, nb), (xl, nl) = tie_chi_squares(measured, [backlash, lag], marks)
    assert (nb, nl) == (2, 2)
    assert (xb, xl) == (pytest.approx(0.0), pytest.approx(hunting))
    assert xl > xb + 9.21
    # No effect moves anything: no marks, every model at χ² 0 (the tie stays a tie).
    assert effect_marks([lag_bare], [lag_bare]) == []
    assert tie_chi_squares(measured, [lag, backlash], []) == [(0.0, 0), (0.0, 0)]
    with pytest.raises(ValueError, match="one of each per tied model"):
        effect_marks([lag], [])


def test_judge_gives_the_generating_model_distance_zero_and_an_offset_force_more() -> None:
    from nanostage import presets
    from nanostage.diagnosis.candidates import applicable_candidates
    from nanostage.diagnosis.objective import simulate_readings_and_commands
    from nanostage.diagnosis.signatures import SignatureJudge
    from nanostage.experiment import Experiment

    system = presets.seed()
    q = system.encoder.count_m
    t = system.sample_period_s
    # Steps both ways and ramps both ways at two speeds, with rests between.
    parts = [np.zeros(100)]
    for target in (2e-4, 0.0, 2e-4, 0.0):
        parts.append(np.full(300, target))
    x = 0.0
    for v in (1e-3, -1e-3, 4e-3, -4e-3):
        r = x + v * t * np.arange(1, 301)
        parts += [r, np.full(150, r[-1])]
        x = r[-1]
    ref = np.concatenate(parts)
    time_s = t * np.arange(ref.size)
    probe = Experiment(name="probe", time_s=time_s, reference_m=ref, position_m=np.zeros(ref.size))
    ((reading, command),) = simulate_readings_and_commands([system], [probe])
    measured = Experiment(
        name="m", time_s=time_s, reference_m=ref, position_m=reading, command_v=command
    )
    judge = SignatureJudge([measured], lambda s, e: s, q, t)
    assert {"rest_command_split_v", "ramp_level_v", "ramp_slope_v_s_per_m"} <= set(judge.measured)
    assert judge.distance(system) == 0.0  # deterministic: the same simulation
    (offset,), _ = applicable_candidates(system, ["offset_force"])
    pushed = offset.apply(system, [0.3 * offset.params[0].upper])
    assert judge.distance(pushed) > 9.0  # a standing force shifts the commands by 3σ or more


def test_misses_are_the_features_off_by_more_than_three_combined_errors() -> None:
    from nanostage.diagnosis.signatures import misses

    m = {"a": Feature(1.0, 0.3), "b": Feature(2.0, 0.1), "c": Feature(0.0, 1.0)}
    s = {"a": Feature(2.0, 0.4), "b": Feature(1.0, 0.1), "c": Feature(2.9, 0.0)}
    out = misses(m, s)
    # a: 1.0/0.5 = 2σ (kept out); b: 1.0/0.141 = 7.1σ; c: 2.9/1.0 = 2.9σ (kept out).
    assert [d["feature"] for d in out] == ["b"]
    assert out[0]["z"] == pytest.approx(1.0 / math.hypot(0.1, 0.1))
    assert [d["feature"] for d in misses(m, s, z_min=1.5)] == ["b", "c", "a"]


def test_report_names_the_signature_chi_square_of_a_tie() -> None:
    from nanostage.diagnosis.report import markdown_report

    report = {
        "selected": ["offset_force"],
        "indistinguishable": {"offset_force": ["asymmetric_friction"]},
        "tie_break": "occam_factor",
        "tie_signatures": [
            {"round": 1, "distances": {"asymmetric_friction": 41.0, "offset_force": 2.5}}
        ],
    }
    md = markdown_report(report)
    assert (
        "signature χ² against the measured marks: `offset_force` 2.5, "
        "`asymmetric_friction` 41" in md
    )
    # Without the margin (reports before it was recorded) the last stage is named.
    assert "selected by the larger Occam factor" in md
    # With it: the marks left the offset alone in the tie (41 > 2.5 + 9.21), and they,
    # not the Occam factor, decided; within the margin the Occam factor decided.
    report["tie_signatures"][0]["margin"] = 9.21
    md = markdown_report(report)
    assert "selected by these marks (the others beyond the margin)" in md
    assert "Occam" not in md
    report["tie_signatures"][0]["distances"]["asymmetric_friction"] = 11.0
    assert "selected by the larger Occam factor" in markdown_report(report)
    # The marks the judge judged on (the features the tied effects move) are named.
    report["tie_signatures"][0]["marks"] = ["ramp_bias_v", "rest_command_mean_v"]
    assert (
        "against the measured marks on the marks the tied effects make (`ramp_bias_v`, "
        "`rest_command_mean_v`)" in markdown_report(report)
    )
    report["tie_signatures"][0]["marks"] = []
    assert "the tied effects make (none)" in markdown_report(report)
    # No distances for the round: nothing said about signatures.
    report["tie_signatures"] = [{"round": 2, "distances": {"a": 1.0, "b": 2.0}}]
    assert "signature χ²" not in markdown_report(report)


def test_the_relative_ranking_lets_every_experiment_count_by_its_own_factor() -> None:
    # "loud" cuts a long step's gap (the first experiment, 100× the others) a little more
    # than "quiet" does, and leaves the three quiet experiments as they were; "quiet" cuts
    # each of those by a factor of 9 in mean square (3 in RMS).
    loud_ms = [0.80e-12, 1.0e-14, 1.0e-14, 1.0e-14]
    quiet_ms = [0.90e-12, 0.11e-14, 0.11e-14, 0.11e-14]
    loud = _result("loud", float(np.sqrt(np.mean(loud_ms))), loud_ms, occam=-1.0)
    quiet = _result("quiet", float(np.sqrt(np.mean(quiet_ms))), quiet_ms, occam=-1.0)
    assert loud.validation_rms_m < quiet.validation_rms_m
    pooled = DiagnosisSettings(ranking="pooled")
    relative = DiagnosisSettings(ranking="relative")
    assert sorted([quiet, loud], key=rank_key("pooled"))[0] is loud
    assert pick_winner(sorted([quiet, loud], key=rank_key("pooled")), pooled) is loud
    ranked = sorted([loud, quiet], key=rank_key("relative"))
    assert ranked[0] is quiet and pick_winner(ranked, relative) is quiet
    # By hand: mean log ratio (quiet − loud) = (log(0.9/0.8) + 3·log 0.11) / 4 < 0.
    by_hand = (np.log(0.90 / 0.80) + 3.0 * np.log(0.11)) / 4.0
    assert quiet.mean_log_ms - loud.mean_log_ms == pytest.approx(by_hand, rel=1e-12)
    assert quiet.geometric_rms_m == pytest.approx(
        float(np.prod(np.sqrt(quiet_ms)) ** 0.25), rel=1e-12
    )
    # Told apart relatively (a consistent factor of 9 on three of four), and "pooled" ties
    # them (within 25 % of each other; the step's difference swamps the others').
    assert not indistinguishable(loud, quiet, "relative")
    assert indistinguishable(loud, quiet, "pooled")
    with pytest.raises(ValueError, match=r"ranking = 'geometric'.*relative, pooled"):
        rank_key("geometric")


@settings(max_examples=60, deadline=None)
@given(
    st_h.lists(
        st_h.tuples(st_h.floats(1e-16, 1e-10), st_h.floats(1e-16, 1e-10), st_h.floats(1e-3, 1e3)),
        min_size=2,
        max_size=8,
    )
)
def test_the_relative_ranking_does_not_depend_on_each_experiments_scale(
    rows: list[tuple[float, float, float]],
) -> None:
    # Scaling one experiment's mean square by any factor, the same for every candidate
    # (a louder experiment kind, another floor weight), changes neither the order of two
    # candidates nor whether they are told apart.
    a_ms = [a for a, _, _ in rows]
    b_ms = [b for _, b, _ in rows]
    a2_ms = [a * c for a, _, c in rows]
    b2_ms = [b * c for _, b, c in rows]
    a, b = _result("a", 1.0, a_ms, 0.0), _result("b", 1.0, b_ms, 0.0)
    a2, b2 = _result("a", 1.0, a2_ms, 0.0), _result("b", 1.0, b2_ms, 0.0)
    key = rank_key("relative")
    d1, d2 = key(a) - key(b), key(a2) - key(b2)
    assert d1 == pytest.approx(d2, abs=1e-9)
    if abs(d1) > 1e-6:
        assert (d1 < 0) == (d2 < 0)
    # Away from the edges of the tie test, the verdict is the same.
    la, lb = np.log(a_ms), np.log(b_ms)
    dl = la - lb
    se = float(np.std(dl, ddof=1) / np.sqrt(len(dl)))
    m = abs(float(np.mean(dl)))
    if abs(m - 2.0 * se) > 1e-6 and abs(m - 2.0 * np.log(1.25)) > 1e-6:
        assert indistinguishable(a, b, "relative") == indistinguishable(a2, b2, "relative")
