"""``presets.preset_provenance``: each preset's provenance is the shipped model file's
``[provenance]`` table (read here independently with tomllib from the package's file),
with the file's package path and what the preset is of it; an unknown name is an error
naming it and every preset."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

import pytest

import nanostage
from nanostage import presets

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

#: The package's shipped model files.
MODEL_FILES = Path(nanostage.__file__).parent / "model_files"
#: The file each preset is read from, written out by hand.
SHIPPED = {
    "seed": "seed.model.toml",
    "emps": "emps.model.toml",
    "emps_naive": "emps.model.toml",
    "emps_asymmetric": "emps.model.toml",
}


def _shipped(file: str) -> dict[str, Any]:
    with (MODEL_FILES / file).open("rb") as fh:
        return dict(tomllib.load(fh)["provenance"])


def test_every_preset_has_a_file_written_out_here() -> None:
    assert set(presets.preset_names()) == set(SHIPPED)


@pytest.mark.parametrize("name", sorted(SHIPPED))
def test_a_presets_provenance_is_its_shipped_files_table(name: str) -> None:
    prov = presets.preset_provenance(name)
    assert prov.pop("preset_file") == f"nanostage/model_files/{SHIPPED[name]}"
    note = prov.pop("preset_note")
    assert isinstance(note, str) and note.strip()
    assert prov == _shipped(SHIPPED[name])


def test_the_seed_provenance_has_table1_as_in_the_shipped_file() -> None:
    rows = _shipped("seed.model.toml")["table1_gains"]
    gains = {r["step_m"]: (r["kp"], r["ki"], r["kd"]) for r in rows}
    # Table 1 of the seed paper (SEED.md), written out by hand.
    assert gains == {
        1e-4: (450.0, 2.0, 40.0),
        5e-4: (450.0, 2.0, 40.0),
        1e-3: (450.0, 5.0, 10.0),
        1e-2: (450.0, 5.0, 25.0),
    }
    assert presets.preset_provenance("seed")["table1_gains"] == rows


def test_the_notes_tell_the_emps_presets_apart() -> None:
    notes = {name: presets.preset_provenance(name)["preset_note"] for name in SHIPPED}
    assert len(set(notes.values())) == len(notes)
    assert "Table 1" in notes["seed"]
    assert "asymmetric" in notes["emps_asymmetric"] and "Coulomb" in notes["emps_naive"]


def test_changing_the_result_changes_no_preset() -> None:
    prov = presets.preset_provenance("seed")
    prov["table1_gains"][0]["kp"] = -1.0
    prov["values"].clear()
    prov["source"] = "changed"
    again = presets.preset_provenance("seed")
    assert again["table1_gains"][0]["kp"] == 450.0
    assert again["values"] and again["source"] != "changed"
    assert presets.table1_gains(1e-4) == (450.0, 2.0, 40.0)


@pytest.mark.parametrize(
    ("name", "message"),
    [
        ("sed", "preset 'sed' is unknown (did you mean 'seed'?); the presets are: "),
        ("nope", "preset 'nope' is unknown; the presets are: "),
        (None, "preset None is unknown; the presets are: "),
    ],
)
def test_an_unknown_preset_is_an_error_naming_it_and_the_presets(name: Any, message: str) -> None:
    with pytest.raises(nanostage.ConfigError) as err:
        presets.preset_provenance(name)
    text = str(err.value)
    assert text == message + ", ".join(presets.preset_names())
    assert isinstance(err.value, ValueError)


def test_check_preset_name_names_the_label_the_nearest_and_every_preset() -> None:
    from nanostage.presets import check_preset_name, preset_names

    for name in preset_names():
        check_preset_name(name)
    with pytest.raises(nanostage.ConfigError) as err:
        check_preset_name("sed", "--preset")
    assert str(err.value) == (
        "--preset 'sed' is unknown (did you mean 'seed'?); the presets are: "
        + ", ".join(preset_names())
    )
