"""Input files of ``diagnose`` and ``predict``: confinement, size limits, one validation
discipline, unit sanity and encodings. Each bad input must give its own error type with a
message naming the key, file, value or limit; valid inputs read as before."""

from __future__ import annotations

import csv
import json
import os
import re
from pathlib import Path
from typing import Any, TypeVar

import numpy as np
import pytest

import nanostage
from nanostage import presets
from nanostage.cli import main
from nanostage.diagnosis import (
    ManifestError,
    TraceError,
    TraceLimits,
    load_manifest,
    load_prediction_manifest,
    read_prediction_trace,
    read_trace,
    write_trace_csv,
)
from nanostage.diagnosis.predict import PredictError, predict, read_prediction_input
from nanostage.experiment import Experiment

SEED_TRAVEL_M = 0.05
E = TypeVar("E", bound=BaseException)


# --------------------------------------------------------------------------------------------
# Helpers
# --------------------------------------------------------------------------------------------


def step_trace(
    n: int = 200, step: float = 100e-6, *, position: bool = True, scale: float = 1.0
) -> str:
    """CSV text of a 1 ms step: time, reference (and a position following it), lengths
    multiplied by ``scale``."""
    header = "time_s,reference_m,position_m" if position else "time_s,reference_m"
    rows = [header]
    for k in range(n):
        ref = step if k >= 20 else 0.0
        pos = step * min(1.0, max(0.0, (k - 20) / 30.0))
        cells = [repr(k * 1e-3), repr(ref * scale)] + ([repr(pos * scale)] if position else [])
        rows.append(",".join(cells))
    return "\n".join(rows) + "\n"


def write(path: Path, text: str) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text, encoding="utf-8")
    return path


def diag_manifest(folder: Path, *experiments: str, model: str = "") -> Path:
    """A diagnosis manifest of the seed preset with the given [[experiment]] bodies."""
    body = '[model]\npreset = "seed"\n' + model
    for e in experiments:
        body += "\n[[experiment]]\n" + e + "\n"
    return write(folder / "diag.toml", body)


def pred_manifest(folder: Path, *experiments: str, head: str = "") -> Path:
    body = head or '[model]\npreset = "seed"\n'
    for e in experiments:
        body += "\n[[experiment]]\n" + e + "\n"
    return write(folder / "predict.toml", body)


def raised(kind: type[E], fn: Any, *args: Any, **kwargs: Any) -> E:
    """The exception ``fn(*args, **kwargs)`` raises (it must raise ``kind``)."""
    with pytest.raises(kind) as info:
        fn(*args, **kwargs)
    return info.value


def one_line(msg: str) -> None:
    assert "\n" not in msg and len(msg) < 1000, msg


# --------------------------------------------------------------------------------------------
# Confinement
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("name", "needle"),
    [
        ("../../x", "name = '../../x' cannot be a file name"),
        ("a/b", "name = 'a/b' cannot be a file name"),
        ("..", "name = '..' cannot be a file name"),
        (".hidden", "name = '.hidden' cannot be a file name"),
        ("", "expected a non-empty string"),
    ],
)
def test_predict_rejects_unsafe_experiment_names_before_any_work(
    tmp_path: Path, name: str, needle: str
) -> None:
    root = tmp_path / "a" / "b"
    write(root / "s.csv", step_trace())
    m = pred_manifest(root, f'name = "{name}"\nfile = "s.csv"')
    out = root / "out"
    with pytest.raises(PredictError) as info:
        predict(m, out)
    msg = str(info.value)
    assert "predict.toml" in msg and "key 'experiment[0].name'" in msg and needle in msg
    one_line(msg)
    assert not out.exists() and not (tmp_path / "x").exists() and not (tmp_path / "x.csv").exists()
    assert sorted(p.name for p in tmp_path.rglob("*")) == ["a", "b", "predict.toml", "s.csv"]


def test_predict_rejects_duplicate_names_case_insensitively(tmp_path: Path) -> None:
    write(tmp_path / "s.csv", step_trace())
    m = pred_manifest(tmp_path, 'name = "Step"\nfile = "s.csv"', 'name = "step"\nfile = "s.csv"')
    with pytest.raises(PredictError) as info:
        predict(m, tmp_path / "out")
    msg = str(info.value)
    assert "key 'experiment[1].name'" in msg and "'step' is a duplicate of 'Step'" in msg
    assert not (tmp_path / "out").exists()


