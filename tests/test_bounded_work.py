"""Bounded work, no silent non-finite results, Ctrl-C and wrong types.

Every simulation has a work budget per control interval (``IntegratorOptions.max_steps``
integrator steps and ``max_events`` stick/slip events), so no configuration inside the
validated ranges runs for ever: a run that exceeds it ends with :class:`SimulationError`
naming the time, the state and the cause (a campaign trial: its status). Ranges whose
extremes the numerics cannot serve are tightened to physical values. A long call stops on
SIGINT. A value of the wrong type is a :class:`ConfigError` (and a :class:`TypeError`) naming
its field path.
"""

from __future__ import annotations

import dataclasses
import math
import os
import signal
import threading
import time
from collections.abc import Callable, Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from typing import Any

import numpy as np
import pytest
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st

import nanostage as ns
from nanostage import cycles
from nanostage.campaign import TrialStatus, run_campaign
from nanostage.config import ForceDrivePlant
from nanostage.effects import (
    AmplifierDynamics,
    Backlash,
    DriveCompliance,
    DwellStaticFriction,
    Effects,
    FrictionModifiers,
    Gms,
    LuGre,
    StaticFrictionMap,
    StochasticFriction,
)
from nanostage.friction import friction_response
from nanostage.simulate import simulate_batch, stop_on_interrupt

SEED = ns.presets.seed(1e-4)


def _plant(**blocks: dict[str, Any]) -> ns.Plant:
    """The seed plant with fields of its blocks replaced: ``_plant(motor={...})``."""
    p = SEED.plant
    return dataclasses.replace(
        p, **{b: dataclasses.replace(getattr(p, b), **v) for b, v in blocks.items()}
    )


def _chattering() -> ns.System:
    """A valid motor-shaft Stribeck law the stick/slip logic cannot resolve: exponent 0.5 (a
    friction slope unbounded at rest) with the smallest Stribeck velocity; every breakaway
    chatters between stick and slip at ever shorter intervals."""
    plant = _plant(motor_friction={"stribeck_exponent": 0.5, "stribeck_velocity_rad_per_s": 1e-3})
    return dataclasses.replace(SEED, plant=plant)


# --------------------------------------------------------------------------------------
# The inputs that used to hang or return NaN
# --------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("block", "name", "value", "field", "shown", "expected"),
    [
        # A 50 ms step of the seed axis never returned (nor answered Ctrl-C).
        ("dahl", "coulomb_force_n", 1e-30, "dahl.coulomb_force_n", "1e-30", "[1e-6, 1e5]"),
        # A million stick/slip events in 80 ms.
        (
            "motor_friction",
            "stribeck_velocity_rad_per_s",
            3.8e-20,
            "motor_friction.stribeck_velocity_rad_per_s",
            "3.8e-20",
            "[1e-3, 1e5]",
        ),
        # Zero integrator steps and a NaN current.
        ("motor", "resistance_ohm", 5e-324, "motor.resistance_ohm", "5e-324", "[1e-3, 1e3]"),
        ("motor", "inductance_h", 5e-324, "motor.inductance_h", "5e-324", "[1e-9, 1e0]"),
        ("dahl", "stiffness_n_per_m", 5e-324, "dahl.stiffness_n_per_m", "5e-324", "[1e-3, 1e12]"),
        ("table", "mass_kg", 5e-324, "table.mass_kg", "5e-324", "[1e-6, 1e4]"),
    ],
)
def test_values_the_numerics_cannot_serve_are_rejected_with_the_range(
    block: str, name: str, value: float, field: str, shown: str, expected: str
) -> None:
    with pytest.raises(ns.ConfigError) as e:
        _plant(**{block: {name: value}})
    assert str(e.value) == f"{field} = {shown} is invalid: expected a finite number in {expected}"
    assert e.value.field == field
    # The bounds themselves are valid.
    lo = float(expected[1:].split(",")[0])
    _plant(**{block: {name: lo}})


