"""The ISO-level diagnosis (nanostage.iso_diagnosis) and its blind benchmark's truth."""

from __future__ import annotations

import ast
import dataclasses
import functools
import json
import math
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import nanostage.iso_diagnosis as idg
from nanostage import ConfigError, iso230_2, iso_truth, presets
from nanostage.campaign import run_campaign
from nanostage.cli import main
from nanostage.config import System
from nanostage.effects import Backlash, StochasticFriction
from nanostage.iso_diagnosis import IsoDiagnosisSettings, diagnose_iso, iso_features
from nanostage.iso_diagnosis_benchmark import run_iso_benchmark
from nanostage.measurement import MeasurementChain, ScaleError, read_iso_measurement
from nanostage.output import to_jsonable

#: Few trials; the in-loop scans at one size each (a campaign each).
FAST = IsoDiagnosisSettings(n_trials=8, seed=3, backlash_widths_m=(12e-6,), friction_spreads=(0.5,))


def _write(path: Path, rows: list[tuple[float, str, int, float, float]]) -> Path:
    lines = ["target_m,direction,run,actual_m,time_s"]
    lines += [f"{t!r},{d},{r},{a!r},{ts!r}" for t, d, r, a, ts in rows]
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


def _standard_rows(
    targets: list[float], runs: int, deviation: Any, dt_s: float = 2.0
) -> list[tuple[float, str, int, float, float]]:
    """The standard cycle's order (per run: up, then down); ``deviation(i, d, run, t)``."""
    rows = []
    t = 0.0
    for run in range(1, runs + 1):
        for d, order in (("+", range(len(targets))), ("-", reversed(range(len(targets))))):
            for i in order:
                t += dt_s
                rows.append((targets[i], d, run, targets[i] + deviation(i, d, run, t), t))
    return rows


# --------------------------------------------------------------------------------------------
# The truth generator is independent of nanostage's chain and effects
# --------------------------------------------------------------------------------------------


def test_the_truth_generator_imports_nothing_of_nanostage() -> None:
    tree = ast.parse(Path(iso_truth.__file__).read_text(encoding="utf-8"))
    stdlib = set(sys.stdlib_module_names)
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for a in node.names:
                assert a.name.split(".")[0] in stdlib | {"numpy"}, a.name
        elif isinstance(node, ast.ImportFrom):
            assert node.level == 0, ast.dump(node)
            top = (node.module or "").split(".")[0]
            assert top in stdlib | {"numpy", "__future__"}, node.module


def test_the_truth_scale_error_is_the_strain_times_the_distance_from_the_fixing_point() -> None:
    case = iso_truth.draw_case("scale_error", 5)
    none = iso_truth.draw_case("none", 5)
    eps, fix = case.parameters["strain"], case.parameters["fixing_point_m"]
    # Same seed: the same schedule and the same loop draws up to the hidden effect's draws.
    x = np.array([r["target_m"] for r in case.rows])
    dev = np.array([r["actual_m"] for r in case.rows]) - x
    assert len(case.rows) == iso_truth.N_TARGETS * iso_truth.RUNS * 2
    # The loop and the noise stay within about a count; the rest is ε·(x − fix).
    resid = dev - eps * (x - fix)
    assert np.max(np.abs(resid)) < 1.5 * iso_truth.COUNT_M
    assert none.effect == "none" and "strain" not in none.parameters


# --------------------------------------------------------------------------------------------
# Features against hand-computed values
# --------------------------------------------------------------------------------------------


def test_features_match_the_hand_computed_values(tmp_path: Path) -> None:
    pitch = 20e-6
    targets = [0.0, 0.0100037, 0.0199911, 0.0300052, 0.04]
    amp, phase, bias, reversal, k = 0.3e-6, 0.7, 0.1e-6, 0.4e-6, 2e-9
    # A group's runs are read 2·(2·5) s apart: t − (the group's mean time) = 20 s·(run − 2).
    rows = _standard_rows(
        targets,
        3,
        lambda i, d, run, t: (
            bias
            + amp * math.sin(2 * math.pi * targets[i] / pitch + phase)
            + (0.5 if d == "+" else -0.5) * reversal
            + k * 20.0 * (run - 2)
        ),
    )
    meas = read_iso_measurement(_write(tmp_path / "m.csv", rows))
    f = iso_features(meas, scale_pitch_m=pitch, screw_lead_m=2e-3)
    mean_bi = np.array([bias + amp * math.sin(2 * math.pi * x / pitch + phase) for x in targets])
    np.testing.assert_allclose(f["mean_deviation_up_m"], mean_bi + reversal / 2, atol=1e-15)
    np.testing.assert_allclose(f["mean_deviation_down_m"], mean_bi - reversal / 2, atol=1e-15)
    np.testing.assert_allclose(f["reversal_m"], reversal, atol=1e-15)
    # Three runs of one group are read 2·(2·5) s apart: s = k · 20 s.
    np.testing.assert_allclose(f["std_up_m"], k * 20.0, rtol=1e-9)
    assert f["trend"]["against"] == "time_s"
    assert f["trend"]["slope_m_per_s"] == pytest.approx(k, rel=1e-9)
    p = f["periodic"]["scale_pitch"]
    assert p["amplitude_m"] == pytest.approx(amp, rel=1e-9)
    assert p["amplitude_se_m"] < 1e-15
    assert set(f["periodic"]) == {"scale_pitch", "screw_lead"}


