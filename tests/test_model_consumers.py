"""Every command and Python entry point that takes a preset also takes a model file (or a
System): the exported seed model gives the preset's results, a changed model changes them,
and a bad model file is a one-line exit-2 error before any work."""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from nanostage import ConfigError, cli, load_model, presets, simulate_step
from nanostage.diagnosis.manifest import ManifestError, load_manifest
from nanostage.diagnosis.predict import predict
from nanostage.studies import reproduce as reproduce_mod
from nanostage.studies import table1

#: Keys of wall-clock timings, left out of the comparisons.
TIMINGS = frozenset({"wall_s", "compute_s", "compute_time_s"})

TUNE_FAST = [
    "--step-um", "100", "--trials", "4", "--popsize", "4", "--maxiter", "1",
    "--eval-trials", "4", "--no-plot", "--quiet",
]  # fmt: skip
CAMPAIGNS_FAST = ["--no-plot", "--campaigns", "--campaign-trials", "2", "--quiet"]


def _strip(value: Any) -> Any:
    if isinstance(value, dict):
        return {k: _strip(v) for k, v in value.items() if k not in TIMINGS}
    if isinstance(value, list):
        return [_strip(v) for v in value]
    return value


def _json(path: Path) -> Any:
    return _strip(json.loads(path.read_text(encoding="utf-8")))


def _run(*argv: str) -> int:
    return cli.main(list(argv))


