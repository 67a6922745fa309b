"""Monte Carlo ISO 230-2 campaigns: many trials of one test cycle on the closed loop.

A *trial* is one run of a whole :class:`~nanostage.cycles.Cycle` (e.g. five repeated
100 µm steps) with its own random draws (stochastic friction level and fluctuation, encoder
noise, sample jitter: whatever the :class:`~nanostage.System` switches on). A *campaign* is
``n_trials`` such trials. Only the positions at the measurement instants are kept (the true
table position, as an interferometer reads it, and the encoder reading), plus a status per
trial, so memory is ``2 · n_trials · n_measurements`` floats whatever the cycle's length.

Determinism rule: trial ``i`` uses the seed ``stream_seed(seed, i)`` (SplitMix64 of the
campaign seed and the trial index) and nothing else, so the same ``seed`` gives bit-identical
results whatever the thread count, the chunking, or the executor the chunks run on.

A numerical failure in one trial is that trial's status (:class:`TrialStatus`) with the time
and state of the failure (:attr:`CampaignResult.failures`); the other trials complete.
Invalid input raises :class:`nanostage.ConfigError` before any trial runs.

Example::

    cycle = nanostage.cycles.step_cycle(step_m=100e-6, repeats=5, dwell_s=0.5,
                                        return_s=0.5, sample_period_s=1e-3)
    result = nanostage.campaign.run_campaign(system, cycle, n_trials=64, seed=1)
    result.evaluate(0).repeatability_up_m        # R↑ of trial 0
    result.distribution()["repeatability_up_m"]   # R↑ of every trial
"""

from __future__ import annotations

import math
import multiprocessing
import os
import sys
import threading
import time
from collections.abc import Callable, Sequence
from concurrent.futures import Executor
from dataclasses import dataclass, replace
from enum import IntEnum
from typing import Any, Final, Literal, Protocol

import numpy as np
import numpy.typing as npt

from . import _core, iso230_2
from ._core import ConfigError
from .checks import executor_arg, int_arg
from .config import System
from .cycles import Cycle
from .measurement import MeasurementChain, arrival_times
from .output import ProgressBar

__all__ = [
    "MAX_THREADS",
    "MAX_TRIALS",
    "CampaignResult",
    "TrialFailure",
    "TrialStatus",
    "run_campaign",
]

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

#: Most trials of one campaign (the core's limit per call).
MAX_TRIALS: Final[int] = 1 << 32
#: Most threads of the local pool.
MAX_THREADS: Final[int] = 1024
#: Seconds between two progress-bar updates.
_REFRESH_S: Final[float] = 0.1

Reading = Literal["interferometer", "position", "encoder"]


class TrialStatus(IntEnum):
    """Outcome of one trial (mirrors the core's ``TrialStatus``)."""

    OK = 0
    STEP_SIZE_TOO_SMALL = 1
    SINGULAR_MATRIX = 2
    NON_FINITE = 3
    TOO_MANY_STEPS = 4
    INTERRUPTED = 5
    NOT_STARTED = 6
    CONFIG = 7
    TOO_MANY_EVENTS = 8


@dataclass(frozen=True, slots=True, kw_only=True)
class TrialFailure:
    """A trial that did not complete.

    Attributes
    ----------
    trial : int
        Trial index.
    status : TrialStatus
        What happened.
    t_s : float
        Simulated time of the failure [s] (NaN for a trial that never started).
    state : tuple of float
        Plant state vector at the failure (empty when not available).
    message : str
        The error in words.
    """

    trial: int
    status: TrialStatus
    t_s: float
    state: tuple[float, ...]
    message: str


class _Future(Protocol):
    def done(self) -> bool: ...
    def result(self) -> Any: ...
    def cancel(self) -> Any: ...


class _Submitter(Protocol):
    def submit(self, fn: Callable[..., Any], /, *args: Any) -> Any: ...