# --------------------------------------------------------------------------------------------
# Diagnoses
# --------------------------------------------------------------------------------------------


def _model_test(
    tmp_path: Path,
    chain: MeasurementChain | None,
    noise_m: float,
    system: System | None = None,
    encoder: bool = False,
) -> Path:
    """A measured test made of one trial of the campaign of ``system`` (default: the seed
    model; another seed), read through ``chain`` and white noise, with the encoder's
    readings when ``encoder``."""
    targets = [0.0, 0.00512, 0.0098, 0.0151, 0.0203, 0.0249]
    rows = _standard_rows(targets, 3, lambda i, d, run, t: 0.0)
    src = _write(tmp_path / "layout.csv", rows)
    meas = read_iso_measurement(src)
    system = presets.preset_system("seed") if system is None else system
    cycle = idg.measurement_cycle(meas, FAST, system.controller.sample_period_s)
    camp = run_campaign(system, cycle, n_trials=1, seed=99, progress=False)
    if chain is not None:
        camp = camp.with_measurement(chain)
    actual = camp.interferometer_m[0] + np.random.default_rng(7).normal(0, noise_m, len(rows))
    out = [(t, d, r, float(a), float(ts)) for (t, d, r, _, ts), a in zip(rows, actual, strict=True)]
    if not encoder:
        return _write(tmp_path / "m.csv", out)
    lines = ["target_m,direction,run,actual_m,time_s,encoder_m"]
    lines += [
        f"{t!r},{d},{r},{a!r},{ts!r},{float(e)!r}"
        for (t, d, r, a, ts), e in zip(out, camp.encoder_m[0], strict=True)
    ]
    path = tmp_path / "m.csv"
    path.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return path


def test_a_scale_error_read_through_the_chain_is_named_with_its_size(tmp_path: Path) -> None:
    chain = MeasurementChain(scale=ScaleError(linear_error_m_per_m=20e-6, datum_m=0.0))
    meas = read_iso_measurement(_model_test(tmp_path, chain, 10e-9))
    rep = diagnose_iso(meas, presets.preset_system("seed"), FAST, in_loop=())
    assert rep["verdict"] == "scale_error"
    top = rep["candidates"][0]
    assert top["name"] == "scale_error" and top["significant"]
    assert top["parameters"]["linear_error_m_per_m"] == pytest.approx(20e-6, rel=0.05)
    # Whatever is tied with it is named with an experiment that separates them.
    for t in rep["indistinguishable"]:
        assert t["separating_test"]
    assert rep["figure_gap_shrink"] > 0.8


def test_the_model_itself_at_the_noise_floor_is_none(tmp_path: Path) -> None:
    meas = read_iso_measurement(_model_test(tmp_path, None, 10e-9))
    rep = diagnose_iso(meas, presets.preset_system("seed"), FAST)
    assert rep["verdict"] == "none"
    assert rep["indistinguishable"] == []
    assert not any(c["significant"] for c in rep["candidates"])
    assert rep["figure_gap_shrink"] == 0.0


def test_a_hidden_thermal_drift_from_the_independent_truth_is_named(tmp_path: Path) -> None:
    path = iso_truth.write_case(iso_truth.draw_case("thermal_drift", 104), tmp_path / "t.csv")
    rep = diagnose_iso(read_iso_measurement(path), presets.preset_system("seed"), FAST, in_loop=())
    names = [rep["verdict"], *(t["candidate"] for t in rep["indistinguishable"])]
    assert "thermal_drift" in names


def _result(name: str, gain: float, dof: int, gap: float = 1.0) -> dict[str, Any]:
    return {
        "name": name,
        "significant": True,
        "likelihood_gain": gain,
        "noise_floor_gain": 16.0,
        "iso_gap": gap,
        "dof": dof,
    }


