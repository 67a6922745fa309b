"""The Rust integrator against the independent scipy model (tests/scipy_reference.py,
``solve_ivp`` Radau at rtol 1e-10) on the same plant and voltage sequence."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

import nanostage as ns

from scipy_reference import simulate_plant_scipy

TIGHT = ns.IntegratorOptions(rtol=1e-10, atol_position_m=1e-14)


def plant(quasi: bool) -> ns.Plant:
    p = ns.presets.seed_plant()
    return dataclasses.replace(p, motor=dataclasses.replace(p.motor, quasi_static_current=quasi))


def voltages(seed: int) -> np.ndarray:
    # Held levels that stick, creep in presliding, slide and reverse.
    rng = np.random.default_rng(seed)
    return np.repeat(rng.uniform(-2.5, 2.5, 25), 8)


@pytest.mark.parametrize("quasi", [False, True])
@pytest.mark.parametrize("seed", [1, 2])
def test_trajectories_agree_with_scipy_radau(quasi: bool, seed: int) -> None:
    p = plant(quasi)
    u = voltages(seed)
    ref = simulate_plant_scipy(dataclasses.asdict(p), u, 1e-3)
    # Stated tolerance: 1e-12 m in position (the motion spans ~100 µm), 1e-5 N in the Dahl
    # force, identical stick/slip pattern at every sample.
    for opts, tol_x, tol_z in [(TIGHT, 1e-12, 1e-5), (ns.IntegratorOptions(), 2e-10, 1e-2)]:
        tr = ns.simulate_plant(p, u, sample_period_s=1e-3, integrator=opts)
        assert np.max(np.abs(tr.position_m - ref["position_m"])) < tol_x
        assert np.max(np.abs(tr.dahl_force_n - ref["dahl_force_n"])) < tol_z
        assert np.array_equal(tr.stuck, ref["stuck"])
    assert np.ptp(ref["position_m"]) > 1e-5  # the run really moves
    assert ref["stuck"].any() and not ref["stuck"].all()


def test_default_tolerance_is_below_a_nanometre_in_closed_loop() -> None:
    s = ns.presets.seed(1e-3)
    tight = dataclasses.replace(s, integrator=TIGHT)
    a = ns.simulate_step(s, 1e-3, duration_s=0.4)
    b = ns.simulate_step(tight, 1e-3, duration_s=0.4)
    assert np.max(np.abs(a.position_m - b.position_m)) < 1e-9