@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class CampaignResult:
    """The positions of every trial at the cycle's measurement instants, and the statuses.

    Arrays are read-only. Compares by identity.

    Attributes
    ----------
    cycle : Cycle
        The test cycle every trial ran.
    seed : int
        Campaign seed (trial ``i`` used ``stream_seed(seed, i)``).
    position_m : ndarray of float64, shape (n_trials, n_measurements)
        True table position at each measurement instant [m] (what an interferometer reads);
        NaN rows for trials that did not complete.
    encoder_m : ndarray of float64, shape (n_trials, n_measurements)
        Encoder reading (counts · count size) at each measurement instant [m]; NaN rows for
        trials that did not complete.
    status : ndarray of int8, shape (n_trials,)
        :class:`TrialStatus` of each trial.
    failures : tuple of TrialFailure
        The trials that did not complete, in trial order.
    compute_s : float
        Wall time of the campaign [s].
    measurement : MeasurementChain or None
        The out-of-loop effects between the table and the interferometer's reading at the
        functional point (:mod:`nanostage.measurement`); None: the reading is the table
        position.
    interferometer_error_m : ndarray of float64, shape (n_trials, n_measurements), or None
        The chain's error at each reading [m] (None without a chain).
    """

    cycle: Cycle
    seed: int
    position_m: FloatArray
    encoder_m: FloatArray
    status: npt.NDArray[np.int8]
    failures: tuple[TrialFailure, ...]
    compute_s: float
    measurement: MeasurementChain | None = None
    interferometer_error_m: FloatArray | None = None

    @property
    def n_trials(self) -> int:
        """Number of trials."""
        return int(self.status.shape[0])

    @property
    def ok(self) -> npt.NDArray[np.bool_]:
        """Mask of the trials that completed, shape ``(n_trials,)``."""
        out: npt.NDArray[np.bool_] = self.status == TrialStatus.OK
        return out

    @property
    def n_failed(self) -> int:
        """Number of trials that did not complete."""
        return int(self.n_trials - np.count_nonzero(self.ok))

    @property
    def time_s(self) -> FloatArray:
        """Time of each reading from the start of the test (trial) [s], shape
        ``(n_measurements,)``: the cycle's schedule (moves, dwells) at its measurement
        instants (:attr:`~nanostage.cycles.Cycle.measure_time_s`)."""
        return self.cycle.measure_time_s

    @property
    def interferometer_m(self) -> FloatArray:
        """The interferometer's reading at the functional point, shape
        ``(n_trials, n_measurements)`` [m]: the table position plus the measurement chain's
        error (the table position itself without a chain)."""
        if self.interferometer_error_m is None:
            return self.position_m
        out: FloatArray = self.position_m + self.interferometer_error_m
        out.flags.writeable = False
        return out

    def with_measurement(self, measurement: MeasurementChain | None) -> CampaignResult:
        """This campaign read through ``measurement`` (the loop's positions unchanged).

        The chain's random parts are drawn per trial from ``(seed, trial)`` (the campaign's
        seed), so the same campaign and chain give the same readings.

        Raises
        ------
        ConfigError
            ``measurement`` is not a :class:`~nanostage.measurement.MeasurementChain`.
        """
        if measurement is None or (
            isinstance(measurement, MeasurementChain) and measurement.is_empty
        ):
            return replace(self, measurement=measurement, interferometer_error_m=None)
        if not isinstance(measurement, MeasurementChain):
            raise ConfigError(
                f"measurement = {measurement!r} is invalid: expected a "
                "nanostage.measurement.MeasurementChain or None"
            )
        cyc = self.cycle
        move_m, dwell_s = arrival_times(cyc.reference_m, cyc.measure_index, cyc.sample_period_s)
        err = measurement.error_m(
            position_m=self.position_m,
            time_s=self.time_s,
            direction=cyc.direction,
            move_m=move_m,
            dwell_s=dwell_s,
            seed=self.seed,
        )
        err.flags.writeable = False
        return replace(self, measurement=measurement, interferometer_error_m=err)

    def actual_m(self, reading: Reading = "interferometer") -> FloatArray:
        """Positions of one reading, shape ``(n_trials, n_measurements)`` [m].

        Parameters
        ----------
        reading : {"interferometer", "position", "encoder"}
            The interferometer at the functional point (:attr:`interferometer_m`), the true
            table position, or the encoder reading.
        """
        if reading == "interferometer":
            return self.interferometer_m
        if reading == "position":
            return self.position_m
        if reading == "encoder":
            return self.encoder_m
        raise ConfigError(
            f"reading = {reading!r} is invalid: expected 'interferometer', 'position' or 'encoder'"
        )

    def evaluate(
        self,
        trial: int | None = None,
        *,
        reading: Reading = "interferometer",
        coverage_factor: float = 2.0,
    ) -> iso230_2.Iso230Result:
        """ISO 230-2 evaluation of one trial, or of all completed trials pooled.

        Parameters
        ----------
        trial : int or None
            Trial index in ``[0, n_trials)``: that trial's test. ``None``: every completed
            trial's measurements taken as further runs of one test (runs renumbered), i.e.
            the test as if the trial-to-trial variation happened between runs.
        reading : {"interferometer", "position", "encoder"}
            Which position to evaluate (default: the interferometer at the functional point,
            as the paper measured; the true table position when the campaign has no
            measurement chain).
        coverage_factor : float, default 2.0
            Coverage factor ``k`` [-].

        Returns
        -------
        iso230_2.Iso230Result

        Raises
        ------
        ConfigError
            On a trial index out of range, or a trial that did not complete.
        """
        actual = self.actual_m(reading)
        cyc = self.cycle
        if trial is not None:
            if isinstance(trial, bool) or not isinstance(trial, (int, np.integer)):
                raise TypeError(f"trial must be an int or None, not {type(trial).__name__}")
            t = int(trial)
            if not 0 <= t < self.n_trials:
                raise ConfigError(
                    f"trial = {t} is invalid: expected an index in [0, {self.n_trials - 1}]"
                )
            if self.status[t] != TrialStatus.OK:
                raise ConfigError(
                    f"trial = {t} is invalid: it did not complete "
                    f"({TrialStatus(int(self.status[t])).name})"
                )
            return cyc.evaluate(actual[t], coverage_factor=coverage_factor)
        rows = np.flatnonzero(self.ok)
        if rows.size == 0:
            raise ConfigError("trial = None is invalid: no trial completed")
        runs_per_trial = int(np.max(cyc.run))
        n = rows.size
        direction = np.where(cyc.direction > 0, "+", "-").astype(np.str_)
        records = iso230_2.MeasurementRecords(
            target_m=np.tile(cyc.target_m, n),
            direction=np.tile(direction, n),
            run=(cyc.run[None, :] + runs_per_trial * np.arange(n)[:, None]).ravel(),
            actual_m=actual[rows].ravel(),
        )
        return records.evaluate(coverage_factor=coverage_factor)

    def distribution(
        self, *, reading: Reading = "interferometer", coverage_factor: float = 2.0
    ) -> dict[str, FloatArray]:
        """Every ISO 230-2 axis parameter of every trial.

        Returns
        -------
        dict of str to ndarray of float64, shape (n_trials,)
            Keyed by :class:`~nanostage.iso230_2.Iso230Result` attribute (``accuracy_up_m``
            for A↑, ``repeatability_up_m`` for R↑, ...) [m]; NaN for trials that did not
            complete and for parameters a unidirectional test does not have.
        """
        names = [attr for _, attr, _ in iso230_2.AXIS_PARAMETERS]
        out = {name: np.full(self.n_trials, np.nan) for name in names}
        for t in np.flatnonzero(self.ok):
            params = self.evaluate(int(t), reading=reading, coverage_factor=coverage_factor)
            for name, value in params.axis_parameters().items():
                if value is not None:
                    out[name][t] = value
        return out

    def summary(
        self, *, reading: Reading = "interferometer", coverage_factor: float = 2.0
    ) -> dict[str, dict[str, float]]:
        """Mean, standard deviation and percentiles (5, 50, 95) over the completed trials of
        each axis parameter that the test has [m]."""
        out: dict[str, dict[str, float]] = {}
        for name, v in self.distribution(reading=reading, coverage_factor=coverage_factor).items():
            v = v[np.isfinite(v)]
            if v.size == 0:
                continue
            p5, p50, p95 = np.percentile(v, [5.0, 50.0, 95.0])
            out[name] = {
                "mean": float(np.mean(v)),
                "std": float(np.std(v, ddof=1)) if v.size > 1 else math.nan,
                "p5": float(p5),
                "median": float(p50),
                "p95": float(p95),
                "n": float(v.size),
            }
        return out


