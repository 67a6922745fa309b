"""Tests of the diagnosis data layer: traces, manifest, segments, gap statistics, report."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

# isort: split
import nanostage
from nanostage.diagnosis import (
    PHASES,
    ManifestError,
    TraceError,
    analyse_gap,
    compare_features,
    gap_statistics,
    iso230_comparison,
    load_manifest,
    markdown_report,
    power_share_near,
    read_trace,
    replace_paths,
    residual,
    segment,
    segment_arrays,
    segment_gap,
    spatial_spectrum,
    time_spectrum,
    to_jsonable,
    write_json,
    write_report,
    write_trace_csv,
)
from nanostage.diagnosis.settings import DEFAULT_LEVEL_SCATTER
from nanostage.effects import EFFECT_NAMES
from nanostage.experiment import Experiment
from nanostage.iso230_2 import evaluate

SHARED = Path(__file__).resolve().parents[1].parent / "shared"
EMPS_MAT = SHARED / "data" / "emps" / "DATA_EMPS.mat"
EMPS_COLUMNS = {"time_s": "t", "reference_m": "qg", "position_m": "qm", "command_v": "vir"}


# --------------------------------------------------------------------------------------------
# Helpers
# --------------------------------------------------------------------------------------------


def sim_experiment(
    step_m: float = 100e-6, duration_s: float = 0.5, name: str = "step"
) -> Experiment:
    """A simulated step as a measured experiment (encoder reading as position)."""
    tr = nanostage.simulate_step(nanostage.presets.seed(step_m), step_m, duration_s=duration_s)
    return Experiment(
        name=name,
        time_s=tr.time_s,
        reference_m=tr.reference_m,
        position_m=tr.encoder_position_m,
        command_v=tr.motor_voltage_v,
    )


def write_csv(path: Path, header: str, rows: list[str]) -> Path:
    path.write_text(header + "\n" + "\n".join(rows) + "\n", encoding="utf-8")
    return path


def step_rows(n: int = 20, *, scale: float = 1.0) -> list[str]:
    """Rows of a tiny step response: time, reference, position (position × scale)."""
    rows = []
    for k in range(n):
        ref = 100e-6 if k >= 2 else 0.0
        pos = 100e-6 * min(1.0, max(0.0, (k - 2) / 5.0))
        rows.append(f"{k * 1e-3!r},{ref!r},{pos * scale!r}")
    return rows


def synthetic_step() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A 1.9 mm step built phase by phase (1 ms samples).

    hold [0, 0.10) s; acceleration 0.4 m/s² [0.10, 0.15) to 20 mm/s; slew [0.15, 0.20);
    braking at -0.4 m/s² [0.20, 0.25) reaching 2.0 mm, crossing the 1.9 mm target at
    0.2276 s; a decaying 40 ms oscillation (amplitude 0.1 mm → 0 linearly) [0.25, 0.40)
    whose first return to the target is at 0.26 s; then a limit cycle of 0.5 µm amplitude
    and 20 ms period.
    """
    t = np.arange(1000) * 1e-3
    target = 1.9e-3
    ref = np.where(t >= 0.1 - 1e-12, target, 0.0)
    a = 0.4
    x = np.zeros_like(t)
    m = (t >= 0.1) & (t < 0.15)
    x[m] = 0.5 * a * (t[m] - 0.1) ** 2
    m = (t >= 0.15) & (t < 0.20)
    x[m] = 0.5e-3 + 0.02 * (t[m] - 0.15)
    m = (t >= 0.20) & (t < 0.25)
    tb = t[m] - 0.2
    x[m] = 1.5e-3 + 0.02 * tb - 0.5 * a * tb**2
    m = (t >= 0.25) & (t < 0.40)
    env = 0.1e-3 * (0.40 - t[m]) / 0.15
    x[m] = target + env * np.cos(2 * np.pi * (t[m] - 0.25) / 0.04)
    m = t >= 0.40
    x[m] = target + 0.5e-6 * np.sin(2 * np.pi * (t[m] - 0.40) / 0.02)
    return t, ref, x


def trapezoid_reference(dt: float = 1e-3) -> tuple[np.ndarray, np.ndarray]:
    """Back-and-forth 20 mm moves: 0.1 s ramps at 0.4 m/s², 20 mm/s cruise, 0.3 s dwells."""
    a, v = 0.4, 0.02
    t_acc = v / a
    d_acc = 0.5 * a * t_acc**2
    cruise = (0.02 - 2 * d_acc) / v
    t_move = 2 * t_acc + cruise
    t = np.arange(round(4 * (t_move + 0.3) / dt)) * dt

    def one(tau: np.ndarray) -> np.ndarray:
        out = np.where(tau < t_acc, 0.5 * a * tau**2, 0.0)
        m = (tau >= t_acc) & (tau < t_acc + cruise)
        out[m] = d_acc + v * (tau[m] - t_acc)
        m = (tau >= t_acc + cruise) & (tau < t_move)
        tb = t_move - tau[m]
        out[m] = 0.02 - 0.5 * a * tb**2
        out[tau >= t_move] = 0.02
        return out

    period = t_move + 0.3
    ph = np.mod(t, 2 * period)
    ref = np.where(ph < period, one(ph), 0.02 - one(ph - period))
    return t, ref


# --------------------------------------------------------------------------------------------
# Traces
# --------------------------------------------------------------------------------------------


def test_csv_round_trip_of_a_simulated_step(tmp_path: Path) -> None:
    exp = sim_experiment()
    path = write_trace_csv(exp, tmp_path / "step_100um.csv")
    back = read_trace(path)
    assert back.name == "step_100um"
    assert back.source == str(path)
    for col in ("time_s", "reference_m", "position_m", "command_v"):
        np.testing.assert_array_equal(getattr(back, col), getattr(exp, col))
    assert back.interferometer_m is None


def test_csv_column_map_and_window(tmp_path: Path) -> None:
    path = write_csv(tmp_path / "renamed.csv", "t,qg,qm,extra", [r + ",7" for r in step_rows(30)])
    exp = read_trace(
        path,
        columns={"time_s": "t", "reference_m": "qg", "position_m": "qm"},
        name="renamed",
        window_s=(0.0, 0.015),
    )
    assert exp.name == "renamed"
    assert exp.n_samples == 15
    assert exp.time_s[-1] == pytest.approx(0.014)
    assert "window" in exp.source


def test_npz_and_mat_with_column_map(tmp_path: Path) -> None:
    from scipy.io import savemat

    exp = sim_experiment()
    cols = {"time_s": "t", "reference_m": "qg", "position_m": "qm", "command_v": "vir"}
    arrays = {cols[c]: getattr(exp, c) for c in cols}
    np.savez(tmp_path / "a.npz", **arrays)
    savemat(tmp_path / "a.mat", {k: v.reshape(-1, 1) for k, v in arrays.items()} | {"gain": 3.0})
    for f in ("a.npz", "a.mat"):
        back = read_trace(tmp_path / f, columns=cols)
        np.testing.assert_array_equal(back.position_m, exp.position_m)
        np.testing.assert_array_equal(back.command_v, exp.command_v)


