"""LabVIEW TDMS traces (npTDMS): read through the manifest exactly as the same data in CSV."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import nanostage
from nanostage.diagnosis import (
    ManifestError,
    TraceError,
    TraceLimits,
    load_manifest,
    read_prediction_trace,
    read_trace,
)
from nanostage.diagnosis.predict import PredictError, predict

nptdms = pytest.importorskip("nptdms")

GROUP = "Measurements"


def _step() -> dict[str, np.ndarray]:
    """A simulated seed step: time on an exact waveform grid, reference, position, command."""
    tr = nanostage.simulate_step(nanostage.presets.seed(100e-6), 100e-6, duration_s=0.2)
    dt = float(tr.time_s[1] - tr.time_s[0])
    n = len(tr.time_s)
    return {
        "time_s": 0.0 + dt * np.arange(n, dtype=np.float64),
        "reference_m": np.asarray(tr.reference_m, dtype=np.float64),
        "position_m": np.asarray(tr.encoder_position_m, dtype=np.float64),
        "command_v": np.asarray(tr.motor_voltage_v, dtype=np.float64),
    }


def _write_csv(path: Path, data: dict[str, np.ndarray]) -> Path:
    cols = list(data)
    np.savetxt(
        path, np.column_stack(list(data.values())), fmt="%.17g", delimiter=",",
        header=",".join(cols), comments="",
    )  # fmt: skip
    return path


def _write_tdms(
    path: Path, channels: dict[tuple[str, str], tuple[np.ndarray, dict[str, Any]]]
) -> Path:
    objs = [
        nptdms.ChannelObject(g, c, data, properties=props)
        for (g, c), (data, props) in channels.items()
    ]
    with nptdms.TdmsWriter(str(path)) as w:
        w.write_segment(objs)
    return path


def _waveform_file(path: Path, data: dict[str, np.ndarray], **extra: Any) -> Path:
    """Reference, position and command as LabVIEW waveforms (no time channel)."""
    wf = {"wf_increment": float(data["time_s"][1]), "wf_start_offset": 0.0, **extra}
    return _write_tdms(
        path,
        {
            (GROUP, "Setpoint"): (data["reference_m"], wf),
            ("Encoder", "Position"): (data["position_m"], wf),
            (GROUP, "Drive"): (data["command_v"], wf),
        },
    )


WAVEFORM_MAP = (
    'columns = { reference_m = "Setpoint", position_m = "Encoder/Position", '
    'command_v = "Drive" }\ngroup = "Measurements"\n'
)


def _manifest(root: Path, file: str, extra: str = "") -> Path:
    (root / "m.toml").write_text(
        f'[model]\npreset = "seed"\n\n[[experiment]]\nname = "x"\nfile = "{file}"\n{extra}'
    )
    return root / "m.toml"


def _read_one(manifest: Path, **kw: Any) -> nanostage.experiment.Experiment:
    ((_, exp),) = load_manifest(manifest, **kw).experiments()
    return exp


def _same(a: nanostage.experiment.Experiment, b: nanostage.experiment.Experiment) -> None:
    for col in ("time_s", "reference_m", "position_m", "command_v"):
        np.testing.assert_array_equal(getattr(a, col), getattr(b, col))
    assert a.interferometer_m is None and b.interferometer_m is None


def test_waveform_channels_read_as_the_same_csv(tmp_path: Path) -> None:
    data = _step()
    _write_csv(tmp_path / "x.csv", data)
    _waveform_file(tmp_path / "x.tdms", data)
    csv = _read_one(_manifest(tmp_path, "x.csv"))
    tdms = _read_one(_manifest(tmp_path, "x.tdms", WAVEFORM_MAP))
    _same(tdms, csv)


def test_time_channel_units_and_window_as_csv(tmp_path: Path) -> None:
    data = _step()
    in_mm = {"t_ms": data["time_s"] * 1e3, "ref": data["reference_m"] * 1e3}
    in_mm |= {"pos": data["position_m"] * 1e3, "cmd": data["command_v"]}
    _write_csv(tmp_path / "x.csv", in_mm)
    _write_tdms(tmp_path / "x.tdms", {("Log", k): (v, {}) for k, v in in_mm.items()})
    spec = (
        'columns = { time_s = "%s", reference_m = "%s", position_m = "%s", command_v = "%s" }\n'
        'units = { reference_m = "mm", position_m = "mm", time_s = "ms" }\n'
        "window_s = [0.0, 0.1]\n"
    )
    csv = _read_one(_manifest(tmp_path, "x.csv", spec % ("t_ms", "ref", "pos", "cmd")))
    tdms = _read_one(_manifest(tmp_path, "x.tdms", spec % ("Log/t_ms", "ref", "pos", "cmd")))
    _same(tdms, csv)
    assert tdms.time_s[-1] < 0.1


def test_unmapped_standard_channel_names_are_found(tmp_path: Path) -> None:
    data = _step()
    _write_tdms(tmp_path / "x.tdms", {(GROUP, k): (v, {}) for k, v in data.items()})
    exp = read_trace(tmp_path / "x.tdms")
    np.testing.assert_array_equal(exp.position_m, data["position_m"])
    np.testing.assert_array_equal(exp.time_s, data["time_s"])


def test_predict_reads_tdms_like_csv(tmp_path: Path) -> None:
    data = _step()
    del data["command_v"]
    _write_csv(tmp_path / "x.csv", data)
    wf = {"wf_increment": float(data["time_s"][1])}
    _write_tdms(
        tmp_path / "x.tdms",
        {
            (GROUP, "reference_m"): (data["reference_m"], wf),
            (GROUP, "Pos"): (data["position_m"], wf),
        },
    )
    a = predict(_manifest(tmp_path, "x.csv"), tmp_path / "a")
    b = predict(_manifest(tmp_path, "x.tdms", 'columns = { position_m = "Pos" }\n'), tmp_path / "b")
    assert (
        a["experiments"]["x"]["samples"] == b["experiments"]["x"]["samples"] == len(data["time_s"])
    )
    assert (tmp_path / "a" / "x.csv").read_bytes() == (tmp_path / "b" / "x.csv").read_bytes()
    cols = read_prediction_trace(tmp_path / "x.tdms", columns={"position_m": "Measurements/Pos"})
    np.testing.assert_array_equal(cols["time_s"], data["time_s"])


@pytest.mark.parametrize(
    ("spec", "expected"),
    [
        (
            'columns = { reference_m = "Setpoint", position_m = "Encoder/Positon" }\n',
            "channel 'Positon' of group 'Encoder', which the group does not have "
            "(did you mean 'Position'?)",
        ),
        (
            'columns = { reference_m = "Setpoint", position_m = "Encodr/Position" }\n',
            "group 'Encodr', which the file does not have (did you mean 'Encoder'?)",
        ),
        (
            'columns = { reference_m = "Setpont", position_m = "Encoder/Position" }\n'
            'group = "Measurements"\n',
            "channel 'Setpont', which group 'Measurements' does not have "
            "(did you mean 'Setpoint'?)",
        ),
        (
            'columns = { reference_m = "Setpoint", position_m = "Position" }\n'
            'group = "Measurement"\n',
            "no group 'Measurement' (did you mean 'Measurements'?)",
        ),
        ('columns = { reference_m = "Setpoint" }\n', "missing required column(s) position_m"),
    ],
)
def test_missing_group_or_channel(tmp_path: Path, spec: str, expected: str) -> None:
    _waveform_file(tmp_path / "x.tdms", _step())
    with pytest.raises(ManifestError) as err:
        _read_one(_manifest(tmp_path, "x.tdms", spec))
    assert expected in str(err.value)
    assert isinstance(err.value.__cause__, TraceError)
    assert "x.tdms" in str(err.value)


def test_length_over_the_limit_from_metadata(tmp_path: Path, monkeypatch: Any) -> None:
    _waveform_file(tmp_path / "x.tdms", _step())
    monkeypatch.setattr(nptdms.TdmsFile, "open", lambda *a, **k: pytest.fail("data read"))
    with pytest.raises(ManifestError, match=r"200 values, above the limit of 100 samples"):
        _read_one(
            _manifest(tmp_path, "x.tdms", WAVEFORM_MAP),
            limits=TraceLimits(max_samples_per_trace=100),
        )


def test_non_finite_and_timing_errors(tmp_path: Path) -> None:
    data = _step()
    data["position_m"][7] = np.nan
    _waveform_file(tmp_path / "nan.tdms", data)
    with pytest.raises(TraceError, match=r"sample 7, column 'Encoder/Position': value .*nan"):
        read_trace(
            tmp_path / "nan.tdms",
            columns={"reference_m": "Setpoint", "position_m": "Encoder/Position"},
            group=GROUP,
        )
    data = _step()
    _write_tdms(
        tmp_path / "mixed.tdms",
        {
            (GROUP, "reference_m"): (data["reference_m"], {"wf_increment": 1e-4}),
            (GROUP, "position_m"): (data["position_m"], {"wf_increment": 2e-4}),
        },
    )
    with pytest.raises(TraceError, match="must share their sampling"):
        read_trace(tmp_path / "mixed.tdms")
    _write_tdms(
        tmp_path / "notime.tdms",
        {(GROUP, k): (data[k], {}) for k in ("reference_m", "position_m")},
    )
    with pytest.raises(TraceError, match="no time: no time_s channel"):
        read_trace(tmp_path / "notime.tdms")
    _waveform_file(tmp_path / "wf.tdms", data)
    with pytest.raises(TraceError, match="leave time_s out of units"):
        read_trace(
            tmp_path / "wf.tdms",
            columns={"reference_m": "Setpoint", "position_m": "Encoder/Position"},
            units={"time_s": "ms"},
        )


def test_group_only_for_tdms(tmp_path: Path) -> None:
    _write_csv(tmp_path / "x.csv", _step())
    with pytest.raises(ManifestError, match=r"group applies to \.tdms files only"):
        load_manifest(_manifest(tmp_path, "x.csv", 'group = "G"\n'))


def test_missing_extra_is_one_line(tmp_path: Path, monkeypatch: Any) -> None:
    _waveform_file(tmp_path / "x.tdms", _step())
    monkeypatch.setitem(sys.modules, "nptdms", None)
    with pytest.raises(ManifestError) as err:
        _read_one(_manifest(tmp_path, "x.tdms", WAVEFORM_MAP))
    msg = str(err.value)
    assert 'pip install "nanostage[tdms]"' in msg and "\n" not in msg
    with pytest.raises(PredictError, match=r'pip install "nanostage\[tdms\]"'):
        predict(_manifest(tmp_path, "x.tdms", 'group = "Measurements"\n'), tmp_path / "out")
