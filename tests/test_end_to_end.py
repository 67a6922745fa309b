"""The whole path a user walks, through the command line: measured traces → ``diagnose`` →
``model.toml`` → ISO 230-2 repeatability by Monte Carlo → tuned gains on that model, which
beat the model's own gains on the same model and the same draws. The commands are the
README's ("From traces to tuned gains"), run as written; the traces come from
``examples/end_to_end/make_traces.py`` (a known truth: the seed axis with the user's gains
and a hidden +6 N offset force). Also the ``--gains`` option of ``reproduce`` and ``tune``.
"""

from __future__ import annotations

import json
import math
import shlex
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from nanostage import ConfigError, cli, load_model, load_model_file, presets
from nanostage.config import FpgaPid, Plant, System
from nanostage.studies import paper_campaigns
from nanostage.studies.reproduce import study_system
from nanostage.tune import Objective, evaluate_gains, tuning_cycle, with_friction_spread

ROOT = Path(__file__).resolve().parents[1]
SCRIPT = "examples/end_to_end/make_traces.py"

#: The README's commands, in order (the test checks that the README holds each line).
COMMANDS = (
    f"python {SCRIPT} --out example",
    "nanostage diagnose example/manifest.toml --out diag",
    "nanostage reproduce --model diag/model.toml --gains model --campaigns "
    "--campaign-trials 16 --out iso",
    "nanostage tune --model diag/model.toml --gains model --step-um 100 --trials 16 "
    "--eval-trials 32 --popsize 4 --maxiter 3 --seed 1 --out tune",
)

#: The truth of the example (examples/end_to_end/make_traces.py).
TRUTH_GAINS = (300.0, 3.0, 20.0)
TRUTH_OFFSET_N = 6.0
TRUTH_DAHL_N = 30.4 * 1.05
#: The encoder count of the seed axis, m.
COUNT_M = 1e-7


def _run(command: str, cwd: Path) -> None:
    argv = shlex.split(command)
    if argv[0] == "python":
        done = subprocess.run(
            [sys.executable, str(ROOT / argv[1]), *argv[2:]],
            cwd=cwd,
            capture_output=True,
            text=True,
            check=False,
        )
        assert done.returncode == 0, done.stderr
        return
    assert argv[0] == "nanostage"
    assert cli.main(argv[1:]) == cli.EXIT_OK, command


def _json(path: Path) -> Any:
    return json.loads(path.read_text(encoding="utf-8"))


