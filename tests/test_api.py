"""Contracts of the Python API: shapes, dtypes, errors, determinism, the README example."""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

import nanostage as ns

README = Path(__file__).resolve().parents[1] / "README.md"


def test_trace_channels_have_one_entry_per_sample() -> None:
    tr = ns.simulate_step(ns.presets.seed(100e-6), 100e-6, duration_s=0.2)
    n = 200
    for name in ns.Trace.__dataclass_fields__:
        v = getattr(tr, name)
        if isinstance(v, np.ndarray):
            assert v.shape == (n,), name
            assert v.flags.c_contiguous, name
    assert tr.position_m.dtype == np.float64
    assert tr.encoder_counts.dtype == np.int64
    assert tr.stuck.dtype == np.bool_
    assert np.allclose(tr.time_s, np.arange(n) * 1e-3, rtol=0, atol=1e-15)


def test_configs_are_frozen_and_keyword_only() -> None:
    s = ns.presets.seed()
    with pytest.raises(dataclasses.FrozenInstanceError):
        s.plant.table.mass_kg = 2.0  # type: ignore[misc]
    with pytest.raises(TypeError):
        ns.Table(1.0)  # type: ignore[misc]
    with pytest.raises(TypeError):
        ns.Table(mass_kg=1.0, masss_kg=2.0)  # type: ignore[call-arg]


@pytest.mark.parametrize(
    ("path", "value", "field"),
    [
        (("table", "mass_kg"), 0.0, "table.mass_kg"),
        (("table", "mass_kg"), -1.0, "table.mass_kg"),
        (("screw", "lead_m"), float("nan"), "screw.lead_m"),
        (("motor", "resistance_ohm"), float("inf"), "motor.resistance_ohm"),
        (("motor", "rotor_inertia_kg_m2"), -1e-7, "motor.rotor_inertia_kg_m2"),
        (("dahl", "stiffness_n_per_m"), 0.0, "dahl.stiffness_n_per_m"),
    ],
)
def test_non_physical_plant_values_name_field_value_and_range(
    path: tuple[str, str], value: float, field: str
) -> None:
    p = ns.presets.seed_plant()
    block = dataclasses.replace(getattr(p, path[0]), **{path[1]: value})
    with pytest.raises(ns.ConfigError) as e:
        dataclasses.replace(p, **{path[0]: block})
    msg = str(e.value)
    assert msg.startswith(f"{field} = ")
    assert re.search(r"expected a finite number in [(\[].*[\])]$", msg), msg
    assert e.value.field == field


def test_bad_controller_timing_and_integrator_values() -> None:
    c = ns.presets.seed_controller()
    with pytest.raises(ns.ConfigError, match=r"^clock_hz = 0"):
        dataclasses.replace(c, clock_hz=0.0)
    with pytest.raises(ns.ConfigError, match=r"^latency_ticks = 40000"):
        dataclasses.replace(c, latency_ticks=40_000)
    with pytest.raises(ns.ConfigError, match=r"^rtol = 0"):
        ns.IntegratorOptions(rtol=0.0)
    with pytest.raises(ns.ConfigError, match=r"^anti_windup = \"sometimes\""):
        dataclasses.replace(c, anti_windup="sometimes")  # type: ignore[arg-type]


def test_bad_reference_and_durations() -> None:
    s = ns.presets.seed()
    with pytest.raises(ns.ConfigError, match=r"^duration_s = -1"):
        ns.simulate_step(s, 1e-3, duration_s=-1.0)
    with pytest.raises(ns.ConfigError, match=r"^sample_period_s = 0"):
        ns.step_reference(1e-3, duration_s=1.0, sample_period_s=0.0)
    with pytest.raises(
        ns.ConfigError,
        match=r"^duration_s = 1000000000000.0 is invalid: expected between 1 and \d+ samples",
    ):
        ns.simulate_step(s, 1e-3, duration_s=1e12)
    with pytest.raises(ns.ConfigError, match=r"reference_m\[3\] = NaN"):
        ns.simulate(s, np.array([0.0, 0.0, 0.0, np.nan]))
    with pytest.raises(ns.ConfigError, match="1-D"):
        ns.simulate(s, np.zeros((2, 2)))


def test_numerical_failure_is_a_simulation_error_with_time_and_state() -> None:
    # Far too few steps allowed per control interval: the integrator must give up cleanly.
    s = dataclasses.replace(ns.presets.seed(), integrator=ns.IntegratorOptions(max_steps=10))
    with pytest.raises(ns.SimulationError) as e:
        ns.simulate_step(s, 1e-3, duration_s=0.3)
    assert e.value.t_s > 0.0
    assert len(e.value.state) == 4