# --------------------------------------------------------------------------------------------
# Running
# --------------------------------------------------------------------------------------------


#: Seconds between two checks of a pool worker that the process it works for still runs.
_PARENT_POLL_S: Final[float] = 0.2
#: The process a worker process of this module watches (see :func:`watch_parent`).
_watched_parent: int | None = None
#: The stop request of the chunks this process runs for an executor (a worker process stops
#: them when its parent is gone).
_worker_control = _core.CampaignControl()


def watch_parent(parent_pid: int) -> None:
    """In a worker process started by the campaign's own process (a process pool), exit
    when that process is gone, so that a campaign killed by SIGTERM or SIGKILL does not leave
    its pool's workers behind (they would otherwise wait for work for ever). Does nothing in
    the campaign's own process (threads) or in a process the campaign's process did not
    start (a Dask worker under its nanny: Dask watches its own workers).

    A worker may take a chunk from its pool's queue after the campaign's process has died;
    it then exits within a poll. Which process started this one comes from :mod:`multiprocessing`
    (the parent's pid and the pipe it holds open while it lives), not from the current
    parent pid, which is that of a reaper once the parent is gone."""
    global _watched_parent
    parent = multiprocessing.parent_process()
    if (
        parent_pid == os.getpid()
        or parent is None
        or parent.pid != parent_pid
        or _watched_parent == parent_pid
    ):
        return
    _watched_parent = parent_pid
    # A reparented worker (fork, spawn) or a dead fork server (forkserver) changes this pid.
    ppid = os.getppid()

    def gone() -> bool:
        # The parent's pipe closes when the parent exits, unless a sibling forked after this
        # worker holds it open; the parent's pid then names no process.
        if os.getppid() != ppid or not parent.is_alive():
            return True
        if os.name != "posix":  # os.kill(pid, 0) is no existence test on Windows
            return False
        try:
            os.kill(parent_pid, 0)
        except ProcessLookupError:
            return True
        except PermissionError:  # the pid names another user's process: reused
            return True
        return False

    def watch() -> None:
        while not gone():
            time.sleep(_PARENT_POLL_S)
        _worker_control.request_stop()
        os._exit(1)

    threading.Thread(target=watch, name="nanostage-parent-watch", daemon=True).start()