def test_the_new_bounds_hold_for_the_effect_library() -> None:
    with pytest.raises(ns.ConfigError, match=r"^plant\.table_friction\.coulomb_force_n = 1e-30"):
        dataclasses.replace(
            SEED,
            effects=Effects(
                table_friction=LuGre(
                    stiffness_n_per_m=1e7,
                    damping_n_s_per_m=0.0,
                    viscous_n_s_per_m=0.0,
                    coulomb_force_n=1e-30,
                    static_force_n=1.0,
                    stribeck_velocity_m_per_s=1e-3,
                )
            ),
        )
    with pytest.raises(ns.ConfigError, match=r"stiffness_n_per_m\[1\] = 1e-9 is invalid"):
        dataclasses.replace(
            SEED,
            effects=Effects(
                table_friction=Gms(
                    stiffness_n_per_m=(1e7, 1e-9),
                    weights=(0.5, 0.5),
                    coulomb_force_n=30.0,
                    static_force_n=36.0,
                    stribeck_velocity_m_per_s=1e-3,
                )
            ),
        )


def test_a_chattering_friction_law_ends_with_a_simulation_error_naming_time_and_cause() -> None:
    start = time.process_time()
    with pytest.raises(ns.SimulationError) as e:
        ns.simulate_step(_chattering(), 1e-4, duration_s=0.05)
    spent = time.process_time() - start
    msg = str(e.value)
    assert msg.startswith("more than 10000 stick/slip events in one control interval at t = ")
    assert "friction switches faster than the model can resolve" in msg
    # The step starts at 10 ms; the first breakaway exhausts the budget.
    assert 0.01 <= e.value.t_s < 0.05
    assert len(e.value.state) == 4 and all(math.isfinite(v) for v in e.value.state)
    assert spent < 30.0  # a generous bound on what used to run for ever
    # The budget is the option.
    small = dataclasses.replace(
        _chattering(), integrator=dataclasses.replace(SEED.integrator, max_events=50)
    )
    with pytest.raises(ns.SimulationError, match=r"^more than 50 stick/slip events"):
        ns.simulate_step(small, 1e-4, duration_s=0.05)


def test_the_budget_options_are_checked() -> None:
    with pytest.raises(ns.ConfigError, match=r"^max_events = 0 is invalid: expected an integer"):
        ns.IntegratorOptions(max_events=0)
    assert ns.IntegratorOptions().max_events == SEED.integrator.max_events == 10_000


def test_a_chattering_trial_gets_its_status_and_a_batch_raises_the_failure() -> None:
    cycle = cycles.step_cycle(
        step_m=100e-6, repeats=2, dwell_s=0.03, return_s=0.02, sample_period_s=1e-3
    )
    r = run_campaign(_chattering(), cycle, n_trials=2, seed=1, threads=1, progress=False)
    assert list(r.status) == [TrialStatus.TOO_MANY_EVENTS] * 2
    for f in r.failures:
        assert f.status == TrialStatus.TOO_MANY_EVENTS
        assert f.t_s > 0 and len(f.state) == 4
        assert "stick/slip events in one control interval" in f.message
    ref = ns.step_reference(1e-4, duration_s=0.05, sample_period_s=1e-3)
    with pytest.raises(ns.SimulationError, match="stick/slip events") as e:
        simulate_batch([SEED, _chattering()], [ref, ref])
    assert e.value.t_s > 0


# --------------------------------------------------------------------------------------
# Wrong types
# --------------------------------------------------------------------------------------


def test_a_wrong_type_is_a_config_error_naming_the_field_path_and_the_type() -> None:
    for bad, shown in [("abc", "'abc' (str)"), (None, "None (NoneType)"), (3.0, "3.0 (float)")]:
        with pytest.raises(ns.ConfigError) as e:
            dataclasses.replace(SEED.plant, motor=bad)
        assert str(e.value) == f"motor = {shown} is invalid: expected a Motor"
        assert isinstance(e.value, TypeError)  # as before: a TypeError too
        assert e.value.field == "motor"
    with pytest.raises(ns.ConfigError) as e:
        dataclasses.replace(SEED, plant="abc")
    assert str(e.value) == (
        "plant = 'abc' (str) is invalid: expected one of Plant, ForceDrivePlant"
    )
    with pytest.raises(TypeError, match=r"^motor\.resistance_ohm = 'x' \(str\) is invalid: "):
        _plant(motor={"resistance_ohm": "x"})
    with pytest.raises(ns.ConfigError, match=r"^max_steps = 'many' \(str\) is invalid: "):
        ns.IntegratorOptions(max_steps="many")  # type: ignore[arg-type]
    with pytest.raises(ns.ConfigError) as e:
        dataclasses.replace(SEED.controller, ticks_per_sample=-5)
    assert str(e.value) == (
        "ticks_per_sample = -5 (int) is invalid: expected an int "
        "(can't convert negative int to unsigned)"
    )
    with pytest.raises(ns.ConfigError) as e:
        dataclasses.replace(SEED, effects=Effects(table_friction="dahl"))  # type: ignore[arg-type]
    assert str(e.value) == (
        "effects.table_friction = 'dahl' (str) is invalid: "
        "expected one of StaticFrictionMap, LuGre, Gms, None"
    )


