"""The shipped presets are model files (nanostage/model_files/*.model.toml) read by the model
file loader; their numbers are pinned here against hand-written values from SEED.md, DOMAIN.md
and the EMPS SOURCE.md (an independent reference, not the files themselves)."""

from __future__ import annotations

import dataclasses
import importlib.resources
import math

import pytest

import nanostage as ns
from nanostage import presets
from nanostage.config import (
    BallScrew,
    CascadeController,
    DahlFriction,
    Encoder,
    ForceDrivePlant,
    FpgaPid,
    Fxp,
    Gearhead,
    Motor,
    OutputStage,
    Plant,
    StribeckFriction,
    System,
    Table,
)
from nanostage.effects import Effects, StaticFrictionMap

#: SEED.md, Table 1: step size, m -> (Kp, Ki, Kd).
TABLE1 = {
    100e-6: (450.0, 2.0, 40.0),
    500e-6: (450.0, 2.0, 40.0),
    1e-3: (450.0, 5.0, 10.0),
    10e-3: (450.0, 5.0, 25.0),
}


def _fxp(word_bits: int, int_bits: int, overflow: str = "saturate", signed: bool = True) -> Fxp:
    return Fxp(
        signed=signed,
        word_bits=word_bits,
        int_bits=int_bits,
        rounding="half_even",
        overflow=overflow,  # type: ignore[arg-type]
    )


def _seed_by_hand(kp: float, ki: float, kd: float) -> System:
    """The seed axis written out: SEED.md (B) where it gives a value, DOMAIN.md §2–4 for the
    planning values (U/I/K)."""
    return System(
        plant=Plant(
            motor=Motor(
                resistance_ohm=3.4,
                inductance_h=70e-6,
                torque_constant_nm_per_a=6.6e-3,
                back_emf_v_s_per_rad=6.6e-3,
                rotor_inertia_kg_m2=1e-7,
                quasi_static_current=False,
            ),
            motor_friction=StribeckFriction(
                static_torque_nm=1.2 * 0.1e-3,
                coulomb_torque_nm=0.1e-3,
                viscous_nm_s_per_rad=2e-8,
                stribeck_velocity_rad_per_s=10.0,
                stribeck_exponent=2.0,
            ),
            gearhead=Gearhead(ratio=19.0, efficiency=0.8),  # SEED.md: 19:1
            screw=BallScrew(lead_m=2e-3, efficiency=0.9, inertia_kg_m2=1e-7),  # lead 2 mm
            table=Table(mass_kg=0.5, external_force_n=0.0),
            # SEED.md: Fc = 30.4 N, n = 1, σ = 75 N/µm
            dahl=DahlFriction(coulomb_force_n=30.4, stiffness_n_per_m=75e6, exponent=1.0),
        ),
        controller=FpgaPid(
            kp=kp,
            ki=ki,
            kd=kd,
            gain_format=_fxp(24, 16),
            measurement_format=_fxp(32, 32, "wrap"),
            error_format=_fxp(32, 32),
            term_format=_fxp(48, 40),
            integrator_format=_fxp(48, 40),
            output_format=_fxp(32, 24),
            dac_format=_fxp(16, 16),
            dac_scale_format=_fxp(16, 0, signed=False),
            output_min=-6.0 / 1e-4,  # ±6 V in units of 0.1 mV
            output_max=6.0 / 1e-4,
            anti_windup="conditional",
            output_unit_v=1e-4,
            dac_lsb_v=20.0 / 2**16,  # 16-bit ±10 V output
            clock_hz=40e6,
            ticks_per_sample=40_000,  # T = 1 ms at 40 MHz
            latency_ticks=130,
        ),
        encoder=Encoder(count_m=100e-9, side="table"),  # Heidenhain 100 nm on the table
        output_stage=OutputStage(amplifier_gain=1.0, amplifier_limit_v=6.0),  # U_N = 6 V
    )


@pytest.mark.parametrize("step_m", list(TABLE1))
def test_seed_at_every_table1_step_is_the_hand_written_axis(step_m: float) -> None:
    expected = _seed_by_hand(*TABLE1[step_m])
    assert repr(presets.seed(step_m)) == repr(expected)
    assert presets.table1_gains(step_m) == TABLE1[step_m]