def _run_chunk(
    system: System,
    cycle_reference: FloatArray,
    measure_index: IntArray,
    start: int,
    stop: int,
    seed: int,
    threads: int = 1,
    parent_pid: int | None = None,
    control: _core.CampaignControl | None = None,
) -> dict[str, Any]:
    """Trials ``start..stop`` of a campaign (the unit of work an executor runs).

    Top level so that it pickles. Returns the core's dict: ``position_m``, ``encoder_m``
    (shape ``(stop - start, n_measurements)``), ``status``, and the ``failed_*`` entries.
    ``parent_pid``: the process running the campaign; a pool worker it started exits when
    that process is gone (:func:`watch_parent`). ``control``: the campaign's stop request and
    progress counter (default: the one of this process's executor chunks).
    """
    if parent_pid is not None:
        watch_parent(int(parent_pid))
    return _core.campaign_run(
        system,
        np.ascontiguousarray(cycle_reference, dtype=np.float64),
        np.ascontiguousarray(measure_index, dtype=np.int64),
        int(start),
        int(stop),
        int(seed),
        int(threads),
        control=_worker_control if control is None else control,
    )


def _check_memory(n_trials: int, n_measure: int) -> None:
    need = 2 * 8 * n_trials * n_measure + n_trials
    try:
        avail = os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return
    if need > avail:
        raise ConfigError(
            f"n_trials = {n_trials} is invalid: the positions need {need / 2**30:.1f} GiB "
            f"but {avail / 2**30:.1f} GiB of memory is available"
        )