def test_a_wrong_type_past_the_constructors_is_named_at_the_core_call() -> None:
    # Objects changed after their checks (frozen dataclasses can be forced) reach the core.
    system = dataclasses.replace(SEED)
    plant = dataclasses.replace(SEED.plant)
    object.__setattr__(plant, "motor", "abc")
    object.__setattr__(system, "plant", plant)
    ref = np.zeros(3)
    with pytest.raises(ns.ConfigError) as e:
        ns.simulate(system, ref)
    assert str(e.value) == "plant.motor = 'abc' (str) is invalid: expected a Motor"
    with pytest.raises(ns.ConfigError, match=r"^systems\[1\]\.plant\.motor = 'abc' \(str\)"):
        simulate_batch([SEED, system], [ref, ref])
    with pytest.raises(ns.ConfigError) as e:
        ns.simulate("abc", ref)  # type: ignore[arg-type]
    assert str(e.value) == "system = 'abc' (str) is invalid: expected a System"
    with pytest.raises(ns.ConfigError, match=r"^plant = 3 \(int\) is invalid: expected a Plant"):
        ns.simulate_plant(3, [0.0], sample_period_s=1e-3)  # type: ignore[arg-type]


# --------------------------------------------------------------------------------------
# Ctrl-C reaches single runs and batches
# --------------------------------------------------------------------------------------


def _endless() -> ns.System:
    """The chattering law of :func:`_chattering` with budgets so large (1e9 steps and events
    per control interval) that a run of it does not end in any reasonable time."""
    s = _chattering()
    return dataclasses.replace(s, integrator=_ENDLESS)


_ENDLESS = dataclasses.replace(SEED.integrator, max_steps=10**9, max_events=10**9)


@contextmanager
def _default_sigint() -> Iterator[None]:
    """Python's default SIGINT handler for the duration (pytest may run as a background job
    with SIGINT ignored)."""
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


@contextmanager
def _timer_sigint(delay_s: float) -> Iterator[None]:
    """SIGINT to this process after ``delay_s`` (whatever handler is installed then)."""
    timer = threading.Timer(delay_s, os.kill, (os.getpid(), signal.SIGINT))
    try:
        timer.start()
        yield
    finally:
        timer.cancel()


@contextmanager
def _sigint_after(delay_s: float) -> Iterator[None]:
    """SIGINT to this process after ``delay_s``, with Python's default handler installed for
    the duration."""
    with _default_sigint(), _timer_sigint(delay_s):
        yield


def _stops_on_ctrl_c(call: Callable[[], object]) -> float:
    """Seconds from the start of ``call`` (which would not end) to the KeyboardInterrupt that
    SIGINT after 0.3 s raises in it."""
    start = time.monotonic()
    with _sigint_after(0.3), pytest.raises(KeyboardInterrupt):
        call()
    return time.monotonic() - start


def test_ctrl_c_stops_a_single_run_inside_a_control_interval() -> None:
    assert _stops_on_ctrl_c(lambda: ns.simulate_step(_endless(), 1e-4, duration_s=0.05)) < 10.0


def test_ctrl_c_stops_a_batch() -> None:
    ref = ns.step_reference(1e-4, duration_s=0.05, sample_period_s=1e-3)
    systems = [SEED, _endless(), _endless()]
    assert _stops_on_ctrl_c(lambda: simulate_batch(systems, [ref] * 3, threads=2)) < 10.0


def test_ctrl_c_stops_an_open_loop_run() -> None:
    plant = _chattering().plant
    u = np.full(50, 1.0)
    run = lambda: ns.simulate_plant(plant, u, sample_period_s=1e-3, integrator=_ENDLESS)  # noqa: E731
    assert _stops_on_ctrl_c(run) < 10.0