def _outside_cases(tmp_path: Path) -> tuple[Path, Path]:
    """A folder with a manifest, and a trace beside the folder (outside it)."""
    root = tmp_path / "project"
    root.mkdir()
    outside = write(tmp_path / "outside.csv", step_trace())
    return root, outside


@pytest.mark.parametrize("how", ["dotdot", "absolute", "symlink"])
def test_trace_files_must_resolve_inside_the_manifests_folder(tmp_path: Path, how: str) -> None:
    root, outside = _outside_cases(tmp_path)
    if how == "dotdot":
        rel = "../outside.csv"
    elif how == "absolute":
        rel = str(outside)
    else:
        (root / "link.csv").symlink_to(outside)
        rel = "link.csv"
    m = diag_manifest(root, f'name = "x"\nfile = "{rel}"')
    with pytest.raises(ManifestError) as info:
        load_manifest(m)
    err = info.value
    assert err.key == "experiment[0].file"
    assert f"resolves to {str(outside)!r}, outside the manifest's folder" in str(err)
    assert "trace_root=" in str(err) and "--trace-root" in str(err)
    one_line(str(err))
    # predict applies the same rule, before anything is written
    p = pred_manifest(root, f'name = "x"\nfile = "{rel}"')
    with pytest.raises(PredictError, match="outside the manifest's folder"):
        predict(p, root / "out")
    assert not (root / "out").exists()
    # ...and an explicit root allows it
    man = load_manifest(m, trace_root=tmp_path)
    assert man.experiment_specs[0].file == outside.resolve()
    assert man.experiments()[0][1].n_samples == 200
    s = predict(p, root / "out", trace_root=tmp_path)
    assert s["experiments"]["x"]["samples"] == 200


def test_model_file_is_confined_too_and_trace_root_must_be_a_folder(tmp_path: Path) -> None:
    root, _ = _outside_cases(tmp_path)
    write(tmp_path / "model.toml", "[plant.table]\nmass_kg = 0.5\n")
    write(root / "s.csv", step_trace())
    m = diag_manifest(root, 'name = "x"\nfile = "s.csv"', model='file = "../model.toml"\n')
    with pytest.raises(ManifestError) as info:
        load_manifest(m)
    assert info.value.key == "model.file" and "outside the manifest's folder" in str(info.value)
    assert load_manifest(m, trace_root=tmp_path).system().plant.table.mass_kg == 0.5
    with pytest.raises(ManifestError, match=r"trace root '.*nope' .* is not a folder"):
        load_manifest(m, trace_root=tmp_path / "nope")