@pytest.fixture(scope="module")
def models(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    d = tmp_path_factory.mktemp("models")
    seed = d / "seed.model.toml"
    assert _run("model", "export", "seed", "--out", str(seed)) == 0
    text = seed.read_text(encoding="utf-8")
    assert "mass_kg = 0.5\n" in text
    heavy = d / "heavy.model.toml"
    heavy.write_text(text.replace("mass_kg = 0.5\n", "mass_kg = 2.0\n"), encoding="utf-8")
    bad = d / "bad.model.toml"
    bad.write_text(text.replace("mass_kg = 0.5\n", "mas_kg = 0.5\n"), encoding="utf-8")
    emps = d / "emps.model.toml"
    assert _run("model", "export", "emps", "--out", str(emps)) == 0
    return {"seed": seed, "heavy": heavy, "bad": bad, "emps": emps}


# ---- the Table 1 system ----------------------------------------------------------------


@pytest.mark.parametrize("step", [100e-6, 500e-6, 1e-3, 10e-3])
def test_table1_system_of_the_exported_seed_is_the_preset(
    models: dict[str, Path], step: float
) -> None:
    assert presets.table1_system(step, load_model(models["seed"])) == presets.seed(step)
    assert presets.table1_system(step) == presets.seed(step)


def test_table1_system_refuses_another_axis(models: dict[str, Path]) -> None:
    with pytest.raises(ConfigError, match=r"rigid_axis.*fpga_pid"):
        presets.table1_system(1e-3, load_model(models["emps"]))
    with pytest.raises(ConfigError, match=r"expected a nanostage\.System"):
        presets.table1_system(1e-3, "seed")  # type: ignore[arg-type]


# ---- the commands ----------------------------------------------------------------------

COMMANDS = {
    "reproduce": (["reproduce", "--no-plot"], "summary.json"),
    "campaigns": (["reproduce", *CAMPAIGNS_FAST], "campaigns.json"),
    "tune": (["tune", *TUNE_FAST], "tune.json"),
}


@pytest.mark.parametrize("command", list(COMMANDS))
def test_exported_seed_model_gives_the_preset_result(
    models: dict[str, Path], tmp_path: Path, command: str
) -> None:
    argv, name = COMMANDS[command]
    assert _run(*argv, "--out", str(tmp_path / "preset")) == 0
    assert _run(*argv, "--model", str(models["seed"]), "--out", str(tmp_path / "model")) == 0
    with_model, with_preset = _json(tmp_path / "model" / name), _json(tmp_path / "preset" / name)
    if command == "campaigns":  # the one result that names its model
        assert with_preset.pop("model") == "seed preset"
        assert with_model.pop("model") == f"file {models['seed']}"
    assert with_model == with_preset


@pytest.mark.parametrize("command", list(COMMANDS))
def test_a_changed_model_changes_the_result(
    models: dict[str, Path], tmp_path: Path, command: str
) -> None:
    argv, name = COMMANDS[command]
    assert _run(*argv, "--model", str(models["seed"]), "--out", str(tmp_path / "a")) == 0
    assert _run(*argv, "--model", str(models["heavy"]), "--out", str(tmp_path / "b")) == 0
    assert _json(tmp_path / "a" / name) != _json(tmp_path / "b" / name)


@pytest.mark.parametrize("command", list(COMMANDS))
@pytest.mark.parametrize(
    ("which", "words"),
    [
        ("bad", ["bad.model.toml", "plant.table.mas_kg", "did you mean 'mass_kg'"]),
        ("emps", ["--model", "emps.model.toml", "rigid_axis", "fpga_pid"]),
        ("missing", ["missing.model.toml"]),
    ],
)
def test_a_bad_model_file_is_one_line_before_any_work(
    models: dict[str, Path],
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
    command: str,
    which: str,
    words: list[str],
) -> None:
    def no_work(*args: object, **kwargs: object) -> None:
        raise AssertionError("work started")

    monkeypatch.setattr(reproduce_mod, "run_experiments", no_work)
    monkeypatch.setattr(table1, "tune", no_work)
    argv, _ = COMMANDS[command]
    path = models["seed"].parent / "missing.model.toml" if which == "missing" else models[which]
    out = tmp_path / "out"
    capsys.readouterr()
    assert _run(*argv, "--model", str(path), "--out", str(out)) == cli.EXIT_ERROR
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1, err
    for w in words:
        assert w in err
    assert not out.exists()


# ---- the Python API --------------------------------------------------------------------


def test_python_api_takes_a_system(models: dict[str, Path], tmp_path: Path) -> None:
    heavy = load_model(models["heavy"])
    a = reproduce_mod.run_experiments()
    b = reproduce_mod.run_experiments(load_model(models["seed"]))
    c = reproduce_mod.run_experiments(heavy)
    assert [e.metrics for e in a] == [e.metrics for e in b]
    assert [e.metrics for e in a] != [e.metrics for e in c]
    s = reproduce_mod.reproduce(tmp_path / "r", plot=False, model=heavy)
    assert _strip(s)["steps"] == _json(tmp_path / "r" / "summary.json")["steps"]
    with pytest.raises(ConfigError, match="Table 1 axis"):
        reproduce_mod.reproduce(tmp_path / "e", plot=False, model=load_model(models["emps"]))
    assert not (tmp_path / "e").exists()


# ---- manifests: [model] file as the nominal model, --model on predict and diagnose ------


def _trace(folder: Path) -> None:
    tr = simulate_step(presets.seed(100e-6), 100e-6, duration_s=0.05)
    n = len(tr.time_s)
    dt = float(tr.time_s[1] - tr.time_s[0])
    cols = {
        "time_s": dt * np.arange(n, dtype=np.float64),
        "reference_m": np.asarray(tr.reference_m, dtype=np.float64),
        "position_m": np.asarray(tr.encoder_position_m, dtype=np.float64),
    }
    np.savetxt(
        folder / "step.csv", np.column_stack(list(cols.values())), fmt="%.17g", delimiter=",",
        header=",".join(cols), comments="",
    )  # fmt: skip


def _manifest(folder: Path, model: str) -> Path:
    (folder / "m.toml").write_text(
        f'[model]\n{model}\n\n[[experiment]]\nname = "step"\nfile = "step.csv"\n',
        encoding="utf-8",
    )
    return folder / "m.toml"


@pytest.fixture
def case(models: dict[str, Path], tmp_path: Path) -> Path:
    """A folder with a trace and the model files (inside the manifest's folder)."""
    _trace(tmp_path)
    for name in ("seed", "heavy", "bad"):
        shutil.copy(models[name], tmp_path / models[name].name)
    (tmp_path / "over.toml").write_text("[plant.table]\nmass_kg = 2.0\n", encoding="utf-8")
    return tmp_path


def _predicted(folder: Path) -> bytes:
    return (folder / "step.csv").read_bytes()


def test_manifest_model_file_is_the_nominal_model(case: Path) -> None:
    preset = load_manifest(_manifest(case, 'preset = "seed"'))
    model = load_manifest(_manifest(case, 'file = "seed.model.toml"'))
    assert model.model.preset is None and model.model.base == presets.seed()
    assert model.system() == preset.system()
    assert model.model.travel_m == preset.model.travel_m
    heavy = load_manifest(_manifest(case, 'file = "heavy.model.toml"'))
    old = load_manifest(_manifest(case, 'preset = "seed"\nfile = "over.toml"'))
    assert heavy.system() == old.system() != preset.system()
    given = load_manifest(
        _manifest(case, 'preset = "seed"'), model=load_model(case / "heavy.model.toml")
    )
    assert given.system() == heavy.system()


def test_predict_with_a_model_file(case: Path) -> None:
    out = {}
    for name, model in [
        ("preset", 'preset = "seed"'),
        ("file", 'file = "seed.model.toml"'),
        ("heavy", 'file = "heavy.model.toml"'),
        ("old", 'preset = "seed"\nfile = "over.toml"'),
    ]:
        assert _run("predict", str(_manifest(case, model)), "--out", str(case / name)) == 0
        out[name] = _predicted(case / name)
    m = _manifest(case, 'preset = "seed"')
    assert (
        _run(
            "predict", str(m), "--model", str(case / "heavy.model.toml"), "--out", str(case / "cli")
        )
        == 0
    )
    assert out["file"] == out["preset"]
    assert out["heavy"] == out["old"] == _predicted(case / "cli") != out["preset"]
    api = predict(m, case / "api", model=load_model(case / "heavy.model.toml"))
    assert api["experiments"]["step"]["samples"] > 0
    assert _predicted(case / "api") == out["heavy"]


@pytest.mark.parametrize("command", ["predict", "diagnose"])
@pytest.mark.parametrize(
    ("model", "option", "words"),
    [
        ('file = "bad.model.toml"', None, ["m.toml", "model.file", "plant.table.mas_kg"]),
        ('preset = "seed"', "bad.model.toml", ["bad.model.toml", "plant.table.mas_kg"]),
        (
            'preset = "seed"\nfile = "seed.model.toml"',
            None,
            ["model.preset", "is a model file", "not both"],
        ),
        ('file = "../outside.model.toml"', None, ["model.file", "outside the manifest's folder"]),
    ],
)
def test_a_bad_manifest_model_is_one_line(
    case: Path,
    capsys: pytest.CaptureFixture[str],
    command: str,
    model: str,
    option: str | None,
    words: list[str],
) -> None:
    shutil.copy(case / "seed.model.toml", case.parent / "outside.model.toml")
    argv = [command, str(_manifest(case, model)), "--out", str(case / "out")]
    if option is not None:
        argv += ["--model", str(case / option)]
    capsys.readouterr()
    assert _run(*argv) == cli.EXIT_ERROR
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1, err
    for w in words:
        assert w in err, err
    assert not (case / "out").exists()


def test_the_folder_rule_and_trace_root(case: Path) -> None:
    shutil.copy(case / "seed.model.toml", case.parent / "outside.model.toml")
    m = _manifest(case, 'file = "../outside.model.toml"')
    with pytest.raises(ManifestError, match="outside the manifest's folder"):
        load_manifest(m)
    assert load_manifest(m, trace_root=case.parent).system() == presets.seed()