def test_ctrl_c_stops_the_runs_of_worker_threads_inside_stop_on_interrupt() -> None:
    start = time.monotonic()
    # The timer starts once the work is submitted: on a loaded machine a worker holding the
    # GIL could otherwise delay the main thread past 0.3 s before it waits for the result,
    # and the KeyboardInterrupt would be raised outside `pytest.raises`.
    with (
        _default_sigint(),
        stop_on_interrupt(),
        ThreadPoolExecutor(max_workers=2) as pool,
    ):
        futures = [
            pool.submit(ns.simulate_step, _endless(), 1e-4, duration_s=0.05) for _ in range(2)
        ]
        with _timer_sigint(0.3), pytest.raises(KeyboardInterrupt):
            for f in futures:
                f.result()
    assert time.monotonic() - start < 10.0
    for f in futures:
        e = f.exception()
        assert isinstance(e, ns.SimulationError) and str(e).startswith("interrupted at t = ")
    # Afterwards runs are not stopped.
    assert ns.simulate_step(SEED, 1e-4, duration_s=0.02).position_m.size == 20


def test_ctrl_c_stops_a_friction_response_in_a_worker_thread_inside_stop_on_interrupt() -> None:
    # 4 million samples of LuGre friction along a sine: seconds of work, stopped at 0.3 s.
    f = ns.effects.LuGre(
        stiffness_n_per_m=1e7,
        damping_n_s_per_m=300.0,
        viscous_n_s_per_m=10.0,
        coulomb_force_n=20.0,
        static_force_n=25.0,
        stribeck_velocity_m_per_s=1e-3,
    )
    t = np.arange(4_000_000) * 1e-4
    x = 1e-4 * np.sin(2 * np.pi * 5 * t)
    v = 1e-4 * 2 * np.pi * 5 * np.cos(2 * np.pi * 5 * t)
    with (
        _default_sigint(),
        stop_on_interrupt(),
        ThreadPoolExecutor(max_workers=1) as pool,
    ):
        future = pool.submit(friction_response, f, t, x, v)
        with _timer_sigint(0.3), pytest.raises(KeyboardInterrupt):
            future.result()
    e = future.exception()
    assert isinstance(e, ns.SimulationError) and str(e).startswith("interrupted at t = "), e


# --------------------------------------------------------------------------------------
# Property: anywhere in the validated ranges, a finite result or a named error
# --------------------------------------------------------------------------------------


def _between(lo: float, hi: float) -> st.SearchStrategy[float]:
    """Anywhere in [lo, hi] (log-uniform for a positive range), the ends included."""
    if lo > 0:
        inner = st.floats(math.log10(lo), math.log10(hi)).map(lambda e: min(max(10.0**e, lo), hi))
    else:
        inner = st.floats(lo, hi)
    return st.one_of(st.sampled_from([lo, hi]), inner)


def _near(nominal: float, lo: float, hi: float) -> st.SearchStrategy[float]:
    """The nominal value or anywhere in the range (most draws change a few fields only)."""
    return st.one_of(st.just(nominal), st.just(nominal), _between(lo, hi))