def test_the_cli_option_trace_root(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    root, _ = _outside_cases(tmp_path)
    p = pred_manifest(root, 'name = "x"\nfile = "../outside.csv"')
    assert main(["predict", str(p), "--out", str(root / "o1")]) == 2
    err = capsys.readouterr().err
    assert "outside the manifest's folder" in err and err.count("\n") == 1
    assert not (root / "o1").exists()
    rc = main(["predict", str(p), "--out", str(root / "o2"), "--trace-root", str(tmp_path)])
    assert rc == 0 and (root / "o2" / "x.csv").is_file()


def test_messages_quote_only_a_short_escaped_column_list(tmp_path: Path) -> None:
    secret = "TOKEN-" + "s3cr3t" * 40
    write(tmp_path / "secret.csv", secret + "\nline two\n")
    with pytest.raises(TraceError) as info:
        read_trace(tmp_path / "secret.csv")
    msg = str(info.value)
    assert "missing required column(s)" in msg and "secret.csv" in msg
    assert secret[:32] in msg and secret[:40] not in msg and "line two" not in msg
    # Control characters are escaped, and a long header is cut to a few names.
    header = "\x1b[31mred," + ",".join(f"c{i}" for i in range(40))
    write(tmp_path / "ctrl.csv", header + "\n1,2\n")
    msg = str(raised(TraceError, read_trace, tmp_path / "ctrl.csv"))
    assert "\x1b" not in msg and "\\x1b[31mred" in msg and "(29 more)" in msg
    one_line(msg)
    # predict names unknown columns the same way
    msg = str(raised(PredictError, read_prediction_input, tmp_path / "ctrl.csv"))
    assert "\x1b" not in msg and "ctrl.csv" in msg
    # A bad cell is quoted shortened and escaped
    write(tmp_path / "cell.csv", step_trace().replace("0.001,", "0.001" + "x" * 80 + ",", 1))
    msg = str(raised(TraceError, read_trace, tmp_path / "cell.csv"))
    assert "line 3" in msg and "'0.001xxxxxxxxxxxxxxx'…" in msg and "x" * 30 not in msg


# --------------------------------------------------------------------------------------------
# Size and memory
# --------------------------------------------------------------------------------------------


def test_size_limits_are_validated() -> None:
    assert TraceLimits().max_samples_per_trace == 2_000_000
    assert TraceLimits().bytes_per_trace == 512 * 2_000_000
    with pytest.raises(nanostage.ConfigError, match=r"TraceLimits.max_samples_total = 0 .*≥ 10"):
        TraceLimits(max_samples_total=0)
    with pytest.raises(nanostage.ConfigError, match=r"max_bytes_per_trace = 1\.5"):
        TraceLimits(max_bytes_per_trace=1.5)  # type: ignore[arg-type]


def test_a_file_above_the_byte_limit_is_refused_unread(tmp_path: Path) -> None:
    # A sparse 2 GiB file: refused from its size alone (reading it would take minutes).
    big = tmp_path / "big.csv"
    with big.open("wb") as fh:
        fh.truncate(2**31)
    with pytest.raises(TraceError) as info:
        read_trace(big)
    msg = str(info.value)
    assert "big.csv" in msg and f"the file has {2**31} bytes" in msg
    assert "limit of 1024000000 bytes per trace" in msg and "--max-trace-samples" in msg
    one_line(msg)


def test_ten_million_rows_are_refused_from_an_estimate(tmp_path: Path) -> None:
    path = tmp_path / "long.csv"
    with path.open("wb") as fh:
        fh.write(b"time_s,reference_m,position_m\n")
        fh.write(b"0,0,0\n" * 10_000_000)
    with pytest.raises(TraceError) as info:
        read_trace(path)
    msg = str(info.value)
    assert re.search(r"about 100\d{5} rows \(estimated from its 60000030 bytes\)", msg)
    assert "limit of 2000000 samples per trace" in msg
    assert "TraceLimits(max_samples_per_trace=...)" in msg and "--max-trace-samples" in msg


def test_rows_are_counted_against_the_limit_while_read(tmp_path: Path) -> None:
    path = write(tmp_path / "s.csv", step_trace(n=1200))
    with pytest.raises(TraceError, match=r"more than 1000 rows, above the limit of 1000 samples"):
        read_trace(path, limits=TraceLimits(max_samples_per_trace=1000))
    assert read_trace(path, limits=TraceLimits(max_samples_per_trace=1200)).n_samples == 1200
    with pytest.raises(TraceError, match=r"has \d+ bytes, above the limit of 1000 bytes"):
        read_trace(path, limits=TraceLimits(max_bytes_per_trace=1000))


def test_npz_and_mat_arrays_are_sized_from_their_headers(tmp_path: Path) -> None:
    from scipy.io import savemat

    t = np.arange(3000) * 1e-3
    ref = np.where(t > 0.1, 1e-4, 0.0)
    np.savez(tmp_path / "a.npz", time_s=t, reference_m=ref, position_m=ref)
    savemat(tmp_path / "a.mat", {"time_s": t, "reference_m": ref, "position_m": ref})
    small = TraceLimits(max_samples_per_trace=1000)
    for f in ("a.npz", "a.mat"):
        with pytest.raises(TraceError) as info:
            read_trace(tmp_path / f, limits=small)
        err = info.value
        assert err.column == "time_s" and "3000 values, above the limit of 1000" in str(err)
        assert read_trace(tmp_path / f).n_samples == 3000
    np.save(tmp_path / "one.npy", t)
    os.replace(tmp_path / "one.npy", tmp_path / "one.npz")
    with pytest.raises(TraceError, match=r"not an \.npz archive"):
        read_trace(tmp_path / "one.npz")


def test_the_total_of_a_manifest_is_limited(tmp_path: Path) -> None:
    write(tmp_path / "s.csv", step_trace(n=400))
    exps = [f'name = "e{i}"\nfile = "s.csv"' for i in range(3)]
    m = diag_manifest(tmp_path, *exps)
    with pytest.raises(ManifestError) as info:
        load_manifest(m, limits=TraceLimits(max_samples_total=1000)).experiments()
    err = info.value
    assert err.key == "experiment[2]" and "brings the experiments to 1200 samples" in str(err)
    assert "limit of 1000 samples per manifest" in str(err) and "--max-total-samples" in str(err)
    assert len(load_manifest(m).experiments()) == 3
    p = pred_manifest(tmp_path, *exps)
    with pytest.raises(PredictError, match="above the limit of 1000 samples per manifest"):
        predict(p, tmp_path / "out", limits=TraceLimits(max_samples_total=1000))
    assert not (tmp_path / "out").exists()


def test_cli_limit_options(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    write(tmp_path / "s.csv", step_trace(n=400))
    p = pred_manifest(tmp_path, 'name = "a"\nfile = "s.csv"')
    assert (
        main(["predict", str(p), "--out", str(tmp_path / "o"), "--max-trace-samples", "300"]) == 2
    )
    err = capsys.readouterr().err
    assert "s.csv" in err and "above the limit of 300 samples per trace" in err
    rc = main(["predict", str(p), "--out", str(tmp_path / "o"), "--max-total-samples", "5"])
    assert rc == 2 and "TraceLimits.max_samples_total = 5" in capsys.readouterr().err


def test_a_large_csv_reads_in_blocks_exactly(tmp_path: Path) -> None:
    """Above one parsing block (65 536 rows) the values are those of a whole-file parse and
    a bad cell is still located by its physical line."""
    n = 70_001
    t = np.arange(n) * 1e-3
    ref = np.where(t > 1.0, 1e-3, 0.0)
    pos = ref * (1 - np.exp(-np.maximum(t - 1.0, 0) / 0.01))
    data = np.column_stack([t, ref, pos])
    path = tmp_path / "long.csv"
    np.savetxt(
        path,
        data,
        fmt="%.17g",
        delimiter=",",
        header="# comment\ntime_s,reference_m,position_m",
        comments="",
    )
    exp = read_trace(path)
    np.testing.assert_array_equal(exp.time_s, t)
    np.testing.assert_array_equal(exp.position_m, pos)
    lines = path.read_text().splitlines()
    lines[68_000] = lines[68_000].replace(",", ",?", 1)
    path.write_text("\n".join(lines) + "\n")
    err = raised(TraceError, read_trace, path)
    assert (err.line, err.column, err.sample) == (68_001, "reference_m", 67_998)


# --------------------------------------------------------------------------------------------
# One validation discipline (predict)
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("text", "needle"),
    [
        (
            '[model]\npreset = "seed"\n[model.overides]\n"plant.table.mass_kg" = 1.0\n',
            "key 'model.overides': unknown key (did you mean 'overrides'?)",
        ),
        ('[model]\npreset = "sed"\n', "key 'model.preset': unknown preset 'sed' (did you mean"),
        (
            '[model]\npreset = "seed"\n[model.overrides]\n"plant.table.mas_kg" = 1.0\n',
            "has no field 'mas_kg' (did you mean 'mass_kg'?)",
        ),
        ('[model]\npreset = "seed"\n[diagnosis]\nseed = 1\n', "key 'diagnosis': a diagnosis table"),
        (
            '[model]\npreset = "seed"\nfree = ["plant.table.mass_kg"]\n',
            "key 'model.free': a diagnosis key",
        ),
        (
            '[model]\npreset = "seed"\n[modle]\n',
            "key 'modle': unknown table (did you mean 'model'?)",
        ),
        ('[model]\npreset = "seed"\ntravel_m = -1\n', "key 'model.travel_m': -1 m is invalid"),
    ],
)
def test_predict_manifest_keys_are_checked(tmp_path: Path, text: str, needle: str) -> None:
    write(tmp_path / "s.csv", step_trace())
    m = pred_manifest(tmp_path, 'name = "a"\nfile = "s.csv"', head=text)
    with pytest.raises(PredictError) as info:
        predict(m, tmp_path / "out")
    assert "predict.toml" in str(info.value) and needle in str(info.value)
    assert isinstance(info.value.__cause__, ManifestError)
    one_line(str(info.value))
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize(
    ("exp", "key", "needle"),
    [
        ('name = "a"\nfile = "s.csv"\nrole = "train"', "experiment[0].role", "a diagnosis key"),
        ('name = "a"\nfile = "s.csv"\nfiel = "x"', "experiment[0].fiel", "did you mean 'file'"),
        (
            'name = "a"\nfile = "s.csv"\ncolumns = { command_v = "u" }',
            "experiment[0].columns.command_v",
            "unknown standard column 'command_v'",
        ),
        (
            'name = "a"\nfile = "s.csv"\nunits = "inch"',
            "experiment[0].units",
            "unknown length unit 'inch'",
        ),
        (
            'name = "a"\nfile = "s.csv"\nunits = { disturbance_v = "mV" }',
            "experiment[0].units.disturbance_v",
            "no unit can be declared for 'disturbance_v'",
        ),
        (
            'name = "a"\nfile = "s.csv"\nunits = { time_s = "mm" }',
            "experiment[0].units.time_s",
            "unknown unit 'mm' for time_s",
        ),
    ],
)
def test_prediction_experiment_keys_are_checked(
    tmp_path: Path, exp: str, key: str, needle: str
) -> None:
    write(tmp_path / "s.csv", step_trace())
    m = pred_manifest(tmp_path, exp)
    with pytest.raises(ManifestError) as info:
        load_prediction_manifest(m)
    assert info.value.key == key and needle in str(info.value)


def _pred_trace_error(tmp_path: Path, text: str) -> str:
    write(tmp_path / "s.csv", text)
    m = pred_manifest(tmp_path, 'name = "a"\nfile = "s.csv"')
    with pytest.raises(PredictError) as info:
        predict(m, tmp_path / "out")
    assert isinstance(info.value.__cause__, TraceError)
    assert not (tmp_path / "out").exists()
    msg = str(info.value)
    assert "s.csv" in msg and "experiment 'a'" in msg
    one_line(msg)
    return msg


def test_predict_traces_get_the_diagnosis_checks(tmp_path: Path) -> None:
    good = step_trace(position=False).splitlines()
    # a gap (one missing sample)
    gap = good[:50] + good[51:]
    msg = _pred_trace_error(tmp_path, "\n".join(gap))
    assert "line 51, column 'time_s'" in msg and "2 times the median step 0.001 s" in msg
    assert "a gap or jitter" in msg
    # non-monotonic
    back = [*good]
    back[30] = back[30].replace("0.029", "0.0275", 1)
    msg = _pred_trace_error(tmp_path, "\n".join(back))
    assert "column 'time_s'" in msg and ("not strictly increasing" in msg or "gap" in msg)
    # non-finite
    bad = [*good]
    bad[40] = bad[40].split(",")[0] + ",inf"
    msg = _pred_trace_error(tmp_path, "\n".join(bad))
    assert "line 41, column 'reference_m'" in msg and "not a finite number" in msg
    # misspelt optional column
    msg = _pred_trace_error(tmp_path, step_trace().replace("position_m", "positon_m", 1))
    assert "unknown column(s) positon_m (did you mean 'position_m'?)" in msg
    # fewer than 10 samples
    msg = _pred_trace_error(tmp_path, "\n".join(good[:6]))
    assert "only 5 sample(s)" in msg
    # sampled at another period than the controller's
    slow = step_trace(position=False).replace("time_s", "t_ms", 1)
    write(tmp_path / "s.csv", slow)
    m = pred_manifest(tmp_path, 'name = "a"\nfile = "s.csv"\ncolumns = { time_s = "t_ms" }')
    assert predict(m, tmp_path / "o")["experiments"]["a"]["samples"] == 200


def test_a_gap_in_a_diagnosis_trace_is_an_error(tmp_path: Path) -> None:
    lines = step_trace().splitlines()
    del lines[100:103]
    path = write(tmp_path / "g.csv", "\n".join(lines))
    err = raised(TraceError, read_trace, path)
    assert (err.line, err.column) == (101, "time_s") and "4 times the median step" in str(err)
    # jitter within ±50 % passes
    rows = [f"{(k + 0.3 * (k % 2)) * 1e-3!r},{1e-4 if k > 5 else 0.0},0.0" for k in range(40)]
    exp = read_trace(write(tmp_path / "j.csv", "time_s,reference_m,position_m\n" + "\n".join(rows)))
    assert exp.n_samples == 40


def test_predict_writes_strict_json_volts_and_nothing_else(tmp_path: Path) -> None:
    # A 0.5 mm step of the seed axis saturates the drive: command at the 6 V limit.
    text = step_trace(n=300, step=0.5e-3, position=False)
    # a measurement that is zero throughout: the relative error is undefined (null)
    rows = text.splitlines()
    text = "\n".join([rows[0] + ",position_m"] + [r + ",0.0" for r in rows[1:]])
    write(tmp_path / "s.csv", text)
    m = pred_manifest(tmp_path, 'name = "step-0.5mm"\nfile = "s.csv"')
    out = tmp_path / "out"
    s = predict(m, out)
    entry = s["experiments"]["step-0.5mm"]
    assert entry["position_relative_error"] is None and entry["samples"] == 300

    def no_constant(name: str) -> Any:
        raise AssertionError(f"non-standard JSON token {name}")

    saved = json.loads((out / "predict.json").read_text(), parse_constant=no_constant)
    assert saved["experiments"]["step-0.5mm"]["position_relative_error"] is None
    assert sorted(p.name for p in out.iterdir()) == [
        "nanostage-run.json",
        "predict.json",
        "step-0.5mm.csv",
    ]
    with (out / "step-0.5mm.csv").open() as fh:
        table = list(csv.DictReader(fh))
    command_v = np.array([float(r["command_v"]) for r in table])
    system = presets.seed()
    ref = np.array([float(r["reference_m"]) for r in table])
    tr = nanostage.simulate(system, ref, initial_position_m=0.0)
    np.testing.assert_array_equal(command_v, tr.command * tr.output_unit_v)
    assert np.max(np.abs(command_v)) == pytest.approx(system.output_stage.amplifier_limit_v)
    assert np.max(np.abs(command_v)) <= 6.0 + 1e-9


def test_a_reference_of_ten_metres_is_implausible(tmp_path: Path) -> None:
    write(tmp_path / "s.csv", step_trace(step=10.0, position=False))
    m = pred_manifest(tmp_path, 'name = "a"\nfile = "s.csv"')
    with pytest.raises(PredictError) as info:
        predict(m, tmp_path / "out")
    msg = str(info.value)
    assert "column 'reference_m': peak-to-peak 10 m exceeds the axis travel of 0.05 m" in msg
    assert 'units = "mm"' in msg
    # a constant 10 (no move) is as implausible: 200 travels from the origin
    rows = ["time_s,reference_m"] + [f"{k * 1e-3!r},10.0" for k in range(50)]
    write(tmp_path / "s.csv", "\n".join(rows))
    with pytest.raises(PredictError, match=r"value 10 m lies more than 10 axis travels \(0.5 m\)"):
        predict(m, tmp_path / "out")


def test_a_valid_prediction_manifest_with_every_option(tmp_path: Path) -> None:
    """units, a column map, a window and controller gains: read as declared."""
    text = step_trace(n=400, step=0.2, position=False)  # a 0.2 mm step written in mm
    write(tmp_path / "data" / "mm.csv", text.replace("reference_m", "ref", 1))
    head = (
        '[model]\npreset = "seed"\ntravel_m = 0.05\n[model.overrides]\n'
        '"plant.table.mass_kg" = 0.9\n[controller]\nkp = 400.0\n'
    )
    m = pred_manifest(
        tmp_path,
        'name = "w"\nfile = "data/mm.csv"\nunits = "mm"\ncolumns = { reference_m = "ref" }\n'
        "window_s = [0.0, 0.3]",
        head=head,
    )
    man = load_prediction_manifest(m)
    assert man.purpose == "predict" and man.model.travel_m == 0.05
    assert man.system(man.experiment_specs[0]).controller.kp == 400.0
    s = predict(m, tmp_path / "out")
    assert s["experiments"]["w"]["samples"] == 300
    out = np.genfromtxt(tmp_path / "out" / "w.csv", delimiter=",", names=True)
    assert np.max(out["reference_m"]) == pytest.approx(0.2e-3, rel=1e-12)
    # run again into the same folder: the earlier run's output is replaced whole
    predict(m, tmp_path / "out")
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == [
        "nanostage-run.json",
        "predict.json",
        "w.csv",
    ]


def test_predict_reads_npz_traces_and_leaves_other_arrays_alone(tmp_path: Path) -> None:
    t = np.arange(200) * 1e-3
    ref = np.where(t > 0.02, 1e-4, 0.0)
    np.savez(tmp_path / "s.npz", time_s=t, reference_m=ref, gain=np.array([2.0]))
    m = pred_manifest(tmp_path, 'name = "a"\nfile = "s.npz"')
    assert predict(m, tmp_path / "out")["experiments"]["a"]["samples"] == 200
    out = np.genfromtxt(tmp_path / "out" / "a.csv", delimiter=",", names=True)
    np.testing.assert_array_equal(out["reference_m"], ref)


def test_predict_checks_the_output_folder_before_any_work(tmp_path: Path) -> None:
    write(tmp_path / "s.csv", step_trace())
    m = pred_manifest(tmp_path, 'name = "a"\nfile = "s.csv"')
    write(tmp_path / "taken" / "mine.txt", "keep")
    with pytest.raises(PredictError, match="is a folder of other files"):
        predict(m, tmp_path / "taken")
    assert [p.name for p in (tmp_path / "taken").iterdir()] == ["mine.txt"]


# --------------------------------------------------------------------------------------------
# Unit sanity of diagnosis traces
# --------------------------------------------------------------------------------------------


def test_a_diagnosis_trace_in_millimetres_is_an_error_with_the_fix(tmp_path: Path) -> None:
    # A 0.5 mm step with every length written in mm: 0.5 "m" on a 50 mm axis.
    write(tmp_path / "mm.csv", step_trace(step=0.5e-3, scale=1e3))
    m = diag_manifest(tmp_path, 'name = "x"\nfile = "mm.csv"')
    man = load_manifest(m)
    with pytest.raises(ManifestError) as info:
        man.experiments()
    err = info.value
    cause = err.__cause__
    assert isinstance(cause, TraceError) and cause.column == "reference_m"
    msg = str(err)
    assert "mm.csv" in msg and "peak-to-peak 0.5 m exceeds the axis travel of 0.05 m" in msg
    assert 'declare the unit (units = "mm"' in msg
    # The declared unit reads it correctly.
    m = diag_manifest(tmp_path, 'name = "x"\nfile = "mm.csv"\nunits = "mm"')
    exp = load_manifest(m).experiments()[0][1]
    assert np.max(exp.reference_m) == pytest.approx(0.5e-3, rel=1e-12)
    assert np.max(exp.position_m) == pytest.approx(0.5e-3, rel=1e-12)
    # per column, and the same through read_trace
    write(tmp_path / "um.csv", step_trace(scale=1e6).replace("reference_m", "r", 1))
    exp = read_trace(
        tmp_path / "um.csv",
        columns={"reference_m": "r"},
        units={"reference_m": "um", "position_m": "µm"},
        travel_m=SEED_TRAVEL_M,
    )
    assert np.max(exp.reference_m) == pytest.approx(100e-6, rel=1e-12)


def test_a_small_mm_move_far_from_the_origin_is_caught(tmp_path: Path) -> None:
    # 10 µm steps at 20 mm, in mm: the peak-to-peak (0.01) fits the travel, the values not.
    rows = ["time_s,reference_m,position_m"]
    for k in range(100):
        r = 20.0 + (0.01 if k > 10 else 0.0)
        rows.append(f"{k * 1e-3!r},{r!r},{20.0 + 0.01 * min(1.0, max(0, k - 10) / 20)!r}")
    write(tmp_path / "far.csv", "\n".join(rows))
    err = raised(TraceError, read_trace, tmp_path / "far.csv", travel_m=0.05)
    assert err.column == "reference_m" and "lies more than 10 axis travels (0.5 m)" in str(err)
    assert read_trace(tmp_path / "far.csv", units="mm", travel_m=0.05).n_samples == 100


def test_model_travel_sets_the_scale(tmp_path: Path) -> None:
    write(tmp_path / "s.csv", step_trace(step=0.08))  # an 80 mm move: beyond the seed's travel
    m = diag_manifest(tmp_path, 'name = "x"\nfile = "s.csv"')
    with pytest.raises(ManifestError, match=r"axis travel of 0\.05 m"):
        load_manifest(m).experiments()
    m = diag_manifest(tmp_path, 'name = "x"\nfile = "s.csv"', model="travel_m = 0.1\n")
    assert load_manifest(m).experiments()[0][1].n_samples == 200
    m = diag_manifest(tmp_path, 'name = "x"\nfile = "s.csv"', model="travel_m = 50\n")
    with pytest.raises(ManifestError) as info:
        load_manifest(m)
    assert info.value.key == "model.travel_m" and "(0, 10]" in str(info.value)


# --------------------------------------------------------------------------------------------
# Encodings and unreadable files
# --------------------------------------------------------------------------------------------


def test_non_utf8_files_name_the_byte_offset(tmp_path: Path) -> None:
    text = step_trace().encode()
    offset = text.index(b"\n", 100) + 3  # inside line 4
    line = text[:offset].count(b"\n") + 1
    bad = text[:offset] + b"\xff" + text[offset:]
    (tmp_path / "latin.csv").write_bytes(bad)
    err = raised(TraceError, read_trace, tmp_path / "latin.csv")
    assert err.line == line and f"offset {offset}" in str(err) and "not UTF-8" in str(err)
    one_line(str(err))
    # far into the file (beyond the reader's first decoded block)
    big = step_trace(n=20_000).encode()
    off2 = len(big) - 50
    (tmp_path / "late.csv").write_bytes(big[:off2] + b"\xe9" + big[off2:])
    err = raised(TraceError, read_trace, tmp_path / "late.csv")
    assert f"offset {off2}" in str(err) and err.line == big[:off2].count(b"\n") + 1
    # predict
    (tmp_path / "s.csv").write_bytes(bad)
    m = pred_manifest(tmp_path, 'name = "a"\nfile = "s.csv"')
    with pytest.raises(
        PredictError, match=rf"s.csv: line {line}: not UTF-8 text: .*offset {offset}"
    ):
        predict(m, tmp_path / "out")
    # a manifest
    (tmp_path / "m.toml").write_bytes(b'[model]\npreset = "s\xe9ed"\n')
    with pytest.raises(ManifestError) as info:
        load_manifest(tmp_path / "m.toml")
    assert info.value.line == 2 and "offset 19" in str(info.value)
    with pytest.raises(PredictError, match=r"m\.toml, line 2: not UTF-8 text"):
        predict(tmp_path / "m.toml", tmp_path / "out")


def test_binary_and_unreadable_files(tmp_path: Path) -> None:
    (tmp_path / "nul.csv").write_bytes(b"time_s,reference_m,position_m\n0,0\x00,0\n")
    err = raised(TraceError, read_trace, tmp_path / "nul.csv")
    assert "cannot parse '0\\x00' as a number" in str(err) and err.line == 2
    (tmp_path / "blob.csv").write_bytes(b"time_s,reference_m,position_m\n" + b"7" * 200_000)
    err = raised(TraceError, read_trace, tmp_path / "blob.csv")
    assert "not a readable CSV file (field larger than field limit" in str(err)
    assert "777" not in str(err)
    if os.geteuid() != 0:  # root reads anything
        p = write(tmp_path / "locked.csv", step_trace())
        p.chmod(0)
        err = raised(TraceError, read_trace, p)
        assert "cannot read the file" in str(err)


# --------------------------------------------------------------------------------------------
# Valid inputs read as before
# --------------------------------------------------------------------------------------------


def test_a_valid_diagnosis_manifest_reads_as_before(tmp_path: Path) -> None:
    tr = nanostage.simulate_step(presets.seed(1e-4), 1e-4, duration_s=0.3)
    exp = Experiment(
        name="s",
        time_s=tr.time_s,
        reference_m=tr.reference_m,
        position_m=tr.encoder_position_m,
        command_v=tr.motor_voltage_v,
    )
    write_trace_csv(exp, tmp_path / "t" / "s.csv")
    m = diag_manifest(tmp_path, 'name = "s"\nfile = "t/s.csv"')
    man = load_manifest(m)
    assert man.purpose == "diagnose" and man.model.travel_m == SEED_TRAVEL_M
    back = man.experiments()[0][1]
    for c in ("time_s", "reference_m", "position_m", "command_v"):
        np.testing.assert_array_equal(getattr(back, c), getattr(exp, c))
    pred = read_prediction_trace(write(tmp_path / "p.csv", step_trace()), travel_m=SEED_TRAVEL_M)
    assert sorted(pred) == ["position_m", "reference_m", "time_s"]