@given(step_um=st.integers(5, 2000))
def test_same_input_gives_bit_identical_runs(step_um: int) -> None:
    s = ns.presets.seed(step_um * 1e-6)
    a = ns.simulate_step(s, step_um * 1e-6, duration_s=0.05)
    b = ns.simulate_step(s, step_um * 1e-6, duration_s=0.05)
    assert a.position_m.tobytes() == b.position_m.tobytes()
    assert a.dac_code.tobytes() == b.dac_code.tobytes()


def test_stuck_means_zero_velocity() -> None:
    tr = ns.simulate_step(ns.presets.seed(100e-6), 100e-6, duration_s=0.5)
    assert np.all(tr.velocity_m_per_s[tr.stuck] == 0.0)
    assert tr.stuck.any()


def test_preset_provenance_covers_every_seed_value() -> None:
    s = ns.presets.seed()
    paths = []
    for block in ("motor", "motor_friction", "gearhead", "screw", "table", "dahl"):
        for f in getattr(s.plant, block).__dataclass_fields__:
            paths.append(f"plant.{block}.{f}")
    paths += [f"encoder.{f}" for f in s.encoder.__dataclass_fields__]
    paths += [f"output_stage.{f}" for f in s.output_stage.__dataclass_fields__]
    for f in s.controller.__dataclass_fields__:
        paths.append("controller.formats" if f.endswith("_format") else f"controller.{f}")
    missing = [p for p in paths if p not in ns.presets.SEED_PROVENANCE]
    assert not missing
    assert ns.presets.SEED_PROVENANCE["plant.dahl.stiffness_n_per_m"].confidence == "I"
    assert s.plant.dahl.stiffness_n_per_m == 75e6


def test_readme_example_runs() -> None:
    text = README.read_text(encoding="utf-8")
    blocks = re.findall(r"```python\n(.*?)```", text, flags=re.S)
    assert blocks, "README has no python example"
    for code in blocks:
        exec(compile(code, str(README), "exec"), {})


@pytest.mark.parametrize("threads", [0, 1, 2])
def test_batch_runs_equal_single_runs_bit_for_bit(threads: int) -> None:
    """`simulate_batch` (one parallel core call) gives each run's trace of `simulate`, bit for
    bit and in order, whatever the thread count: rigid and component plants, a known force,
    seeds and start positions of their own."""
    from nanostage.effects import Backlash, Effects, StochasticFriction
    from nanostage.simulate import simulate, simulate_batch

    rigid = ns.presets.seed(1e-4)
    comp = dataclasses.replace(rigid, effects=Effects(backlash=Backlash(width_m=10e-6)))
    noisy = dataclasses.replace(
        rigid, effects=Effects(stochastic=StochasticFriction(level_spread=0.05))
    )
    ref = ns.step_reference(1e-4, duration_s=0.1, sample_period_s=1e-3)
    force = np.where(np.arange(ref.size) > 50, 2.0, 0.0)
    runs = [
        (rigid, ref, None, 0, None),
        (comp, -ref, None, 0, 3e-6),
        (noisy, ref, force, 7, None),
        (noisy, 2 * ref, None, 8, 1e-6),
    ]
    batch = simulate_batch(
        [r[0] for r in runs],
        [r[1] for r in runs],
        force_disturbances_n=[r[2] for r in runs],
        seeds=[r[3] for r in runs],
        initial_positions_m=[r[4] for r in runs],
        threads=threads,
    )
    for (s, r, f, seed, x0), b in zip(runs, batch, strict=True):
        a = simulate(s, r, force_disturbance_n=f, seed=seed, initial_position_m=x0)
        for ch in ("position_m", "motor_position_m", "encoder_counts", "dac_code", "command"):
            assert getattr(a, ch).tobytes() == getattr(b, ch).tobytes(), ch
        assert (a.output_unit_v, a.count_m) == (b.output_unit_v, b.count_m)


def test_batch_checks_its_inputs_and_raises_a_failed_runs_error() -> None:
    from nanostage.simulate import simulate_batch

    s = ns.presets.seed(1e-4)
    ref = ns.step_reference(1e-4, duration_s=0.05, sample_period_s=1e-3)
    with pytest.raises(ValueError, match=r"seeds has 1 entries; expected one per system \(2\)"):
        simulate_batch([s, s], [ref, ref], seeds=[1])
    slow = dataclasses.replace(s, integrator=ns.IntegratorOptions(max_steps=10))
    with pytest.raises(ns.SimulationError) as e:
        simulate_batch([s, slow], [ref, ref])
    assert e.value.t_s > 0.0
