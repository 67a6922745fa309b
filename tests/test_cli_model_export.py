"""``nanostage model export PRESET`` keeps the shipped model file's provenance: the exported
file has the shipped ``[provenance]`` table whole (read here straight from the package's
file), names the preset, and loads back to the preset's System."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

import nanostage
from nanostage import presets
from nanostage.cli import main

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

#: The package's shipped model files.
MODEL_FILES = Path(nanostage.__file__).parent / "model_files"
#: What the export adds to the shipped provenance.
EXPORT_KEYS = {"preset", "preset_file", "preset_note", "command", "version"}


@pytest.mark.parametrize("name", presets.preset_names())
def test_an_exported_preset_keeps_its_provenance_and_loads_back(name: str, tmp_path: Path) -> None:
    out = tmp_path / f"{name}.model.toml"
    assert main(["model", "export", name, "--out", str(out)]) == 0
    doc = nanostage.load_model_file(out)
    assert doc.system == presets.preset_system(name)
    prov = dict(doc.provenance)
    shipped_file = prov["preset_file"]
    assert shipped_file == f"nanostage/model_files/{name.split('_')[0]}.model.toml"
    with (MODEL_FILES / Path(shipped_file).name).open("rb") as fh:
        shipped = tomllib.load(fh)["provenance"]
    assert shipped and not EXPORT_KEYS & shipped.keys()
    assert {k: v for k, v in prov.items() if k not in EXPORT_KEYS} == shipped
    assert prov["preset"] == name and prov["command"] == f"nanostage model export {name}"
    assert prov["version"] == nanostage.__version__ and prov["preset_note"]


def test_the_exported_seed_carries_table1_and_each_values_provenance(tmp_path: Path) -> None:
    out = tmp_path / "seed.model.toml"
    assert main(["model", "export", "seed", "--out", str(out)]) == 0
    prov = nanostage.load_model_file(out).provenance
    gains = {row["step_m"]: (row["kp"], row["ki"], row["kd"]) for row in prov["table1_gains"]}
    assert gains == {s: presets.table1_gains(s) for s in (1e-4, 5e-4, 1e-3, 1e-2)}
    values = prov["values"]
    assert set(values) == set(presets.SEED_PROVENANCE)
    for path, p in presets.SEED_PROVENANCE.items():
        assert values[path] == {"unit": p.unit, "source": p.source, "confidence": p.confidence}