@pytest.fixture(scope="module")
def walked(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The folder in which every README command has run."""
    d = tmp_path_factory.mktemp("walk")
    mp = pytest.MonkeyPatch()
    mp.chdir(d)
    try:
        for command in COMMANDS:
            _run(command, d)
    finally:
        mp.undo()
    return d


def test_the_readme_gives_these_commands() -> None:
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    section = readme.split("### From traces to tuned gains", 1)[1].split("\n#", 1)[0]
    lines = [line.strip() for line in section.splitlines()]
    for command in COMMANDS:
        assert command in lines, command


def test_the_example_script_is_deterministic(walked: Path, tmp_path: Path) -> None:
    _run(COMMANDS[0].replace("--out example", f"--out {tmp_path / 'again'}"), tmp_path)
    names = sorted(p.name for p in (walked / "example").iterdir())
    assert names == sorted(p.name for p in (tmp_path / "again").iterdir())
    assert len([n for n in names if n.endswith(".csv")]) == 8
    for n in names:
        assert (walked / "example" / n).read_bytes() == (tmp_path / "again" / n).read_bytes()


def test_diagnose_finds_the_hidden_offset_force(walked: Path) -> None:
    report = _json(walked / "diag" / "report.json")
    assert report["selected"] == ["offset_force"]
    # The validation gap with the Dahl level refitted alone is about 2.2 µm (the offset force
    # shifts every slew); the offset force takes it near the noise floor (29 nm).
    before = report["gap_before"]["total_rms_m"]
    after = report["gap_after"]["total_rms_m"]
    assert before > 1e-6
    assert after < 0.1 * before
    assert after < 5 * report["noise_floor_rms_m"]
    # The model file: the identified force and Dahl level near the truth's, and the
    # manifest's controller gains (the user's, not Table 1's).
    doc = load_model_file(walked / "diag" / "model.toml")
    model = doc.system
    assert isinstance(model.plant, Plant) and isinstance(model.controller, FpgaPid)
    force = model.plant.table.external_force_n
    # Measured: 6.24 N (the Dahl level and the force trade against each other through the
    # per-trial friction scatter); a wrong sign or effect would be far outside 10 %.
    assert force == pytest.approx(TRUTH_OFFSET_N, rel=0.1)
    assert model.plant.dahl.coulomb_force_n == pytest.approx(TRUTH_DAHL_N, rel=0.05)
    se = doc.identified["plant.table.external_force_n"].std_error
    assert se is not None and 0.0 < se < 0.1 * abs(force)
    c = model.controller
    assert (c.kp, c.ki, c.kd) == TRUTH_GAINS
    assert doc.provenance["selected_effects"] == ["offset_force"]


def test_the_iso_campaigns_give_the_repeatability_of_the_model(walked: Path) -> None:
    res = _json(walked / "iso" / "campaigns.json")
    assert res["gains"] == "model"
    summary = _json(walked / "iso" / "summary.json")
    assert {(s["kp"], s["ki"], s["kd"]) for s in summary["steps"]} == {TRUTH_GAINS}
    model = load_model(walked / "diag" / "model.toml")
    st = paper_campaigns.CampaignSettings(**{**res["settings"], "spreads": (0.2,)})
    for step_m, key in ((100e-6, "100um"), (1e-3, "1000um")):
        row = next(r for r in res["scan"][key] if r["spread"] == 0.2)
        r_up = row["R_up"]["mean_m"]
        assert row["n_failed"] == 0
        # Every step ends within about a count of the target: the encoder reads within ±1
        # count of the target and the true position within a count of the reading, so a
        # trial's five readings lie in a band of 4 counts, whose sample standard deviation
        # is at most 2 counts·√(5/4) and R↑ = 4s at most 0.89 µm. Friction scatter
        # (spread 0.2) makes the trials end at different points: R↑ > 0.
        assert 0.0 < r_up < 4 * 2 * COUNT_M * math.sqrt(5 / 4)
        # The figure by hand: R↑ of one target = 4 × the sample standard deviation of each
        # trial's readings, averaged over the trials (same model, gains, seed, draws).
        camp = paper_campaigns.step_campaign(step_m, 0.2, st, model=model, gains="model")
        readings = np.asarray(camp.actual_m())  # the reading the campaigns evaluate
        assert readings.shape == (st.n_trials, st.repeats)
        by_hand = float(np.mean(4.0 * np.std(readings, axis=1, ddof=1)))
        assert r_up == pytest.approx(by_hand, rel=1e-9)


def test_the_tuned_gains_beat_the_models_own(walked: Path) -> None:
    report = _json(walked / "tune" / "tune.json")
    assert report["gains"] == "model"
    row = report["steps"][0]
    start, tuned = row["model"], row["tuned"]
    assert (start["kp"], start["ki"], start["kd"]) == TRUTH_GAINS
    assert tuned["objective"] < 0.5 * start["objective"]
    md = (walked / "tune" / "tune.md").read_text(encoding="utf-8")
    assert md.startswith("# The model's gains against tuned gains\n")
    assert "| 100 µm | model | 300, 3, 20 | conditional |" in md
    # The same comparison again, outside the command: the model file, the command's
    # objective (mix), friction spread (0.2) and held-out draws (seed 2, 32 trials).
    model = with_friction_spread(load_model(walked / "diag" / "model.toml"), 0.2)
    for name, c in (("model", start), ("tuned", tuned)):
        assert _objective(model, c, seed=2) == c["objective"], name
    # And on draws neither the search nor the comparison saw.
    assert _objective(model, tuned, seed=99) < _objective(model, start, seed=99)


def _objective(model: System, gains: dict[str, Any], *, seed: int) -> float:
    """The ``tune`` command's objective (mix) of ``gains`` on the 100 µm tuning cycle, 32
    trials with campaign seed ``seed``."""
    return evaluate_gains(
        model,
        tuning_cycle(100e-6),
        objective=Objective.mix(),
        n_trials=32,
        seed=seed,
        kp=gains["kp"],
        ki=gains["ki"],
        kd=gains["kd"],
        anti_windup=gains["anti_windup"],
    ).metrics.objective


# ---- the --gains option -------------------------------------------------------------------


def _own_gains_model() -> System:
    """The seed axis with gains that are no step size's Table 1 gains."""
    return presets.with_gains(presets.seed(1e-3), kp=300.0, ki=3.0, kd=20.0)


@pytest.mark.parametrize("step", [100e-6, 1e-3])
def test_study_system_keeps_or_replaces_the_gains(step: float) -> None:
    model = _own_gains_model()
    assert study_system(step, model, "model") == model
    assert study_system(step, model) == presets.table1_system(step, model)
    table1 = study_system(step, model, "table1").controller
    assert isinstance(table1, FpgaPid)
    assert (table1.kp, table1.ki, table1.kd) == presets.table1_gains(step)
    assert study_system(step) == presets.seed(step)


def test_study_system_errors() -> None:
    with pytest.raises(ConfigError, match=r"gains = 'model' needs a model"):
        study_system(1e-3, None, "model")
    with pytest.raises(ConfigError, match=r"gains = 'mine' is invalid: expected one of"):
        study_system(1e-3, _own_gains_model(), "mine")  # type: ignore[arg-type]
    emps = presets.preset_system("emps")
    with pytest.raises(ConfigError, match=r"rigid_axis.*fpga_pid"):
        study_system(1e-3, emps, "model")


def test_reproduce_keeps_the_models_gains(tmp_path: Path) -> None:
    from nanostage import save_model

    path = tmp_path / "own.model.toml"
    save_model(_own_gains_model(), path)
    base = ["reproduce", "--no-plot", "--model", str(path)]
    assert cli.main([*base, "--gains", "model", "--out", str(tmp_path / "m")]) == 0
    assert cli.main([*base, "--out", str(tmp_path / "t")]) == 0
    own = _json(tmp_path / "m" / "summary.json")["steps"]
    table1 = _json(tmp_path / "t" / "summary.json")["steps"]
    assert [(s["kp"], s["ki"], s["kd"]) for s in own] == [TRUTH_GAINS] * 4
    assert [(s["kp"], s["ki"], s["kd"]) for s in table1] == [
        presets.table1_gains(s) for s in (100e-6, 500e-6, 1e-3, 10e-3)
    ]
    # The 1 mm step with the model's gains is the plain simulation of the model file.
    from nanostage import simulate_step, step_metrics

    m = step_metrics(simulate_step(load_model(path), 1e-3, duration_s=0.6))
    assert own[2]["settling_time_s"] == m.settling_time_s
    assert own[2]["overshoot_m"] == m.overshoot_m


@pytest.mark.parametrize("command", ["reproduce", "tune"])
def test_gains_model_without_a_model_is_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], command: str
) -> None:
    out = tmp_path / "out"
    capsys.readouterr()
    assert cli.main([command, "--gains", "model", "--out", str(out)]) == cli.EXIT_ERROR
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    assert err.startswith(f"nanostage {command}: --gains: gains = 'model' needs a model")
    assert "--model FILE" in err
    assert not out.exists()
