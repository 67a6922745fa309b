"""Direction asymmetry of the table friction laws (Dahl, LuGre, GMS): the seed axis with an
asymmetric Dahl law against the force balance of steady sliding, the friction responses'
steady levels, the model file and the checks of the parameter."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

import nanostage
from nanostage import presets
from nanostage.config import DahlFriction, System
from nanostage.diagnosis.candidates import applicable_candidates
from nanostage.effects import Effects, Gms, LuGre
from nanostage.friction import friction_response
from nanostage.model_file import model_to_toml, parse_model

SPEED_M_PER_S = 2e-3
RAMP_S = 0.4


def _lugre(**changes: float) -> LuGre:
    """A LuGre table law of the seed's Coulomb level (30.4 N), with ``changes``."""
    base = LuGre(
        stiffness_n_per_m=1e7,
        damping_n_s_per_m=0.0,
        viscous_n_s_per_m=0.0,
        coulomb_force_n=30.4,
        static_force_n=40.0,
        stribeck_velocity_m_per_s=5e-4,
    )
    return dataclasses.replace(base, **changes)


def _with_dahl_asymmetry(system: System, a: float) -> System:
    plant = system.plant
    assert isinstance(plant, nanostage.Plant)
    dahl = dataclasses.replace(plant.dahl, asymmetry=a)
    return dataclasses.replace(system, plant=dataclasses.replace(plant, dahl=dahl))


def _up_down_reference(system: System) -> tuple[np.ndarray, np.ndarray]:
    """A ramp at +2 mm/s for 0.4 s, a 0.1 s hold, a ramp back at −2 mm/s for 0.4 s."""
    t = np.arange(0.0, 2 * RAMP_S + 0.15, system.controller.sample_period_s)
    up = np.clip(t - 0.02, 0.0, RAMP_S) * SPEED_M_PER_S
    down = np.clip(t - (RAMP_S + 0.12), 0.0, RAMP_S) * SPEED_M_PER_S
    return t, up - down


def _steady_voltages(system: System) -> tuple[float, float, float, float]:
    """Mean motor voltage and table friction force over the last 0.15 s of each ramp."""
    t, ref = _up_down_reference(system)
    tr = nanostage.simulate(system, ref)
    up = (t > 0.02 + RAMP_S - 0.15) & (t < 0.02 + RAMP_S)
    down = (t > RAMP_S + 0.12 + RAMP_S - 0.15) & (t < RAMP_S + 0.12 + RAMP_S)
    assert np.all(tr.velocity_m_per_s[up] > 0) and np.all(tr.velocity_m_per_s[down] < 0)
    return (
        float(np.mean(tr.motor_voltage_v[up])),
        float(np.mean(tr.motor_voltage_v[down])),
        float(np.mean(tr.table_friction_force_n[up])),
        float(np.mean(tr.table_friction_force_n[down])),
    )


def _force_balance_voltage(system: System, direction: float, a: float) -> float:
    """The motor voltage that holds steady sliding at ±2 mm/s, from the plant's parameters:
    at the motor ``k_t·i = T_c + b·ω + r·F_table/η`` (the plant reflects the motor map and
    the drive force through ``r`` and ``η``), ``u = R·i + k_e·ω``, ``F_table = Fc·(1 ± a)``.
    The Stribeck term of the motor map is 0 at 12 Stribeck velocities."""
    p = system.plant
    assert isinstance(p, nanostage.Plant)
    r = p.screw.lead_m / (2 * math.pi * p.gearhead.ratio)
    eta = p.gearhead.efficiency * p.screw.efficiency
    omega = direction * SPEED_M_PER_S / r
    assert abs(omega) > 10 * p.motor_friction.stribeck_velocity_rad_per_s
    f_table = direction * p.dahl.coulomb_force_n * (1 + a * direction)
    torque = (
        direction * p.motor_friction.coulomb_torque_nm
        + p.motor_friction.viscous_nm_s_per_rad * omega
        + r * (f_table + p.table.external_force_n) / eta
    )
    current = torque / p.motor.torque_constant_nm_per_a
    return p.motor.resistance_ohm * current + p.motor.back_emf_v_s_per_rad * omega


def test_steady_sliding_voltage_follows_the_asymmetric_table_level() -> None:
    seed = presets.seed()
    a = 0.3
    fc = seed.plant.dahl.coulomb_force_n  # type: ignore[union-attr]
    u_up, u_down, f_up, f_down = _steady_voltages(_with_dahl_asymmetry(seed, a))
    # The table law saturates at its asymmetric levels (0.8 mm of sliding, 0.4 µm of
    # presliding).
    assert f_up == pytest.approx(fc * (1 + a), rel=1e-6)
    assert f_down == pytest.approx(-fc * (1 - a), rel=1e-6)
    # The loop's steady command is the force balance's, in each direction.
    assert u_up == pytest.approx(_force_balance_voltage(seed, 1.0, a), rel=0.005)
    assert u_down == pytest.approx(_force_balance_voltage(seed, -1.0, a), rel=0.005)
    # The difference between the directions is R·r·2a·Fc/(η·k_t) (0.22 V): the motor map
    # and the back EMF cancel in it.
    delta = u_up + u_down
    expected = _force_balance_voltage(seed, 1.0, a) + _force_balance_voltage(seed, -1.0, a)
    assert expected > 0.2
    assert delta == pytest.approx(expected, rel=0.02)
    # The symmetric law: no difference.
    u_up0, u_down0, f_up0, f_down0 = _steady_voltages(seed)
    assert f_up0 == pytest.approx(-f_down0, rel=1e-9)
    assert abs(u_up0 + u_down0) < 0.05 * expected
    # And the opposite asymmetry reverses it.
    u_up_n, u_down_n, _, _ = _steady_voltages(_with_dahl_asymmetry(seed, -a))
    assert u_up_n + u_down_n == pytest.approx(-expected, rel=0.02)


