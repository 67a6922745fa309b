"""The model file: bit-identical round trips, the errors, the CLI export."""

from __future__ import annotations

import dataclasses
import math
import re
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import nanostage as ns
from nanostage import presets
from nanostage.cli import main
from nanostage.effects import (
    AmplifierDynamics,
    Backlash,
    DriveCompliance,
    DwellStaticFriction,
    Effects,
    EncoderErrors,
    FrictionModifiers,
    Gms,
    Interferometer,
    LuGre,
    StaticFrictionMap,
    StochasticFriction,
    lead_periodic_friction,
    position_random_friction,
)
from nanostage.model_file import (
    IdentifiedParameter,
    ModelFileError,
    model_to_toml,
    parse_model,
)


def _bits(obj: Any) -> Any:
    """The tree with every float as its bits (``-0.0`` differs from ``0.0``)."""
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return (
            type(obj).__name__,
            {f.name: _bits(getattr(obj, f.name)) for f in dataclasses.fields(obj)},
        )
    if isinstance(obj, tuple):
        return tuple(_bits(v) for v in obj)
    if isinstance(obj, float):
        return ("float", obj.hex())
    return (type(obj).__name__, obj)


def _round_trip(system: ns.System, tmp_path: Path) -> ns.System:
    path = tmp_path / "m.model.toml"
    ns.save_model(system, path)
    back = ns.load_model(path)
    assert back == system
    assert _bits(back) == _bits(system)
    return back


@pytest.mark.parametrize("name", presets.preset_names())
def test_every_preset_round_trips_bit_for_bit(name: str, tmp_path: Path) -> None:
    _round_trip(presets.preset_system(name), tmp_path)


def _seed_with(effects: Effects) -> ns.System:
    return dataclasses.replace(presets.seed(), effects=effects)


EFFECT_SETS = {
    "static_map": Effects(
        table_friction=StaticFrictionMap(
            static_force_n=35.0,
            coulomb_force_n=30.4,
            viscous_n_s_per_m=12.5,
            asymmetry=-0.0,
            dwell=DwellStaticFriction(rise_n=2.0, time_constant_s=0.3),
            memory_lag_s=2e-3,
        ),
        motor_friction=FrictionModifiers(asymmetry=0.05, memory_lag_s=1e-3),
        stochastic=StochasticFriction(level_spread=0.2, within_spread=0.01),
        sensor_delay_samples=1,
    ),
    "lugre_and_drive_train": Effects(
        table_friction=LuGre(
            stiffness_n_per_m=7.5e7,
            damping_n_s_per_m=1e3,
            viscous_n_s_per_m=10.0,
            coulomb_force_n=30.4,
            static_force_n=35.0,
            stribeck_velocity_m_per_s=1e-3,
        ),
        backlash=Backlash(width_m=5e-6),
        compliance=DriveCompliance(axial_stiffness_n_per_m=2e8),
        amplifier=AmplifierDynamics(),
        jitter_s=1e-6,
    ),
    "gms_and_sensors": Effects(
        table_friction=Gms(
            stiffness_n_per_m=(5e7, 2.5e7, 1e7),
            weights=(0.5, 0.3, 0.2),
            coulomb_force_n=30.4,
            static_force_n=33.0,
            stribeck_velocity_m_per_s=2e-3,
        ),
        position_friction=(
            lead_periodic_friction(lead_m=2e-3, amplitudes=(0.05, 0.01), phases_rad=(0.1, -0.0)),
            position_random_friction(rms=0.03, seed=3),
        ),
        encoder_errors=EncoderErrors(cyclic_amplitude_m=5e-9, noise_std_m=1e-9),
        interferometer=Interferometer(noise_std_m=2e-10),
        computation_delay_samples=2,
    ),
}


@pytest.mark.parametrize("name", list(EFFECT_SETS))
def test_systems_with_effects_round_trip_bit_for_bit(name: str, tmp_path: Path) -> None:
    _round_trip(_seed_with(EFFECT_SETS[name]), tmp_path)


def test_only_the_effects_switched_on_are_written() -> None:
    text = model_to_toml(_seed_with(EFFECT_SETS["lugre_and_drive_train"]))
    assert '[effects.table_friction]\nkind = "lugre"' in text
    assert "[effects.backlash]" in text and "jitter_s = 1e-06" in text
    assert "stochastic" not in text and "interferometer" not in text
    assert "sensor_delay_samples" not in text


