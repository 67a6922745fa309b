"""The independent truth family (nanostage.diagnosis.independent_truth): its independence
from nanostage's models, its physics, its controller, determinism and the case it writes."""

from __future__ import annotations

import ast
import dataclasses as dc
import math
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.integrate import solve_ivp
from scipy.optimize import brentq

from nanostage import presets
from nanostage.diagnosis import independent_truth as it
from nanostage.diagnosis import load_manifest
from nanostage.diagnosis.candidates import CANDIDATES

import pid_reference as ref

FloatArray = np.ndarray

MODULE = Path(it.__file__)


def _short_design(count: int = 2) -> list[it.DesignedExperiment]:
    return it.experiment_design(
        count,
        move_s=0.06,
        dwells_s=(0.02,),
        ramp_speeds_m_per_s=(1e-3,),
        ramp_length_m=10e-6,
    )


def test_imports_nothing_of_nanostage_but_output() -> None:
    # The module and the manifest head it shares with the other family.
    tree = ast.parse(MODULE.read_text(encoding="utf-8"))
    head = ast.parse((MODULE.parent / "case_manifest.py").read_text(encoding="utf-8"))
    tree.body.extend(head.body)
    stdlib = set(sys.stdlib_module_names)
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                top = a.name.split(".")[0]
                assert top in stdlib or top in ("numpy", "scipy"), a.name
        elif isinstance(node, ast.ImportFrom):
            if node.level == 0:
                top = (node.module or "").split(".")[0]
                assert top in stdlib or top in ("numpy", "scipy", "__future__"), node.module
            else:
                # Relative: only the output helpers and the shared manifest head.
                allowed = {(2, "output"), (1, "case_manifest")}
                assert (node.level, node.module) in allowed, ast.dump(node)


def test_copied_seed_numbers_match_the_preset() -> None:
    d = dc.asdict(presets.seed(1e-3))
    pl = d["plant"]
    v = it.SEED
    assert v["resistance_ohm"] == pl["motor"]["resistance_ohm"]
    assert v["inductance_h"] == pl["motor"]["inductance_h"]
    assert v["torque_constant_nm_per_a"] == pl["motor"]["torque_constant_nm_per_a"]
    assert v["back_emf_v_s_per_rad"] == pl["motor"]["back_emf_v_s_per_rad"]
    assert v["rotor_inertia_kg_m2"] == pl["motor"]["rotor_inertia_kg_m2"]
    assert v["static_torque_nm"] == pl["motor_friction"]["static_torque_nm"]
    assert v["coulomb_torque_nm"] == pl["motor_friction"]["coulomb_torque_nm"]
    assert v["viscous_nm_s_per_rad"] == pl["motor_friction"]["viscous_nm_s_per_rad"]
    assert v["gear_ratio"] == pl["gearhead"]["ratio"]
    assert v["gear_efficiency"] == pl["gearhead"]["efficiency"]
    assert v["lead_m"] == pl["screw"]["lead_m"]
    assert v["screw_efficiency"] == pl["screw"]["efficiency"]
    assert v["screw_inertia_kg_m2"] == pl["screw"]["inertia_kg_m2"]
    assert v["mass_kg"] == pl["table"]["mass_kg"]
    assert v["table_coulomb_force_n"] == pl["dahl"]["coulomb_force_n"]
    assert v["table_stiffness_n_per_m"] == pl["dahl"]["stiffness_n_per_m"]
    assert v["count_m"] == d["encoder"]["count_m"]
    assert v["amplifier_limit_v"] == d["output_stage"]["amplifier_limit_v"]
    c = d["controller"]
    assert v["sample_period_s"] == c["ticks_per_sample"] / c["clock_hz"]
    assert v["latency_s"] == c["latency_ticks"] / c["clock_hz"]
    assert it.DAC_LSB_V == c["dac_lsb_v"]
    assert it.OUTPUT_UNIT_V == c["output_unit_v"]
    assert it.OUTPUT_LIMIT == c["output_max"] == -c["output_min"]
    for key, fmt in it.SEED_FORMATS.items():
        f = c[f"{key}_format"]
        assert fmt == (f["signed"], f["word_bits"], f["int_bits"], f["rounding"], f["overflow"])
    for step, gains in it.TABLE1_GAINS.items():
        assert gains == presets.table1_gains(step)