def _trace_error(path: Path, **kwargs: object) -> TraceError:
    with pytest.raises(TraceError) as info:
        read_trace(path, **kwargs)  # type: ignore[arg-type]
    err = info.value
    assert str(path) in str(err)
    assert err.file == str(path)
    return err


def test_missing_required_columns_lists_missing_and_found(tmp_path: Path) -> None:
    path = write_csv(tmp_path / "m.csv", "time_s,pos", [f"{k},0,0" for k in range(12)])
    err = _trace_error(path)
    assert err.line == 1
    assert "reference_m" in str(err) and "position_m" in str(err)
    assert "found: time_s, pos" in str(err)
    assert "line 1" in str(err)


def test_non_numeric_and_empty_cells_name_line_and_column(tmp_path: Path) -> None:
    rows = step_rows()
    rows[4] = "0.004,1e-4,abc"
    path = write_csv(tmp_path / "bad.csv", "# a comment\ntime_s,reference_m,position_m", rows)
    err = _trace_error(path)
    assert (err.line, err.column) == (7, "position_m")  # comment + header + 5th data row
    assert "line 7" in str(err) and "'position_m'" in str(err) and "'abc'" in str(err)
    rows = step_rows()
    rows[1] = "0.001,,0"
    err = _trace_error(write_csv(tmp_path / "empty.csv", "time_s,reference_m,position_m", rows))
    assert (err.line, err.column) == (3, "reference_m")
    assert "empty cell" in str(err)


def test_nan_and_inf_report_the_first_offending_line_and_column(tmp_path: Path) -> None:
    rows = step_rows()
    rows[9] = "0.009,1e-4,inf"
    rows[5] = "0.005,nan,nan"
    err = _trace_error(write_csv(tmp_path / "nan.csv", "time_s,reference_m,position_m", rows))
    assert (err.line, err.column) == (7, "reference_m")
    assert "NaN/inf" in str(err)


def test_non_monotonic_time_names_the_line(tmp_path: Path) -> None:
    rows = step_rows()
    rows[6] = rows[6].replace("0.006", "0.004", 1)
    err = _trace_error(write_csv(tmp_path / "t.csv", "time_s,reference_m,position_m", rows))
    assert (err.line, err.column) == (8, "time_s")
    assert "not strictly increasing" in str(err) and "line 7" in str(err)


def test_too_few_samples_and_constant_reference(tmp_path: Path) -> None:
    err = _trace_error(
        write_csv(tmp_path / "short.csv", "time_s,reference_m,position_m", step_rows(6))
    )
    assert "only 6 sample(s)" in str(err)
    rows = [f"{k * 1e-3},0.0,0.0" for k in range(20)]
    err = _trace_error(write_csv(tmp_path / "flat.csv", "time_s,reference_m,position_m", rows))
    assert err.column == "reference_m" and "never moves" in str(err)
    # A constant disturbance does not drive anything either.
    rows = [f"{k * 1e-3},0.0,0.0,0.5" for k in range(20)]
    header = "time_s,reference_m,position_m,disturbance_v"
    err = _trace_error(write_csv(tmp_path / "flat_v.csv", header, rows))
    assert err.column == "reference_m" and "known disturbance column" in str(err)
    # An open-loop pulse test: the reference never moves, a known voltage drives the axis.
    rows = [f"{k * 1e-3},0.0,{k * 1e-7},{0.01 * k}" for k in range(20)]
    exp = read_trace(write_csv(tmp_path / "pulse.csv", header, rows))
    assert exp.disturbance_v is not None and exp.disturbance_v[-1] == pytest.approx(0.19)


def test_millimetres_are_detected(tmp_path: Path) -> None:
    # Position in mm against a reference in m: scale ratio 1000.
    path = write_csv(tmp_path / "mm.csv", "time_s,reference_m,position_m", step_rows(scale=1e3))
    err = _trace_error(path)
    assert err.column == "position_m"
    assert "looks like millimetres; convert to metres" in str(err)
    # Everything in mm, a 10 mm step: peak-to-peak 10 "m" > 1 m.
    rows = [f"{k * 1e-3},{10.0 if k > 2 else 0.0},{10.0 * min(1, k / 8)}" for k in range(20)]
    err = _trace_error(write_csv(tmp_path / "mm2.csv", "time_s,reference_m,position_m", rows))
    assert err.column == "reference_m" and "millimetres" in str(err)
    # Reference in mm, position in m that follows it.
    rows = [
        f"{k * 1e-3},{0.1 if k >= 2 else 0.0},{1e-4 * min(1, max(0, (k - 2) / 5))}"
        for k in range(20)
    ]
    err = _trace_error(write_csv(tmp_path / "mm3.csv", "time_s,reference_m,position_m", rows))
    assert err.column == "reference_m" and "millimetres" in str(err)