def test_a_change_from_run_to_run_within_the_loops_tolerance_still_separates_two_fits() -> None:
    # 3 targets × 2 directions × 4 runs; two fits 30 nm apart (below half a count of 100 nm).
    group = np.repeat(np.arange(6), 4)
    runs = np.tile(np.arange(4) - 1.5, 6)
    results = [_result("refractive_index_drift", 1000.0, 2), _result("thermal_drift", 1100.0, 3)]
    # Apart from run to run at each target and direction (a drift's course): the better
    # likelihood wins although the other has fewer parameters.
    course = {"refractive_index_drift": (np.zeros(24), 0.0), "thermal_drift": (27e-9 * runs, 0.0)}
    assert idg._select(results, course, 0.1, 50e-9, group, 10e-9) == ("thermal_drift", [])
    # Without the groups (the old criterion), 30 nm is within the loop's tolerance: a tie,
    # and the one with fewer parameters is the verdict.
    assert idg._select(results, course, 0.1, 50e-9) == (
        "refractive_index_drift",
        ["thermal_drift"],
    )
    # Apart by a pattern over the targets and directions, the same in every run: that is
    # what the loop's stop may do within its tolerance, still a tie.
    pattern = {
        "refractive_index_drift": (np.zeros(24), 0.0),
        "thermal_drift": (30e-9 * np.where(group % 2 == 0, 1.0, -1.0), 0.0),
    }
    assert idg._select(results, pattern, 0.1, 50e-9, group, 10e-9) == (
        "refractive_index_drift",
        ["thermal_drift"],
    )
    # Apart from run to run but with likelihood gains within the noise floor: a tie.
    close = [_result("refractive_index_drift", 1000.0, 2), _result("thermal_drift", 1010.0, 3)]
    assert idg._select(close, course, 0.1, 50e-9, group, 10e-9) == (
        "refractive_index_drift",
        ["thermal_drift"],
    )


def test_a_slow_thermal_drift_is_told_from_an_index_drift_by_its_course_in_time(
    tmp_path: Path,
) -> None:
    # τ = 1450 s over a 413 s test: nearly linear, it levels off by 40 nm rms beside the
    # best constant-rate drift, within the loop's tolerance but the same at no two runs.
    case = iso_truth.draw_case("thermal_drift", 6)
    assert case.parameters["tau_s"] > 3 * case.rows[-1]["time_s"]
    path = iso_truth.write_case(case, tmp_path / "t.csv")
    rep = diagnose_iso(read_iso_measurement(path), presets.preset_system("seed"), in_loop=())
    assert rep["verdict"] == "thermal_drift"
    assert "refractive_index_drift" not in [t["candidate"] for t in rep["indistinguishable"]]
    # A constant-rate index drift: the thermal drift's extra time constant explains nothing
    # more, they stay tied and the simpler is the verdict.
    index = iso_truth.write_case(
        iso_truth.draw_case("refractive_index_drift", 3), tmp_path / "i.csv"
    )
    rep = diagnose_iso(read_iso_measurement(index), presets.preset_system("seed"), in_loop=())
    assert rep["verdict"] == "refractive_index_drift"
    assert "thermal_drift" in [t["candidate"] for t in rep["indistinguishable"]]


def test_the_same_seed_gives_the_same_report(tmp_path: Path) -> None:
    path = iso_truth.write_case(iso_truth.draw_case("abbe", 11), tmp_path / "a.csv")
    meas = read_iso_measurement(path)
    system = presets.preset_system("seed")
    a = diagnose_iso(meas, system, FAST, in_loop=())
    b = diagnose_iso(meas, system, FAST, in_loop=())
    for r in (a, b):
        r.pop("timing_s")
    assert json.dumps(to_jsonable(a)) == json.dumps(to_jsonable(b))


# --------------------------------------------------------------------------------------------
# Bad input and settings: errors before any campaign runs
# --------------------------------------------------------------------------------------------


def _no_campaign(monkeypatch: pytest.MonkeyPatch) -> None:
    def never(*args: Any, **kwargs: Any) -> Any:
        raise AssertionError("a campaign ran although the input is bad")

    monkeypatch.setattr(idg, "run_campaign", never)


@pytest.mark.parametrize(
    ("edit", "fragments"),
    [
        (lambda rows: rows[:-1], ["line", "column 'run'", "has 2 runs but"]),
        (
            lambda rows: [(*r[:4], 100.0 - r[4]) for r in rows],
            ["line 3", "column 'time_s'", "not after"],
        ),
        (
            lambda rows: [
                (0.2, d, r, 0.2 + 1e-7, ts) if t == 0.02 else (t, d, r, a, ts)
                for t, d, r, a, ts in rows
            ],
            ["line 4", "column 'target_m'", "outside the travel"],
        ),
    ],
    ids=["missing run", "times backwards", "target outside the travel"],
)
def test_bad_measurements_name_file_line_and_column_before_any_campaign(
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
    edit: Any,
    fragments: list[str],
) -> None:
    _no_campaign(monkeypatch)
    rows = _standard_rows([0.0, 0.01, 0.02], 3, lambda i, d, run, t: 1e-7)
    path = _write(tmp_path / "bad.csv", edit(rows))
    code = main(["iso-diagnose", str(path), "--out", str(tmp_path / "out"), "--quiet"])
    err = capsys.readouterr().err.strip()
    assert code == 2, err
    assert len(err.splitlines()) == 1 and "bad.csv" in err
    for fragment in fragments:
        assert fragment in err, err
    assert not (tmp_path / "out").exists()


