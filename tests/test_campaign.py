"""Campaigns: contract, determinism (threads, chunks, ProcessPoolExecutor, a real dask
LocalCluster), per-trial failures, Ctrl-C, the progress bar, bad input."""

from __future__ import annotations

import os
import signal
import threading
import time
from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor
from dataclasses import replace

import numpy as np
import pytest

import nanostage as ns
from nanostage import _core, cycles, presets
from nanostage.campaign import CampaignResult, TrialStatus, _run_chunk, run_campaign
from nanostage.effects import StochasticFriction

MASK64 = (1 << 64) - 1


def stream_seed(seed: int, stream: int) -> int:
    """SplitMix64 finaliser, written independently of the core."""
    z = (seed ^ (stream * 0x9E3779B97F4A7C15)) & MASK64
    z = ((z ^ (z >> 30)) * 0xBF58476D1CE4E5B9) & MASK64
    z = ((z ^ (z >> 27)) * 0x94D049BB133111EB) & MASK64
    return z ^ (z >> 31)


def stochastic(step_m: float = 100e-6, spread: float = 0.3) -> ns.System:
    s = presets.seed(step_m)
    st = StochasticFriction(level_spread=spread, within_spread=0.1, correlation_time_s=0.02)
    return replace(s, effects=replace(s.effects, stochastic=st))


@pytest.fixture(scope="module")
def cycle() -> cycles.Cycle:
    # Three 100 µm steps, about 0.5 s simulated per trial.
    return cycles.step_cycle(
        step_m=100e-6, repeats=3, dwell_s=0.1, return_s=0.05, sample_period_s=1e-3
    )


@pytest.fixture(scope="module")
def reference(cycle: cycles.Cycle) -> CampaignResult:
    return run_campaign(stochastic(), cycle, n_trials=8, seed=11, threads=1, progress=False)


def test_contract(reference: CampaignResult, cycle: cycles.Cycle) -> None:
    r = reference
    assert r.position_m.shape == r.encoder_m.shape == (8, cycle.n_measurements)
    assert r.position_m.dtype == np.float64 and r.status.dtype == np.int8
    assert not r.position_m.flags.writeable and not r.status.flags.writeable
    assert r.n_trials == 8 and r.n_failed == 0 and r.failures == ()
    assert np.all(r.status == TrialStatus.OK)
    # The encoder reading is the position quantised to 100 nm counts (floor).
    assert np.all(np.abs(r.encoder_m - r.position_m) <= 100e-9 + 1e-15)
    with pytest.raises(TypeError):
        run_campaign(stochastic(), cycle, 8)  # type: ignore[misc]


def test_each_trial_is_a_single_run_with_its_own_seed(
    reference: CampaignResult, cycle: cycles.Cycle
) -> None:
    system = stochastic()
    for t in (0, 5):
        tr = ns.simulate(system, cycle.reference_m, seed=stream_seed(11, t))
        np.testing.assert_array_equal(reference.position_m[t], cycle.at_measurements(tr.position_m))
        np.testing.assert_array_equal(
            reference.encoder_m[t], cycle.at_measurements(tr.encoder_position_m)
        )
    # The draws matter: trials differ.
    assert len({tuple(row) for row in reference.position_m}) > 1


def test_identical_for_threads_and_chunks(reference: CampaignResult, cycle: cycles.Cycle) -> None:
    for threads, chunk in ((2, None), (2, 3), (1, 5)):
        r = run_campaign(
            stochastic(),
            cycle,
            n_trials=8,
            seed=11,
            threads=threads,
            chunk_trials=chunk,
            progress=False,
        )
        np.testing.assert_array_equal(r.position_m, reference.position_m)
        np.testing.assert_array_equal(r.encoder_m, reference.encoder_m)
        np.testing.assert_array_equal(r.status, reference.status)
    other = run_campaign(stochastic(), cycle, n_trials=8, seed=12, progress=False)
    assert not np.array_equal(other.position_m, reference.position_m)


def test_process_pool_gives_identical_results(
    reference: CampaignResult, cycle: cycles.Cycle
) -> None:
    with ProcessPoolExecutor(max_workers=2) as ex:
        r = run_campaign(
            stochastic(), cycle, n_trials=8, seed=11, executor=ex, chunk_trials=3, progress=False
        )
    np.testing.assert_array_equal(r.position_m, reference.position_m)
    np.testing.assert_array_equal(r.encoder_m, reference.encoder_m)
    np.testing.assert_array_equal(r.status, reference.status)