@settings(max_examples=25, deadline=None)
@given(
    mass=st.floats(1e-6, 1e4),
    lead=st.floats(1e-5, 0.1),
    external=st.floats(-1e3, 1e3),
    kp=st.floats(-1e4, 1e4),
    spread=st.floats(0.0, 0.3),
)
def test_round_trip_property(
    mass: float, lead: float, external: float, kp: float, spread: float
) -> None:
    s = presets.seed()
    plant = dataclasses.replace(
        s.plant,
        table=dataclasses.replace(s.plant.table, mass_kg=mass, external_force_n=external),
        screw=dataclasses.replace(s.plant.screw, lead_m=lead),
    )
    s = dataclasses.replace(
        s,
        plant=plant,
        controller=dataclasses.replace(s.controller, kp=kp),
        effects=Effects(stochastic=StochasticFriction(level_spread=spread)),
    )
    back = parse_model(model_to_toml(s)).system
    assert _bits(back) == _bits(s)


@pytest.mark.parametrize("value", [-0.0, 1.2345678901234567e-300, -3.0517578125e-05, 0.1 + 0.2])
def test_extreme_floats_read_back_exactly(value: float) -> None:
    s = presets.seed()
    table = dataclasses.replace(s.plant.table, external_force_n=-0.0)
    s = dataclasses.replace(
        s,
        plant=dataclasses.replace(s.plant, table=table),
        controller=dataclasses.replace(s.controller, kd=value),
    )
    back = parse_model(model_to_toml(s)).system
    assert _bits(back) == _bits(s)
    assert math.copysign(1.0, back.controller.kd) == math.copysign(1.0, value)
    assert math.copysign(1.0, back.plant.table.external_force_n) == -1.0


def test_numbers_beyond_the_ranges_read_back_exactly_in_provenance(tmp_path: Path) -> None:
    prov = {"big": 9.87654321e300, "tiny": 5e-324, "max": 1.7976931348623157e308, "neg": -0.0}
    path = tmp_path / "m.toml"
    ns.save_model(presets.seed(), path, provenance=prov)
    back = ns.load_model_file(path).provenance
    assert {k: v.hex() for k, v in back.items()} == {k: v.hex() for k, v in prov.items()}


def test_the_exported_seed_simulates_as_the_preset(tmp_path: Path) -> None:
    path = tmp_path / "seed.model.toml"
    assert main(["model", "export", "seed", "--out", str(path)]) == 0
    a = ns.simulate_step(presets.seed(), 1e-3, duration_s=0.05)
    b = ns.simulate_step(ns.load_model(path), 1e-3, duration_s=0.05)
    for name in ("position_m", "encoder_counts", "dac_code", "current_a"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))


def test_provenance_and_identified_entries_read_back(tmp_path: Path) -> None:
    path = tmp_path / "model.toml"
    prov = {"data": "runs/a.csv", "command": "nanostage diagnose m.toml", "rms_nm": 12.5}
    ident = {
        "plant.table.mass_kg": IdentifiedParameter(std_error=0.01, lower=0.1, upper=2.0),
        "plant.dahl.coulomb_force_n": {"std_error": 0.5},
    }
    ns.save_model(presets.seed(), path, provenance=prov, identified=ident)
    doc = ns.load_model_file(path)
    assert doc.system == presets.seed()
    assert doc.provenance == prov
    assert doc.identified["plant.table.mass_kg"] == ident["plant.table.mass_kg"]
    assert doc.identified["plant.dahl.coulomb_force_n"] == IdentifiedParameter(std_error=0.5)
    assert ns.load_model(path) == presets.seed()


SEED_TEXT = model_to_toml(presets.seed())
_MOTOR = re.search(r"\[plant\.motor\]\n(?:[^\[].*\n)*\n", SEED_TEXT)
assert _MOTOR is not None