def test_millimetres_in_a_metre_file_are_an_error(tmp_path: Path) -> None:
    rows = _standard_rows([0.0, 10.0, 20.0], 3, lambda i, d, run, t: 1e-4)
    with pytest.raises(iso230_2.Iso230InputError, match=r"m\.csv"):
        read_iso_measurement(_write(tmp_path / "m.csv", rows))


@pytest.mark.parametrize(
    ("field", "value", "fragment"),
    [
        ("n_trials", 2, "n_trials = 2 is invalid: expected an integer in [4, 4096]"),
        ("dwell_s", 0.0, "dwell_s = 0.0 is invalid: expected a value in [0.001, 60] s"),
        ("scatter_tolerance", 0.5, "scatter_tolerance = 0.5 is invalid"),
        ("loop_tolerance_m", -1e-9, "loop_tolerance_m = -1e-09 is invalid"),
        ("in_loop_trials", 1, "in_loop_trials = 1 is invalid: expected an integer in [2, 4096]"),
        (
            "backlash_widths_m",
            (8e-6, 6e-6),
            "backlash_widths_m = (8e-06, 6e-06) is invalid: expected an ascending tuple",
        ),
        ("friction_spreads", (0.2, 0.7), "friction_spreads = (0.2, 0.7) is invalid"),
    ],
)
def test_settings_are_checked(field: str, value: object, fragment: str) -> None:
    with pytest.raises(ConfigError) as exc:
        IsoDiagnosisSettings(**{field: value})  # type: ignore[arg-type]
    assert fragment in str(exc.value)


# --------------------------------------------------------------------------------------------
# The command and the benchmark write their folders
# --------------------------------------------------------------------------------------------


def _small_scans(monkeypatch: pytest.MonkeyPatch) -> None:
    """The command's settings with the in-loop scans at one size each."""
    monkeypatch.setattr(
        idg,
        "IsoDiagnosisSettings",
        functools.partial(
            IsoDiagnosisSettings, backlash_widths_m=(12e-6,), friction_spreads=(0.5,)
        ),
    )


def test_the_command_writes_the_report(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    _small_scans(monkeypatch)
    path = iso_truth.write_case(iso_truth.draw_case("abbe", 11), tmp_path / "a.csv")
    out = tmp_path / "out"
    code = main(
        ["iso-diagnose", str(path), "--trials", "8", "--no-plot", "--quiet", "--out", str(out)]
    )
    assert code == 0, capsys.readouterr().err
    rep = json.loads((out / "report.json").read_text(encoding="utf-8"))
    assert rep["verdict"] == "abbe"
    assert {p.name for p in out.iterdir()} >= {"report.json", "report.md"}
    assert "Verdict: abbe" in (out / "report.md").read_text(encoding="utf-8")


def test_a_one_case_benchmark_scores_its_case(tmp_path: Path) -> None:
    s = run_iso_benchmark(tmp_path / "b", cases=1, seed=5, settings=FAST, progress=False)
    row = s["rows"][0]
    assert s["cases"] == 1 and row["hidden"] in iso_truth.EFFECTS
    assert (tmp_path / "b" / "cases" / "case_0000.csv").exists()
    assert sum(sum(r.values()) for r in s["confusion"].values()) == 1
    assert "Confusion" in (tmp_path / "b" / "benchmark.md").read_text(encoding="utf-8")


@pytest.mark.parametrize("encoder", [False, True])
def test_the_benchmark_command_writes_the_encoders_readings_with_encoder(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, encoder: bool
) -> None:
    import nanostage.iso_diagnosis_benchmark as ibm

    # The diagnosis itself is the library's (tested above): here only what the option
    # changes, the cases' files and what the diagnosis reads from them.
    seen: list[Any] = []

    def stub(meas: Any, *args: Any, **kwargs: Any) -> dict[str, Any]:
        seen.append(meas)
        gap = {"figure_gap_rms_m": 1e-7, "iso_gap": 1.0}
        return {
            "verdict": "none",
            "indistinguishable": [],
            "candidates": [],
            "gap_before": gap,
            "gap_after": gap,
            "figure_gap_shrink": 0.0,
        }

    monkeypatch.setattr(ibm, "diagnose_iso", stub)
    out = tmp_path / "b"
    argv = ["iso-diagnose-benchmark", "--cases", "1", "--seed", "5", "--quiet", "--out", str(out)]
    assert main(argv + ["--encoder"] * encoder) == 0
    header = (out / "cases" / "case_0000.csv").read_text(encoding="utf-8").splitlines()[0]
    assert ("encoder_m" in header.split(",")) is encoder
    assert (seen[0].encoder_m is not None) is encoder
    summary = json.loads((out / "benchmark.json").read_text(encoding="utf-8"))
    assert summary["encoder_readings"] is encoder
    title = (out / "benchmark.md").read_text(encoding="utf-8").splitlines()[0]
    assert ("with the encoder's readings" in title) is encoder
    assert summary["magnitude_scale"] == 1.0 and "times their drawn size" not in title
    scaled = tmp_path / "scaled"
    assert main([*argv[:-1], str(scaled), "--scale", "0.3"]) == 0
    summary = json.loads((scaled / "benchmark.json").read_text(encoding="utf-8"))
    assert summary["magnitude_scale"] == 0.3
    assert summary["rows"][0]["hidden_parameters"]["magnitude_scale"] == 0.3
    title = (scaled / "benchmark.md").read_text(encoding="utf-8").splitlines()[0]
    assert "hidden effects at 0.3 times their drawn size" in title
    calls = len(seen)
    assert main([*argv[:-1], str(tmp_path / "bad"), "--scale", "0"]) != 0
    assert len(seen) == calls and not (tmp_path / "bad").exists()
    # The sizes, stored per case and drawn again from the seed for a run without them,
    # and the pooled table of both runs (the module's command).
    stored = summary["rows"][0]["hidden_size_counts"]
    del summary["rows"][0]["hidden_size_counts"]
    (scaled / "benchmark.json").write_text(json.dumps(summary), encoding="utf-8")
    pooled = ibm.pooled_rows([out, scaled])
    assert pooled[1]["hidden_size_counts"] == stored and pooled[1]["magnitude_scale"] == 0.3
    unscaled = iso_truth.draw_case(pooled[0]["hidden"], 5 * 100_000)
    assert pooled[0]["hidden_size_counts"] == unscaled.hidden_size_counts
    assert ibm.main([str(out), str(scaled)]) == 0
    assert ibm.main([str(tmp_path / "missing")]) == 2
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "benchmark.json").write_text('{"cases": 1}', encoding="utf-8")
    with pytest.raises(ValueError, match="no list of case rows"):
        ibm.pooled_rows([tmp_path / "other"])


