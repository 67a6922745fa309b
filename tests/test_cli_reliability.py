"""The command line's conventions and the output folders: one-line errors with exit code 2
(``--debug`` for the traceback), output checked before any work and written whole or not at
all, SIGINT/SIGTERM stopping a run cleanly, and no process-pool worker left behind."""

from __future__ import annotations

import importlib
import json
import math
import os
import signal
import subprocess
import sys
import textwrap
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import nanostage
from nanostage import iso230_2, iso_diagnosis, iso_diagnosis_benchmark, measurement, output
from nanostage.cli import Terminated, main
from nanostage.diagnosis import benchmark
from nanostage.diagnosis import run as diagnosis_run
from nanostage.output import (
    RUN_MANIFEST,
    OutputError,
    check_file_stems,
    check_output_dir,
    staged_output,
    write_json,
)
from nanostage.studies import emps, emps_study, iso_gap, paper_campaigns, reproduce, table1

from conftest import SHARED, write_emps_mat

EMPS_MAT = SHARED / "data" / "emps" / "DATA_EMPS.mat"

Run = Callable[..., tuple[int, str, str]]


@pytest.fixture
def cli(capsys: pytest.CaptureFixture[str]) -> Run:
    """``cli(*argv)``: run ``nanostage`` in-process; returns (exit code, stdout, stderr)."""

    def run(*argv: str) -> tuple[int, str, str]:
        code = main(list(argv))
        captured = capsys.readouterr()
        return code, captured.out, captured.err

    return run


def one_error_line(err: str) -> str:
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert "Traceback" not in err
    return lines[0]


def leftovers(parent: Path) -> list[str]:
    """Staging folders a run left beside its output."""
    return sorted(p.name for p in parent.iterdir() if ".partial-" in p.name or ".old-" in p.name)


def never(*args: Any, **kwargs: Any) -> Any:
    raise AssertionError("the work started although the output folder is unusable")


# --------------------------------------------------------------------------------------------
# output.py
# --------------------------------------------------------------------------------------------


def test_check_file_stems_accepts_safe_unique_names() -> None:
    assert check_file_stems(["step_100um", "run-2", "a.b", "X" * 100], "name") == [
        "step_100um",
        "run-2",
        "a.b",
        "X" * 100,
    ]


@pytest.mark.parametrize(
    ("names", "fragment"),
    [
        ([""], "cannot be a file name"),
        (["../x"], "cannot be a file name"),
        (["a/b"], "cannot be a file name"),
        ([".hidden"], "cannot be a file name"),
        (["a..b"], "cannot be a file name"),
        (["x" * 101], "cannot be a file name"),
        (["name with space"], "cannot be a file name"),
        (["Run", "run"], "duplicate of 'Run'"),
        ([3], "cannot be a file name"),
    ],
)
def test_check_file_stems_rejects(names: list[Any], fragment: str) -> None:
    with pytest.raises(OutputError, match=fragment) as info:
        check_file_stems(names, "experiment.name")
    assert "experiment.name" in str(info.value)
    assert isinstance(info.value, ValueError)


def test_check_output_dir_cases(tmp_path: Path) -> None:
    new = tmp_path / "new" / "deeper"
    assert check_output_dir(new) == new.absolute()
    assert not (tmp_path / "new").exists()  # creates nothing
    empty = tmp_path / "empty"
    empty.mkdir()
    assert check_output_dir(empty) == empty
    earlier = tmp_path / "earlier"
    earlier.mkdir()
    (earlier / RUN_MANIFEST).write_text("{}", encoding="utf-8")
    (earlier / "summary.json").write_text("{}", encoding="utf-8")
    assert check_output_dir(earlier) == earlier
    afile = tmp_path / "file.txt"
    afile.write_text("x", encoding="utf-8")
    with pytest.raises(OutputError, match="is an existing file, not a folder"):
        check_output_dir(afile)
    other = tmp_path / "other"
    other.mkdir()
    (other / "notes.txt").write_text("mine", encoding="utf-8")
    with pytest.raises(OutputError, match=r"folder of other files \(1 entries"):
        check_output_dir(other)
    with pytest.raises(OutputError, match="cannot write into"):
        check_output_dir(afile / "sub")  # the nearest existing parent is a file


@pytest.mark.skipif(not hasattr(os, "geteuid") or os.geteuid() == 0, reason="root writes anywhere")
def test_check_output_dir_unwritable_parent(tmp_path: Path) -> None:
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o555)
    try:
        with pytest.raises(OutputError, match="cannot write into"):
            check_output_dir(locked / "out")
    finally:
        locked.chmod(0o755)


def test_staged_output_success_writes_the_folder_and_its_manifest(tmp_path: Path) -> None:
    out = tmp_path / "out"
    with staged_output(out, "unit test") as folder:
        assert folder.parent == tmp_path and folder.name.startswith(".out.partial-")
        (folder / "a.txt").write_text("A", encoding="utf-8")
        (folder / "sub").mkdir()
        (folder / "sub" / "b.txt").write_text("B", encoding="utf-8")
        assert not out.exists()  # nothing visible until the end
    manifest = json.loads((out / RUN_MANIFEST).read_text(encoding="utf-8"))
    assert manifest == {"command": "unit test", "files": ["a.txt", "sub/b.txt"]}
    assert (out / "sub" / "b.txt").read_text(encoding="utf-8") == "B"
    assert leftovers(tmp_path) == []
    # A plain folder's permissions (not a private temporary folder's).
    if os.name == "posix":
        umask = os.umask(0)
        os.umask(umask)
        assert out.stat().st_mode & 0o777 == 0o777 & ~umask


@pytest.mark.parametrize("error", [RuntimeError("boom"), KeyboardInterrupt()])
def test_staged_output_failure_leaves_nothing(tmp_path: Path, error: BaseException) -> None:
    out = tmp_path / "out"
    with pytest.raises(type(error)), staged_output(out, "unit test") as folder:
        (folder / "half.txt").write_text("half", encoding="utf-8")
        raise error
    assert not out.exists()
    assert leftovers(tmp_path) == []