def _chunks(n_trials: int, chunk_trials: int) -> list[tuple[int, int]]:
    return [(a, min(a + chunk_trials, n_trials)) for a in range(0, n_trials, chunk_trials)]


def _run_local(
    system: System,
    cycle: Cycle,
    bounds: Sequence[tuple[int, int]],
    seed: int,
    threads: int,
    bar: ProgressBar,
    control: _core.CampaignControl,
) -> list[dict[str, Any]]:
    """Run the chunks one after the other on a worker thread; the calling thread shows the
    progress and turns Ctrl-C into a stop request."""
    parts: list[dict[str, Any]] = []
    error: list[BaseException] = []

    def work() -> None:
        try:
            for a, b in bounds:
                # After a stop request the remaining chunks return at once (NOT_STARTED).
                parts.append(
                    _run_chunk(
                        system,
                        cycle.reference_m,
                        cycle.measure_index,
                        a,
                        b,
                        seed,
                        threads,
                        control=control,
                    )
                )
        except BaseException as exc:  # handed to the calling thread
            error.append(exc)

    worker = threading.Thread(target=work, name="nanostage-campaign", daemon=True)
    worker.start()
    try:
        while worker.is_alive():
            worker.join(_REFRESH_S)
            bar.update(control.progress)
    except KeyboardInterrupt:
        control.request_stop()
        worker.join()
        raise
    if error:
        raise error[0]
    return parts


def _run_executor(
    system: System,
    cycle: Cycle,
    bounds: Sequence[tuple[int, int]],
    seed: int,
    threads: int,
    executor: _Submitter,
    bar: ProgressBar,
) -> list[dict[str, Any]]:
    me = os.getpid()
    futures: list[_Future] = []
    try:
        for a, b in bounds:
            futures.append(
                executor.submit(
                    _run_chunk,
                    system,
                    cycle.reference_m,
                    cycle.measure_index,
                    a,
                    b,
                    seed,
                    threads,
                    me,
                )
            )
        while True:
            done = [f.done() for f in futures]
            bar.update(sum(b - a for (a, b), d in zip(bounds, done, strict=True) if d))
            if all(done):
                break
            time.sleep(_REFRESH_S)
        return [f.result() for f in futures]
    except BaseException:
        # Ctrl-C, SIGTERM (raised as KeyboardInterrupt by the command line) or a failed
        # chunk: the chunks not yet started are cancelled. The executor is the caller's: it
        # is not shut down (a running chunk ends on its own, or with its worker process).
        for f in futures:
            f.cancel()
        raise


