"""The ISO campaign's measurement chain (nanostage.measurement): each out-of-loop effect
against hand-computed values, the in-loop interpolation error through the closed loop,
the readings' timestamps, an ISO evaluation with a known scale error, and the properties
(no effect: the reading is the table position; determinism for a seed)."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from nanostage import ConfigError, presets
from nanostage.campaign import CampaignResult, TrialStatus, run_campaign
from nanostage.cycles import MoveProfile, standard_test_cycle, step_cycle
from nanostage.effects import EncoderErrors
from nanostage.measurement import (
    AbbeError,
    InterferometerEnvironment,
    MeasurementChain,
    ScaleError,
    SettlingResidual,
    ThermalDrift,
    arrival_times,
)


def _step_cycle(step_m: float = 100e-6, repeats: int = 5, start_m: float = 0.0):  # type: ignore[no-untyped-def]
    return step_cycle(
        step_m=step_m,
        repeats=repeats,
        start_m=start_m,
        dwell_s=0.5,
        return_s=0.5,
        sample_period_s=1e-3,
    )


def _fake_result(cycle, position_m: np.ndarray, seed: int = 0) -> CampaignResult:  # type: ignore[no-untyped-def]
    """A campaign whose loop put the table exactly at the given positions."""
    n = position_m.shape[0]
    return CampaignResult(
        cycle=cycle,
        seed=seed,
        position_m=position_m,
        encoder_m=position_m,
        status=np.zeros(n, dtype=np.int8),
        failures=(),
        compute_s=0.0,
    )


def _chain_error(chain: MeasurementChain, x_m: float, *, t_s: float = 0.0, d: int = 1) -> float:
    return float(
        chain.error_m(
            position_m=np.array([[x_m]]),
            time_s=np.array([t_s]),
            direction=np.array([d]),
            move_m=np.array([0.0]),
            dwell_s=np.array([0.0]),
        )[0, 0]
    )


# --------------------------------------------------------------------------------------------
# Each effect against a hand computation
# --------------------------------------------------------------------------------------------


def test_abbe_error_is_offset_times_tan_of_the_angle_at_the_position() -> None:
    abbe = AbbeError(
        offset_m=0.02, angle_rad=1e-5, slope_rad_per_m=2e-3, reversal_rad=4e-6, centre_m=0.0
    )
    chain = MeasurementChain(abbe=(abbe,))
    # x = 10 mm, ↑: θ = 1e-5 + 2e-3·0.01 + 2e-6 = 3.2e-5 rad; 0.02 m · tan θ = 6.4e-7 m.
    assert _chain_error(chain, 0.01, d=1) == pytest.approx(6.4e-7, rel=1e-8)
    # ↓: θ = 1e-5 + 2e-5 − 2e-6 = 2.8e-5 rad → 5.6e-7 m.
    assert _chain_error(chain, 0.01, d=-1) == pytest.approx(5.6e-7, rel=1e-8)
    # A large angle shows the tangent: 0.1 m · tan(0.05) = 5.004170837e-3 m.
    big = MeasurementChain(abbe=(AbbeError(offset_m=0.1, angle_rad=0.05),))
    assert _chain_error(big, 0.0) == pytest.approx(5.004170837e-3, rel=1e-9)
    # Waviness: amplitude 1e-5 rad, period 4 mm; at x = 1 mm sin(π/2) = 1 → 0.03 · 1e-5.
    wave = MeasurementChain(
        abbe=(AbbeError(offset_m=0.03, wave_amplitude_rad=1e-5, wave_period_m=4e-3),)
    )
    assert _chain_error(wave, 1e-3) == pytest.approx(3e-7, rel=1e-8)
    assert _chain_error(wave, 3e-3) == pytest.approx(-3e-7, rel=1e-8)


def test_thermal_drift_is_alpha_length_times_the_first_order_rise() -> None:
    th = ThermalDrift(
        temperature_rise_k=2.0,
        time_constant_s=600.0,
        test_start_s=300.0,
        scale_expansion_per_k=10e-6,
        scale_datum_m=0.0,
        structure_m_per_k=2e-6,
    )
    chain = MeasurementChain(thermal=th)
    # ΔT(120 s) = 2 · (e^−0.5 − e^−0.7) = 2 · (0.6065306597 − 0.4965853038) = 0.2198907118 K
    assert float(th.temperature_k(np.array(120.0))) == pytest.approx(0.2198907118, rel=1e-9)
    # δ = (10e-6 · 0.025 + 2e-6) · 0.2198907118 = 2.25e-6 · 0.2198907118 = 4.947541016e-7 m
    assert _chain_error(chain, 0.025, t_s=120.0) == pytest.approx(4.947541016e-7, rel=1e-9)
    # Both instruments are zeroed at the test's start: no error at t = 0.
    assert _chain_error(chain, 0.025, t_s=0.0) == 0.0


def test_interferometer_refractive_index_drift_over_dead_and_measured_path() -> None:
    ifm = InterferometerEnvironment(
        refractive_index_rate_per_s=1e-9, dead_path_m=0.5, zero_position_m=0.0
    )
    # (0.5 + 0.01) m · 1e-9 /s · 10 s = 5.1e-9 m
    assert _chain_error(MeasurementChain(interferometer=ifm), 0.01, t_s=10.0) == pytest.approx(
        5.1e-9, rel=1e-9
    )


def test_interferometer_noise_has_its_standard_deviation_and_is_seeded() -> None:
    chain = MeasurementChain(interferometer=InterferometerEnvironment(noise_std_m=5e-8))
    pos = np.zeros((400, 50))
    kw = {
        "position_m": pos,
        "time_s": np.zeros(50),
        "direction": np.ones(50),
        "move_m": np.zeros(50),
        "dwell_s": np.zeros(50),
    }
    err = chain.error_m(**kw, seed=7)
    # 20 000 draws: the sample std is within 3 % of 5e-8 (its relative std is 0.5 %).
    assert float(np.std(err)) == pytest.approx(5e-8, rel=0.03)
    assert abs(float(np.mean(err))) < 3e-9
    np.testing.assert_array_equal(err, chain.error_m(**kw, seed=7))
    assert not np.array_equal(err, chain.error_m(**kw, seed=8))
    # Trial i draws from (seed, i) only: any subset of trials reads the same.
    sub = chain.error_m(**{**kw, "position_m": pos[:2]}, seed=7, trials=[5, 9])
    np.testing.assert_array_equal(sub, err[[5, 9]])


def test_settling_residual_at_the_dwell_after_the_move() -> None:
    cyc = _step_cycle(100e-6, repeats=3)
    move, dwell = arrival_times(cyc.reference_m, cyc.measure_index, cyc.sample_period_s)
    np.testing.assert_allclose(move, [100e-6] * 3, rtol=1e-12)
    np.testing.assert_allclose(dwell, [0.5] * 3, rtol=1e-12)
    s = SettlingResidual(
        amplitude_m=1e-6,
        amplitude_per_move=0.01,
        frequency_hz=10.0,
        damping_ratio=0.05,
        phase_spread_rad=0.0,
        creep_fraction=0.01,
        creep_time_constant_s=0.25,
    )
    # amplitude 1e-6 + 0.01 · 1e-4 = 2e-6; ζω t = 0.05 · 20π · 0.5 = π/2;
    # ω_d t = 10π · √(1 − 0.0025); creep 0.01 · 1e-4 · e^−2.
    osc = 2e-6 * math.exp(-math.pi / 2) * math.cos(10.0 * math.pi * math.sqrt(0.9975))
    creep = 1e-6 * math.exp(-2.0)
    res = _fake_result(cyc, np.tile(cyc.target_m, (2, 1))).with_measurement(
        MeasurementChain(settling=s)
    )
    np.testing.assert_allclose(res.interferometer_error_m, osc - creep, rtol=1e-9)
    # A random phase keeps every reading inside the decayed envelope.
    rnd = replace(s, phase_spread_rad=math.pi, creep_fraction=0.0)
    err = _fake_result(cyc, np.zeros((200, 3))).with_measurement(MeasurementChain(settling=rnd))
    env = 2e-6 * math.exp(-math.pi / 2)
    e = err.interferometer_error_m
    assert e is not None
    assert np.max(np.abs(e)) <= env * (1 + 1e-12)
    assert np.max(np.abs(e)) > 0.9 * env


def test_arrival_times_of_a_trapezoidal_move() -> None:
    cyc = step_cycle(
        step_m=1e-3,
        repeats=2,
        dwell_s=0.2,
        return_s=0.3,
        sample_period_s=1e-3,
        move=MoveProfile(kind="trapezoid", max_velocity_m_per_s=0.01, acceleration_m_per_s2=0.1),
    )
    move, dwell = arrival_times(cyc.reference_m, cyc.measure_index, cyc.sample_period_s)
    np.testing.assert_allclose(move, [1e-3, 1e-3], rtol=1e-12)
    # The reading is at the end of the dwell, counted from the arrival sample.
    np.testing.assert_allclose(dwell, [0.2, 0.2], rtol=1e-12)


# --------------------------------------------------------------------------------------------
# Timestamps, ISO evaluation, properties
# --------------------------------------------------------------------------------------------


def test_reading_times_follow_the_schedule() -> None:
    cyc = _step_cycle(100e-6, repeats=5)
    res = _fake_result(cyc, np.tile(cyc.target_m, (1, 1)))
    # 500 samples at the start, then per run: step, 500 samples of dwell (read at its end),
    # return, 500 samples: the readings are at 1.000 s + 1.001 s · (j − 1).
    np.testing.assert_allclose(res.time_s, 1.0 + 1.001 * np.arange(5), rtol=0, atol=1e-12)


def test_iso_with_only_a_linear_scale_error_gives_the_hand_computed_e() -> None:
    cyc = standard_test_cycle(
        travel_m=0.04,
        overrun_m=1e-3,
        dwell_s=0.01,
        move=MoveProfile(),
        sample_period_s=1e-3,
        seed=3,
        runs=5,
    )
    res = _fake_result(cyc, np.tile(cyc.target_m, (1, 1))).with_measurement(
        MeasurementChain(scale=ScaleError(linear_error_m_per_m=5e-6, datum_m=0.0))
    )
    iso = res.evaluate(0)
    span = float(np.max(cyc.targets_m) - np.min(cyc.targets_m))
    # Deviation ε·x at every target, no scatter: E↑ = E = ε · (max − min target).
    assert iso.systematic_deviation_up_m == pytest.approx(5e-6 * span, rel=1e-9)
    assert iso.systematic_deviation_m == pytest.approx(5e-6 * span, rel=1e-9)
    assert iso.repeatability_up_m == pytest.approx(0.0, abs=1e-15)
    assert res.evaluate(0, reading="position").systematic_deviation_m == 0.0


def test_no_effect_reads_the_table_position_bit_for_bit() -> None:
    cyc = _step_cycle(100e-6, repeats=3)
    system = presets.seed(100e-6)
    plain = run_campaign(system, cyc, n_trials=3, seed=4, progress=False)
    empty = run_campaign(
        system, cyc, n_trials=3, seed=4, progress=False, measurement=MeasurementChain()
    )
    assert np.all(plain.status == TrialStatus.OK)
    for res in (plain, empty):
        np.testing.assert_array_equal(res.interferometer_m, plain.position_m)
        assert (
            res.evaluate(1).repeatability_up_m
            == res.evaluate(1, reading="position").repeatability_up_m
        )
    np.testing.assert_array_equal(empty.position_m, plain.position_m)


def test_a_chain_is_deterministic_for_a_seed_and_leaves_the_loop_alone() -> None:
    cyc = _step_cycle(100e-6, repeats=3)
    system = presets.seed(100e-6)
    chain = MeasurementChain(
        abbe=(AbbeError(offset_m=0.02, noise_std_rad=1e-6),),
        thermal=ThermalDrift(temperature_rise_k=1.0, time_constant_s=60.0, structure_m_per_k=1e-6),
        settling=SettlingResidual(amplitude_m=1e-7),
        interferometer=InterferometerEnvironment(noise_std_m=1e-8),
    )
    a = run_campaign(system, cyc, n_trials=4, seed=11, progress=False, measurement=chain)
    b = run_campaign(system, cyc, n_trials=4, seed=11, progress=False, measurement=chain)
    plain = run_campaign(system, cyc, n_trials=4, seed=11, progress=False)
    np.testing.assert_array_equal(a.interferometer_m, b.interferometer_m)
    np.testing.assert_array_equal(a.position_m, plain.position_m)
    np.testing.assert_array_equal(a.encoder_m, plain.encoder_m)
    assert not np.array_equal(a.interferometer_m, plain.position_m)
    np.testing.assert_array_equal(
        plain.with_measurement(chain).interferometer_m, a.interferometer_m
    )


def test_interpolation_error_acts_in_the_loop_with_its_period_and_amplitude() -> None:
    """The loop servoes the encoder reading x + A·sin(2πx/λ): the table ends at about
    target − A·sin(2π·target/λ) (the interferometer sees it; the encoder does not)."""
    amp, period = 1e-6, 100e-6
    base = presets.seed(100e-6)
    system = replace(
        base,
        effects=replace(
            base.effects,
            encoder_errors=EncoderErrors(cyclic_amplitude_m=amp, cyclic_period_m=period),
        ),
    )
    # Targets at phases 90°, 270° and one period later than 90°.
    targets = (1025e-6, 1075e-6, 1125e-6)
    dev = []
    for x in targets:
        cyc = _step_cycle(100e-6, repeats=2, start_m=x - 100e-6)
        res = run_campaign(system, cyc, n_trials=1, seed=0, progress=False)
        assert res.status[0] == TrialStatus.OK
        # The loop ends within a few counts of the target on the encoder (what it sees) ...
        assert np.all(np.abs(res.encoder_m[0] - cyc.target_m) <= 3.01e-7)
        # ... and the interferometer at the table differs from the encoder reading by the
        # interpolation error: x − q·floor((x + A·sin(2πx/λ))/q) ∈ −A·sin(2πx/λ) + [0, q).
        dev.append(res.interferometer_m[0] - res.encoder_m[0])
    q = 1e-7
    assert np.all(dev[0] >= -amp - 1e-9) and np.all(dev[0] < -amp + q + 1e-9)
    assert np.all(dev[1] >= amp - 1e-9) and np.all(dev[1] < amp + q + 1e-9)
    # One period on: the same error (within the count's share).
    assert np.all(dev[2] >= -amp - 1e-9) and np.all(dev[2] < -amp + q + 1e-9)


@pytest.mark.parametrize(
    ("make", "words"),
    [
        (lambda: AbbeError(offset_m=2.0), ["AbbeError.offset_m", "2.0", "[-1, 1] m"]),
        (
            lambda: ThermalDrift(time_constant_s=0.0),
            ["ThermalDrift.time_constant_s", "0.0", "(0, 1e+07] s"],
        ),
        (
            lambda: SettlingResidual(damping_ratio=1.0),
            ["SettlingResidual.damping_ratio", "1.0", "(0, 1)"],
        ),
        (
            lambda: InterferometerEnvironment(noise_std_m=-1e-9),
            ["InterferometerEnvironment.noise_std_m", "-1e-09", "[0, 0.001] m"],
        ),
        (
            lambda: ScaleError(linear_error_m_per_m=math.nan),
            ["ScaleError.linear_error_m_per_m", "nan", "[-0.001, 0.001] m/m"],
        ),
        (lambda: AbbeError(offset_m=True), ["AbbeError.offset_m", "True", "real number"]),
        (lambda: MeasurementChain(abbe=[AbbeError(offset_m=0.0)]), ["MeasurementChain.abbe"]),  # type: ignore[arg-type]
        (lambda: MeasurementChain(thermal=1.0), ["MeasurementChain.thermal", "ThermalDrift"]),  # type: ignore[arg-type]
    ],
)
def test_invalid_parameters_name_field_value_and_range(make, words) -> None:  # type: ignore[no-untyped-def]
    with pytest.raises(ConfigError) as info:
        make()
    msg = str(info.value)
    assert "\n" not in msg
    for w in words:
        assert w in msg


def test_run_campaign_rejects_a_wrong_measurement_before_any_trial() -> None:
    with pytest.raises(ConfigError, match="measurement = 'x' is invalid"):
        run_campaign(
            presets.seed(100e-6),
            _step_cycle(),
            n_trials=1,
            progress=False,
            measurement="x",  # type: ignore[arg-type]
        )


# --------------------------------------------------------------------------------------------
# The paper's case (nanostage iso-gap)
# --------------------------------------------------------------------------------------------


def test_the_study_figure_of_a_test_is_the_iso_a_and_r() -> None:
    from nanostage.studies.iso_gap import single_target_figures_m

    cyc = _step_cycle(100e-6, repeats=5)
    res = run_campaign(presets.seed(100e-6), cyc, n_trials=2, seed=2, progress=False)
    read = res.with_measurement(
        MeasurementChain(interferometer=InterferometerEnvironment(noise_std_m=1e-7))
    )
    fig = single_target_figures_m(read.interferometer_m)
    for t in range(2):
        iso = read.evaluate(t)
        assert fig[t] == pytest.approx(iso.accuracy_up_m, rel=1e-12)
        assert fig[t] == pytest.approx(iso.repeatability_up_m, rel=1e-12)


def test_the_study_calibrates_white_noise_to_the_hand_computed_size() -> None:
    """Pure white interferometer noise σ gives a mean 4·s over 5 runs of 4·c4·σ with
    c4(5) = 0.9400: 3.19 µm needs σ ≈ 0.848 µm, i.e. about 85 × the 10 nm of factor 1
    (the loop's own 0.2 µm scatter adds a little in quadrature)."""
    from nanostage.studies import iso_gap

    st = iso_gap.GapSettings(n_trials=64, return_s=(0.5,), n_grid=9)
    study = iso_gap._Study(st, 1, lambda _m: None)
    noise = next(c for c in iso_gap.CANDIDATES if c.name == "interferometer_noise")
    out = iso_gap._calibrate_one(study, (noise,), 0.5, 100e-6)
    assert out["factor"] == pytest.approx(3.19e-6 / (4 * 0.9400 * 10e-9), rel=0.12)
    assert out["verdict"] == "implausible magnitude"
    # Step-size independent: the 1 mm prediction is the same size; the paper's 1.83 µm
    # lies inside the band of one test's figure.
    assert out["predicted"]["mean_m"] == pytest.approx(3.19e-6, rel=0.15)
    assert out["paper_inside_band"]
    # A scale error shifts the one target: it cannot make any scatter.
    scale = next(c for c in iso_gap.CANDIDATES if c.name == "scale_error")
    assert iso_gap._calibrate_one(study, (scale,), 0.5, 100e-6)["verdict"] == "cannot reach"


def test_the_study_settings_are_checked() -> None:
    from nanostage.studies.iso_gap import GapSettings

    with pytest.raises(
        ConfigError, match=r"GapSettings.return_s = 90.0 is invalid: .*\[0.001, 60\] s"
    ):
        GapSettings(return_s=(90.0,))
    with pytest.raises(ConfigError, match=r"GapSettings.n_trials = 1 is invalid: .*\[2, "):
        GapSettings(n_trials=1)


# --------------------------------------------------------------------------------------------
# A measured ISO test as input: every problem named with file, line and column
# --------------------------------------------------------------------------------------------

_HEADER = "target_m,direction,run,actual_m,encoder_m,time_s,temperature_k"


def _measurement_rows(targets: tuple[float, ...] = (0.0, 0.01), runs: int = 3) -> list[list[str]]:
    """A unidirectional test in the order it ran: run by run, target by target."""
    rows = []
    t = 0.0
    for r in range(1, runs + 1):
        for x in targets:
            t += 2.0
            rows.append(
                [repr(x), "+", str(r), repr(x + 1e-7 * r), repr(x + 2e-8), repr(t), "293.4"]
            )
    return rows


def _write(tmp_path, rows: list[list[str]], header: str = _HEADER):  # type: ignore[no-untyped-def]
    path = tmp_path / "meas.csv"
    path.write_text(
        "# a measured test\n" + header + "\n" + "\n".join(",".join(r) for r in rows) + "\n",
        encoding="utf-8",
    )
    return path


def test_a_measured_test_reads_with_its_encoder_times_and_temperatures(tmp_path) -> None:  # type: ignore[no-untyped-def]
    from nanostage.measurement import read_iso_measurement

    m = read_iso_measurement(_write(tmp_path, _measurement_rows()), travel_m=(0.0, 0.05))
    assert m.time_s is not None and m.encoder_m is not None and m.temperature_k is not None
    np.testing.assert_allclose(m.time_s, 2.0 * np.arange(1, 7))
    np.testing.assert_allclose(m.encoder_m, [2e-8, 0.01 + 2e-8] * 3, rtol=0, atol=1e-15)
    np.testing.assert_allclose(m.temperature_k, 293.4)
    # Deviations 0.1, 0.2, 0.3 µm at both targets: R↑ = 4 · 0.1 µm.
    assert m.evaluate().repeatability_up_m == pytest.approx(4e-7, rel=1e-9)
    # In °C and millimetres.
    rows = [[*r[:4], repr(float(r[4]) * 1e3), r[5], "20.25"] for r in _measurement_rows()]
    header = "target_m,direction,run,actual_m,encoder_mm,time_s,temperature_c"
    m2 = read_iso_measurement(_write(tmp_path, rows, header))
    assert m2.encoder_m is not None and m2.temperature_k is not None
    np.testing.assert_allclose(m2.encoder_m, m.encoder_m, rtol=1e-12, atol=1e-18)
    np.testing.assert_allclose(m2.temperature_k, 293.4)


def _moved(row: list[str], by_m: float) -> list[str]:
    return [repr(float(row[0]) + by_m), *row[1:3], repr(float(row[3]) + by_m), *row[4:]]


def _bad(rows: list[list[str]], i: int, column: int, value: str) -> list[list[str]]:
    out = [list(r) for r in rows]
    out[i][column] = value
    return out


@pytest.mark.parametrize(
    ("edit", "line", "column", "words"),
    [
        # A missing run: run 2 at target 0 is absent (its row removed).
        (lambda rows: rows[:2] + rows[3:], 3, "run", ["runs [1, 3]", "[2] missing"]),
        # Unequal runs: target 0.01 has a fourth run.
        (
            lambda rows: [*rows, ["0.01", "+", "4", "0.0100004", "0.01", "14.0", "293.4"]],
            4,
            "run",
            ["has 4 runs", "line 3", "has 3"],
        ),
        # Millimetres in the metre column of the encoder.
        (lambda rows: _bad(rows, 1, 4, "10.00002"), 4, "encoder_m", ["mixed units"]),
        # A temperature in °C in the kelvin column.
        (lambda rows: _bad(rows, 2, 6, "20.3"), 5, "temperature_k", ["20.3", "°C"]),
        # A target outside the travel [0, 0.05] m (the second target moved by 5 cm).
        (
            lambda rows: [_moved(r, 0.05) if r[0] == "0.01" else r for r in rows],
            4,
            "target_m",
            ["0.06 m is outside the travel [0, 0.05] m"],
        ),
        # Time going backwards at the fourth reading.
        (lambda rows: _bad(rows, 3, 5, "5.0"), 6, "time_s", ["5 s is not after", "6 s"]),
    ],
)
def test_a_bad_measured_test_names_file_line_and_column(  # type: ignore[no-untyped-def]
    tmp_path, edit, line, column, words
) -> None:
    from nanostage.iso230_2 import Iso230InputError
    from nanostage.measurement import read_iso_measurement

    path = _write(tmp_path, edit(_measurement_rows()))
    with pytest.raises(Iso230InputError) as info:
        read_iso_measurement(path, travel_m=(0.0, 0.05))
    err = info.value
    assert (err.source, err.line, err.column) == (str(path), line, column)
    msg = str(err)
    assert msg.startswith(f"{path}, line {line}, column {column!r}: ")
    assert "\n" not in msg
    for w in words:
        assert w in msg