@st.composite
def _seed_plants(draw: st.DrawFn) -> Callable[[], ns.Plant]:
    p = SEED.plant
    m, f, g, s, t, d = p.motor, p.motor_friction, p.gearhead, p.screw, p.table, p.dahl
    tc = draw(st.one_of(st.just(f.coulomb_torque_nm), st.just(0.0), _between(1e-9, 10.0)))
    ts = min(tc + draw(_near(f.static_torque_nm - f.coulomb_torque_nm, 1e-9, 10.0)), 10.0)
    motor = ns.Motor(
        resistance_ohm=draw(_near(m.resistance_ohm, 1e-3, 1e3)),
        inductance_h=draw(_near(m.inductance_h, 1e-9, 1.0)),
        torque_constant_nm_per_a=draw(_near(m.torque_constant_nm_per_a, 1e-9, 10.0)),
        back_emf_v_s_per_rad=draw(_near(m.back_emf_v_s_per_rad, 1e-9, 10.0)),
        rotor_inertia_kg_m2=draw(_near(m.rotor_inertia_kg_m2, 1e-12, 1.0)),
        quasi_static_current=draw(st.booleans()),
    )
    friction = ns.StribeckFriction(
        static_torque_nm=ts,
        coulomb_torque_nm=tc,
        viscous_nm_s_per_rad=draw(_near(f.viscous_nm_s_per_rad, 0.0, 1.0)),
        stribeck_velocity_rad_per_s=draw(_near(f.stribeck_velocity_rad_per_s, 1e-3, 1e5)),
        stribeck_exponent=draw(_near(2.0, 0.5, 4.0)),
    )
    gearhead = ns.Gearhead(
        ratio=draw(_near(g.ratio, 1.0, 1e4)), efficiency=draw(_near(g.efficiency, 1e-3, 1.0))
    )
    screw = ns.BallScrew(
        lead_m=draw(_near(s.lead_m, 1e-5, 0.1)),
        efficiency=draw(_near(s.efficiency, 1e-3, 1.0)),
        inertia_kg_m2=draw(_near(s.inertia_kg_m2, 0.0, 1.0)),
    )
    table = ns.Table(
        mass_kg=draw(_near(t.mass_kg, 1e-6, 1e4)),
        external_force_n=draw(_near(t.external_force_n, -1e4, 1e4)),
    )
    dahl = ns.DahlFriction(
        coulomb_force_n=draw(_near(d.coulomb_force_n, 1e-6, 1e5)),
        stiffness_n_per_m=draw(_near(d.stiffness_n_per_m, 1e-3, 1e12)),
        exponent=draw(_near(1.0, 0.5, 4.0)),
    )
    return lambda: ns.Plant(
        motor=motor, motor_friction=friction, gearhead=gearhead, screw=screw, table=table, dahl=dahl
    )


@st.composite
def _static_maps(draw: st.DrawFn, fc0: float = 30.4) -> StaticFrictionMap:
    fc = draw(st.one_of(st.just(fc0), st.just(0.0), _between(1e-9, 1e5)))
    return StaticFrictionMap(
        static_force_n=min(fc + draw(_near(0.2 * fc0, 0.0, 1e5)), 1e5),
        coulomb_force_n=fc,
        viscous_n_s_per_m=draw(_near(0.0, 0.0, 1e7)),
        stribeck_velocity_m_per_s=draw(_near(1e-3, 1e-12, 10.0)),
        stribeck_exponent=draw(_near(2.0, 0.5, 4.0)),
        asymmetry=draw(_near(0.0, -0.9, 0.9)),
        viscous_asymmetry=draw(_near(0.0, -0.9, 0.9)),
        dwell=draw(
            st.none()
            | st.builds(
                DwellStaticFriction, rise_n=_between(0.0, 1e4), time_constant_s=_between(1e-6, 1e3)
            )
        ),
        memory_lag_s=draw(st.none() | _between(1e-6, 1.0)),
    )


@st.composite
def _table_frictions(draw: st.DrawFn) -> StaticFrictionMap | LuGre | Gms | None:
    kind = draw(st.sampled_from(["none", "static", "lugre", "gms"]))
    if kind == "none":
        return None
    if kind == "static":
        return draw(_static_maps())
    fc = draw(_near(30.4, 1e-6, 1e5))
    fs = min(fc + draw(_near(6.0, 0.0, 1e5)), 1e5)
    vs = draw(_near(1e-3, 1e-12, 10.0))
    fv = draw(_near(0.0, 0.0, 1e7))
    if kind == "lugre":
        return LuGre(
            stiffness_n_per_m=draw(_near(1e7, 1e-3, 1e12)),
            damping_n_s_per_m=draw(_near(0.0, 0.0, 1e7)),
            viscous_n_s_per_m=fv,
            coulomb_force_n=fc,
            static_force_n=fs,
            stribeck_velocity_m_per_s=vs,
        )
    n = draw(st.integers(1, 8))
    raw = [draw(st.floats(0.05, 1.0)) for _ in range(n)]
    weights = tuple(w / sum(raw) for w in raw)
    return Gms(
        stiffness_n_per_m=tuple(draw(_near(1e7, 1e-3, 1e12)) for _ in range(n)),
        weights=weights,
        coulomb_force_n=fc,
        static_force_n=fs,
        stribeck_velocity_m_per_s=vs,
        viscous_n_s_per_m=fv,
    )