def run_campaign(
    system: System,
    cycle: Cycle,
    *,
    n_trials: int,
    seed: int = 0,
    threads: int | None = None,
    executor: Executor | _Submitter | None = None,
    chunk_trials: int | None = None,
    progress: bool = True,
    control: _core.CampaignControl | None = None,
    measurement: MeasurementChain | None = None,
) -> CampaignResult:
    """Run ``n_trials`` trials of ``cycle`` on the closed loop of ``system``.

    Parameters
    ----------
    system : System
        The loop; its random effects (stochastic friction, noise, jitter) are drawn anew in
        every trial.
    cycle : Cycle
        The test every trial runs (:func:`~nanostage.cycles.step_cycle`,
        :func:`~nanostage.cycles.standard_test_cycle`). The axis starts at rest at
        ``cycle.reference_m[0]``.
    n_trials : int
        Number of trials, in ``[1, 2**32]``.
    seed : int, default 0
        Campaign seed, in ``[0, 2**64)``; trial ``i`` uses ``stream_seed(seed, i)``.
    threads : int, optional
        Threads of the local Rust pool, in ``[1, 1024]``; default: all cores for a local run,
        1 per chunk with an executor.
    executor : concurrent.futures.Executor or dask.distributed.Client, optional
        Runs chunks of trials (:func:`_run_chunk`, picklable) with ``submit``; the results
        are concatenated in trial order and are identical to a local run.
    chunk_trials : int, optional
        Trials per chunk, in ``[1, n_trials]``. Default: all in one call locally,
        ``ceil(n_trials / 32)`` with an executor.
    progress : bool, default True
        Show a progress bar on stderr.
    control : nanostage._core.CampaignControl, optional
        Stop request and progress counter of a local campaign, to stop it or watch it from
        another thread (default: a new one; each campaign has its own).
    measurement : MeasurementChain, optional
        Out-of-loop effects between the table and the interferometer at the functional point
        (:mod:`nanostage.measurement`), applied at the readings after the loop has run
        (:meth:`CampaignResult.with_measurement`); default: the interferometer reads the
        table position.

    Returns
    -------
    CampaignResult

    Raises
    ------
    ConfigError
        Invalid system, cycle or arguments (before any trial runs).
    KeyboardInterrupt
        On Ctrl-C: a local campaign is stopped within about a second (the running trials
        stop within 256 control samples), pending executor chunks are cancelled; partial
        results are discarded.
    """
    if not isinstance(cycle, Cycle):
        raise TypeError(f"cycle must be a nanostage.cycles.Cycle, not {type(cycle).__name__}")
    n = int_arg("n_trials", n_trials, 1, MAX_TRIALS)
    s = int_arg("seed", seed, 0, 2**64 - 1)
    if threads is None:
        n_threads = 1 if executor is not None else max(1, os.cpu_count() or 1)
    else:
        n_threads = int_arg("threads", threads, 1, MAX_THREADS)
    if chunk_trials is None:
        chunk = n if executor is None else max(1, math.ceil(n / 32))
    else:
        chunk = int_arg("chunk_trials", chunk_trials, 1, n)
    if cycle.n_measurements == 0:
        raise ConfigError("cycle is invalid: it has no measurement instants")
    executor_arg(executor)
    if measurement is not None and not isinstance(measurement, MeasurementChain):
        raise ConfigError(
            f"measurement = {measurement!r} is invalid: expected a "
            "nanostage.measurement.MeasurementChain or None"
        )
    _core.validate_system(system)
    _check_memory(n, cycle.n_measurements)
    bounds = _chunks(n, chunk)
    bar = ProgressBar(n, sys.stderr if progress else None, "campaign")
    t0 = time.perf_counter()
    if executor is None:
        ctl = _core.CampaignControl() if control is None else control
        parts = _run_local(system, cycle, bounds, s, n_threads, bar, ctl)
    else:
        parts = _run_executor(system, cycle, bounds, s, n_threads, executor, bar)
    compute_s = time.perf_counter() - t0
    bar.update(n, final=True)
    result = _assemble(cycle, s, parts, bounds, compute_s)
    return result if measurement is None else result.with_measurement(measurement)


def _assemble(
    cycle: Cycle,
    seed: int,
    parts: Sequence[dict[str, Any]],
    bounds: Sequence[tuple[int, int]],
    compute_s: float,
) -> CampaignResult:
    failures: list[TrialFailure] = []
    status_parts = []
    for (a, _), p in zip(bounds, parts, strict=True):
        status = np.asarray(p["status"], dtype=np.int8)
        status_parts.append(status)
        for trial, t_s, msg, state in zip(
            p["failed_trial"], p["failed_t_s"], p["failed_message"], p["failed_state"], strict=True
        ):
            k = int(trial)
            failures.append(
                TrialFailure(
                    trial=k,
                    status=TrialStatus(int(status[k - a])),
                    t_s=float(t_s),
                    state=tuple(float(x) for x in state),
                    message=str(msg),
                )
            )
    position = np.concatenate([np.asarray(p["position_m"], dtype=np.float64) for p in parts])
    encoder = np.concatenate([np.asarray(p["encoder_m"], dtype=np.float64) for p in parts])
    status_all = np.concatenate(status_parts)
    for arr in (position, encoder, status_all):
        arr.flags.writeable = False
    return CampaignResult(
        cycle=cycle,
        seed=seed,
        position_m=position,
        encoder_m=encoder,
        status=status_all,
        failures=tuple(failures),
        compute_s=compute_s,
    )