def test_dask_local_cluster_gives_identical_results(
    reference: CampaignResult, cycle: cycles.Cycle
) -> None:
    distributed = pytest.importorskip("dask.distributed")
    with (
        distributed.LocalCluster(
            n_workers=2, processes=True, threads_per_worker=1, dashboard_address=None
        ) as cluster,
        distributed.Client(cluster) as client,
    ):
        r = run_campaign(
            stochastic(),
            cycle,
            n_trials=8,
            seed=11,
            executor=client,
            chunk_trials=2,
            progress=False,
        )
        workers = client.run(os.getpid)
    assert len(set(workers.values())) == 2
    np.testing.assert_array_equal(r.position_m, reference.position_m)
    np.testing.assert_array_equal(r.encoder_m, reference.encoder_m)
    np.testing.assert_array_equal(r.status, reference.status)


def test_a_failing_trial_is_its_status(cycle: cycles.Cycle) -> None:
    # The friction level differs per trial and with it the integrator's work: find a step
    # limit that fails some trials but not all, then check each failure against the single
    # run that raises.
    base = stochastic()
    for max_steps in range(10, 400, 10):
        system = replace(base, integrator=replace(base.integrator, max_steps=max_steps))
        r = run_campaign(system, cycle, n_trials=8, seed=5, progress=False)
        if 0 < r.n_failed < 8:
            break
    else:
        pytest.fail("no step limit fails only some trials")
    assert [f.trial for f in r.failures] == list(np.flatnonzero(~r.ok))
    for t in range(8):
        seed = stream_seed(5, t)
        if r.ok[t]:
            tr = ns.simulate(system, cycle.reference_m, seed=seed)
            np.testing.assert_array_equal(r.position_m[t], cycle.at_measurements(tr.position_m))
            continue
        assert np.all(np.isnan(r.position_m[t]))
        f = next(f for f in r.failures if f.trial == t)
        assert f.status == TrialStatus.TOO_MANY_STEPS == r.status[t]
        with pytest.raises(ns.SimulationError) as exc:
            ns.simulate(system, cycle.reference_m, seed=seed)
        assert exc.value.t_s == f.t_s
        assert list(f.state) == exc.value.state and len(f.state) > 0
        assert str(exc.value) == f.message
    # Evaluation skips the failed trials (and refuses a failed one by index).
    dist = r.distribution()["repeatability_up_m"]
    assert np.all(np.isnan(dist[~r.ok])) and np.all(np.isfinite(dist[r.ok]))
    with pytest.raises(ns.ConfigError, match="did not complete"):
        r.evaluate(int(np.flatnonzero(~r.ok)[0]))


def test_evaluation(reference: CampaignResult, cycle: cycles.Cycle) -> None:
    one = reference.evaluate(3)
    direct = cycle.evaluate(reference.position_m[3])
    assert one.repeatability_up_m == direct.repeatability_up_m
    # One target: ISO's A↑ = (x̄ + 2s) − (x̄ − 2s) = 4s = R↑ exactly, and E↑ = 0.
    dist = reference.distribution()
    np.testing.assert_allclose(dist["accuracy_up_m"], dist["repeatability_up_m"], rtol=1e-12)
    assert np.all(dist["systematic_deviation_up_m"] == 0.0)
    assert np.all(np.isnan(dist["repeatability_m"]))  # unidirectional: no bidirectional R
    enc = reference.evaluate(3, reading="encoder")
    assert enc.repeatability_up_m == cycle.evaluate(reference.encoder_m[3]).repeatability_up_m
    # Pooled: all 8 · 3 measurements as 24 runs of one target.
    pooled = reference.evaluate()
    dev = reference.position_m.ravel() - cycle.target_m[0]
    assert pooled.deviations_up_m[0].shape == (24,)
    np.testing.assert_allclose(pooled.std_up_m[0], np.std(dev, ddof=1), rtol=1e-12)
    s = reference.summary()
    assert s["repeatability_up_m"]["n"] == 8
    assert s["repeatability_up_m"]["p5"] <= s["repeatability_up_m"]["median"]
    for bad in (-1, 8):
        with pytest.raises(ns.ConfigError, match="trial"):
            reference.evaluate(bad)
    with pytest.raises(ns.ConfigError, match="reading"):
        reference.evaluate(0, reading="laser")  # type: ignore[arg-type]


def test_progress_bar_on_stderr(cycle: cycles.Cycle, capsys: pytest.CaptureFixture[str]) -> None:
    run_campaign(stochastic(), cycle, n_trials=4, seed=1, progress=True)
    err = capsys.readouterr().err
    assert "4/4 trials" in err and err.endswith("\n")
    run_campaign(stochastic(), cycle, n_trials=2, seed=1, progress=False)
    assert capsys.readouterr().err == ""