def test_table1_rows_are_the_papers_and_the_nearest_row_is_taken() -> None:
    assert presets._table1_rows() == TABLE1
    # nearest row on a log scale: 223 µm is nearer 100 µm than 500 µm (√(1e-4·5e-4) ≈ 224 µm)
    assert presets.table1_gains(223e-6) == TABLE1[100e-6]
    assert presets.table1_gains(225e-6) == TABLE1[500e-6]
    assert presets.table1_gains(-3.2e-3) == TABLE1[10e-3]  # √(1e-3·1e-2) ≈ 3.16 mm
    assert presets.table1_gains(3.1e-3) == TABLE1[1e-3]
    with pytest.raises(ns.ConfigError, match=r"step_m = 0\.0 is invalid"):
        presets.table1_gains(0.0)


def _emps_by_hand(**plant: object) -> System:
    """The EMPS axis from data/emps/SOURCE.md (the authors' symmetric identification)."""
    base = ForceDrivePlant(
        drive_gain_n_per_v=35.1507,
        mass_kg=95.1089,
        friction=StaticFrictionMap(
            static_force_n=20.3935, coulomb_force_n=20.3935, viscous_n_s_per_m=203.5034
        ),
        external_force_n=-3.1648,
    )
    return System(
        plant=dataclasses.replace(base, **plant),  # type: ignore[arg-type]
        controller=CascadeController(
            kp_per_s=160.18, kv_v_s_per_m=243.45, sample_period_s=1e-3, saturation_v=10.0
        ),
        encoder=Encoder(count_m=5e-8, side="motor"),
        effects=Effects(computation_delay_samples=1),
    )


def test_emps_presets_are_the_authors_identification() -> None:
    assert repr(presets.preset_system("emps")) == repr(_emps_by_hand())
    naive = StaticFrictionMap(static_force_n=0.0, coulomb_force_n=0.0, viscous_n_s_per_m=203.5034)
    assert repr(presets.preset_system("emps_naive")) == repr(
        _emps_by_hand(friction=naive, external_force_n=0.0)
    )
    asym = presets.preset_system("emps_asymmetric")
    plant = asym.plant
    assert isinstance(plant, ForceDrivePlant)
    assert plant.mass_kg == 95.1540 and plant.external_force_n == 0.0
    f = plant.friction
    # SOURCE.md: Fc+ = 20.1440 N, Fc− = 20.6277 N, Fv+ = 166.7061, Fv− = 240.4236 N·s/m
    assert math.isclose(f.coulomb_force_n * (1 + f.asymmetry), 20.1440, rel_tol=1e-14)
    assert math.isclose(f.coulomb_force_n * (1 - f.asymmetry), 20.6277, rel_tol=1e-14)
    assert math.isclose(f.viscous_n_s_per_m * (1 + f.viscous_asymmetry), 166.7061, rel_tol=1e-14)
    assert math.isclose(f.viscous_n_s_per_m * (1 - f.viscous_asymmetry), 240.4236, rel_tol=1e-14)
    assert f.static_force_n == f.coulomb_force_n
    assert dataclasses.replace(asym, plant=_emps_by_hand().plant) == _emps_by_hand()


@pytest.mark.parametrize("name", ["seed", "emps"])
def test_the_shipped_file_is_a_model_file_in_the_package(name: str) -> None:
    resource = importlib.resources.files("nanostage") / "model_files" / f"{name}.model.toml"
    with importlib.resources.as_file(resource) as path:
        doc = ns.load_model_file(path)
    assert doc.system == presets._document(name).system
    assert doc.provenance["source"]


def test_the_files_are_parsed_once() -> None:
    presets.seed()
    before = presets._document.cache_info()
    for step in TABLE1:
        presets.seed(step)
        presets.preset_system("emps_asymmetric")
    after = presets._document.cache_info()
    assert after.misses == before.misses and after.hits > before.hits


def test_a_bad_table1_row_in_the_seed_file_names_the_key(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    doc = presets._document("seed")
    rows = [dict(r) for r in doc.provenance["table1_gains"]]
    rows[2]["step_m"] = -1e-3
    bad = dataclasses.replace(doc, provenance={**doc.provenance, "table1_gains": rows})
    monkeypatch.setattr(presets, "_document", lambda name: bad)
    presets._table1_rows.cache_clear()
    try:
        with pytest.raises(
            ns.ModelFileError,
            match=r"seed\.model\.toml: provenance\.table1_gains\[2\]\.step_m = -0\.001 is "
            r"invalid: expected > 0 m",
        ):
            presets.table1_gains(1e-3)
    finally:
        presets._table1_rows.cache_clear()