def test_pid_matches_the_reference_on_a_recorded_sequence() -> None:
    def fmt(t: tuple[bool, int, int, str, str]) -> dict[str, object]:
        return dict(
            zip(("signed", "word_bits", "int_bits", "rounding", "overflow"), t, strict=True)
        )

    rng = np.random.default_rng(3)
    n = 400
    # Errors from a few counts to beyond saturation, reference steps and reversals.
    r = np.cumsum(rng.integers(-2, 3, n)) + np.where(np.arange(n) > 200, 3000, 0)
    y = r - rng.integers(-40, 41, n) - np.where((np.arange(n) % 97) < 5, 2000, 0)
    for kp, ki, kd in ((450.0, 2.0, 40.0), (450.0, 5.0, 10.0), (0.0, 2.0, 0.0), (12.3, 0.7, 3.1)):
        cfg = {f"{k}_format": fmt(v) for k, v in it.SEED_FORMATS.items()}
        cfg |= {
            "kp": kp,
            "ki": ki,
            "kd": kd,
            "anti_windup": "conditional",
            "output_min": -it.OUTPUT_LIMIT,
            "output_max": it.OUTPUT_LIMIT,
            "output_unit_v": it.OUTPUT_UNIT_V,
            "dac_lsb_v": it.DAC_LSB_V,
        }
        want = ref.run(cfg, [int(a) for a in r], [int(b) for b in y])
        pid = it.FixedPointPid(kp, ki, kd)
        got = [pid.step(int(a), int(b)) for a, b in zip(r, y, strict=True)]
        assert [g[0] for g in got] == want["u"]
        assert [g[1] for g in got] == want["code"]


def test_open_loop_sliding_speed_matches_the_force_balance() -> None:
    t = it.draw_truth("none", 11)
    p = t.p
    u = 2.5
    out = it.simulate_open_loop(t, np.full(150, u))
    v_end = out["velocity_m_per_s"][-1]
    r, eta = t.r, t.eta

    def balance(v: float) -> float:
        w = v / r
        i = (u - p["back_emf_v_s_per_rad"] * w) / p["resistance_ohm"]
        g = p["coulomb_torque_nm"] + (p["static_torque_nm"] - p["coulomb_torque_nm"]) * math.exp(
            -((w / p["stribeck_velocity_rad_per_s"]) ** 2)
        )
        tm = g + p["viscous_nm_s_per_rad"] * w
        return eta / r * (p["torque_constant_nm_per_a"] * i - tm) - p["table_coulomb_force_n"]

    v_ss = brentq(balance, 1e-6, u / p["back_emf_v_s_per_rad"] * r)
    assert v_end == pytest.approx(v_ss, rel=1e-6)
    assert np.std(out["velocity_m_per_s"][-20:]) < 1e-6 * v_ss


def _friction_path(
    hidden: str, seed: int, x_of_t: Any, v_of_t: Any, t_end: float, n: int = 400
) -> tuple[FloatArray, FloatArray]:
    """Table position and friction force of a drawn truth's table law along a prescribed
    motion (the friction states integrated by scipy at tight tolerance)."""
    t = it.draw_truth(hidden, seed)
    run = it._Run(t, level=1.0)
    zi = [it._ZT, *range(it._N_STATES, run.n_states)]

    def state(tt: float, z: FloatArray) -> FloatArray:
        y = np.zeros(run.n_states)
        y[it._X], y[it._V] = x_of_t(tt), v_of_t(tt)
        y[zi] = z
        return y

    def rate(tt: float, z: FloatArray) -> FloatArray:
        dy = np.zeros(run.n_states)
        run.table_friction(state(tt, z), dy)
        return dy[zi]

    ts = np.linspace(0.0, t_end, n)
    sol = solve_ivp(
        rate, (0.0, t_end), np.zeros(len(zi)), t_eval=ts, rtol=1e-10, atol=1e-16, method="LSODA"
    )
    assert sol.success
    force = np.array(
        [
            run.table_friction(state(tt, sol.y[:, k]), np.zeros(run.n_states))
            for k, tt in enumerate(ts)
        ]
    )
    return np.array([x_of_t(tt) for tt in ts]), force