@pytest.mark.usefixtures("without_matplotlib")
def test_without_matplotlib_the_report_is_written_with_a_note(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    _small_scans(monkeypatch)
    path = iso_truth.write_case(iso_truth.draw_case("none", 5), tmp_path / "n.csv")
    out = tmp_path / "out"
    assert main(["iso-diagnose", str(path), "--trials", "8", "--quiet", "--out", str(out)]) == 0
    err = capsys.readouterr().err
    assert not (out / "diagnosis.png").exists() and (out / "report.json").is_file()
    assert 'pip install "nanostage[plot]"' in err
    assert "matplotlib is not installed" in (out / "report.md").read_text(encoding="utf-8")


def test_an_executor_gives_the_local_report(tmp_path: Path) -> None:
    from concurrent.futures import ThreadPoolExecutor

    path = iso_truth.write_case(iso_truth.draw_case("interpolation_error", 13), tmp_path / "i.csv")
    meas = read_iso_measurement(path)
    system = presets.preset_system("seed")
    local = diagnose_iso(meas, system, FAST)
    with ThreadPoolExecutor(2) as ex:
        remote = diagnose_iso(meas, system, FAST, executor=ex)
    for r in (local, remote):
        r.pop("timing_s")
    assert json.dumps(to_jsonable(local)) == json.dumps(to_jsonable(remote))
    assert local["verdict"] == "interpolation_error"


def test_with_encoder_readings_a_loop_that_stops_counts_off_is_not_blamed_on_the_chain(
    tmp_path: Path,
) -> None:
    # The loop stops 3 counts high on every ↑ approach (an in-loop reversal the encoder
    # sees): on the interferometer alone it looks like a tilt or a creep; the interferometer
    # minus the encoder has no chain effect in it.
    case = iso_truth.draw_case("none", 21)
    for r in case.rows:
        if r["direction"] == "+":
            r["actual_m"] += 3 * iso_truth.COUNT_M
            r["encoder_m"] += 3 * iso_truth.COUNT_M
    system = presets.preset_system("seed")
    with_enc = read_iso_measurement(iso_truth.write_case(case, tmp_path / "e.csv", encoder=True))
    rep = diagnose_iso(with_enc, system, FAST, in_loop=())
    assert rep["measured"]["fitted_channel"] == "interferometer_minus_encoder"
    assert rep["verdict"] == "none"
    alone = read_iso_measurement(iso_truth.write_case(case, tmp_path / "i.csv"))
    assert diagnose_iso(alone, system, FAST, in_loop=())["verdict"] != "none"


# --------------------------------------------------------------------------------------------
# In-loop candidates: campaigns of the model with the effect
# --------------------------------------------------------------------------------------------

#: The scans of the in-loop tests; the measurement is the model itself, so its stop is
#: trusted to 20 nm (the loop's nuisance stays small).
IN_LOOP = IsoDiagnosisSettings(
    n_trials=8,
    seed=3,
    backlash_widths_m=(8e-6, 10e-6, 12e-6),
    friction_spreads=(0.2, 0.5),
    loop_tolerance_m=20e-9,
)
CHAIN = {c.name for c in idg.CANDIDATES}


def test_a_backlash_in_the_loop_is_named_backlash_with_its_width(tmp_path: Path) -> None:
    base = presets.preset_system("seed")
    system = dataclasses.replace(
        base, effects=dataclasses.replace(base.effects, backlash=Backlash(width_m=11e-6))
    )
    meas = read_iso_measurement(_model_test(tmp_path, None, 5e-9, system, encoder=True))
    rep = diagnose_iso(meas, base, IN_LOOP)
    assert rep["verdict"] == "backlash", [(c["name"], c["significant"]) for c in rep["candidates"]]
    top = rep["candidates"][0]
    # With the encoder's readings, an in-loop effect is fitted where the loop's stop shows.
    assert top["in_loop"] and top["fitted_channel"] == "encoder"
    # The scan interpolates between 10 and 12 µm: within ±1.5 µm of the width.
    assert top["parameters"]["width_m"] == pytest.approx(11e-6, abs=1.5e-6)
    # The encoder sees the table: the chain's candidates find nothing beside the encoder.
    assert not any(c["significant"] for c in rep["candidates"] if c["name"] in CHAIN)
    assert "backlash" not in rep["not_covered"]


def test_friction_scatter_in_the_loop_is_named_with_its_spread(tmp_path: Path) -> None:
    base = presets.preset_system("seed")
    sf = StochasticFriction(level_spread=0.4, within_spread=0.4)
    system = dataclasses.replace(base, effects=dataclasses.replace(base.effects, stochastic=sf))
    path = _model_test(tmp_path, None, 5e-9, system, encoder=True)
    rep = diagnose_iso(read_iso_measurement(path), base, IN_LOOP)
    assert rep["verdict"] == "friction_scatter", [
        (c["name"], c["significant"]) for c in rep["candidates"]
    ]
    top = rep["candidates"][0]
    assert top["parameters"]["spread"] == pytest.approx(0.4, abs=0.15)
    # The chain's candidates, beside the encoder, reproduce the ISO quantities far worse.
    assert rep["indistinguishable"] == []
    assert all(c["iso_gap"] > 3 * top["iso_gap"] for c in rep["candidates"] if c["name"] in CHAIN)


def test_the_truths_in_loop_effects_move_the_stop_the_encoder_sees() -> None:
    # A backlash: the table stays past the target in the approach's direction by the
    # coast (coast fraction × width), within its jitter, beside the loop's nominal stop;
    # the encoder (on the table) reads the count the table stopped in.
    case = iso_truth.draw_case("backlash", 7)
    p = case.parameters
    lost = p["coast_fraction"] * p["width_m"]
    assert 0.12e-6 <= lost <= 0.176e-6
    x = np.array([r["target_m"] for r in case.rows])
    dev = np.array([r["actual_m"] for r in case.rows]) - x
    d = np.array([1.0 if r["direction"] == "+" else -1.0 for r in case.rows])
    # The nominal stop and bias are within 1.4/2 + 0.3 count, the jitter and noise on top.
    bound = (0.7 + 0.3) * iso_truth.COUNT_M + p["jitter_m"] + 5 * p["reading_noise_m"]
    assert np.max(np.abs(dev - d * lost)) < bound
    enc = np.array([r["encoder_m"] for r in case.rows])
    # The encoder rounds where the loop stopped (noise aside): within half a count of it.
    assert np.max(np.abs(enc - x - dev)) < 0.5 * iso_truth.COUNT_M + 5 * p["reading_noise_m"]
    # Friction scatter: the stops spread over the dead zone plus the stick-slip scatter.
    fs = iso_truth.draw_case("friction_scatter", 7)
    q = fs.parameters
    dev_fs = np.array([r["actual_m"] - r["target_m"] for r in fs.rows])
    expected = math.sqrt(
        (q["dead_zone_counts"] * iso_truth.COUNT_M) ** 2 / 3 + q["stick_slip_m"] ** 2
    )
    # Beside the bias per target and direction (±0.3 count), 110 readings: within 25 %.
    assert np.std(dev_fs) == pytest.approx(
        math.hypot(expected, 0.3 * iso_truth.COUNT_M / math.sqrt(3)), rel=0.25
    )


@pytest.mark.parametrize("effect", iso_truth.EFFECTS)
def test_the_truths_scale_multiplies_the_hidden_error_and_nothing_else(effect: str) -> None:
    # Each reading is the nominal loop's stop and noise plus scale × the hidden error (a
    # friction scatter's stop moves from the nominal's to its own), from the same draws:
    # the readings are linear in the scale, and scale 1 is the default case exactly.
    def actual(scale: float | None) -> np.ndarray:
        kw = {} if scale is None else {"scale": scale}
        case = iso_truth.draw_case(effect, 11, **kw)
        return np.array([r["actual_m"] for r in case.rows])

    full, half, quarter = actual(1.0), actual(0.5), actual(0.25)
    assert np.array_equal(full, actual(None))
    if effect == "none":
        assert np.array_equal(full, half) and np.array_equal(full, quarter)
        return
    assert np.max(np.abs(full - half)) > 1e-9
    np.testing.assert_allclose(full - quarter, 1.5 * (full - half), rtol=0, atol=1e-15)
    assert iso_truth.draw_case(effect, 11, scale=0.5).parameters["magnitude_scale"] == 0.5


def test_the_truths_hidden_error_is_what_the_effect_adds_to_each_reading() -> None:
    # A scale error: strain × distance from the fixing point, times the scale.
    case = iso_truth.draw_case("scale_error", 4, scale=0.5)
    p = case.parameters
    x = np.array([r["target_m"] for r in case.rows])
    np.testing.assert_allclose(
        case.hidden_error_m, 0.5 * p["strain"] * (x - p["fixing_point_m"]), rtol=1e-12, atol=0
    )
    e = case.hidden_error_m
    assert case.hidden_size_counts == pytest.approx(float(np.std(e)) / iso_truth.COUNT_M)
    # Every effect (a friction scatter's stop included): the readings at two scales differ
    # by the difference of their hidden errors; none has no error and size 0.
    for effect in iso_truth.EFFECTS:
        a, b = iso_truth.draw_case(effect, 9, scale=0.8), iso_truth.draw_case(effect, 9, scale=0.2)
        da = np.array([r["actual_m"] for r in a.rows]) - np.array([r["actual_m"] for r in b.rows])
        np.testing.assert_allclose(da, a.hidden_error_m - b.hidden_error_m, rtol=0, atol=1e-15)
    assert iso_truth.draw_case("none", 9).hidden_size_counts == 0.0


def test_cases_are_counted_by_the_size_of_their_hidden_error() -> None:
    import nanostage.iso_diagnosis_benchmark as ibm

    def row(hidden: str, size: float, correct: bool) -> dict[str, Any]:
        return {"hidden": hidden, "hidden_size_counts": size, "correct": correct}

    rows = [
        row("none", 0.0, True),
        row("abbe", 0.1, False),
        row("abbe", 0.3, True),
        row("abbe", 0.4, False),
        row("backlash", 1.0, True),
        row("backlash", 7.0, True),
    ]
    table = ibm.detection_by_size(rows)
    assert table["abbe"] == {"0–0.25": [0, 1], "0.25–0.5": [1, 2]}
    assert table["backlash"] == {"1–2": [1, 1], "≥ 5": [1, 1]}
    assert table["all"]["0.25–0.5"] == [1, 2] and "none" not in table
    md = ibm.detection_markdown(rows)
    assert "| abbe | 0/1 | 1/2 | — | — | — | — |" in md
    assert md.splitlines()[-1] == "| all | 0/1 | 1/2 | — | 1/1 | — | 1/1 |"


@pytest.mark.parametrize("bad", [0.0, -0.5, 1.5, math.nan, True, "1"])
def test_a_scale_outside_zero_to_one_is_an_error_naming_it(bad: object) -> None:
    with pytest.raises(ValueError, match=r"scale = .* expected a number in \(0, 1\]"):
        iso_truth.draw_case("abbe", 1, scale=bad)  # type: ignore[arg-type]


def test_the_truths_hunting_backlash_swings_by_its_width_and_the_encoder_sees_it() -> None:
    case = iso_truth.draw_case("backlash", 1)
    p = case.parameters
    assert p["hunting"] == 1.0 and 14e-6 <= p["width_m"] <= 30e-6
    x = np.array([r["target_m"] for r in case.rows])
    dev = np.array([r["actual_m"] for r in case.rows]) - x
    d = np.array([1.0 if r["direction"] == "+" else -1.0 for r in case.rows])
    # About the swing's centre (past the target in the approach's direction), the table is
    # at most half a swing away, beside the loop's nominal stop (within a count) and noise.
    about = dev - d * p["centre_fraction"] * p["width_m"]
    swing = p["swing_fraction"] * p["width_m"]
    loop = 1.0 * iso_truth.COUNT_M + 5 * p["reading_noise_m"]
    assert np.max(np.abs(about)) <= swing + loop
    # The stuck part of the cycle: that share of the readings at an end of the swing
    # (binomial, 110 readings: within 4 standard deviations).
    at_end = np.mean(np.abs(np.abs(about) - swing) <= loop)
    n = len(case.rows)
    sd = math.sqrt(p["stuck_fraction"] * (1 - p["stuck_fraction"]) / n)
    assert abs(at_end - p["stuck_fraction"]) < 4 * sd + 0.02
    # The encoder on the table sees the swing.
    enc = np.array([r["encoder_m"] for r in case.rows])
    assert np.max(np.abs(enc - x - dev)) < 0.5 * iso_truth.COUNT_M + 5 * p["reading_noise_m"]
    # Half the backlash cases hunt (the truth's own draw), the others coast.
    hunting = [iso_truth.draw_case("backlash", k).parameters["hunting"] for k in range(1, 41)]
    assert 10 <= sum(hunting) <= 30


def test_the_scan_keeps_a_hunting_sizes_change_per_direction_and_the_rest_as_scatter() -> None:
    effect = np.array([1.0, 5.0, -3.0, -7.0, 2.0, 0.0])
    up = np.array([True, True, False, False, True, False])
    group = np.array([0, 0, 1, 1, 0, 1])
    mean, rest = idg._direction_split(effect, up)
    assert mean.tolist() == [8 / 3, 8 / 3, -10 / 3, -10 / 3, 8 / 3, -10 / 3]
    assert rest == pytest.approx(float(np.mean((effect - mean) ** 2)))
    # Here the groups are the directions: the rms within them is the rest's.
    assert idg._within_rms(effect, group) == pytest.approx(math.sqrt(rest))


def _few_readings(case: iso_truth.TruthCase, targets: int, runs: int) -> iso_truth.TruthCase:
    keep = sorted({r["target_m"] for r in case.rows})[:targets]
    kept = [r["target_m"] in keep and r["run"] <= runs for r in case.rows]
    rows = [r for r, k in zip(case.rows, kept, strict=True) if k]
    return iso_truth.TruthCase(case.effect, case.parameters, rows, case.hidden_error_m[kept])


HUNT = IsoDiagnosisSettings(
    n_trials=8, seed=3, backlash_widths_m=(12e-6, 14e-6, 20e-6), friction_spreads=(0.5,)
)


@pytest.mark.parametrize("seed", [1, 15])
def test_a_backlash_that_makes_the_loop_hunt_is_named_backlash(tmp_path: Path, seed: int) -> None:
    # The truth's hunting backlash (its own stick-slip swing), on 4 targets × 3 runs.
    case = _few_readings(iso_truth.draw_case("backlash", seed), 4, 3)
    assert case.parameters["hunting"] == 1.0
    system = presets.preset_system("seed")
    path = iso_truth.write_case(case, tmp_path / "e.csv", encoder=True)
    rep = diagnose_iso(read_iso_measurement(path), system, HUNT)
    assert rep["verdict"] == "backlash", [(c["name"], c["significant"]) for c in rep["candidates"]]
    top = rep["candidates"][0]
    # The model hunts from 14 µm on: those sizes keep their change per direction only.
    assert top["scan"]["hunting"] == [False, True, True]
    assert top["parameters"]["width_m"] > 12e-6
    assert rep["indistinguishable"] == []
    # Without the encoder, a scatter of the interferometer's readings can stand for the
    # swing: the report names what is tied with the experiment that separates them.
    alone = iso_truth.write_case(case, tmp_path / "i.csv")
    rep = diagnose_iso(read_iso_measurement(alone), system, HUNT)
    names = [rep["verdict"], *(t["candidate"] for t in rep["indistinguishable"])]
    assert "backlash" in names
    for t in rep["indistinguishable"]:
        if {rep["verdict"], t["candidate"]} == {"backlash", "interferometer_noise"}:
            assert "encoder" in t["separating_test"]


def test_the_encoders_readings_separate_a_stop_scatter_from_the_interferometers_noise(
    tmp_path: Path,
) -> None:
    # Without the encoder both add a random scatter per reading; with it, the in-loop
    # candidates are fitted on the encoder's deviations, where the interferometer's noise
    # is not.
    case = iso_truth.draw_case("interferometer_noise", 12)
    path = iso_truth.write_case(case, tmp_path / "n.csv", encoder=True)
    rep = diagnose_iso(read_iso_measurement(path), presets.preset_system("seed"), FAST)
    assert rep["verdict"] == "interferometer_noise"
    by_name = {c["name"]: c for c in rep["candidates"]}
    assert by_name["friction_scatter"]["fitted_channel"] == "encoder"
    assert not by_name["friction_scatter"]["significant"]
    assert "friction_scatter" not in [t["candidate"] for t in rep["indistinguishable"]]