def test_staged_output_replaces_the_previous_run_or_leaves_it_whole(tmp_path: Path) -> None:
    out = tmp_path / "out"
    with staged_output(out, "first") as folder:
        (folder / "old.txt").write_text("old", encoding="utf-8")
        (folder / "shared.txt").write_text("first", encoding="utf-8")
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    # A failed (or interrupted) second run: the first run's folder stays as it was.
    for error in (RuntimeError("failed"), KeyboardInterrupt()):
        with pytest.raises(type(error)), staged_output(out, "second") as folder:
            (folder / "shared.txt").write_text("second", encoding="utf-8")
            (folder / "new.txt").write_text("new", encoding="utf-8")
            raise error
        assert {p.name: p.read_bytes() for p in out.iterdir()} == before
    # A successful second run replaces it whole: no stale file of the first run remains.
    with staged_output(out, "second") as folder:
        (folder / "shared.txt").write_text("second", encoding="utf-8")
    assert sorted(p.name for p in out.iterdir()) == [RUN_MANIFEST, "shared.txt"]
    assert (out / "shared.txt").read_text(encoding="utf-8") == "second"
    assert leftovers(tmp_path) == []


def test_a_signal_between_the_renames_puts_the_previous_folder_back(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    out = tmp_path / "out"
    with staged_output(out, "first") as folder:
        (folder / "first.txt").write_text("first", encoding="utf-8")
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    real_replace = os.replace
    calls = []

    def replace(src: Any, dst: Any) -> None:
        calls.append((Path(src).name, Path(dst).name))
        if len(calls) == 2:  # the new folder into place
            raise KeyboardInterrupt
        real_replace(src, dst)

    monkeypatch.setattr(output.os, "replace", replace)
    with pytest.raises(KeyboardInterrupt), staged_output(out, "second") as folder:
        (folder / "second.txt").write_text("second", encoding="utf-8")
    monkeypatch.undo()
    assert calls[0] == ("out", "previous") and calls[1][1] == "out"
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before
    assert leftovers(tmp_path) == []


def test_staged_output_checks_before_the_body_runs(tmp_path: Path) -> None:
    afile = tmp_path / "out"
    afile.write_text("x", encoding="utf-8")
    ran = []
    with pytest.raises(OutputError, match="existing file"), staged_output(afile, "x"):
        ran.append(1)
    assert ran == []


def test_write_json_is_strict(tmp_path: Path) -> None:
    data = {
        "nan": math.nan,
        "inf": -math.inf,
        "np": np.float64(np.inf),
        "arr": np.array([1.0, np.nan]),
        "int": np.int64(3),
        "flag": np.bool_(True),
        "path": Path("a/b"),
        "tuple": (1, 2),
        1: "key",
        "µ": "µm",
    }
    p = write_json(data, tmp_path / "sub" / "x.json")
    text = p.read_text(encoding="utf-8")
    for token in ("NaN", "Infinity"):
        assert token not in text

    def reject(token: str) -> None:
        raise AssertionError(f"non-standard token {token}")

    back = json.loads(text, parse_constant=reject)
    assert back == {
        "nan": None,
        "inf": None,
        "np": None,
        "arr": [1.0, None],
        "int": 3,
        "flag": True,
        "path": "a/b",
        "tuple": [1, 2],
        "1": "key",
        "µ": "µm",
    }
    with pytest.raises(TypeError, match="cannot write object to JSON"):
        write_json({"x": object()}, tmp_path / "y.json")


# --------------------------------------------------------------------------------------------
# One-line errors, exit code 2
# --------------------------------------------------------------------------------------------


def _files(tmp_path: Path) -> dict[str, Path]:
    """Bad inputs of every kind, written once per test."""
    f: dict[str, Path] = {}
    f["file"] = tmp_path / "a_file.txt"
    f["file"].write_text("not a folder", encoding="utf-8")
    f["latin1"] = tmp_path / "latin1.csv"
    f["latin1"].write_bytes(b"target_m,direction,run,actual_m\n0.0,+,1,1e-6\n0.0,+,2,2\xb5-6\n")
    f["junk_mat"] = tmp_path / "junk.mat"
    f["junk_mat"].write_bytes(b"this is not a MAT file")
    return f


ERROR_CASES: list[tuple[list[str], list[str]]] = [
    # (argv with {file}/{latin1}/{junk_mat}/{tmp} placeholders, fragments of the one line)
    (["reproduce", "--out", "{file}"], ["--out", "a_file.txt", "existing file"]),
    (
        ["reproduce", "--campaigns", "--campaign-trials", "0", "--out", "{tmp}/r"],
        ["--campaign-trials", "n_trials = 0", "[1, 4294967296]"],
    ),
    (
        ["reproduce", "--campaigns", "--threads", "0", "--out", "{tmp}/r"],
        ["--threads", "threads = 0", "[1, 1024]"],
    ),
    (
        ["reproduce", "--campaigns", "--campaign-backlash-m", "0.5", "--out", "{tmp}/r"],
        ["--campaign-backlash-m", "0.5", "[0, 0.0001] m"],
    ),
    (["reproduce", "--campaign-trials", "many"], ["--campaign-trials", "'many'", "integer"]),
    (["reproduce", "--model", "{tmp}/missing.model.toml", "--out", "{tmp}/r"], ["missing.model"]),
    (
        ["reproduce", "--campaigns", "--model", "{file}", "--out", "{tmp}/r"],
        ["a_file.txt", "TOML"],
    ),
    (
        ["diagnose-benchmark", "--cases", "0", "--out", "{tmp}/b"],
        ["--cases", "cases = 0", "[1, 10000]"],
    ),
    (
        ["diagnose-benchmark", "--seed", "-1", "--out", "{tmp}/b"],
        ["--seed", "seed = -1", "[0, 4294967295]"],
    ),
    (
        ["diagnose-benchmark", "--level-scatter", "0.3", "--out", "{tmp}/b"],
        ["--level-scatter", "level_scatter = 0.3", "[0, 0.2]"],
    ),
    (["tune", "--trials", "0", "--out", "{tmp}/t"], ["--trials", "n_trials = 0", "[1, 100000]"]),
    (["tune", "--step-um", "-100", "--out", "{tmp}/t"], ["--step-um", "step_m = -", "(0, 1] m"]),
    (["tune", "--eval-trials", "0", "--out", "{tmp}/t"], ["--eval-trials", "eval_trials = 0"]),
    (["tune", "--spread", "0.9", "--out", "{tmp}/t"], ["--spread", "level_spread", "0.9"]),
    (["tune", "--threads", "0", "--out", "{tmp}/t"], ["--threads", "threads = 0", "[1, 1024]"]),
    (["tune", "--out", "{file}"], ["--out", "a_file.txt", "existing file"]),
    (["tune", "--model", "{tmp}/missing.model.toml", "--out", "{tmp}/t"], ["missing.model"]),
    (["tune", "--model", "{file}", "--out", "{tmp}/t"], ["a_file.txt", "TOML"]),
    (["iso230", "{tmp}/missing.csv"], ["missing.csv", "No such file"]),
    (
        ["iso230", "{latin1}", "--out", "{tmp}/i"],
        ["latin1.csv", "line 3", "not UTF-8", "byte offset 54"],
    ),
    (["iso230", "{latin1}", "--units", "cm"], ["--units", "'cm'", "'m', 'mm'"]),
    (["emps", "--mat", "{tmp}/missing.mat", "--out", "{tmp}/e"], ["missing.mat", "not found"]),
    (["emps", "--mat", "{tmp}", "--out", "{tmp}/e"], ["is a folder", "DATA_EMPS.mat"]),
    (["emps", "--mat", "{junk_mat}", "--out", "{tmp}/e"], ["junk.mat", "cannot read as a MAT"]),
    (["emps", "--out", "{file}"], ["--out", "a_file.txt", "existing file"]),
    (["diagnose", "{tmp}/missing.toml", "--out", "{tmp}/d"], ["missing.toml"]),
    (["diagnose", "{tmp}/missing.toml", "--out", "{file}"], ["--out", "existing file"]),
    (["predict", "{tmp}/missing.toml", "--out", "{tmp}/p"], ["missing.toml"]),
    (
        ["predict", "{tmp}/m.toml", "--model", "{file}", "--out", "{tmp}/p"],
        ["a_file.txt", "TOML"],
    ),
    (
        ["diagnose", "{tmp}/m.toml", "--model", "{tmp}/missing.model.toml", "--out", "{tmp}/d"],
        ["missing.model.toml"],
    ),
    (["model", "export", "sed", "--out", "{tmp}/m.toml"], ["'sed'", "did you mean 'seed'"]),
    (["model", "export", "seed", "--out", "{tmp}"], ["--out", "is a folder"]),
    (["model", "export", "seed", "--out", "{tmp}/no/m.toml"], ["--out", "does not exist"]),
    (["iso-gap", "--trials", "1", "--out", "{tmp}/g"], ["--trials", "n_trials = 1", "[2, "]),
    (["iso-gap", "--threads", "0", "--out", "{tmp}/g"], ["--threads", "threads = 0", "[1, 1024]"]),
    (
        ["iso-diagnose", "{tmp}/m.csv", "--trials", "1", "--out", "{tmp}/d"],
        ["--trials", "n_trials = 1", "[4, 4096]"],
    ),
    (
        ["iso-diagnose", "{tmp}/m.csv", "--preset", "sed", "--out", "{tmp}/d"],
        ["--preset", "'sed'", "did you mean 'seed'"],
    ),
    (["iso-diagnose", "{tmp}/missing.csv", "--out", "{tmp}/d"], ["missing.csv"]),
    (
        ["iso-diagnose-benchmark", "--cases", "0", "--out", "{tmp}/b"],
        ["--cases", "cases = 0", "[1, 10000]"],
    ),
    (["no-such-command"], ["invalid choice", "'no-such-command'"]),
]


@pytest.mark.parametrize(("argv", "fragments"), ERROR_CASES, ids=lambda v: " ".join(v)[:60])
def test_every_error_is_one_line_with_exit_code_2(
    cli: Run, tmp_path: Path, argv: list[str], fragments: list[str]
) -> None:
    files = _files(tmp_path)
    args = [a.format(tmp=tmp_path, **files) for a in argv]
    code, out, err = cli(*args)
    assert code == 2, (out, err)
    line = one_error_line(err)
    assert line.startswith("nanostage")
    for fragment in fragments:
        assert fragment in line, line
    # Nothing was written.
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(p.name for p in files.values())


@pytest.mark.parametrize(
    ("argv", "label"),
    [
        (["iso-diagnose", "{tmp}/m.csv", "--preset", "sed", "--out", "{tmp}/d"], "--preset"),
        (["model", "export", "sed", "--out", "{tmp}/m.toml"], "preset"),
    ],
)
def test_an_unknown_preset_is_named_with_the_nearest_and_every_preset(
    cli: Run, tmp_path: Path, argv: list[str], label: str
) -> None:
    code, _, err = cli(*[a.format(tmp=tmp_path) for a in argv])
    assert code == 2
    assert one_error_line(err) == (
        f"nanostage {argv[0]}: {label} 'sed' is unknown (did you mean 'seed'?); the presets "
        f"are: {', '.join(nanostage.presets.preset_names())}"
    )


def test_debug_shows_the_traceback(cli: Run, tmp_path: Path) -> None:
    for argv in (
        ["--debug", "diagnose-benchmark", "--cases", "0"],
        ["diagnose-benchmark", "--cases", "0", "--debug"],
    ):
        code, _, err = cli(*argv, "--out", str(tmp_path / "b"))
        assert code == 2
        assert "Traceback (most recent call last)" in err and "ConfigError" in err
        assert err.strip().splitlines()[-1] == (
            "nanostage diagnose-benchmark: --cases: cases = 0 is invalid: expected an integer "
            "in [1, 10000]"
        )


def test_an_unexpected_error_is_one_line_too(
    cli: Run, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    def broken(*args: Any, **kwargs: Any) -> Any:
        raise ZeroDivisionError("division by zero")

    monkeypatch.setattr(reproduce, "reproduce_into", broken)
    code, _, err = cli("reproduce", "--out", str(tmp_path / "r"), "--no-plot")
    assert code == 1
    line = one_error_line(err)
    assert "internal error: ZeroDivisionError: division by zero" in line
    assert "run with --debug for the traceback" in line
    assert not (tmp_path / "r").exists() and leftovers(tmp_path) == []
    code, _, err = cli("--debug", "reproduce", "--out", str(tmp_path / "r"), "--no-plot")
    assert code == 1 and "Traceback" in err


# --------------------------------------------------------------------------------------------
# Output checked before any work, written whole or not at all
# --------------------------------------------------------------------------------------------

#: (argv after the command's name, what to make fail if it is called) per command.
WORK: dict[str, tuple[list[str], list[tuple[Any, str]]]] = {
    "reproduce": ([], [(reproduce, "reproduce_into")]),
    "reproduce --campaigns": (
        ["--campaigns"],
        [(reproduce, "reproduce_into"), (paper_campaigns, "write_paper_campaigns_into")],
    ),
    "tune": (["--step-um", "100"], [(table1, "tune_table1")]),
    "diagnose": (["{manifest}"], [(diagnosis_run, "_setup")]),
    "diagnose-benchmark": (["--cases", "1"], [(benchmark, "_run_benchmark")]),
    "emps": (["--mat", "{junk_mat}"], [(emps_study, "load_emps")]),
    "iso230": (["{csv}"], [(iso230_2, "read_measurement_csv")]),
    "iso-gap": ([], [(iso_gap, "iso_gap")]),
    "iso-diagnose": (
        ["{csv}"],
        [(measurement, "read_iso_measurement"), (iso_diagnosis, "write_iso_diagnosis")],
    ),
    "iso-diagnose-benchmark": ([], [(iso_diagnosis_benchmark, "run_iso_benchmark")]),
    "predict": (
        ["{manifest}"],
        [(importlib.import_module("nanostage.diagnosis.predict"), "predict")],
    ),
}


@pytest.mark.parametrize("command", list(WORK))
@pytest.mark.parametrize("kind", ["existing file", "folder of other files"])
def test_an_unusable_out_is_rejected_before_any_work(
    cli: Run, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, command: str, kind: str
) -> None:
    extra, work = WORK[command]
    for module, name in work:
        monkeypatch.setattr(module, name, never)
    files = _files(tmp_path)
    manifest = tmp_path / "m.toml"
    manifest.write_text('[model]\npreset = "seed"\n', encoding="utf-8")
    csv_path = tmp_path / "meas.csv"
    csv_path.write_text("target_m,direction,run,actual_m\n", encoding="utf-8")
    if kind == "existing file":
        out = files["file"]
    else:
        out = tmp_path / "mine"
        out.mkdir()
        (out / "thesis.tex").write_text("precious", encoding="utf-8")
    args = [a.format(manifest=manifest, csv=csv_path, **files) for a in extra]
    code, _, err = cli(command.split()[0], *args, "--out", str(out))
    assert code == 2
    line = one_error_line(err)
    assert "--out" in line and str(out.name) in line and kind in line
    if kind == "folder of other files":
        assert [p.name for p in out.iterdir()] == ["thesis.tex"]
    assert leftovers(tmp_path) == []


def test_a_run_replaces_its_previous_output_whole(cli: Run, tmp_path: Path) -> None:
    out = tmp_path / "r"
    assert cli("reproduce", "--out", str(out))[0] == 0
    assert {p.name for p in out.iterdir()} == {RUN_MANIFEST, "summary.json", "steps.png"}
    # The same folder again without the figure: the old figure does not survive beside the
    # new summary.
    assert cli("reproduce", "--out", str(out), "--no-plot")[0] == 0
    assert {p.name for p in out.iterdir()} == {RUN_MANIFEST, "summary.json"}
    manifest = json.loads((out / RUN_MANIFEST).read_text(encoding="utf-8"))
    assert manifest["files"] == ["summary.json"]
    summary = json.loads((out / "summary.json").read_text(encoding="utf-8"))
    assert len(summary["steps"]) == 4
    assert leftovers(tmp_path) == []


@pytest.mark.parametrize(
    ("error", "code", "line"),
    [
        (KeyboardInterrupt(), 130, "nanostage reproduce: interrupted"),
        (Terminated(), 143, "nanostage reproduce: terminated (SIGTERM)"),
        (OSError(28, "No space left on device", "campaigns.json"), 2, None),
    ],
)
def test_an_interrupted_campaign_run_leaves_the_previous_folder_intact(
    cli: Run,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    error: BaseException,
    code: int,
    line: str | None,
) -> None:
    out = tmp_path / "r"
    assert cli("reproduce", "--out", str(out), "--no-plot")[0] == 0
    before = {p.name: p.read_bytes() for p in out.iterdir()}

    def interrupted(folder: Path, *args: Any, **kwargs: Any) -> Any:
        # Halfway: a new campaign file is written, then the run stops.
        (folder / "campaigns.json").write_text("{}", encoding="utf-8")
        raise error

    monkeypatch.setattr(paper_campaigns, "write_paper_campaigns_into", interrupted)
    got, _, err = cli("reproduce", "--out", str(out), "--no-plot", "--campaigns")
    assert got == code
    message = one_error_line(err)
    if line is not None:
        assert message == line
    else:
        assert "campaigns.json: No space left on device" in message
    # The previous run's folder as it was: no new summary beside old files, no half file.
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before
    assert leftovers(tmp_path) == []


def test_campaign_arguments_are_checked_before_the_summary_is_written(
    cli: Run, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(reproduce, "reproduce_into", never)
    out = tmp_path / "r"
    for bad in (["--campaign-trials", "-3"], ["--campaign-seed", "-1"], ["--threads", "2000"]):
        code, _, err = cli("reproduce", "--out", str(out), "--campaigns", *bad)
        assert code == 2 and bad[0] in one_error_line(err)
        assert not out.exists()


def test_benchmark_cases_zero_is_rejected_before_anything(tmp_path: Path) -> None:
    for cases in (0, -1, 10_001, 2.0, True):
        with pytest.raises(nanostage.ConfigError, match=r"cases = .* expected an integer in"):
            benchmark.run_benchmark(tmp_path / "b", cases=cases)  # type: ignore[arg-type]
    with pytest.raises(nanostage.ConfigError, match="hidden"):
        benchmark.run_benchmark(tmp_path / "b", cases=1, hidden=["no_such_effect"])
    assert not (tmp_path / "b").exists()


def test_the_api_functions_stage_their_folders(tmp_path: Path) -> None:
    summary = reproduce.reproduce(tmp_path / "r", plot=False)
    assert summary["steps"]
    assert (tmp_path / "r" / RUN_MANIFEST).is_file()
    data = json.loads((tmp_path / "r" / "summary.json").read_text(encoding="utf-8"))
    assert data["slew_at_voltage_limit"]["voltage_v"] == 6.0
    other = tmp_path / "other"
    other.mkdir()
    (other / "keep.txt").write_text("keep", encoding="utf-8")
    with pytest.raises(OutputError, match="folder of other files"):
        reproduce.reproduce(other, plot=False)
    with pytest.raises(OutputError, match="folder of other files"):
        paper_campaigns.write_paper_campaigns(other, paper_campaigns.CampaignSettings(n_trials=1))
    report: dict[str, Any] = {"steps": [], "objective": {}}
    with pytest.raises(OutputError, match="folder of other files"):
        table1.write_tune_report(other, report, plot=False)
    assert [p.name for p in other.iterdir()] == ["keep.txt"]


# --------------------------------------------------------------------------------------------
# iso230: units and encodings
# --------------------------------------------------------------------------------------------


def _iso_rows(scale: float, header: str = "target_m,direction,run,actual_m") -> str:
    """A bidirectional test of a precision stage: 11 targets 1 mm apart, 5 runs, deviations
    of a few tenths of a micrometre; lengths written in units of ``scale`` metres."""
    rng = np.random.default_rng(3)
    rows = [header]
    for i in range(11):
        target_m = i * 1e-3
        for d in "+-":
            for r in range(1, 6):
                dev_m = float(rng.normal(0.0, 1e-7)) + (5e-8 if d == "+" else -5e-8)
                rows.append(f"{target_m / scale!r},{d},{r},{(target_m + dev_m) / scale!r}")
    return "\n".join(rows) + "\n"


def test_iso230_millimetres_are_an_error_naming_the_fix(tmp_path: Path, cli: Run) -> None:
    mm = tmp_path / "mm.csv"
    mm.write_text(_iso_rows(1e-3), encoding="utf-8")
    with pytest.raises(iso230_2.Iso230InputError, match="look like millimetres") as info:
        iso230_2.read_measurement_csv(mm)
    assert "--units mm" in str(info.value) and "target_mm" in str(info.value)
    code, _, err = cli("iso230", str(mm), "--out", str(tmp_path / "o"))
    assert code == 2
    line = one_error_line(err)
    assert "mm.csv" in line and "11 targets over 10 m" in line and "--units mm" in line
    assert not (tmp_path / "o").exists()
    # Read as metres anyway (the check off), every figure is 1000 times too large.
    as_m = iso230_2.read_measurement_csv(mm, check_units=False).evaluate()
    right = iso230_2.read_measurement_csv(mm, units="mm").evaluate()
    assert as_m.accuracy_up_m == pytest.approx(1000 * right.accuracy_up_m, rel=1e-6)
    assert 0.2e-6 < right.accuracy_up_m < 2e-6


def test_iso230_metres_and_millimetres_give_the_same_figures(tmp_path: Path, cli: Run) -> None:
    m = tmp_path / "m.csv"
    m.write_text(_iso_rows(1.0), encoding="utf-8")
    mm = tmp_path / "mm.csv"
    mm.write_text(_iso_rows(1e-3), encoding="utf-8")
    mm_cols = tmp_path / "mm_cols.csv"
    mm_cols.write_text(_iso_rows(1e-3, "target_mm,direction,run,actual_mm"), encoding="utf-8")
    ref = iso230_2.read_measurement_csv(m).evaluate().axis_parameters()
    for path, units in ((mm, "mm"), (mm_cols, None)):
        got = iso230_2.read_measurement_csv(path, units=units).evaluate().axis_parameters()
        assert got.keys() == ref.keys()
        for k, v in ref.items():
            assert v is not None and got[k] == pytest.approx(v, rel=1e-9, abs=1e-15), k
    assert ref["accuracy_up_m"] is not None and 0.2e-6 < ref["accuracy_up_m"] < 2e-6
    outs = []
    for path, extra in ((m, []), (mm, ["--units", "mm"]), (mm_cols, [])):
        out = tmp_path / f"out_{path.stem}"
        code, _, _ = cli("iso230", str(path), "--out", str(out), *extra)
        assert code == 0
        outs.append(json.loads((out / "iso230_2.json").read_text(encoding="utf-8")))
        assert (out / RUN_MANIFEST).is_file()
    for o in outs[1:]:
        assert o["axis"].keys() == outs[0]["axis"].keys()
        for k, v in outs[0]["axis"].items():
            assert o["axis"][k] == pytest.approx(v, rel=1e-9, abs=1e-15), k


def test_iso230_non_utf8_names_file_line_and_byte_offset(tmp_path: Path) -> None:
    good = _iso_rows(1.0).encode()
    offset = good.index(b"\n", 400) + 5  # inside a data row
    bad = tmp_path / "bad.csv"
    bad.write_bytes(good[:offset] + b"\xff" + good[offset:])
    with pytest.raises(iso230_2.Iso230InputError, match="not UTF-8") as info:
        iso230_2.read_measurement_csv(bad)
    assert f"byte offset {offset}" in str(info.value) and "0xff" in str(info.value)
    assert info.value.line == good[:offset].count(b"\n") + 1
    # Beyond the first read buffer of the text decoder: the offset is still the file's.
    big = ("# padding\n" * 5000).encode() + good
    off2 = len(big) - 30
    late = tmp_path / "late.csv"
    late.write_bytes(big[:off2] + b"\xe9" + big[off2:])
    with pytest.raises(iso230_2.Iso230InputError, match=f"byte offset {off2}") as info:
        iso230_2.read_measurement_csv(late)
    assert info.value.line == big[:off2].count(b"\n") + 1


# --------------------------------------------------------------------------------------------
# emps: input checks
# --------------------------------------------------------------------------------------------


def test_emps_has_no_source_tree_default_once_installed(
    cli: Run, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.delenv(emps.EMPS_ENV_VAR, raising=False)
    installed = tmp_path / "site-packages" / "nanostage" / "studies" / "emps.py"
    monkeypatch.setattr(emps, "__file__", str(installed))
    with pytest.raises(FileNotFoundError, match="--mat PATH"):
        emps.default_emps_path()
    code, _, err = cli("emps", "--out", str(tmp_path / "e"))
    assert code == 2
    line = one_error_line(err)
    assert "--mat" in line and emps.EMPS_ENV_VAR in line
    assert not (tmp_path / "e").exists()


def _emps_mat(tmp_path: Path, name: str, **scale: float) -> Path:
    from scipy.io import loadmat, savemat

    if not EMPS_MAT.is_file():
        pytest.skip(f"EMPS data not found at {EMPS_MAT}")
    mat = {k: v for k, v in loadmat(str(EMPS_MAT)).items() if not k.startswith("__")}
    for key, factor in scale.items():
        mat[key] = mat[key] * factor
    path = tmp_path / name
    savemat(str(path), mat)
    return path


@pytest.mark.parametrize(
    ("scale", "fragment"),
    [
        ({"qm": 1e3, "qg": 1e3}, "variable 'qg' reaches 246.357"),
        ({"qm": 1e3}, "variable 'qm' reaches 246.378"),
        # A short stroke in millimetres stays within ±5 "m": the controller law finds it.
        ({"qm": 20.0, "qg": 20.0}, "differs from the cascade controller law"),
    ],
)
def test_emps_positions_in_millimetres_are_an_error(
    cli: Run,
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    scale: dict[str, float],
    fragment: str,
) -> None:
    path = _emps_mat(tmp_path, "mm.mat", **scale)
    monkeypatch.setattr(emps_study, "yardstick", never)
    monkeypatch.setattr(emps_study, "output_error_fit", never)
    code, _, err = cli("emps", "--mat", str(path), "--out", str(tmp_path / "e"))
    assert code == 2
    line = one_error_line(err)
    assert "mm.mat" in line and fragment in line and "metres" in line
    assert not (tmp_path / "e").exists()


def test_emps_real_data_pass_the_input_checks() -> None:
    if not EMPS_MAT.is_file():
        pytest.skip(f"EMPS data not found at {EMPS_MAT}")
    emps_study.check_study_data(emps.load_emps(EMPS_MAT))


def test_emps_wrong_mat_content_is_an_error(tmp_path: Path) -> None:
    one = {k: np.zeros((1, 1)) for k in ("t", "qg", "qm", "vir")}
    cases: list[tuple[dict[str, object], str]] = [
        ({"qm": np.array(["abc"])}, "variable 'qm' is not numeric"),
        ({"kp": np.array(["fast"])}, "variable 'kp' should be one finite number"),
        (one, "1 samples"),
        ({"qm": np.linspace(0.0, 1.0, 50)[:, None]}, "qm spans 1 but qg spans 0.001"),
    ]
    for i, (override, fragment) in enumerate(cases):
        path = write_emps_mat(tmp_path / f"w{i}.mat", **override)
        with pytest.raises(ValueError, match=fragment):
            emps.load_emps(path)
    # Too short for the study, though loadable.
    data = emps.load_emps(write_emps_mat(tmp_path / "short.mat"))
    with pytest.raises(ValueError, match="at least 100"):
        emps_study.check_study_data(data)


# --------------------------------------------------------------------------------------------
# Signals (subprocesses: the only way to send a real signal to a whole run)
# --------------------------------------------------------------------------------------------

#: Runs the CLI with SIGINT and SIGTERM at their defaults, however the test was launched (a
#: shell starts background jobs with SIGINT ignored, and a child inherits that).
LAUNCH = (
    "import signal, sys; signal.signal(signal.SIGINT, signal.default_int_handler); "
    "signal.signal(signal.SIGTERM, signal.SIG_DFL); from nanostage.cli import main; "
    "sys.exit(main(sys.argv[1:]))"
)


def _start(cwd: Path, argv: list[str], log: Path) -> subprocess.Popen[bytes]:
    env = {**os.environ, "PYTHONIOENCODING": "utf-8", "PYTHONUNBUFFERED": "1"}
    with log.open("wb") as err:
        return subprocess.Popen(
            [sys.executable, "-c", LAUNCH, *argv],
            cwd=cwd,
            stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,
            stderr=err,
            env=env,
        )


def _wait_for(log: Path, marker: str, proc: subprocess.Popen[bytes], timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    while marker not in log.read_text(encoding="utf-8", errors="replace"):
        if proc.poll() is not None:
            pytest.fail(f"the run ended before {marker!r}: {log.read_text(encoding='utf-8')}")
        if time.monotonic() > deadline:
            proc.kill()
            pytest.fail(f"no {marker!r} within {timeout_s} s")
        time.sleep(0.05)


@pytest.mark.skipif(os.name != "posix", reason="POSIX signals")
@pytest.mark.parametrize(
    ("sig", "code", "word"),
    [(signal.SIGTERM, 143, "terminated (SIGTERM)"), (signal.SIGINT, 130, "interrupted")],
)
def test_a_signal_stops_a_campaign_run_and_keeps_the_previous_folder(
    tmp_path: Path, sig: signal.Signals, code: int, word: str
) -> None:
    out = tmp_path / "r"
    assert main(["reproduce", "--out", str(out), "--no-plot"]) == 0
    before = {p.name: p.read_bytes() for p in out.iterdir()}
    log = tmp_path / "err.txt"
    # 20000 trials per campaign: tens of seconds each, far longer than the signal's delay.
    argv = ["reproduce", "--out", "r", "--no-plot", "--campaigns", "--campaign-trials", "20000"]
    proc = _start(tmp_path, argv, log)
    _wait_for(log, "scan 100 µm steps", proc, timeout_s=120)
    time.sleep(0.5)  # inside the first campaign
    t0 = time.monotonic()
    proc.send_signal(sig)
    got = proc.wait(timeout=120)  # a generous bound on something that would otherwise hang
    stop_s = time.monotonic() - t0
    err = log.read_text(encoding="utf-8")
    assert got == code, err
    assert err.strip().splitlines()[-1] == f"nanostage reproduce: {word}"
    assert "Traceback" not in err
    assert {p.name: p.read_bytes() for p in out.iterdir()} == before
    assert leftovers(tmp_path) == []
    print(f"stopped {stop_s:.2f} s after {sig.name}")


@pytest.mark.skipif(os.name != "posix", reason="POSIX signals")
def test_sigterm_stops_tune_with_nothing_written(tmp_path: Path) -> None:
    log = tmp_path / "err.txt"
    argv = ["tune", "--step-um", "100", "--trials", "3000", "--maxiter", "50", "--out", "t"]
    proc = _start(tmp_path, argv, log)
    _wait_for(log, "tuning the 100 µm step", proc, timeout_s=120)
    time.sleep(1.0)
    t0 = time.monotonic()
    proc.send_signal(signal.SIGTERM)
    got = proc.wait(timeout=120)
    stop_s = time.monotonic() - t0
    err = log.read_text(encoding="utf-8")
    assert got == 143, err
    assert err.strip().splitlines()[-1].endswith("nanostage tune: terminated (SIGTERM)")
    assert not (tmp_path / "t").exists() and leftovers(tmp_path) == []
    print(f"stopped {stop_s:.2f} s after SIGTERM")


@pytest.mark.skipif(os.name != "posix", reason="POSIX signals")
def test_sigterm_stops_diagnose_with_nothing_written(tmp_path: Path) -> None:
    manifest, _ = benchmark.generate_case("offset_force", 5, tmp_path / "case")
    log = tmp_path / "err.txt"
    proc = _start(tmp_path, ["diagnose", str(manifest), "--out", "d"], log)
    _wait_for(log, "round 1 [2/", proc, timeout_s=300)
    t0 = time.monotonic()
    proc.send_signal(signal.SIGTERM)
    got = proc.wait(timeout=120)
    stop_s = time.monotonic() - t0
    err = log.read_text(encoding="utf-8")
    assert got == 143, err
    assert err.strip().splitlines()[-1] == "nanostage diagnose: terminated (SIGTERM)"
    assert not (tmp_path / "d").exists() and leftovers(tmp_path) == []
    print(f"stopped {stop_s:.2f} s after SIGTERM")


POOL_SCRIPT = textwrap.dedent(
    """
    import dataclasses, multiprocessing, os, sys, threading
    from concurrent.futures import ProcessPoolExecutor
    from nanostage import cycles, effects, presets, tune
    from nanostage.campaign import run_campaign

    base = presets.seed(100e-6)
    system = dataclasses.replace(
        base,
        effects=dataclasses.replace(
            base.effects, stochastic=effects.StochasticFriction(level_spread=0.1)
        ),
    )
    with ProcessPoolExecutor(2, mp_context=multiprocessing.get_context("fork")) as ex:
        def report():
            if len(ex._processes) < 2:  # the pool starts its workers on the first submit
                threading.Timer(0.2, report).start()
                return
            with open(sys.argv[1] + ".tmp", "w") as f:
                f.write(" ".join(str(p) for p in ex._processes))
            os.replace(sys.argv[1] + ".tmp", sys.argv[1])
        threading.Timer(1.0, report).start()
        if sys.argv[2] == "campaign":
            cycle = cycles.step_cycle(
                step_m=100e-6, repeats=10000, dwell_s=0.5, return_s=0.5, sample_period_s=1e-3
            )
            run_campaign(system, cycle, n_trials=8, executor=ex, chunk_trials=1, progress=False)
        else:
            tune.tune(
                system,
                tune.tuning_cycle(100e-6),
                objective=tune.Objective.mix(),
                n_trials=3000,
                popsize=4,
                maxiter=50,
                executor=ex,
                progress=False,
            )
    """
)


def _alive(pid: int) -> bool:
    try:
        status = Path(f"/proc/{pid}/status").read_text(encoding="utf-8")
    except (FileNotFoundError, ProcessLookupError):
        return False
    return "\nState:\tZ" not in status  # a zombie has exited


def _describe(pid: int) -> str:
    """A live process's state, parent and what each of its threads waits in (from /proc),
    for the message of a failed assertion."""
    try:
        status = Path(f"/proc/{pid}/status").read_text(encoding="utf-8").splitlines()
        lines = [ln for ln in status if ln.split(":")[0] in ("State", "PPid", "Threads")]
        for task in sorted(Path(f"/proc/{pid}/task").iterdir()):
            wchan = (task / "wchan").read_text(encoding="utf-8").strip()
            lines.append(f"thread {task.name} waits in {wchan or '-'}")
    except OSError as exc:
        return f"process {pid}: {exc}"
    return f"process {pid}: " + "; ".join(lines)


def _pids_written(
    path: Path, proc: subprocess.Popen[bytes], log: Path, deadline: float
) -> list[int]:
    """The process ids a script writes to ``path`` once its processes have started."""
    while not (path.exists() and path.read_text(encoding="utf-8").strip()):
        assert proc.poll() is None, log.read_text(encoding="utf-8")
        assert time.monotonic() < deadline, f"the script wrote no {path.name}"
        time.sleep(0.05)
    return [int(p) for p in path.read_text(encoding="utf-8").split()]


def _threads(pid: int) -> int:
    return len(list(Path(f"/proc/{pid}/task").iterdir()))


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="fork and /proc")
@pytest.mark.parametrize(
    ("what", "sig"),
    [("campaign", signal.SIGTERM), ("campaign", signal.SIGKILL), ("tune", signal.SIGTERM)],
)
def test_pool_workers_exit_with_the_campaign_process(
    tmp_path: Path, what: str, sig: signal.Signals
) -> None:
    script = tmp_path / "pool.py"
    script.write_text(POOL_SCRIPT, encoding="utf-8")
    pids_file = tmp_path / "pids.txt"
    log = tmp_path / "err.txt"
    with log.open("wb") as err:
        proc = subprocess.Popen(
            [sys.executable, str(script), str(pids_file), what],
            stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,
            stderr=err,
        )
    workers: list[int] = []
    try:
        deadline = time.monotonic() + 120
        workers = _pids_written(pids_file, proc, log, deadline)
        assert len(workers) == 2 and all(_alive(p) for p in workers)
        # A worker watches its parent from its first chunk on, in a thread of its own: wait
        # until both have one. (CPU time alone does not tell: unpickling the first chunk's
        # cycle takes a few tenths of a second.)
        while min(_threads(p) for p in workers) < 2:
            assert proc.poll() is None, log.read_text(encoding="utf-8")
            assert time.monotonic() < deadline, "the workers did not start computing"
            time.sleep(0.05)
        proc.send_signal(sig)  # the campaign's process dies at once, no clean-up runs
        proc.wait(timeout=60)
        deadline = time.monotonic() + 30  # workers poll their parent every 0.2 s
        while any(_alive(p) for p in workers) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert not any(_alive(p) for p in workers), "\n".join(
            [_describe(p) for p in workers if _alive(p)] + [log.read_text(encoding="utf-8")]
        )
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        for p in workers:  # after a failure: leave no worker behind
            if _alive(p):
                os.kill(p, signal.SIGKILL)


LATE_SCRIPT = textwrap.dedent(
    """
    import multiprocessing, os, sys, time
    from nanostage import cycles, presets
    from nanostage.campaign import _run_chunk

    def work(parent_pid, release):
        # A pool worker that takes a chunk from its queue after the campaign's process died.
        while not os.path.exists(release):
            time.sleep(0.02)
        cycle = cycles.step_cycle(
            step_m=100e-6, repeats=2, dwell_s=0.2, return_s=0.2, sample_period_s=1e-3
        )
        system = presets.seed(100e-6)
        _run_chunk(system, cycle.reference_m, cycle.measure_index, 0, 1, 0, 1, parent_pid)
        time.sleep(600)  # then it waits for the next chunk, for ever

    if __name__ == "__main__":
        ctx = multiprocessing.get_context(sys.argv[3])
        worker = ctx.Process(target=work, args=(os.getpid(), sys.argv[2]))
        worker.start()
        # An idle sibling started after it (a pool worker that never got a chunk): forked, it
        # holds the pipe through which the worker would see its parent exit.
        sibling = ctx.Process(target=time.sleep, args=(600,))
        sibling.start()
        with open(sys.argv[1] + ".tmp", "w") as f:
            f.write(f"{worker.pid} {sibling.pid}")
        os.replace(sys.argv[1] + ".tmp", sys.argv[1])
        time.sleep(600)
    """
)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="fork and /proc")
@pytest.mark.parametrize("start_method", ["fork", "spawn", "forkserver"])
def test_a_worker_that_takes_a_chunk_after_the_campaign_process_died_exits(
    tmp_path: Path, start_method: str
) -> None:
    script = tmp_path / "late.py"
    script.write_text(LATE_SCRIPT, encoding="utf-8")
    pid_file, release = tmp_path / "pid.txt", tmp_path / "release"
    log = tmp_path / "err.txt"
    with log.open("wb") as err:
        proc = subprocess.Popen(
            [sys.executable, str(script), str(pid_file), str(release), start_method],
            stdin=subprocess.DEVNULL,
            stdout=subprocess.DEVNULL,
            stderr=err,
        )
    worker = sibling = 0
    try:
        worker, sibling = _pids_written(pid_file, proc, log, time.monotonic() + 120)
        proc.kill()
        proc.wait(timeout=60)
        assert _alive(worker)
        release.touch()  # the worker takes its chunk now, its parent dead
        deadline = time.monotonic() + 60
        while _alive(worker) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert not _alive(worker), _describe(worker) + "\n" + log.read_text(encoding="utf-8")
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
        for p in (worker, sibling):
            if p and _alive(p):
                os.kill(p, signal.SIGKILL)