@pytest.mark.parametrize("hidden", ["lugre", "presliding_gms"])
@pytest.mark.parametrize("speed_in_stribeck_velocities", [0.3, 1.0, 3.0])
def test_steady_sliding_force_is_the_stribeck_curve(
    hidden: str, speed_in_stribeck_velocities: float
) -> None:
    # Sliding at a constant speed, the table law's force settles at the Coulomb level times
    # 1 + (r − 1)·exp(−(v/vₛ)²) (the Maxwell-slip elements' slip forces summing to it).
    t = it.draw_truth(hidden, 5)
    e, fc = t.effect, t.p["table_coulomb_force_n"]
    v = speed_in_stribeck_velocities * e["stribeck_velocity_m_per_s"]
    expected = fc * (
        1.0 + (e["static_ratio"] - 1.0) * math.exp(-((v / e["stribeck_velocity_m_per_s"]) ** 2))
    )
    # Long enough for the softest element to slide: 20 of its sliding deflections.
    ks = e.get("stiffnesses_n_per_m", [t.p["table_stiffness_n_per_m"]])
    z_far = max(fc * e["static_ratio"] / k for k in ks)
    _, f = _friction_path(hidden, 5, lambda tt: v * tt, lambda tt: v, 20.0 * z_far / v)
    assert f[-1] == pytest.approx(expected, rel=1e-6)


def test_maxwell_slip_presliding_bends_over_its_elements_and_saturates() -> None:
    t = it.draw_truth("presliding_gms", 3)
    e, p = t.effect, t.p
    k_total = sum(e["stiffnesses_n_per_m"])
    v = 1e-7  # far below the Stribeck velocity: the static level
    f_static = p["table_coulomb_force_n"] * (
        1.0 + (e["static_ratio"] - 1.0) * math.exp(-((v / e["stribeck_velocity_m_per_s"]) ** 2))
    )
    z_far = max(
        w * f_static / k for w, k in zip(e["weights"], e["stiffnesses_n_per_m"], strict=True)
    )
    t_end = 10.0 * z_far / v
    x, f = _friction_path("presliding_gms", 3, lambda tt: v * tt, lambda tt: v, t_end, n=2001)
    # Initial slope: all elements elastic, the total stiffness (and the dampers at v).
    c_total = sum(it._Run(t, level=1.0).slip_c)
    k0 = (f[1] - f[0]) / (x[1] - x[0])
    assert k0 == pytest.approx(k_total, rel=1e-3)
    assert f[0] == pytest.approx(c_total * v, rel=1e-6)
    # Saturates at the static level once every element slides.
    assert f[-1] == pytest.approx(f_static, rel=1e-3)
    # Gradual: where one element of the whole stiffness would reach the level, the elements
    # together give well under it (the stiff ones slip first).
    at = np.interp(f_static / k_total, x, f)
    assert at < 0.7 * f_static
    # The secant stiffness falls monotonically (no element stiffens the curve again).
    sec = f[1:] / x[1:]
    assert np.all(np.diff(sec) <= 1e-9 * k_total)


@pytest.mark.parametrize("hidden", ["lugre", "presliding_gms", "none"])
def test_table_laws_dissipate_over_a_closed_presliding_cycle(hidden: str) -> None:
    # x = A·sin(ωt) over whole periods: the work the table law takes, ∮ F dx, is positive
    # (the laws are passive) and the cycle ends where it started.
    amp, w = 40e-9, 2.0 * math.pi * 5.0
    x, f = _friction_path(
        hidden,
        8,
        lambda tt: amp * math.sin(w * tt),
        lambda tt: amp * w * math.cos(w * tt),
        2.0 / 5.0,
        n=4001,
    )
    work = float(np.sum(0.5 * (f[1:] + f[:-1]) * np.diff(x)))
    assert work > 0.0
    assert x[-1] == pytest.approx(x[0], abs=1e-15)


def test_backlash_table_lags_the_motor_by_the_dead_band_on_a_reversal() -> None:
    t = it.draw_truth("backlash", 4)
    e = t.effect
    n = 120
    out = it.simulate_open_loop(t, np.concatenate([np.full(n, 2.0), np.full(n, -2.0)]))
    d = out["motor_position_m"] - out["position_m"]
    k = e["contact_stiffness_n_per_m"]
    fc = t.p["table_coulomb_force_n"]
    # Sliding both ways, the link carries the table friction: the Hertzian flank contact,
    # of tangent stiffness k at that load, is compressed by 1.5·Fc/k (F ∝ δ^1.5) on either
    # side of the dead band.
    assert d[n] == pytest.approx(0.5 * e["width_m"] + 1.5 * fc / k, rel=1e-4)
    assert d[-1] == pytest.approx(-0.5 * e["width_m"] - 1.5 * fc / k, rel=1e-4)
    # After the reversal the motor crosses the gap while the table stays (within its
    # presliding relaxation, below a micrometre).
    xm, x = out["motor_position_m"], out["position_m"]
    crossing = np.flatnonzero(xm[n:] < xm[n] - 0.9 * e["width_m"])[0] + n
    assert np.all(x[n:crossing] > x[n] - 1e-6)
    assert x[-1] < x[n] - 100e-6