@st.composite
def _effects(draw: st.DrawFn) -> Effects:
    return Effects(
        table_friction=draw(_table_frictions()),
        motor_friction=FrictionModifiers(
            asymmetry=draw(_near(0.0, -0.9, 0.9)),
            dwell=draw(
                st.none()
                | st.builds(
                    DwellStaticFriction,
                    rise_n=_between(0.0, 1e4),
                    time_constant_s=_between(1e-6, 1e3),
                )
            ),
            memory_lag_s=draw(st.none() | _between(1e-6, 1.0)),
        ),
        stochastic=draw(
            st.none()
            | st.builds(
                StochasticFriction,
                level_spread=_between(0.0, 0.5),
                within_spread=_between(0.0, 0.5),
                correlation_time_s=_between(1e-6, 1e3),
            )
        ),
        backlash=draw(
            st.none()
            | st.builds(
                Backlash,
                width_m=_between(0.0, 1e-2),
                contact_stiffness_n_per_m=_between(1e-3, 1e12),
                damping_n_s_per_m=_between(0.0, 1e8),
            )
        ),
        compliance=draw(
            st.none()
            | st.builds(
                DriveCompliance,
                stiffness_n_per_m=_between(1e-3, 1e12),
                damping_n_s_per_m=_between(0.0, 1e8),
                axial_stiffness_n_per_m=st.none() | _between(1e-3, 1e12),
                axial_damping_n_s_per_m=_between(0.0, 1e8),
            )
        ),
        amplifier=draw(
            st.none()
            | st.builds(
                AmplifierDynamics,
                bandwidth_hz=_between(1e-3, 1e7),
                slew_v_per_s=_between(1e-3, 1e12),
            )
        ),
    )


@st.composite
def _systems(draw: st.DrawFn) -> tuple[Callable[[], ns.System], float]:
    """A system to build (building may raise ConfigError) and a step size."""
    step = draw(st.sampled_from([1e-6, 1e-4, 1e-3]))
    effects = draw(_effects())
    if draw(st.integers(0, 4)) == 0:
        base = ns.presets.emps()
        assert isinstance(base.plant, ForceDrivePlant)
        plant = dataclasses.replace(
            base.plant,
            friction=draw(_static_maps(fc0=20.0)),
            mass_kg=draw(_near(base.plant.mass_kg, 1e-6, 1e4)),
            drive_mass_kg=draw(_near(0.0, 0.0, 1e4)),
        )
        effects = dataclasses.replace(effects, motor_friction=FrictionModifiers())

        def build_force() -> ns.System:
            return dataclasses.replace(base, plant=plant, effects=effects)

        return build_force, step
    make_plant = draw(_seed_plants())

    def build() -> ns.System:
        return dataclasses.replace(ns.presets.seed(step), plant=make_plant(), effects=effects)

    return build, step


class _RunTooLong(Exception):
    pass


@contextmanager
def _alarm(seconds: float) -> Iterator[None]:
    """Fail (do not hang) if the body takes longer than ``seconds``: SIGALRM's handler raises
    inside the run, which polls for signals."""

    def expire(signum: int, frame: object) -> None:
        raise _RunTooLong(f"a run took more than {seconds} s")

    previous = signal.signal(signal.SIGALRM, expire)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0.0)
        signal.signal(signal.SIGALRM, previous)


_FLOAT_CHANNELS = (
    "position_m",
    "velocity_m_per_s",
    "current_a",
    "motor_voltage_v",
    "command",
    "motor_friction_force_n",
    "table_friction_force_n",
    "motor_position_m",
)


@settings(deadline=None, suppress_health_check=[HealthCheck.too_slow, HealthCheck.filter_too_much])
@given(case=_systems())
def test_anywhere_in_the_ranges_a_run_is_finite_or_a_named_error(
    case: tuple[Callable[[], ns.System], float],
) -> None:
    build, step = case
    with _alarm(60.0):
        try:
            system = build()
            tr = ns.simulate_step(system, step, duration_s=0.012, start_s=0.002)
        except ns.ConfigError as e:
            event("ConfigError")
            assert " is invalid: expected " in str(e) and "\n" not in str(e)
            return
        except ns.SimulationError as e:
            event(f"SimulationError: {str(e).split(' at t = ')[0][:40]}")
            assert math.isfinite(e.t_s) and e.t_s >= 0.0
            assert " at t = " in str(e) and "\n" not in str(e)
            return
    event("finite result")
    for name in _FLOAT_CHANNELS:
        assert np.all(np.isfinite(getattr(tr, name))), name
