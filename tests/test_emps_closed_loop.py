"""EMPS in closed loop with the same components as the seed axis: the Rust cascade
controller against the logged command, the authors' yardstick, output-error identification
and prediction under a known command disturbance.

Real-data tests read ``../shared/data/emps/DATA_EMPS.mat`` and skip, naming the path, when
it is absent.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

import nanostage as ns
from nanostage import _core, presets
from nanostage.config import replace_paths
from nanostage.diagnosis.predict import PredictError, predict
from nanostage.studies.emps import EmpsData, cascade_command_v, load_emps
from nanostage.studies.emps_study import output_error_fit, simulate_experiment, yardstick

from conftest import SHARED

MAT = SHARED / "data" / "emps" / "DATA_EMPS.mat"


@pytest.fixture(scope="module")
def data() -> EmpsData:
    if not MAT.exists():
        pytest.skip(f"EMPS data not found at {MAT} (CI has ../shared beside the checkout)")
    return load_emps(MAT)


def test_rust_cascade_reproduces_logged_command(data: EmpsData) -> None:
    """The emulated controller (Rust) turns the logged reference and position into the logged
    command to 0.004 V rms, like the independent numpy law; a one-sample shift does not."""
    e = data.experiment
    assert e.command_v is not None
    ctl = presets.emps().controller
    u = _core.cascade_run(ctl, e.reference_m, e.position_m)
    err = u[2:] - e.command_v[2:]
    assert np.sqrt(np.mean(err**2)) < 0.004
    assert np.max(np.abs(err)) < 0.013
    ref = cascade_command_v(e.reference_m, e.position_m, data.kp_per_s, data.kv_v_s_per_m, 1e-3)
    # Same law, different evaluation order: equal to rounding (1e-9 V).
    np.testing.assert_allclose(u, ref, rtol=0, atol=1e-9)
    shifted = u[2:-1] - e.command_v[3:]
    assert np.sqrt(np.mean(shifted**2)) > 0.04


def test_authors_model_in_closed_loop_meets_their_yardstick(data: EmpsData) -> None:
    """The authors' symmetric model in the nanostage loop: position error below their
    0.014 %, velocity within 0.5 %, force within 10 % (they report 5.8 % with their own
    simulation; see docs/emps.md for why ours is higher)."""
    y = yardstick(presets.emps(), data)
    assert y.position < 0.00014
    assert y.velocity < 0.005
    assert y.force < 0.10
    # The naive model (no Coulomb friction, no offset) is clearly worse on force.
    assert yardstick(presets.emps_naive(), data).force > 1.5 * y.force


def test_output_error_identification_converges_from_a_perturbed_start(data: EmpsData) -> None:
    """Closed-loop output-error identification lands on the same parameters from the
    authors' values and from a start 5–10 % off, near the IDIM-LS values, and improves the
    force error of the perturbed start."""
    start = replace_paths(
        presets.emps(),
        {
            "plant.mass_kg": 90.0,
            "plant.friction.viscous_n_s_per_m": 180.0,
            "plant.friction.coulomb_force_n": 18.0,
            "plant.friction.static_force_n": 18.0,
            "plant.external_force_n": 0.0,
        },
    )
    a = output_error_fit(data, start)
    b = output_error_fit(data)
    for k, v in a.values.items():
        assert abs(v - b.values[k]) <= 3 * max(a.std_errors[k], b.std_errors[k]) + 0.02, k
        assert np.isfinite(a.std_errors[k]) and a.std_errors[k] > 0
    assert abs(a.values["plant.mass_kg"] - 95.11) < 1.5
    assert abs(a.values["plant.friction.coulomb_force_n"] - 20.39) < 2.0
    assert abs(a.values["plant.external_force_n"] - (-3.16)) < 0.5
    assert yardstick(a.system, data).force < yardstick(start, data).force


def _pulse_case(tmp_path: Path) -> tuple[Path, np.ndarray, np.ndarray]:
    """A synthetic validation-style run: EMPS-like reference with a square pulse train
    (0.5 s on, 0.5 s off, 1.5 V) added to the command after saturation."""
    n = 3000
    t = np.arange(n) * 1e-3
    ref = 0.05 * (1 - np.cos(2 * np.pi * t / 3.0)) / 2
    dist = np.where((t % 1.0) < 0.5, 1.5, 0.0)
    meas = ns.simulate(presets.emps(), ref, command_disturbance_v=dist).encoder_position_m
    (tmp_path / "pulses.csv").write_text(
        "time_s,reference_m,disturbance_v,position_m\n"
        + "\n".join(
            f"{float(a)!r},{float(b)!r},{float(c)!r},{float(d)!r}"
            for a, b, c, d in zip(t, ref, dist, meas, strict=True)
        )
    )
    (tmp_path / "predict.toml").write_text(
        '[model]\npreset = "emps"\n[model.overrides]\n"plant.mass_kg" = 95.1089\n\n'
        '[[experiment]]\nname = "pulses"\nfile = "pulses.csv"\n'
    )
    return tmp_path / "predict.toml", ref, dist


def test_predict_with_a_known_pulse_train(tmp_path: Path) -> None:
    manifest, ref, dist = _pulse_case(tmp_path)
    summary = predict(manifest, tmp_path / "out")
    out = np.genfromtxt(tmp_path / "out" / "pulses.csv", delimiter=",", names=True)
    direct = simulate_experiment(
        presets.emps(),
        ns.experiment.Experiment(
            name="p",
            time_s=out["time_s"],
            reference_m=ref,
            position_m=np.full(len(ref), ref[0]),
            disturbance_v=dist,
        ),
    )
    np.testing.assert_array_equal(out["position_m"], direct.encoder_position_m)
    np.testing.assert_array_equal(out["command_v"], direct.command)
    # The prediction reproduces its own (noise-free) measurement exactly...
    assert summary["experiments"]["pulses"]["position_relative_error"] == 0.0
    # ...and the pulses matter: without them the command differs by about the pulse height.
    free = ns.simulate(presets.emps(), ref)
    assert np.max(np.abs(free.command - direct.command)) > 1.0
    # The controller compensates the pulses: command ≈ −pulse once settled (±0.3 V).
    settled = (out["time_s"] % 1.0 > 0.3) & (out["time_s"] % 1.0 < 0.5) & (out["time_s"] > 1)
    assert np.all(np.abs(direct.command[settled] - free.command[settled] + dist[settled]) < 0.3)


def test_predict_bad_input_names_the_file_and_line(tmp_path: Path) -> None:
    manifest, _, _ = _pulse_case(tmp_path)
    lines = (tmp_path / "pulses.csv").read_text(encoding="utf-8").splitlines()
    lines[5] = lines[5].replace(",", ",x", 1)
    (tmp_path / "pulses.csv").write_text("\n".join(lines))
    with pytest.raises(PredictError, match=r"pulses.csv: line 6, column 'reference_m'"):
        predict(manifest, tmp_path / "out")
    (tmp_path / "predict.toml").write_text('[model]\npreset = "nope"\n')
    with pytest.raises(PredictError, match="unknown preset 'nope'"):
        predict(manifest, tmp_path / "out")


def test_emps_preset_components() -> None:
    """The EMPS preset uses the shared components: force drive, table static map with true
    stiction, motor-side encoder of 5e-8 m, cascade controller, one-sample delay."""
    s = presets.emps()
    assert isinstance(s.plant, ns.config.ForceDrivePlant)
    assert s.encoder.count_m == 5e-8 and s.encoder.side == "motor"
    assert s.effects.computation_delay_samples == 1
    asym = presets.emps(asymmetric=True)
    f = asym.plant.friction  # type: ignore[union-attr]
    assert f.coulomb_force_n * (1 + f.asymmetry) == pytest.approx(20.1440)
    assert f.viscous_n_s_per_m * (1 - f.viscous_asymmetry) == pytest.approx(240.4236)
    assert dataclasses.replace(s).plant == s.plant


def test_diagnosis_on_real_data_from_the_naive_model(data: EmpsData, tmp_path: Path) -> None:
    """The manifest cuts DATA_EMPS into time windows (train 1 and 3, validate 2 and 4); from
    mass + viscous friction only, the diagnosis first adds Coulomb friction, and the model
    it selects simulates the measured force better than the naive one."""
    from nanostage.diagnosis.run import diagnose
    from nanostage.diagnosis.settings import DiagnosisSettings
    from nanostage.studies.emps_study import write_manifest

    m = write_manifest(
        tmp_path / "naive.toml",
        preset="emps_naive",
        free={"plant.mass_kg": (50, 200), "plant.friction.viscous_n_s_per_m": (10, 1000)},
        mat_path=MAT,
        candidates=["coulomb_viscous", "offset_force", "lead_periodic_friction"],
    )
    fast = DiagnosisSettings(n_starts_nominal=1, n_starts_candidate=1, forward_rounds=1)
    d = diagnose(m, None, settings=fast, progress=False)
    r = d.report
    assert [f["validate"] for f in r["folds"]] == [["window2", "window4"]]
    assert r["selected"] == ["coulomb_viscous"]
    assert r["gap_after"]["total_rms_m"] < 0.6 * r["gap_before"]["total_rms_m"]
    fc = r["candidates"][0]["parameters"]["coulomb_viscous.coulomb_force_n"]["value"]
    assert 15.0 < fc < 26.0  # IDIM-LS: 20.4 N
    assert yardstick(d.model, data).force < 0.7 * yardstick(presets.emps_naive(), data).force