def test_progress_counter_is_readable_while_running() -> None:
    long = cycles.step_cycle(
        step_m=100e-6, repeats=10, dwell_s=0.2, return_s=0.1, sample_period_s=1e-3
    )
    control = _core.CampaignControl()
    seen: list[int] = []
    worker = threading.Thread(
        target=_run_chunk,
        args=(stochastic(), long.reference_m, long.measure_index, 0, 12, 0),
        kwargs={"control": control},
    )
    worker.start()
    while worker.is_alive():
        seen.append(control.progress)
        time.sleep(0.01)
    worker.join()
    assert control.progress == 12
    assert any(0 < v < 12 for v in seen), seen


def test_ctrl_c_stops_within_a_second() -> None:
    # 20 trials of 1000 s simulated each: far more than 0.3 s of work however fast the
    # plant gets (30 s trials stopped being enough); SIGINT after 0.3 s.
    long = cycles.step_cycle(
        step_m=100e-6, repeats=1000, dwell_s=0.5, return_s=0.5, sample_period_s=1e-3
    )
    # A shell starts background jobs with SIGINT ignored and pytest keeps that disposition:
    # install Python's own handler for this test so it passes however pytest was launched.
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    timer = threading.Timer(0.3, os.kill, (os.getpid(), signal.SIGINT))
    t0 = time.perf_counter()
    control = _core.CampaignControl()
    timer.start()
    try:
        with pytest.raises(KeyboardInterrupt):
            run_campaign(
                stochastic(), long, n_trials=20, threads=2, progress=False, control=control
            )
        elapsed = time.perf_counter() - t0
    finally:
        timer.cancel()
        signal.signal(signal.SIGINT, previous)
    assert elapsed < 2.0, elapsed
    assert control.stop_requested
    # The next campaign starts afresh.
    short = cycles.step_cycle(
        step_m=100e-6, repeats=2, dwell_s=0.05, return_s=0.05, sample_period_s=1e-3
    )
    r = run_campaign(stochastic(), short, n_trials=2, progress=False)
    assert r.n_failed == 0


def test_a_stop_request_from_elsewhere_marks_trials() -> None:
    # About 1000 s simulated per trial: none may end before the stop request at 0.3 s.
    long = cycles.step_cycle(
        step_m=100e-6, repeats=1000, dwell_s=0.5, return_s=0.5, sample_period_s=1e-3
    )
    control = _core.CampaignControl()
    timer = threading.Timer(0.3, control.request_stop)
    timer.start()
    try:
        r = run_campaign(
            stochastic(),
            long,
            n_trials=6,
            threads=2,
            chunk_trials=2,
            progress=False,
            control=control,
        )
    finally:
        timer.cancel()
    assert r.n_failed == 6
    assert set(r.status.tolist()) <= {TrialStatus.INTERRUPTED, TrialStatus.NOT_STARTED}
    assert TrialStatus.INTERRUPTED in r.status.tolist()
    for f in r.failures:
        assert (f.status == TrialStatus.NOT_STARTED) == np.isnan(f.t_s)


def test_bad_input_raises_before_work(cycle: cycles.Cycle) -> None:
    s = stochastic()
    for kwargs, match in (
        ({"n_trials": 0}, "n_trials"),
        ({"n_trials": 2, "threads": 0}, "threads"),
        ({"n_trials": 2, "seed": -1}, "seed"),
        ({"n_trials": 2, "seed": 2**64}, "seed"),
        ({"n_trials": 2, "chunk_trials": 3}, "chunk_trials"),
    ):
        with pytest.raises(ns.ConfigError, match=match):
            run_campaign(s, cycle, progress=False, **kwargs)  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="n_trials"):
        run_campaign(s, cycle, n_trials=2.0, progress=False)  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="cycle"):
        run_campaign(s, cycle.reference_m, n_trials=2, progress=False)  # type: ignore[arg-type]
    with pytest.raises(TypeError, match="submit"):
        run_campaign(s, cycle, n_trials=2, executor=object(), progress=False)  # type: ignore[arg-type]
    # A System validates itself when built; force an invalid one past that check.
    bad = replace(s)
    object.__setattr__(
        bad, "effects", replace(s.effects, stochastic=StochasticFriction(level_spread=0.5))
    )
    object.__setattr__(bad.effects.stochastic, "level_spread", 0.9)
    control = _core.CampaignControl()
    with ThreadPoolExecutor(1) as ex, pytest.raises(ns.ConfigError, match="level_spread"):
        run_campaign(bad, cycle, n_trials=2, executor=ex, progress=False, control=control)
    assert control.progress == 0
    with pytest.raises(ns.ConfigError, match="measure_index"):
        _run_chunk(s, cycle.reference_m, np.array([5, 5]), 0, 1, 0)
    with pytest.raises(ns.ConfigError, match="measure_index"):
        _run_chunk(s, cycle.reference_m, np.array([-1]), 0, 1, 0)