BAD = {
    "unknown key": (
        SEED_TEXT.replace("mass_kg = 0.5", "mas_kg = 0.5"),
        "m.toml: unknown key plant.table.mas_kg (did you mean 'mass_kg'?)",
    ),
    "unknown top-level table": (
        SEED_TEXT.replace("[encoder]", "[encodr]"),
        "m.toml: unknown key encodr (did you mean 'encoder'?)",
    ),
    "missing key": (
        SEED_TEXT.replace("ratio = 19.0\n", ""),
        "m.toml: missing required key plant.gearhead.ratio (a number)",
    ),
    "missing section": (
        SEED_TEXT.replace(_MOTOR.group(0), ""),
        "m.toml: missing required table [plant.motor]",
    ),
    "missing controller": (
        SEED_TEXT.split("[controller]")[0],
        "m.toml: missing required table [controller]",
    ),
    "wrong type": (
        SEED_TEXT.replace("mass_kg = 0.5", 'mass_kg = "0.5"'),
        "m.toml: plant.table.mass_kg = '0.5' (str) is invalid: expected a number",
    ),
    "bool for an int": (
        SEED_TEXT.replace("ticks_per_sample = 40000", "ticks_per_sample = true"),
        "m.toml: controller.ticks_per_sample = True (boolean) is invalid: expected an integer",
    ),
    "millimetres for metres": (
        SEED_TEXT.replace("lead_m = 0.002", "lead_m = 2.0"),
        "m.toml: plant.screw.lead_m = 2 is invalid: expected a finite number in [1e-5, 1e-1]",
    ),
    "controller out of range": (
        SEED_TEXT.replace("ticks_per_sample = 40000", "ticks_per_sample = 0"),
        "m.toml: controller.ticks_per_sample = 0 is invalid: expected an integer in [1, 2^40]",
    ),
    "newer schema": (
        SEED_TEXT.replace("schema_version = 1", "schema_version = 2"),
        "m.toml: schema_version = 2 is newer than this nanostage reads (at most 1)",
    ),
    "no schema": (
        SEED_TEXT.replace("schema_version = 1", ""),
        "m.toml: missing required key schema_version",
    ),
    "unknown effect": (
        SEED_TEXT + "\n[effects.backlsh]\nwidth_m = 1e-6\n",
        "m.toml: unknown effect effects.backlsh (did you mean 'backlash'?)",
    ),
    "effect out of range": (
        SEED_TEXT + "\n[effects.backlash]\nwidth_m = -1e-6\n",
        "m.toml: plant.links[0].backlash_m = -1e-6 is invalid",
    ),
    "unknown kind": (
        SEED_TEXT.replace('kind = "rigid_axis"', 'kind = "rigid"'),
        "m.toml: plant.kind = 'rigid' is invalid: expected one of 'rigid_axis', 'force_drive' "
        "(did you mean 'rigid_axis'?)",
    ),
    "bad literal": (
        SEED_TEXT.replace('side = "table"', 'side = "tabel"'),
        "m.toml: encoder.side = 'tabel' is invalid: expected one of 'table', 'motor' "
        "(did you mean 'table'?)",
    ),
    "identified path": (
        SEED_TEXT + '\n[identified."plant.table.mas_kg"]\nstd_error = 0.1\n',
        'm.toml: identified."plant.table.mas_kg" is not a numeric parameter of the model '
        "(did you mean 'plant.table.mass_kg'?)",
    ),
    "identified key": (
        SEED_TEXT + '\n[identified."plant.table.mass_kg"]\nstd_eror = 0.1\n',
        'm.toml: unknown key identified."plant.table.mass_kg".std_eror '
        "(did you mean 'std_error'?)",
    ),
    "not TOML": ("schema_version = \n", "m.toml: not valid TOML"),
}


@pytest.mark.parametrize("case", list(BAD))
def test_bad_input_names_the_file_and_the_key(case: str) -> None:
    text, message = BAD[case]
    with pytest.raises(ModelFileError) as err:
        parse_model(text, source="m.toml")
    assert str(err.value).startswith(message), str(err.value)
    assert isinstance(err.value, ns.ConfigError)


def test_an_effect_that_does_not_fit_the_plant_kind(tmp_path: Path) -> None:
    path = tmp_path / "emps.model.toml"
    path.write_text(model_to_toml(presets.emps()) + "\n[effects.backlash]\nwidth_m = 1e-5\n")
    with pytest.raises(ModelFileError, match=re.escape(f"{path}: plant.drive.drive_mass_kg")) as e:
        ns.load_model(path)
    assert "the [effects] keys given: computation_delay_samples, backlash" in str(e.value)


def test_cli_export_writes_every_preset(tmp_path: Path) -> None:
    for name in presets.preset_names():
        out = tmp_path / f"{name}.model.toml"
        assert main(["model", "export", name, "--out", str(out)]) == 0
        doc = ns.load_model_file(out)
        assert doc.system == presets.preset_system(name)
        assert doc.provenance["command"] == f"nanostage model export {name}"


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["sed"], "preset 'sed' is unknown (did you mean 'seed'?)"),
        (["seed", "--out-dir"], "error:"),
    ],
)
def test_cli_export_bad_input_is_one_line_exit_2(
    argv: list[str], message: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    if "--out" not in argv:
        argv = [*argv, "--out", str(tmp_path / "m.toml")]
    assert main(["model", "export", *argv]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1


def test_cli_export_refuses_a_folder_or_a_missing_parent(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["model", "export", "seed", "--out", str(tmp_path)]) == 2
    assert "is a folder" in capsys.readouterr().err
    assert main(["model", "export", "seed", "--out", str(tmp_path / "no" / "m.toml")]) == 2
    assert "does not exist" in capsys.readouterr().err


def test_the_documented_example_is_the_seed_preset() -> None:
    doc = (Path(__file__).parents[1] / "docs" / "model-file.md").read_text(encoding="utf-8")
    blocks = re.findall(r"```toml\n(.*?)```", doc, flags=re.S)
    example = next(b for b in blocks if "schema_version" in b)
    assert parse_model(example, source="docs/model-file.md").system == presets.seed()
