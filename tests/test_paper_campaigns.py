"""The paper's step campaigns: the calibration logic on known objectives, a small end-to-end
run, and the ``nanostage reproduce`` command with and without ``--campaigns``."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from nanostage import presets
from nanostage.cli import main
from nanostage.studies.paper_campaigns import (
    GIVEN_MODEL_NAME,
    CampaignSettings,
    _calibrate,
    _readings,
    _system,
    markdown,
    paper_campaigns,
    step_campaign,
)


def test_calibration_finds_a_bracketed_root() -> None:
    calls: list[float] = []

    def f(s: float) -> float:
        calls.append(s)
        return 1e-5 * s  # 3.19 µm at s = 0.319

    grid = [(s, f(s)) for s in (0.0, 0.1, 0.2, 0.3, 0.4, 0.5)]
    cal = _calibrate(f, grid, 3.19e-6, 1e-6)
    assert cal["reached"] and cal["bracket"] == [0.3, 0.4]
    assert cal["spread"] == pytest.approx(0.319, abs=1e-5)
    # A decreasing objective is bracketed as well.
    grid = [(s, 1e-5 * (0.5 - s)) for s in (0.0, 0.25, 0.5)]
    cal = _calibrate(lambda s: 1e-5 * (0.5 - s), grid, 3.19e-6, 1e-6)
    assert cal["spread"] == pytest.approx(0.181, abs=1e-5)


def test_calibration_reports_the_reachable_range_when_out_of_reach() -> None:
    grid = [(0.0, 0.3e-6), (0.25, 0.1e-6), (0.5, 0.2e-6)]
    cal = _calibrate(lambda s: math.nan, grid, 3.19e-6, 1e-3)
    assert not cal["reached"]
    assert cal["reachable_range_m"] == [0.1e-6, 0.3e-6]
    assert cal["spread"] == 0.0 and cal["closest_m"] == 0.3e-6


def test_small_end_to_end_run() -> None:
    st = CampaignSettings(
        repeats=2, dwell_s=0.2, return_s=0.1, n_trials=3, seed=4, spreads=(0.0, 0.3)
    )
    res = paper_campaigns(st, threads=1)
    assert set(res["scan"]) == {"100um", "1000um"}
    for rows in res["scan"].values():
        assert [r["spread"] for r in rows] == [0.0, 0.3]
        for r in rows:
            assert r["n_failed"] == 0
            # One target: A↑ = R↑ for every trial, hence for the mean.
            assert r["A_up"]["mean_m"] == pytest.approx(r["R_up"]["mean_m"], rel=1e-12)
            assert r["R_up"]["p5_m"] <= r["R_up"]["median_m"] <= r["R_up"]["p95_m"]
    # With no spread every trial is the same run: no spread of R↑ over trials.
    r0 = res["scan"]["100um"][0]["R_up"]
    assert r0["p5_m"] == r0["p95_m"]
    for name in ("A_up", "R_up", "A_up_pooled", "R_up_pooled"):
        c = res["calibration"][name]
        assert c["spread"] in (0.0, 0.3) or 0.0 <= c["spread"] <= 0.3
        assert c["predicted_1mm_over_paper"] > 0.0
    assert res["better_reading"].startswith("indistinguishable")
    md = markdown(res)
    assert "| 100um | 0.300 |" in md and "Which reading" in md
    json.dumps(res)


def test_reproduce_is_unchanged_by_default_and_runs_campaigns_on_request(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(["reproduce", "--out", str(tmp_path / "a"), "--no-plot"]) == 0
    assert (tmp_path / "a" / "summary.json").exists()
    assert not (tmp_path / "a" / "campaigns.json").exists()
    assert "campaign" not in capsys.readouterr().out
    out = tmp_path / "b"
    args = ["reproduce", "--out", str(out), "--no-plot", "--campaigns", "--quiet"]
    assert main([*args, "--campaign-trials", "2", "--threads", "1"]) == 0
    res = json.loads((out / "campaigns.json").read_text(encoding="utf-8"))
    assert res["settings"]["n_trials"] == 2
    assert set(res["calibration"]) == {"A_up", "R_up", "A_up_pooled", "R_up_pooled"}
    md = (out / "campaigns.md").read_text(encoding="utf-8")
    assert md.startswith("# ISO 230-2")
    assert res["model"] == "seed preset" and "\nSeed axis, Table 1 gains per step size" in md
    assert "Calibration" in capsys.readouterr().out


def test_campaigns_on_a_model_file_name_the_file_not_the_seed_axis(tmp_path: Path) -> None:
    model = tmp_path / "axis.model.toml"
    assert main(["model", "export", "seed", "--out", str(model)]) == 0
    out = tmp_path / "r"
    args = ["reproduce", "--out", str(out), "--no-plot", "--campaigns", "--quiet"]
    argv = [*args, "--campaign-trials", "2", "--threads", "1", "--model", str(model)]
    assert main(argv) == 0
    res = json.loads((out / "campaigns.json").read_text(encoding="utf-8"))
    assert res["model"] == f"file {model}"
    md = (out / "campaigns.md").read_text(encoding="utf-8")
    assert f"\nAxis of the model file {model}, Table 1 gains per step size" in md
    assert "Seed axis" not in md


def test_the_model_name_defaults_and_is_checked() -> None:
    st = CampaignSettings(repeats=2, n_trials=2, spreads=(0.0,))
    seed = presets.seed()
    res = paper_campaigns(st, threads=1, model=seed)
    assert res["model"] == GIVEN_MODEL_NAME and "Axis of the model a given System" in markdown(res)
    # A result written before the model was recorded is the seed axis's.
    del res["model"]
    assert "\nSeed axis, " in markdown(res)
    with pytest.raises(ValueError, match="model_name = 'x' is given without a model"):
        paper_campaigns(st, model_name="x")
    with pytest.raises(ValueError, match="model_name = '' is invalid: expected a non-empty"):
        paper_campaigns(st, model=seed, model_name="")


def test_backlash_width_is_checked_before_any_work(tmp_path: Path) -> None:
    for bad in (-1e-6, math.nan, 2e-4):
        with pytest.raises(ValueError, match=r"backlash_width_m = .* expected a width in"):
            CampaignSettings(backlash_width_m=bad)
    out = tmp_path / "r"
    args = ["reproduce", "--out", str(out), "--no-plot", "--campaigns"]
    assert main([*args, "--campaign-backlash-m", "0.5"]) == 2
    assert not out.exists()  # nothing was simulated or written


def test_backlash_in_the_loop_scatters_the_steps_by_micrometres() -> None:
    """The held-out check of docs/campaigns.md: with the gearhead backlash in the loop the
    100 µm steps hunt through the dead band and end micrometres apart, where the paper's model
    ends each step within about one 100 nm count (R↑ of ±1 count ≈ 0.23 µm)."""
    plain = CampaignSettings(repeats=3, n_trials=2, seed=4)
    assert _system(100e-6, 0.0, plain.backlash_width_m).effects.backlash is None
    with_backlash = CampaignSettings(repeats=3, n_trials=2, seed=4, backlash_width_m=5e-6)
    system = _system(100e-6, 0.0, with_backlash.backlash_width_m)
    assert system.effects.backlash is not None and system.effects.backlash.width_m == 5e-6
    r0 = _readings(step_campaign(100e-6, 0.0, plain, threads=1))
    r1 = _readings(step_campaign(100e-6, 0.0, with_backlash, threads=1))
    assert r0["n_failed"] == r1["n_failed"] == 0
    assert r0["R_up"]["mean_m"] < 0.5e-6 < 1e-6 < r1["R_up"]["mean_m"]