def _contact(run: Any, depth_m: float, rate_m_per_s: float, side: float = 1.0) -> float:
    """The link force with the motor ``depth_m`` into the flank on ``side`` (±1), closing
    at ``rate_m_per_s`` (the table at rest at 0)."""
    y = np.zeros(run.n_states)
    y[it._TH] = side * (0.5 * run.truth.effect["width_m"] + depth_m) / run.r
    y[it._W] = side * rate_m_per_s / run.r
    return float(run.link_force(y))


def test_backlash_contact_is_hertzian_continuous_and_only_pushes() -> None:
    t = it.draw_truth("backlash", 6)
    run = it._Run(t, level=1.0)
    k, c = t.effect["contact_stiffness_n_per_m"], t.effect["contact_damping_n_s_per_m"]
    fc = t.p["table_coulomb_force_n"]
    for side in (1.0, -1.0):
        # Inside the dead band nothing is transmitted; at touch-down force and stiffness
        # start from zero, whatever the closing rate (no jump for the integrator).
        assert _contact(run, -1e-9, 1e-3, side) == 0.0
        assert abs(_contact(run, 1e-15, 1e-3, side)) < 1e-12 * fc
        # At the table's sliding load the tangent stiffness and damping are the drawn ones.
        ref = 1.5 * fc / k
        assert side * _contact(run, ref, 0.0, side) == pytest.approx(fc, rel=1e-12)
        h = 1e-6 * ref
        slope = (_contact(run, ref + h, 0.0, side) - _contact(run, ref - h, 0.0, side)) / (2 * h)
        assert side * slope == pytest.approx(k, rel=1e-6)
        damp = (_contact(run, ref, 1e-4, side) - _contact(run, ref, -1e-4, side)) / 2e-4
        assert side * damp == pytest.approx(c, rel=1e-9)
        # Grows as depth^1.5.
        ratio = _contact(run, 8 * ref, 0.0, side) / _contact(run, 2 * ref, 0.0, side)
        assert ratio == pytest.approx(8.0, rel=1e-12)
        # Separating fast, the damper cannot pull: the force stays on the pushing side.
        assert _contact(run, ref, -10.0 * fc / c, side) == 0.0


@given(
    amp=st.floats(0.01, 3.0),
    freq=st.floats(1.0, 2000.0),
    seed=st.integers(0, 50),
)
@settings(max_examples=40, deadline=None)
def test_backlash_contact_dissipates_over_a_closed_indentation(
    amp: float, freq: float, seed: int
) -> None:
    # δ(t) = A·ref·(1 − cos ωt)/2 over one period: the Hertzian part gives back what it
    # took, the Hunt-Crossley damping only takes (∮ F dδ ≥ 0, and > 0 when moving).
    t = it.draw_truth("backlash", seed)
    run = it._Run(t, level=1.0)
    ref = 1.5 * t.p["table_coulomb_force_n"] / t.effect["contact_stiffness_n_per_m"]
    w = 2.0 * math.pi * freq
    tt = np.linspace(0.0, 1.0 / freq, 4001)
    depth = amp * ref * 0.5 * (1.0 - np.cos(w * tt))
    rate = amp * ref * 0.5 * w * np.sin(w * tt)
    f = np.array([_contact(run, d, r) for d, r in zip(depth, rate, strict=True)])
    work = float(np.sum(0.5 * (f[1:] + f[:-1]) * np.diff(depth)))
    elastic = float(np.max(f)) * amp * ref
    assert work > -1e-6 * elastic