def test_a_stuck_stage_is_not_mistaken_for_millimetres(tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    rows = [f"{k * 1e-3},{1e-4 if k >= 2 else 0.0},{1e-7 * rng.integers(0, 2)}" for k in range(40)]
    exp = read_trace(write_csv(tmp_path / "stuck.csv", "time_s,reference_m,position_m", rows))
    assert exp.n_samples == 40


def test_column_map_errors(tmp_path: Path) -> None:
    path = write_csv(tmp_path / "c.csv", "t,qg,qm", step_rows())
    err = _trace_error(path, columns={"time_s": "t", "referense_m": "qg", "position_m": "qm"})
    assert err.column == "referense_m" and "unknown column" in str(err)
    err = _trace_error(path, columns={"time_s": "t", "reference_m": "qg", "position_m": "q"})
    assert err.column == "q" and err.line == 1 and "found: t, qg, qm" in str(err)


def test_unequal_lengths_in_npz_and_mat(tmp_path: Path) -> None:
    from scipy.io import savemat

    t = np.arange(20) * 1e-3
    arrays: dict[str, Any] = {
        "time_s": t,
        "reference_m": np.full(20, 1e-4),
        "position_m": np.zeros(19),
    }
    np.savez(tmp_path / "u.npz", **arrays)
    err = _trace_error(tmp_path / "u.npz")
    assert err.column == "position_m" and "19 samples" in str(err)
    savemat(
        tmp_path / "u.mat", {"t": t.reshape(-1, 1), "r": arrays["reference_m"], "x": np.zeros(18)}
    )
    err = _trace_error(
        tmp_path / "u.mat", columns={"time_s": "t", "reference_m": "r", "position_m": "x"}
    )
    assert err.column == "x" and "18 samples" in str(err)


def test_npz_nan_names_sample_and_column(tmp_path: Path) -> None:
    exp = sim_experiment()
    pos = exp.position_m.copy()
    pos[33] = np.nan
    np.savez(tmp_path / "n.npz", time_s=exp.time_s, reference_m=exp.reference_m, position_m=pos)
    err = _trace_error(tmp_path / "n.npz")
    assert (err.sample, err.column, err.line) == (33, "position_m", None)
    assert "sample 33" in str(err)


def test_window_outside_the_trace_and_other_files(tmp_path: Path) -> None:
    path = write_csv(tmp_path / "w.csv", "time_s,reference_m,position_m", step_rows())
    err = _trace_error(path, window_s=(0.5, 1.0))
    assert err.column == "time_s" and "outside the trace" in str(err)
    err = _trace_error(tmp_path / "nope.csv")
    assert "no such file" in str(err)
    (tmp_path / "x.xlsx").write_text("")
    assert "unknown trace format" in str(_trace_error(tmp_path / "x.xlsx"))
    rows = step_rows()
    rows[3] += ",1,2"
    err = _trace_error(write_csv(tmp_path / "wide.csv", "time_s,reference_m,position_m", rows))
    assert err.line == 5 and "fields" in str(err)


@pytest.mark.skipif(not EMPS_MAT.exists(), reason="EMPS data not available")
def test_reads_the_emps_mat_file() -> None:
    exp = read_trace(EMPS_MAT, columns=EMPS_COLUMNS)
    assert exp.n_samples == 24841
    assert exp.sample_period_s == pytest.approx(1e-3, rel=1e-4)
    assert float(np.ptp(exp.reference_m)) == pytest.approx(0.246357, rel=1e-4)


# --------------------------------------------------------------------------------------------
# Manifest
# --------------------------------------------------------------------------------------------


def _project(tmp_path: Path, n: int = 3) -> Path:
    (tmp_path / "traces").mkdir()
    for i in range(n):
        write_trace_csv(sim_experiment(name=f"s{i}"), tmp_path / "traces" / f"s{i}.csv")
    return tmp_path


GOOD = """
[model]
preset = "seed"
free = ["plant.dahl.coulomb_force_n", "plant.dahl.stiffness_n_per_m"]
[model.overrides]
"plant.table.mass_kg" = 0.8
plant.dahl.exponent = 1.0
[model.bounds]
"plant.dahl.coulomb_force_n" = [5.0, 100.0]

[controller]
kind = "fpga_pid"
kp = 450.0
ki = 2.0

[diagnosis]
candidates = ["lugre", "backlash"]
seed = 7

[[experiment]]
name = "a"
file = "traces/s0.csv"
window_s = [0.0, 0.3]
controller = { kd = 40.0 }

[[experiment]]
name = "b"
file = "traces/s1.csv"

[[experiment]]
name = "c"
file = "traces/s2.csv"
columns = { position_m = "position_m" }
"""


def test_manifest_loads_resolves_and_splits(tmp_path: Path) -> None:
    root = _project(tmp_path)
    (root / "diag.toml").write_text(GOOD)
    man = load_manifest(root / "diag.toml")
    assert man.model.preset == "seed"
    assert man.model.free == ("plant.dahl.coulomb_force_n", "plant.dahl.stiffness_n_per_m")
    assert man.model.bounds["plant.dahl.coulomb_force_n"] == (5.0, 100.0)
    sigma = man.model.initial["plant.dahl.stiffness_n_per_m"]
    assert man.model.bounds["plant.dahl.stiffness_n_per_m"] == pytest.approx((sigma / 3, sigma * 3))
    assert dict(man.model.overrides) == {"plant.table.mass_kg": 0.8, "plant.dahl.exponent": 1.0}
    assert man.diagnosis.candidates == ("lugre", "backlash") and man.diagnosis.seed == 7
    a, b, _ = man.experiment_specs
    assert a.file == (root / "traces" / "s0.csv").resolve()
    assert dict(a.controller.gains) == {"kp": 450.0, "ki": 2.0, "kd": 40.0}
    assert dict(b.controller.gains) == {"kp": 450.0, "ki": 2.0}
    system = man.system(a)
    assert system.plant.table.mass_kg == 0.8
    assert (system.controller.kp, system.controller.ki, system.controller.kd) == (450, 2, 40)
    exps = man.experiments()
    assert [e.name for _, e in exps] == ["a", "b", "c"]
    assert exps[0][1].time_s[-1] < 0.3 and exps[1][1].n_samples == 500
    folds = man.splits()
    assert [(f.train, f.validate) for f in folds] == [
        (("b", "c"), ("a",)),
        (("a", "c"), ("b",)),
        (("a", "b"), ("c",)),
    ]


def test_manifest_roles_give_one_fold_and_all_candidates(tmp_path: Path) -> None:
    root = _project(tmp_path, 2)
    (root / "m.toml").write_text(
        '[model]\npreset = "seed"\n[diagnosis]\ncandidates = "all"\n'
        '[[experiment]]\nname = "x"\nfile = "traces/s0.csv"\nrole = "train"\n'
        '[[experiment]]\nname = "y"\nfile = "traces/s1.csv"\nrole = "validate"\n'
    )
    man = load_manifest(root / "m.toml")
    assert man.diagnosis.candidates == EFFECT_NAMES
    assert [(f.train, f.validate) for f in man.splits()] == [(("x",), ("y",))]
    assert man.diagnosis.level_scatter == DEFAULT_LEVEL_SCATTER == 0.01
    plain = (root / "m.toml").read_text()
    for given, value in (("0.02", 0.02), ("0", 0.0)):
        text = plain.replace('"all"\n', f'"all"\nlevel_scatter = {given}\n')
        (root / "m.toml").write_text(text)
        assert load_manifest(root / "m.toml").diagnosis.level_scatter == value


def test_manifest_model_file_overrides(tmp_path: Path) -> None:
    root = _project(tmp_path, 1)
    (root / "model.toml").write_text("[plant.table]\nmass_kg = 0.5\n")
    (root / "m.toml").write_text(
        '[model]\npreset = "seed"\nfile = "model.toml"\n'
        '[[experiment]]\nname = "x"\nfile = "traces/s0.csv"\n'
    )
    assert load_manifest(root / "m.toml").system().plant.table.mass_kg == 0.5
    (root / "model.toml").write_text("[plant.table]\nmas_kg = 0.5\n")
    with pytest.raises(ManifestError) as info:
        load_manifest(root / "m.toml")
    assert "model.toml" in str(info.value) and "'mass_kg'" in str(info.value)


BASE = '[model]\npreset = "seed"\n'
EXP = '[[experiment]]\nname = "x"\nfile = "traces/s0.csv"\n'


@pytest.mark.parametrize(
    ("text", "key", "needle"),
    [
        (
            BASE + '[[experiment]]\nname = "x"\nfile = "traces/missing.csv"\n',
            "experiment[0].file",
            "experiment 'x': trace file 'traces/missing.csv' not found",
        ),
        (
            BASE + '[diagnosis]\ncandidates = ["lugre", "lugree"]\n' + EXP,
            "diagnosis.candidates[1]",
            "valid effects: coulomb_viscous, stribeck",
        ),
        (
            BASE + "[diagnosis]\nlevel_scatter = 0.5\n" + EXP,
            "diagnosis.level_scatter",
            "0.5 is out of range: expected a relative friction level scatter in [0, 0.2]",
        ),
        (
            BASE + '[diagnosis]\nlevel_scatter = "2 %"\n' + EXP,
            "diagnosis.level_scatter",
            "expected a number",
        ),
        ('[model]\npreset = "sead"\n' + EXP, "model.preset", "did you mean 'seed'"),
        (BASE + EXP + 'role = "test"\n', "experiment[0].role", "valid roles: train, validate"),
        (BASE + '[controller]\nkind = "pid"\n' + EXP, "controller.kind", "unknown controller kind"),
        (BASE + '[controller]\nkind = "cascade"\n' + EXP, "controller.kind", "does not fit"),
        (BASE + EXP + EXP, "experiment[1].name", "duplicate experiment name 'x'"),
        (
            BASE + 'free = ["plant.dahl.coulomb_force_n"]\n[model.bounds]\n'
            '"plant.dahl.coulomb_force_n" = [40.0, 100.0]\n' + EXP,
            "model.bounds.plant.dahl.coulomb_force_n",
            "do not contain the preset value 30.4",
        ),
        (
            BASE + 'free = ["plant.dahl.coulomb_force_n"]\n[model.bounds]\n'
            '"plant.dahl.coulomb_force_n" = [50.0, 10.0]\n' + EXP,
            "model.bounds.plant.dahl.coulomb_force_n",
            "must be below the upper bound",
        ),
        (
            BASE + 'free = ["plant.dahl.coulomb_forse_n"]\n' + EXP,
            "model.free[0]",
            "has no field 'coulomb_forse_n' (did you mean 'coulomb_force_n'?)",
        ),
        (BASE + 'free = ["plant.dahl"]\n' + EXP, "model.free[0]", "not a numeric parameter"),
        (
            BASE + '[model.overrides]\n"plant.table.mass_kg" = "heavy"\n' + EXP,
            "model.overrides.plant.table.mass_kg",
            "expected a number",
        ),
        (BASE + "[[experiments]]\nname = 'x'\n", "experiments", "did you mean [[experiment]]"),
        (BASE + EXP + "window_s = [2.0, 1.0]\n", "experiment[0].window_s", "is not before stop"),
        (BASE + EXP + "colour = 'red'\n", "experiment[0].colour", "unknown key"),
        (
            BASE + EXP + 'role = "train"\n[[experiment]]\nname = "y"\nfile = "traces/s0.csv"\n',
            "experiment[1].role",
            "has no role while others do",
        ),
    ],
)
def test_manifest_errors_name_file_and_key(
    tmp_path: Path, text: str, key: str, needle: str
) -> None:
    root = _project(tmp_path, 1)
    (root / "bad.toml").write_text(text)
    with pytest.raises(ManifestError) as info:
        load_manifest(root / "bad.toml")
    err = info.value
    assert "bad.toml" in str(err)
    assert err.key == key and f"key {key!r}" in str(err)
    assert needle in str(err)


def test_manifest_syntax_error_names_the_line(tmp_path: Path) -> None:
    (tmp_path / "s.toml").write_text('[model]\npreset = "seed"\nfree = [\n"a",\n= 3\n')
    with pytest.raises(ManifestError) as info:
        load_manifest(tmp_path / "s.toml")
    assert info.value.line == 5 and "s.toml, line 5" in str(info.value)


def test_manifest_window_outside_the_trace_fails_before_fitting(tmp_path: Path) -> None:
    root = _project(tmp_path, 1)
    (root / "w.toml").write_text(BASE + EXP + "window_s = [1.0, 2.0]\n")
    man = load_manifest(root / "w.toml")  # the trace's span is only known when read
    with pytest.raises(ManifestError) as info:
        man.experiments()
    msg = str(info.value)
    assert "w.toml" in msg and "experiment[0]" in msg and "experiment 'x'" in msg
    assert "s0.csv" in msg and "outside the trace" in msg
    assert isinstance(info.value.__cause__, TraceError)


# --------------------------------------------------------------------------------------------
# Segments
# --------------------------------------------------------------------------------------------


def _assert_partition(masks: dict[str, np.ndarray], n: int) -> None:
    total = np.zeros(n, dtype=np.int64)
    for m in masks.values():
        assert m.shape == (n,) and m.dtype == bool
        total += m
    np.testing.assert_array_equal(total, 1)


def test_simulated_1mm_step_has_a_slew_phase_at_the_voltage_limit() -> None:
    tr = nanostage.simulate_step(nanostage.presets.seed(1e-3), 1e-3, duration_s=0.5)
    seg = segment_arrays(tr.time_s, tr.reference_m, tr.encoder_position_m)
    masks = seg.masks()
    _assert_partition(masks, tr.time_s.size)
    _assert_partition(seg.motion_masks(), tr.time_s.size)
    _assert_partition(seg.direction_masks(), tr.time_s.size)
    _assert_partition(seg.position_masks(), tr.time_s.size)
    slew = masks["slew"]
    assert slew.sum() >= 40  # ≈ 60 ms at 14 mm/s
    at_limit = np.abs(tr.motor_voltage_v) >= tr.amplifier_limit_v - 1e-9
    assert np.mean(at_limit[slew]) >= 0.95
    assert masks["acceleration"][tr.time_s < 0.02].any()
    assert masks["hold"][-100:].all()
    (move,) = seg.moves
    assert move.kind == "step" and move.target_m == 1e-3 and move.direction == 1
    assert abs(move.final_error_m) <= 1e-7
    assert move.overshoot_m > 10e-6
    order = [p for p, _, _ in seg.intervals()]
    assert order[:3] == ["hold", "acceleration", "slew"] and order[-1] == "hold"


def test_segment_boundaries_of_a_constructed_signal() -> None:
    t, ref, x = synthetic_step()
    seg = segment_arrays(t, ref, x)
    iv = {p: (a, b) for p, a, b in seg.intervals()[1:]}  # skip the initial hold
    # Speed within 10 % of the 20 mm/s peak from 0.145 s (0.4 m/s² · 45 ms = 18 mm/s) to
    # 0.205 s; the target is crossed at 0.2276 s; the overshoot returns at 0.26 s; the
    # oscillation has decayed into the limit-cycle band at ≈ 0.40 s.
    expected = {
        "acceleration": (100, 145),
        "slew": (145, 205),
        "braking": (205, 228),
        "overshoot": (228, 260),
        "settling": (260, 400),
        "hold": (400, 1000),
    }
    for phase, (a, b) in expected.items():
        assert iv[phase][0] == pytest.approx(a, abs=2), phase
        assert iv[phase][1] == pytest.approx(b, abs=2), phase
    (move,) = seg.moves
    assert move.limit_cycle is not None
    assert move.limit_cycle.amplitude_m == pytest.approx(0.5e-6, rel=0.02)
    assert move.limit_cycle.period_s == pytest.approx(0.02, rel=0.02)
    assert move.overshoot_m == pytest.approx(0.1e-3, rel=1e-3)
    assert move.peak_speed_m_per_s == pytest.approx(0.02, rel=0.01)


def test_no_limit_cycle_in_a_quiet_hold() -> None:
    t, ref, x = synthetic_step()
    x = x.copy()
    x[t >= 0.40] = 1.9e-3 + np.random.default_rng(3).normal(0.0, 1e-8, np.count_nonzero(t >= 0.40))
    (move,) = segment_arrays(t, ref, x).moves
    assert move.limit_cycle is None
    assert move.hold_start == pytest.approx(400, abs=2)


def test_step_sequence_gives_one_move_per_step() -> None:
    system = nanostage.presets.seed(100e-6)
    n = 1200
    ref = np.zeros(n)
    ref[10:] = 100e-6
    ref[400:] = 300e-6
    ref[800:] = 150e-6
    tr = nanostage.simulate(system, ref)
    seg = segment_arrays(tr.time_s, tr.reference_m, tr.encoder_position_m)
    assert [(m.start, m.stop, m.direction) for m in seg.moves] == [
        (10, 400, 1),
        (400, 800, 1),
        (800, n, -1),
    ]
    assert [m.target_m for m in seg.moves] == [100e-6, 300e-6, 150e-6]
    _assert_partition(seg.masks(), n)
    for m in seg.moves:
        assert m.hold_start < m.stop and abs(m.final_error_m) <= 2e-7
        assert seg.phase[m.start] == PHASES.index("acceleration")


def test_smooth_trajectory_slew_is_the_constant_velocity_reference() -> None:
    t, ref = trapezoid_reference()
    x = np.interp(t - 0.004, t, ref)  # a 4 ms lag
    seg = segment_arrays(t, ref, x)
    assert len(seg.moves) == 4 and all(m.kind == "ramp" for m in seg.moves)
    assert [m.direction for m in seg.moves] == [1, -1, 1, -1]
    v_ref = np.gradient(ref, t)
    cruise = np.abs(np.abs(v_ref) - 0.02) < 1e-9
    slew = seg.masks()["slew"]
    assert np.mean(slew == cruise) > 0.99
    acc = seg.masks()["acceleration"]
    speeding_up = (np.abs(np.gradient(np.abs(v_ref), t)) > 0.2) & (
        np.gradient(np.abs(v_ref), t) > 0
    )
    assert np.mean(acc[speeding_up]) > 0.95
    _assert_partition(seg.masks(), t.size)
    assert seg.masks()["hold"].sum() > 0.5 * 4 * 300
    plus = seg.direction_masks()["+"]
    assert plus[seg.moves[0].start + 20 : seg.moves[0].reference_stop - 20].all()


@pytest.mark.skipif(not EMPS_MAT.exists(), reason="EMPS data not available")
def test_emps_segments_into_back_and_forth_ramps() -> None:
    seg = segment(read_trace(EMPS_MAT, columns=EMPS_COLUMNS))
    assert len(seg.moves) == 8  # 7 velocity reversals
    assert all(m.kind == "ramp" for m in seg.moves)
    counts = {k: int(v.sum()) for k, v in seg.masks().items()}
    assert counts["slew"] > 0.6 * seg.n_samples
    assert counts["acceleration"] > 1000 and counts["braking"] > 1000


def test_sliding_threshold_and_position_bins() -> None:
    t, ref, x = synthetic_step()
    low = segment_arrays(t, ref, x, sliding_threshold_m_per_s=1e-4, n_position_bins=4)
    high = segment_arrays(t, ref, x, sliding_threshold_m_per_s=1.5e-2, n_position_bins=4)
    assert high.sliding.sum() < low.sliding.sum()
    assert np.all(high.sliding <= low.sliding)
    assert len(low.position_masks()) == 4
    assert low.position_bin_edges_m[0] == x.min() and low.position_bin_edges_m[-1] == x.max()
    assert low.position_bin[np.argmax(x)] == 3 and low.position_bin[0] == 0


# --------------------------------------------------------------------------------------------
# Gap
# --------------------------------------------------------------------------------------------


def test_segment_gap_by_hand() -> None:
    r = np.array([1.0, -1.0, 2.0, 2.0, 0.0, 3.0]) * 1e-6
    masks = {
        "a": np.array([1, 1, 0, 0, 0, 0], dtype=bool),
        "b": np.array([0, 0, 1, 1, 1, 0], dtype=bool),
        "c": np.array([0, 0, 0, 0, 0, 1], dtype=bool),
    }
    g = segment_gap(r, masks)
    # sums of squares (µm²): a 2, b 8, c 9 → total 19
    assert g["a"].rms_m == pytest.approx(1e-6)
    assert g["b"].rms_m == pytest.approx(math.sqrt(8 / 3) * 1e-6)
    assert g["c"].rms_m == pytest.approx(3e-6)
    assert [g[k].share for k in "abc"] == pytest.approx([2 / 19, 8 / 19, 9 / 19])
    assert [g[k].n_samples for k in "abc"] == [2, 3, 1]


def _perturbed_pair(step_m: float, n: int = 1) -> tuple[list[Experiment], list[np.ndarray]]:
    s = nanostage.presets.seed(step_m)
    s2 = replace_paths(s, {"plant.dahl.coulomb_force_n": 15.0})
    rng = np.random.default_rng(0)
    exps, sims = [], []
    sim = nanostage.simulate_step(s2, step_m, duration_s=0.4).encoder_position_m
    for i in range(n):
        e = sim_experiment(step_m, 0.4, name=f"e{i}")
        offset = 1e-7 * rng.integers(-20, 20)
        exps.append(dataclasses.replace(e, position_m=e.position_m + offset))
        sims.append(sim)
    return exps, sims


def test_gap_shares_add_to_one_and_totals_match() -> None:
    exps, sims = _perturbed_pair(1e-3, 2)
    segs = [segment(e) for e in exps]
    res = [residual(e, s) for e, s in zip(exps, sims, strict=True)]
    stats = gap_statistics(res, segs, partitions=("phase", "motion", "direction", "position"))
    r = np.concatenate(res)
    assert stats.rms_m == pytest.approx(float(np.sqrt(np.mean(r**2))))
    assert stats.rms_m > 1e-6
    for pname, segs_stats in stats.partitions.items():
        assert sum(g.share for g in segs_stats.values()) == pytest.approx(1.0), pname
        assert sum(g.n_samples for g in segs_stats.values()) == r.size
    assert stats.partitions["phase"]["slew"].n_samples > 0


def test_residual_rejects_a_wrong_length() -> None:
    exp = sim_experiment()
    with pytest.raises(ValueError, match=r"expected \(500,\)"):
        residual(exp, np.zeros(499))


def test_features_by_hand_on_the_constructed_signal() -> None:
    t, ref, x = synthetic_step()
    exp = Experiment(name="synthetic", time_s=t, reference_m=ref, position_m=x)
    seg = segment(exp)
    (fc,) = compare_features(exp, x + 1e-6, seg)
    # 10 % (0.19 mm) at 0.1308 s during the acceleration, 90 % (1.71 mm) at 0.2119 s while
    # braking: rise time 81.1 ms; overshoot 0.1 mm.
    assert fc.measured.rise_time_s == pytest.approx(0.0811, abs=1e-3)
    assert fc.measured.overshoot_m == pytest.approx(0.1e-3, rel=1e-3)
    assert fc.measured.final_error_m == pytest.approx(0.0, abs=1e-8)
    assert fc.simulated.final_error_m == pytest.approx(-1e-6, rel=1e-3)
    assert fc.measured.settling_time_s == pytest.approx(0.30, abs=3e-3)
    rows = {r["feature"]: r for r in fc.rows()}
    assert rows["overshoot_m"]["difference"] == pytest.approx(1e-6, rel=1e-3)


def _ramp_motion(ripple_m: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    t, ref = trapezoid_reference()
    x = np.interp(t - 0.004, t, ref)
    v = np.gradient(x, t)
    noise = np.random.default_rng(5).normal(0.0, 2e-7, t.size)
    r = ripple_m * np.sin(2 * np.pi * x / 2e-3) * np.sign(v) * (np.abs(v) > 1e-4) + noise
    return x, r, segment_arrays(t, ref, x).direction


def test_spatial_spectrum_finds_a_2mm_ripple_and_not_when_absent() -> None:
    x, r, d = _ramp_motion(1e-6)
    spec = spatial_spectrum([x], [r], [d])
    assert spec is not None and spec.unit == "1/m" and spec.n_records == 4
    peak = spec.frequency[np.argmax(spec.psd[1:]) + 1]
    assert peak == pytest.approx(500.0, rel=0.05)  # 1 / 2 mm
    assert power_share_near(spec, 2e-3) > 0.5
    x, r, d = _ramp_motion(0.0)
    spec = spatial_spectrum([x], [r], [d])
    assert spec is not None
    assert power_share_near(spec, 2e-3) < 0.05
    assert math.isnan(power_share_near(spec, 0.5))  # 20 mm of travel: < 2 periods


def test_time_spectrum_peaks_at_an_injected_frequency() -> None:
    t = np.arange(4000) * 1e-3
    r = 1e-6 * np.sin(2 * np.pi * 50.0 * t) + np.random.default_rng(2).normal(0, 1e-7, t.size)
    spec = time_spectrum([r, r[:3000]], 1e-3, nperseg=512)
    assert spec.unit == "Hz" and spec.n_records == 2
    assert spec.frequency[np.argmax(spec.psd)] == pytest.approx(50.0, abs=2.0)
    assert power_share_near(spec, 0.02) > 0.8


def test_iso230_campaign_matches_the_evaluator() -> None:
    exps, sims = _perturbed_pair(100e-6, 5)
    segs = [segment(e) for e in exps]
    iso = iso230_comparison(exps, sims, segs)
    assert iso is not None and not iso.bidirectional and iso.n_records == 5
    dev = [float(np.median(e.position_m[-50:])) - 100e-6 for e in exps]
    direct = evaluate([100e-6], [dev])
    assert iso.measured.repeatability_up_m == pytest.approx(direct.repeatability_up_m, abs=1e-12)
    assert iso.measured.repeatability_up_m > 0.0
    assert iso.simulated.repeatability_up_m == 0.0
    assert iso230_comparison(exps[:1], sims[:1], segs[:1]) is None  # one run: no campaign


# --------------------------------------------------------------------------------------------
# Report
# --------------------------------------------------------------------------------------------


def test_json_handles_numpy_and_nan_and_round_trips(tmp_path: Path) -> None:
    data = {
        "a": np.float64(1.5),
        "b": np.arange(3),
        "c": [math.nan, np.float32(2.0), math.inf],
        "d": {"x": np.bool_(True), 3: (1, 2)},
        "p": tmp_path,
    }
    path = write_json(data, tmp_path / "r.json")
    text = path.read_text(encoding="utf-8")
    assert "NaN" not in text and "Infinity" not in text
    back = json.loads(text)
    assert back == {
        "a": 1.5,
        "b": [0, 1, 2],
        "c": [None, 2.0, None],
        "d": {"x": True, "3": [1, 2]},
        "p": str(tmp_path),
    }
    assert to_jsonable(back) == back


def test_report_files_tables_and_figures(tmp_path: Path) -> None:
    exps, sims = _perturbed_pair(1e-3, 2)
    segs = [segment(e) for e in exps]
    before = analyse_gap(exps, sims, segmentations=segs)
    after = analyse_gap(exps, [e.position_m + 1e-7 for e in exps], segmentations=segs)
    report = {
        "gap_before": before.to_dict(),
        "gap_after": after.to_dict(),
        "candidates": [
            {"effect": "lugre", "score": 0.9, "gap_rms_m": 2e-7},
            {"effect": "backlash", "score": 0.2, "gap_rms_m": 1.1e-6},
        ],
        "selected": ["lugre"],
        "seed": 1,
    }
    files = write_report(
        report, tmp_path / "out", gap_experiments=[g.figure_data() for g in before.experiments]
    )
    back = json.loads(files.json.read_text(encoding="utf-8"))
    assert back["selected"] == ["lugre"]
    assert back["gap_before"]["overall"]["rms_m"] == pytest.approx(before.overall.rms_m)
    md = files.markdown.read_text(encoding="utf-8")
    assert "## Gap per segment" in md and "| Segment | n | RMS before [µm] |" in md
    assert "| slew |" in md and "#### By motion" in md
    assert "## Candidates (ranked)" in md and "| 1 | lugre | 0.9 | 0.2 |" in md
    assert "- `lugre`" in md
    assert "## Response features, measured vs simulated" in md and "rise_time_s [ms]" in md
    assert "Simulated after" in md
    for fig in (files.gap_map, files.residual_spectrum):
        assert fig is not None and fig.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
        assert fig.stat().st_size > 10_000
    assert "![Gap map](gap_map.png)" in md


def test_markdown_without_after_and_with_iso() -> None:
    exps, sims = _perturbed_pair(100e-6, 3)
    gap = analyse_gap(exps, sims).to_dict(spectra=False)
    md = markdown_report({"gap_before": gap, "candidates": []})
    assert "RMS after" not in md and "No candidates." in md
    assert "## ISO 230-2 (final hold positions)" in md and "| R↑ |" in md


def test_markdown_gap_table_has_the_best_single_effect_where_it_differs() -> None:
    """How far, per segment: nominal, best single effect, selected set. The single effect's
    columns appear with two effects selected (and with none: the best any single effect
    did), not with one (they would repeat the after columns)."""
    exps, sims = _perturbed_pair(100e-6, 3)
    exact = [e.position_m for e in exps]
    gaps = [analyse_gap(exps, s).to_dict(spectra=False) for s in (sims, exact, exact)]
    # A perfect model gives zero RMS: distinguishable from the perturbed one in the table.
    rep = {
        "gap_before": gaps[0],
        "gap_best_single": gaps[1],
        "gap_after": gaps[2],
        "best_single_effect": "backlash",
        "candidates": [],
    }
    head = "| Segment | n | RMS before [µm] | share before | RMS backlash alone [µm] |"
    md = markdown_report(rep | {"selected": ["backlash", "gms"]})
    assert head in md and "share backlash alone | RMS after [µm] | share after |" in md
    assert "backlash alone: the best single effect, after: the selected set" in md
    md_none = markdown_report(rep | {"selected": []})
    assert head in md_none
    md_one = markdown_report(rep | {"selected": ["backlash"]})
    assert "alone" not in md_one and "| RMS before [µm] | share before | RMS after [µm] |" in md_one
    # Each segment row: the single effect's cells between before and after.
    rows = [
        [c.strip() for c in line.strip().strip("|").split("|")]
        for line in md.splitlines()
        if line.startswith("| ") and not line.startswith(("| Segment", "| **total**", "| ---"))
    ]
    filled = [r for r in rows if len(r) == 8 and r[1] not in ("0", "—")]
    assert len(filled) >= 3 and all(r[4] == r[6] == "0" != r[2] for r in filled)


def test_markdown_names_a_tie_and_how_it_was_decided() -> None:
    base = {"candidates": [], "selected": ["asymmetric_friction"]}
    ties = {"asymmetric_friction": ["offset_force"]}
    md = markdown_report(base | {"indistinguishable": ties, "tie_break": "occam_factor"})
    assert "cannot tell it from `offset_force`" in md and "larger Occam factor" in md
    md = markdown_report(base | {"indistinguishable": ties, "tie_break": "validation_gap"})
    assert "smaller validation gap" in md and "Occam" not in md
    md = markdown_report(base | {"indistinguishable": {}, "tie_break": "occam_factor"})
    assert "- `asymmetric_friction`\n" in md and "Occam" not in md
    md = markdown_report(
        base | {"indistinguishable": ties, "tie_break": "validation_gap", "ranking": "relative"}
    )
    assert "smaller geometric validation gap" in md


def test_markdown_summary_names_parameters_at_their_bounds() -> None:
    at = [{"parameter": "plant.motor.rotor_inertia_kg_m2", "value": 1.5e-7, "bound": "upper"}]
    bounds = {"nominal": at, "selected_model": []}
    md = markdown_report({"candidates": [], "selected": [], "calibration_at_bounds": bounds})
    assert "**Calibration at its bounds:** `plant.motor.rotor_inertia_kg_m2` (upper)" in md
    assert "an effect it has absorbed can be missed" in md
    md = markdown_report(
        {"candidates": [], "selected": ["backlash"], "calibration_at_bounds": bounds}
    )
    assert "Calibration at its bounds" in md and "can be missed" not in md
    none = {"nominal": [], "selected_model": []}
    md = markdown_report({"candidates": [], "selected": [], "calibration_at_bounds": none})
    assert "Calibration at its bounds" not in md


def test_markdown_reads_the_evidence_advice_and_selection() -> None:
    """The readable report has what report.json has for a person: a summary, each selected
    effect's evidence with its parameters and errors, the experiment advice, the candidates
    with their parameters (not JSON), the forward selection, the refit control, the
    calibrated nominal parameters and the candidates not fitted; times in seconds."""
    cand = {
        "effect": "backlash",
        "validation_rms_m": 2.0e-7,
        "validation_geometric_rms_m": 1.5e-7,
        "shrink": 0.9766,
        "geometric_shrink": 0.9412,
        "significant": True,
        "p_value": 0.0,
        "train_rms_m": 2.1e-7,
        "log_occam_factor": -13.7,
        "parameters": {
            "backlash.width_m": {"value": 1.442e-5, "std_error": 2.2e-8, "unit": "m"},
            "backlash.contact_stiffness_n_per_m": {
                "value": 3.5e7,
                "std_error": 2e5,
                "unit": "N/m",
            },
        },
        "validation_rms_by_experiment_m": [1e-7, 3e-7],
        "why": ["validation gap 8435 → 198 nm", "bootstrap p = 0.000"],
    }
    delay = cand | {
        "effect": "sensor_delay",
        "significant": False,
        "parameters": {"sensor_delay.samples": {"value": 1, "unit": "samples"}},
    }
    report = {
        "gap_before": {"rms_m": 8.4e-6, "partitions": {}},
        "gap_after": {"rms_m": 2.0e-7, "partitions": {}},
        "candidates": [cand, delay],
        "selected": ["backlash"],
        "indistinguishable": {"backlash": []},
        "tie_break": "occam_factor",
        "noise_floor_rms_m": 8.7e-8,
        "unexplained_rms_m": 1.8e-7,
        "explained_fraction": 0.999,
        "evidence": [
            {
                "round": 1,
                "effect": "backlash",
                "shrink": 0.9766,
                "p_value": 0.0,
                "parameters": cand["parameters"],
                "segments_fixed": ["braking: 6036 → 36 nm (+99%)"],
                "lead_share_before": 0.5,
                "lead_share_after": 0.25,
                "why": ["validation gap 8435 → 198 nm"],
            }
        ],
        "advice": [
            {
                "effects": ["dwell_static_friction"],
                "issue": "all dwell times lie within a factor 2",
                "experiment": "repeat one move after dwells of 0.05 s, 0.5 s and 5 s",
            }
        ],
        "forward_selection": [
            {"round": 1, "candidates": [cand, delay]},
            {"round": 2, "candidates": [delay | {"shrink": -0.4}]},
        ],
        "refit_control": [
            {
                "round": 2,
                "restarted_from": "lugre",
                "train_rms_before_m": 2.061e-7,
                "train_rms_after_m": 1.832e-7,
                "validation_rms_before_m": 1.977e-7,
                "validation_rms_after_m": 1.851e-7,
                "validation_shrink": 0.064,
                "adopted": True,
            },
            {
                "round": 2,
                "restarted_from": "dahl",
                "train_rms_before_m": 2.061e-7,
                "train_rms_after_m": 1.712e-7,
                "validation_rms_before_m": 1.977e-7,
                "validation_rms_after_m": 2.4e-7,
                "validation_shrink": -0.21,
                "adopted": False,
            },
        ],
        "nominal_parameters": {"plant.dahl.coulomb_force_n": {"value": 28.8, "std_error": 2.37}},
        "selected_model_parameters": {
            "plant.dahl.coulomb_force_n": {"value": 31.5, "std_error": 0.8}
        },
        "skipped": {"dahl": "the nominal model already uses Dahl friction on the table"},
        "folds": [{"train": ["a", "b"], "validate": ["c", "d", "e"]}],
        "timing_s": 92.8,
        "seed": 3,
    }
    md = markdown_report(report)
    assert "- **Selected:** `backlash`" in md
    assert "pooled): 8400.0 → 200.0 nm RMS (shrink 97.6%)" in md
    assert "- **Noise floor:** 87.0 nm RMS; unexplained above it: 180.0 nm" in md
    assert "2 training and 3 validation experiment(s)" in md and "- **Time:** 92.8 s" in md
    assert "### 1. `backlash` (round 1)" in md
    assert "- Segments it fixed most: braking: 6036 → 36 nm (+99%)" in md
    assert "screw lead's spatial period: 50.0% → 25.0%" in md
    assert "| `backlash.width_m` | 1.442e-05 | 2.2e-08 | m |" in md
    assert "## Experiment advice" in md
    assert (
        "- `dwell_static_friction`: all dwell times lie within a factor 2. **Experiment:** "
        "repeat one move after dwells of 0.05 s, 0.5 s and 5 s" in md
    )
    assert "best pooled validation gap first" in md  # a report without a ranking: pooled
    relative = markdown_report(report | {"ranking": "relative"})
    assert "best geometric gap first" in relative and "best pooled" not in relative
    row = next(line for line in md.splitlines() if line.startswith("| 1 | `backlash`"))
    assert "| 200.0 | 150.0 | 97.7 % | 94.1 % | yes | 0.000 | 210.0 | -13.70 |" in row
    assert (
        "width_m = 1.442e-05 ± 2.2e-08 m<br>contact_stiffness_n_per_m = 3.5e+07 ± 2e+05 N/m" in row
    )
    assert "validation gap 8435 → 198 nm; bootstrap p = 0.000" in row and "{" not in row
    assert "samples = 1 |" in md  # a unit that repeats the name is left out
    assert "| 1 | `backlash` | `backlash` 97.7 %, `sensor_delay` 97.7 % (n.s.) |" in md
    assert "| 2 | — | `sensor_delay` -40.0 % (n.s.) |" in md
    assert "| 2 | `lugre` | 206.1 → 183.2 | 197.7 → 185.1 | yes |" in md
    assert "| 2 | `dahl` | 206.1 → 171.2 | 197.7 → 240.0 | no: validation worse |" in md
    assert "| `plant.dahl.coulomb_force_n` | 28.8 | 2.37 | 31.5 | 0.8 |" in md
    nothing = markdown_report(report | {"selected": []})
    assert "| `plant.dahl.coulomb_force_n` | 28.8 | 2.37 |\n" in nothing
    # Nothing selected above the floor: the unexplained gap with its partial explanations,
    # each saying what it was judged on.
    unexplained = {
        "gap_rms_m": 2.9e-7,
        "floor_ratio": 10.0,
        "partial_explanations": [
            {"effect": "offset_force", "shrink": 0.46, "why_not": [], "judged": "every experiment"}
        ],
    }
    plain = markdown_report(report | {"selected": [], "unexplained": unexplained})
    assert (
        "- **Unexplained gap** of 290.0 nm RMS (10.0× the noise floor): no candidate explains it "
        "by the selection rules; best partial explanations: `offset_force` (shrink 46%, judged "
        "on every experiment)" in plain
    )
    assert "| `dahl` | the nominal model already uses Dahl friction on the table |" in md
    # Rendered above, so not repeated among the other keys; a leftover scalar is.
    other = md.split("## Other")[1]
    assert "timing_s" not in other and "noise_floor" not in other and "| seed | 3 |" in other
    # Without advice in the report there is no advice section; an empty list says so.
    assert "## Experiment advice" not in markdown_report({"candidates": []})
    empty = markdown_report({"candidates": [], "advice": []})
    assert "None of the design checks found a gap" in empty and "not judged" in empty


def test_replace_paths_rebuilds_each_level_once_and_checks_every_path() -> None:
    """Several paths in one group and a path into another group: the copy equals the
    dataclass replacements written out; a bad path at any depth raises before anything is
    built, naming the field."""
    s = nanostage.presets.seed(1e-3)
    out = replace_paths(
        s,
        {
            "plant.dahl.coulomb_force_n": 15.0,
            "plant.dahl.stiffness_n_per_m": 2e7,
            "plant.table.mass_kg": 3.0,
            "encoder.count_m": 2e-7,
        },
    )
    p = s.plant
    assert isinstance(p, nanostage.Plant)
    want = dataclasses.replace(
        s,
        plant=dataclasses.replace(
            p,
            dahl=dataclasses.replace(p.dahl, coulomb_force_n=15.0, stiffness_n_per_m=2e7),
            table=dataclasses.replace(p.table, mass_kg=3.0),
        ),
        encoder=dataclasses.replace(s.encoder, count_m=2e-7),
    )
    assert out == want
    with pytest.raises(KeyError, match="has no field 'stifness_n_per_m'"):
        replace_paths(s, {"plant.dahl.coulomb_force_n": 15.0, "plant.dahl.stifness_n_per_m": 1.0})


def test_sample_period_is_the_median_step_and_follows_a_replaced_time_axis() -> None:
    t = np.array([0.0, 1e-3, 2e-3, 3.5e-3, 4.5e-3])
    x = np.zeros(5)
    e = Experiment(name="e", time_s=t, reference_m=x, position_m=x)
    assert e.sample_period_s == float(np.median(np.diff(t))) == 1e-3
    e2 = dataclasses.replace(e, time_s=2 * t)
    assert e2.sample_period_s == 2e-3 and e.sample_period_s == 1e-3
    assert dataclasses.replace(e2, time_s=t).sample_period_s == 1e-3