@pytest.mark.parametrize("law", ["dahl", "lugre", "gms"])
def test_friction_response_slides_at_the_asymmetric_levels(law: str) -> None:
    fc, a, v = 30.4, -0.45, 0.05
    friction: DahlFriction | LuGre | Gms
    if law == "dahl":
        friction = DahlFriction(coulomb_force_n=fc, stiffness_n_per_m=7.5e7, asymmetry=a)
    elif law == "lugre":
        friction = _lugre(coulomb_force_n=fc, static_force_n=1.3 * fc, asymmetry=a)
    else:
        friction = Gms(
            stiffness_n_per_m=(3e7, 1e7, 3e6),
            weights=(0.3, 0.3, 0.4),
            coulomb_force_n=fc,
            static_force_n=1.2 * fc,
            stribeck_velocity_m_per_s=1e-3,
            asymmetry=a,
        )
    t = np.linspace(0.0, 0.04, 401)
    for d in (1.0, -1.0):
        f = friction_response(friction, t, d * v * t, np.full_like(t, d * v))
        # The GMS yield approaches the slip force as a power of the displacement.
        tol = 1e-4 if law == "gms" else 1e-8
        assert f[-1] == pytest.approx(d * fc * (1 + a * d), rel=tol)


def test_model_file_round_trips_an_asymmetry_and_omits_zero() -> None:
    seed = presets.seed()
    text0 = model_to_toml(seed)
    assert "asymmetry" not in text0.split("[plant.dahl]")[1].split("[controller]")[0]
    asym = _with_dahl_asymmetry(seed, 0.25)
    text = model_to_toml(asym)
    assert "asymmetry = 0.25" in text.split("[plant.dahl]")[1].split("[controller]")[0]
    assert parse_model(text).system == asym
    lugre = _lugre()
    gms = Gms(
        stiffness_n_per_m=(3e7, 1e7),
        weights=(0.5, 0.5),
        coulomb_force_n=30.4,
        static_force_n=35.0,
        stribeck_velocity_m_per_s=1e-3,
    )
    for law in (lugre, gms):
        sym = dataclasses.replace(seed, effects=Effects(table_friction=law))
        assert "asymmetry" not in model_to_toml(sym)
        s = dataclasses.replace(
            seed, effects=Effects(table_friction=dataclasses.replace(law, asymmetry=-0.4))
        )
        text = model_to_toml(s)
        assert "asymmetry = -0.4" in text
        assert parse_model(text).system == s


def test_asymmetry_out_of_range_is_named() -> None:
    seed = presets.seed()
    with pytest.raises(nanostage.ConfigError, match=r"dahl\.asymmetry = 0\.95 is invalid"):
        _with_dahl_asymmetry(seed, 0.95)
    lugre = _lugre(asymmetry=-1.0)
    with pytest.raises(nanostage.ConfigError, match=r"table_friction\.asymmetry = -1 is invalid"):
        dataclasses.replace(seed, effects=Effects(table_friction=lugre))
    # The rigid plant alone has no asymmetry: it refuses one rather than ignore it.
    plant = _with_dahl_asymmetry(seed, 0.2).plant
    assert isinstance(plant, nanostage.Plant)
    with pytest.raises(nanostage.ConfigError, match=r"plant\.dahl\.asymmetry = 0\.2"):
        nanostage.simulate_plant(plant, np.zeros(5), sample_period_s=1e-3)


def test_asymmetric_friction_candidate_sets_motor_and_table_levels() -> None:
    seed = presets.seed()
    cands, _ = applicable_candidates(seed, ["asymmetric_friction"])
    (cand,) = cands
    assert [p.name for p in cand.params] == ["asymmetry", "table_asymmetry"]
    s = cand.apply(seed, [0.1, -0.25])
    assert s.effects.motor_friction.asymmetry == 0.1
    assert s.plant.dahl.asymmetry == -0.25  # type: ignore[union-attr]
    s = cand.apply(seed, [0.2, 0.2])
    # A truth with the same asymmetry on both sides is the candidate at that value.
    truth = dataclasses.replace(
        _with_dahl_asymmetry(seed, 0.2),
        effects=dataclasses.replace(
            seed.effects,
            motor_friction=dataclasses.replace(seed.effects.motor_friction, asymmetry=0.2),
        ),
    )
    assert s == truth
    # A LuGre table friction in the effects takes it instead of the (unused) Dahl.
    lugre = _lugre()
    s = cand.apply(dataclasses.replace(seed, effects=Effects(table_friction=lugre)), [-0.3, -0.3])
    assert isinstance(s.effects.table_friction, LuGre)
    assert s.effects.table_friction.asymmetry == -0.3
    assert s.effects.motor_friction.asymmetry == -0.3
    assert s.plant.dahl.asymmetry == 0.0  # type: ignore[union-attr]
    # The force drive keeps its two-parameter static-map candidate.
    emps = presets.emps()
    (cand_e,), _ = applicable_candidates(emps, ["asymmetric_friction"])
    assert [p.name for p in cand_e.params] == ["asymmetry", "viscous_asymmetry"]
    e = cand_e.apply(emps, [0.1, -0.2])
    assert (e.plant.friction.asymmetry, e.plant.friction.viscous_asymmetry) == (0.1, -0.2)  # type: ignore[union-attr]