def test_backlash_dwell_that_once_stalled_integrates_at_a_modest_cost() -> None:
    # A 1.5 s dwell of the design's micro-step experiment, the motor resting at a flank's
    # edge: with a contact force that jumped at touch-down, and the rotor-free amplifier
    # state carried, scipy's Radau stalled at its 456th interval (its finite-difference
    # step on the unused state overflowed). Now each interval takes tens of evaluations.
    t = it.draw_truth("backlash", 1480001)
    e = it.experiment_design()[5]
    assert e.name == "exp05_micro"
    calls = 0
    orig = it._Run.rhs

    def counted(self: Any, u: float, s: FloatArray) -> FloatArray:
        nonlocal calls
        calls += 1
        return orig(self, u, s)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(it._Run, "rhs", counted)
        out = it.simulate_closed_loop(t, e.reference_m[:600], e.gains, 1480001 * 1000 + 5)
    assert calls < 600 * 150
    assert np.all(np.isfinite(out["true_position_m"]))


def test_a_stalled_integration_is_reported_not_hung(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(it, "MAX_RHS_PER_INTERVAL", 5)
    t = it.draw_truth("offset_force", 3)
    design = _short_design(1)
    with pytest.raises(it.IntegrationStalled, match=r"'offset_force', case seed 3, experiment 0"):
        it._closed_loop_job((t, design[0].reference_m, design[0].gains, 3000, False, False))
    run = it._Run(t, level=1.0)
    with pytest.raises(it.IntegrationStalled, match=r"over 5 right-hand-side evaluations"):
        run.advance(it._initial_state(run, 1e-3, 0.0), 1.0, 1e-3)


def test_an_interval_radau_stalls_on_is_integrated_by_lsoda(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # The rotor at full voltage crossing the dead band of a 24 µm backlash, the table at
    # rest (case seed 1560001, exp10_reversal, where a benchmark run once stopped): Radau's
    # Newton iterations kept failing (77 857 evaluations for the 1 ms interval), LSODA
    # needs about 250. The result agrees with a tight BDF run within a few tolerance units.
    monkeypatch.setattr(it, "MAX_RHS_PER_INTERVAL", 3000)
    run = it._Run(it.draw_truth("backlash", 1560001), level=1.0)
    y = np.array([0.02403130048, 7.342e-11, 1434.264, -47.51217, -1.860637, -7.478667e-4, 0, 0])
    with pytest.raises(it.IntegrationStalled, match=r"\(Radau\)"):
        run._advance(y, -6.0, 1e-3, "Radau")
    out = run.advance(y, -6.0, 1e-3)
    act = run.active

    def f(_t: float, s: FloatArray) -> FloatArray:
        z = y.copy()
        z[act] = s
        return run.rhs(-6.0, z)[act]

    ref = solve_ivp(f, (0.0, 1e-3), y[act], method="BDF", rtol=1e-11, atol=run.active_atol / 100)
    err = np.abs(out[act] - ref.y[:, -1]) / (1e-9 * np.abs(ref.y[:, -1]) + run.active_atol)
    assert np.max(err) < 20.0
    assert out[it._W] < -150.0  # the rotor sped up through the dead band


def test_rigid_rotor_follows_the_table() -> None:
    # Rigid, the rotor's angle and speed are not integrated: they follow the table's.
    t = it.draw_truth("none", 5)
    run = it._Run(t, level=1.0)
    assert it._UA not in run.active_states() and it._TH not in run.active_states()
    y0 = it._initial_state(run, 1e-3, 0.0)
    y = y0
    for _ in range(30):
        y = run.advance(y, 2.0, 1e-3)
    assert y[it._X] > y0[it._X] + 1e-6
    assert y[it._TH] == pytest.approx(y0[it._TH] + (y[it._X] - y0[it._X]) / run.r, rel=1e-14)
    assert y[it._W] == y[it._V] / run.r
    lag = it._Run(it.draw_truth("amplifier_dynamics", 5), level=1.0)
    chain = it._Run(it.draw_truth("drive_compliance", 5), level=1.0)
    assert it._UA in lag.active_states()
    assert {it._TH, it._W} <= set(chain.active_states().tolist())


def test_hidden_effects_drawn_and_named() -> None:
    for h in it.HIDDEN_EFFECTS:
        t = it.draw_truth(h, 2)
        assert t.hidden == h
        assert (t.effect == {}) == (h == "none")
        # Nominal parameters are off the preset in every case.
        assert t.p["table_coulomb_force_n"] != it.SEED["table_coulomb_force_n"]
    assert not set(it.NOT_YET_WRITTEN) & set(it.HIDDEN_EFFECTS)
    # Every written effect is found by names the diagnosis can answer with.
    for h in set(it.HIDDEN_EFFECTS) - {"none"}:
        assert it.ACCEPT.get(h, frozenset({h})) <= set(CANDIDATES), h
    with pytest.raises(ValueError, match="unknown hidden effect"):
        it.draw_truth("gremlins", 1)


def test_experiment_design_covers_the_kinds() -> None:
    d = it.experiment_design(12)
    assert len(d) == 12
    kinds = {e.name.split("_", 1)[1] for e in d}
    assert kinds == {"step", "micro", "ramp", "reversal"}
    assert {e.role for e in d} == {"train", "validate"}
    ramps = [e for e in d if e.name.endswith("ramp")]
    speeds = sorted(float(np.max(np.abs(np.diff(e.reference_m)))) / 1e-3 for e in ramps)
    assert speeds == pytest.approx([20e-6, 200e-6, 1e-3])
    for e in ramps:  # out and back: a reversal
        assert e.reference_m[-1] == pytest.approx(e.reference_m[0])
    micro = [e for e in d if e.name.endswith("micro")]
    for e in micro:
        assert abs(e.reference_m[-1] - e.reference_m[0]) == pytest.approx(3e-7)
    assert len(it.experiment_design(5, dwells_s=(0.1,))) == 5
    with pytest.raises(ValueError):
        it.experiment_design(0)


@pytest.mark.parametrize("hidden", ["none", "dwell_static_friction"])
def test_same_seed_same_traces(tmp_path: Path, hidden: str) -> None:
    design = _short_design(1)
    a = it.write_case(hidden, 7, tmp_path / "a", design=design)
    b = it.write_case(hidden, 7, tmp_path / "b", design=design)
    c = it.write_case(hidden, 8, tmp_path / "c", design=design)
    names = sorted(p.name for p in (tmp_path / "a").iterdir())
    assert names == sorted(p.name for p in (tmp_path / "b").iterdir())
    for name in names:
        assert (tmp_path / "a" / name).read_bytes() == (tmp_path / "b" / name).read_bytes()
    trace = design[0].name + ".csv"
    assert (tmp_path / "a" / trace).read_bytes() != (tmp_path / "c" / trace).read_bytes()
    assert a[1] == b[1] and a[1] != c[1]


def test_spawned_workers_write_the_same_files(tmp_path: Path) -> None:
    design = _short_design(3)
    it.write_case("backlash", 11, tmp_path / "one", design=design)
    it.write_case("backlash", 11, tmp_path / "two", design=design, workers=2)
    names = sorted(p.name for p in (tmp_path / "one").iterdir())
    assert names == sorted(p.name for p in (tmp_path / "two").iterdir())
    for name in names:
        assert (tmp_path / "one" / name).read_bytes() == (tmp_path / "two" / name).read_bytes()
    for bad in (0, 257, 1.5, True):
        with pytest.raises(ValueError, match="workers"):
            it.write_case("none", 1, tmp_path / "bad", design=design, workers=bad)  # type: ignore[arg-type]
    assert not (tmp_path / "bad").exists()


def test_written_case_is_read_by_the_diagnosis(tmp_path: Path) -> None:
    manifest, truth = it.write_case("offset_force", 3, tmp_path / "case", design=_short_design(3))
    assert truth["hidden"] == "offset_force" and truth["family"] == "independent"
    assert "force_n" in truth["parameters"]
    m = load_manifest(manifest)
    exps = m.experiments()
    assert len(exps) == 3
    for spec, e in exps:
        assert spec.role in ("train", "validate")
        assert e.command_v is not None
        assert np.max(np.abs(e.command_v)) <= 6.0
        # Encoder readings are whole counts.
        counts = e.position_m / 1e-7
        assert np.allclose(counts, np.round(counts), atol=1e-6)
    assert {s.name for s in m.splits()} == {"roles"}


def _same(a: dict[str, np.ndarray], b: dict[str, np.ndarray]) -> bool:
    return a.keys() == b.keys() and all(np.array_equal(a[k], b[k]) for k in a)


def test_deterministic_run_has_no_noise_and_the_same_start() -> None:
    """The truth's own deterministic model: no encoder noise (the reading is the floor of
    the true position), the friction level at its median, the start the recorded run drew."""
    t = it.draw_truth("offset_force", 5)
    e = _short_design(1)[0]
    q = t.p["count_m"]
    det = it.simulate_closed_loop(t, e.reference_m, e.gains, 9, deterministic=True)
    run = it.simulate_closed_loop(t, e.reference_m, e.gains, 9)
    assert _same(det, it.simulate_closed_loop(t, e.reference_m, e.gains, 9, deterministic=True))
    assert np.array_equal(det["position_m"], np.floor(det["true_position_m"] / q) * q)
    assert det["true_position_m"][0] == run["true_position_m"][0]
    assert not np.array_equal(det["true_position_m"], run["true_position_m"])
    # Another seed starts elsewhere within the first count, and from there alone differs.
    other = it.simulate_closed_loop(t, e.reference_m, e.gains, 10, deterministic=True)
    assert other["true_position_m"][0] != det["true_position_m"][0]


@pytest.mark.parametrize("hidden", ["offset_force", "backlash"])
def test_without_hidden_is_the_nominal_truth_from_the_same_draws(hidden: str) -> None:
    """Without its hidden effect a run is the nominal truth's run from the same draws: the
    same to the last bit (with a backlash, whose flank is drawn all the same, the
    deterministic runs; the noisy ones draw their noise after it); with the effect it
    differs (the effect's footprint)."""
    t = it.draw_truth(hidden, 6)
    bare = dc.replace(t, hidden="none", effect={})
    e = _short_design(1)[0]
    for det in (True, False) if hidden != "backlash" else (True,):
        without = it.simulate_closed_loop(
            t, e.reference_m, e.gains, 3, deterministic=det, without_hidden=True
        )
        assert _same(
            without, it.simulate_closed_loop(bare, e.reference_m, e.gains, 3, deterministic=det)
        )
        full = it.simulate_closed_loop(t, e.reference_m, e.gains, 3, deterministic=det)
        assert not np.array_equal(full["true_position_m"], without["true_position_m"])
    # A backlash's flank is still drawn: the noisy run without it is not the nominal run.
    if hidden == "backlash":
        noisy = it.simulate_closed_loop(t, e.reference_m, e.gains, 3, without_hidden=True)
        assert not _same(noisy, it.simulate_closed_loop(bare, e.reference_m, e.gains, 3))


def test_oracle_readings_are_the_deterministic_model_of_the_written_case() -> None:
    design = _short_design(3)
    names = [design[0].name, design[2].name]
    got = it.oracle_readings("offset_force", 4, names, design=design)
    assert list(got) == names
    t = it.draw_truth("offset_force", 4)
    q = t.p["count_m"]
    for i in (0, 2):
        e = design[i]
        # write_case's stream of experiment i: seed · 1000 + i.
        det = it.simulate_closed_loop(t, e.reference_m, e.gains, 4 * 1000 + i, deterministic=True)
        assert np.array_equal(got[e.name], det["true_position_m"] - 0.5 * q)
    bare = it.oracle_readings("offset_force", 4, names[:1], design=design, without_hidden=True)
    assert not np.array_equal(bare[names[0]], got[names[0]])
    with pytest.raises(ValueError, match="'nope' are not experiments of the design"):
        it.oracle_readings("offset_force", 4, ["nope"], design=design)
    with pytest.raises(ValueError, match="workers"):
        it.oracle_readings("offset_force", 4, names, design=design, workers=0)


@pytest.mark.parametrize("seed", [1, 2, 3, 4])
def test_pipelined_loop_moves_whole_cycles_late(seed: int) -> None:
    """A pipelined controller: the command the loop computes is the same sample by sample
    until the axis has moved, and the axis starts to move ``pipeline_cycles`` samples later
    than without the pipeline (the extra latency is under a quarter of a cycle)."""
    t = it.draw_truth("computation_delay", seed)
    cycles = int(t.effect["pipeline_cycles"])
    assert cycles in (1, 2)
    assert 0.0 <= t.effect["extra_latency_s"] <= 0.25 * t.p["sample_period_s"]
    ref = np.concatenate([np.full(5, 2e-3), np.full(60, 2.1e-3)])
    gains = it.TABLE1_GAINS[100e-6]
    late = it.simulate_closed_loop(t, ref, gains, 9, deterministic=True)
    now = it.simulate_closed_loop(t, ref, gains, 9, deterministic=True, without_hidden=True)

    def first_move(run: dict[str, np.ndarray]) -> int:
        x = run["true_position_m"]
        return int(np.argmax(np.abs(x - x[0]) > 1e-9))

    assert first_move(late) - first_move(now) == cycles
    # Up to the first reading that differs, the loop computes the same commands.
    k = first_move(now)
    assert np.array_equal(late["command_v"][: k + 1], now["command_v"][: k + 1])
