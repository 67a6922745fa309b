"""Single runs: the closed loop (plant + FPGA PID) or the plant alone.

Array conventions: every channel is a 1-D ``float64``/``int64``/``bool`` array with one
entry per control sample ``n`` at ``time_s[n] = n · T``. Plant channels (position, velocity,
current, friction forces, ``stuck``) are sampled at ``t_n``; controller channels (error,
P/I/D terms, command, DAC code, flags, ``motor_voltage_v``) are the update computed from the
sample at ``t_n``, which the plant sees from ``t_n + latency`` on. Positions are positive
along +x; the error is reference − measurement.

Every run has a bounded amount of work per control interval (``IntegratorOptions.max_steps``
and ``max_events``): one that needs more ends with :class:`nanostage.SimulationError` naming
the time, the state and the cause, and a channel that is not finite is an error, never a
result. A run answers Ctrl-C while it computes: called from the main thread, the
``KeyboardInterrupt`` of SIGINT stops it within a fraction of a second (:func:`simulate`,
:func:`simulate_batch`, :func:`simulate_plant`, :func:`simulate_open_loop`); runs in other
threads stop too inside :func:`stop_on_interrupt`.
"""

from __future__ import annotations

import math
import os
import signal
import threading
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from types import FrameType
from typing import Any

import numpy as np
import numpy.typing as npt

from . import _core
from .config import FpgaPid, IntegratorOptions, Plant, System

__all__ = [
    "DriveOpenLoopTrace",
    "OpenLoopTrace",
    "Trace",
    "simulate",
    "simulate_batch",
    "simulate_open_loop",
    "simulate_plant",
    "simulate_step",
    "step_reference",
    "stop_on_interrupt",
]

#: Bytes one recorded sample takes (all channels).
BYTES_PER_SAMPLE = 8 * 21
#: Most samples the core accepts in one trace.
MAX_SAMPLES = 1 << 24

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]
BoolArray = npt.NDArray[np.bool_]


@dataclass(frozen=True, slots=True, kw_only=True)
class Trace:
    """A closed-loop run. See the module docstring for when each channel is sampled."""

    time_s: FloatArray
    reference_m: FloatArray
    reference_counts: IntArray
    position_m: FloatArray
    velocity_m_per_s: FloatArray
    encoder_counts: IntArray
    current_a: FloatArray
    motor_voltage_v: FloatArray
    command: FloatArray
    dac_code: IntArray
    error_counts: FloatArray
    p_term: FloatArray
    i_term: FloatArray
    d_term: FloatArray
    flags: npt.NDArray[np.uint32]
    motor_friction_force_n: FloatArray
    table_friction_force_n: FloatArray
    stuck: BoolArray
    motor_position_m: FloatArray
    interferometer_m: FloatArray | None
    stats: dict[str, int]
    count_m: float
    sample_period_s: float
    output_unit_v: float
    amplifier_limit_v: float

    @property
    def encoder_position_m(self) -> FloatArray:
        """The encoder reading in metres (``encoder_counts · count_m``)."""
        out: FloatArray = self.encoder_counts.astype(np.float64) * self.count_m
        return out


@dataclass(frozen=True, slots=True, kw_only=True)
class OpenLoopTrace:
    """The plant driven by a held voltage per sample; ``n + 1`` samples including t = 0."""

    time_s: FloatArray
    position_m: FloatArray
    velocity_m_per_s: FloatArray
    dahl_force_n: FloatArray
    current_a: FloatArray
    stuck: BoolArray
    stats: dict[str, int]


#: The stop flag the runs of this module pass to the core while :func:`stop_on_interrupt` is
#: active (None otherwise).
_interrupt_stop: _core.StopFlag | None = None


def interrupt_stop() -> _core.StopFlag | None:
    """The stop flag of the innermost active :func:`stop_on_interrupt` block (None outside
    one): the ``stop=`` argument every core run of the package passes."""
    return _interrupt_stop


@contextmanager
def stop_on_interrupt() -> Iterator[None]:
    """Within the block, SIGINT (Ctrl-C) also stops the simulations that other threads of this
    process are running (e.g. the workers of a ``ThreadPoolExecutor``): they end with
    :class:`nanostage.SimulationError` ("interrupted at t = ..."), while the main thread gets
    the ``KeyboardInterrupt`` of the handler that was installed before. Without it, a worker's
    run would go on to its end (the main thread's own runs stop anyway).

    Entered from another thread than the main one, or with SIGINT ignored (a background
    job), it changes nothing. Each block has its own stop request (a :class:`_core.StopFlag`),
    so runs started after it are not stopped.
    """
    previous = signal.getsignal(signal.SIGINT)
    if threading.current_thread() is not threading.main_thread() or previous == signal.SIG_IGN:
        yield
        return

    global _interrupt_stop
    stop = _core.StopFlag()

    def interrupt(signum: int, frame: FrameType | None) -> None:
        stop.request_stop()
        if callable(previous):
            previous(signum, frame)
        else:
            raise KeyboardInterrupt

    outer, _interrupt_stop = _interrupt_stop, stop
    signal.signal(signal.SIGINT, interrupt)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
        _interrupt_stop = outer


def _check_samples(n: int, field_name: str, value: float) -> None:
    if n < 1 or n > MAX_SAMPLES:
        raise _core.ConfigError(
            f"{field_name} = {value} is invalid: expected between 1 and {MAX_SAMPLES} samples "
            f"(got {n})"
        )
    try:
        avail = os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return
    need = n * BYTES_PER_SAMPLE
    if need > avail:
        raise _core.ConfigError(
            f"{field_name} = {value} is invalid: its trace needs {need / 2**30:.1f} GiB but "
            f"{avail / 2**30:.1f} GiB of memory is available"
        )


def step_reference(
    step_m: float, *, duration_s: float, sample_period_s: float, start_s: float = 0.01
) -> FloatArray:
    """A step reference: 0 before ``start_s``, ``step_m`` from then on, one value per sample.

    Parameters
    ----------
    step_m : float
        Step size, m (either sign).
    duration_s : float
        Length of the run, s (> 0).
    sample_period_s : float
        Control period, s (> 0).
    start_s : float
        Time of the step, s (≥ 0).

    Returns
    -------
    ndarray, shape (n_samples,)
        Reference position, m.
    """
    for name, v, ok, rng in [
        ("step_m", step_m, math.isfinite(step_m), "a finite step in m"),
        ("duration_s", duration_s, math.isfinite(duration_s) and duration_s > 0, "> 0 s"),
        (
            "sample_period_s",
            sample_period_s,
            math.isfinite(sample_period_s) and sample_period_s > 0,
            "> 0 s",
        ),
        ("start_s", start_s, math.isfinite(start_s) and start_s >= 0, ">= 0 s"),
    ]:
        if not ok:
            raise _core.ConfigError(f"{name} = {v} is invalid: expected {rng}")
    n = round(duration_s / sample_period_s)
    _check_samples(n, "duration_s", duration_s)
    t = np.arange(n) * sample_period_s
    out: FloatArray = np.where(t >= start_s - 1e-12, float(step_m), 0.0).astype(np.float64)
    return out


def _series(value: npt.ArrayLike | None, name: str, n: int) -> FloatArray | None:
    if value is None:
        return None
    arr = np.ascontiguousarray(value, dtype=np.float64)
    if arr.shape != (n,):
        raise _core.ConfigError(
            f"{name} = array of shape {arr.shape} is invalid: expected shape ({n},) like "
            "reference_m"
        )
    return arr


def simulate(
    system: System,
    reference_m: npt.ArrayLike,
    *,
    force_disturbance_n: npt.ArrayLike | None = None,
    command_disturbance_v: npt.ArrayLike | None = None,
    seed: int = 0,
    initial_position_m: float | None = None,
) -> Trace:
    """Run the closed loop over a reference trajectory.

    Parameters
    ----------
    system : System
        Plant, controller, encoder, output stage, integrator options and effects.
    reference_m : array_like, shape (n_samples,)
        Reference position at each control sample, m.
    force_disturbance_n : array_like, shape (n_samples,), optional
        Known force on the table held over each sample interval, N (positive along +x).
    command_disturbance_v : array_like, shape (n_samples,), optional
        Known voltage added to the controller's saturated output of each sample, V.
    seed : int
        Seed of every random draw (stochastic friction, noise, jitter); the same seed gives a
        bit-identical run.
    initial_position_m : float, optional
        Where the axis rests at t = 0 (every mass, links relaxed), m. Default: the first
        reference value.

    Returns
    -------
    Trace
        Every channel at every control sample.

    Raises
    ------
    ConfigError
        Invalid configuration or reference (names the field, value and valid range).
    SimulationError
        A numerical failure (carries ``t_s`` and ``state``).
    """
    ref = _reference(reference_m, seed)
    out = _core.simulate_system(
        system,
        ref,
        _series(force_disturbance_n, "force_disturbance_n", ref.size),
        _series(command_disturbance_v, "command_disturbance_v", ref.size),
        int(seed),
        float(ref[0] if initial_position_m is None else initial_position_m),
        stop=_interrupt_stop,
    )
    return _trace(system, out)


def simulate_batch(
    systems: Sequence[System],
    references_m: Sequence[npt.ArrayLike],
    *,
    force_disturbances_n: Sequence[npt.ArrayLike | None] | None = None,
    command_disturbances_v: Sequence[npt.ArrayLike | None] | None = None,
    seeds: Sequence[int] | None = None,
    initial_positions_m: Sequence[float | None] | None = None,
    threads: int = 0,
) -> list[Trace]:
    """:func:`simulate` for several runs at once: one call into the core, which runs them in
    parallel (``threads`` workers; 0: one per CPU) with the GIL released once, so that many
    short runs scale over the cores (one Python thread per short run spends much of its time
    handing the GIL over). The same traces as :func:`simulate` run by run, bit for bit, in the
    order given; every input is checked before any run starts, and the first failed run (in
    that order) raises its error. Optional sequences give one entry per run (None: the
    default of :func:`simulate`)."""
    n = len(systems)

    def per_run(values: Sequence[Any] | None, name: str) -> list[Any]:
        if values is None:
            return [None] * n
        if len(values) != n:
            raise ValueError(f"{name} has {len(values)} entries; expected one per system ({n})")
        return list(values)

    seed_list = [0 if s is None else s for s in per_run(seeds, "seeds")]
    refs = [
        _reference(r, sd)
        for r, sd in zip(per_run(references_m, "references_m"), seed_list, strict=True)
    ]
    forces = per_run(force_disturbances_n, "force_disturbances_n")
    commands = per_run(command_disturbances_v, "command_disturbances_v")
    starts = per_run(initial_positions_m, "initial_positions_m")
    if threads < 0:
        raise ValueError(f"threads = {threads} is invalid: expected 0 (one per CPU) or more")
    outs = _core.simulate_system_batch(
        list(systems),
        refs,
        [_series(f, "force_disturbance_n", r.size) for f, r in zip(forces, refs, strict=True)],
        [_series(c, "command_disturbance_v", r.size) for c, r in zip(commands, refs, strict=True)],
        [int(s) for s in seed_list],
        [float(r[0] if x is None else x) for x, r in zip(starts, refs, strict=True)],
        int(threads),
        stop=_interrupt_stop,
    )
    return [_trace(s, o) for s, o in zip(systems, outs, strict=True)]


def _reference(reference_m: npt.ArrayLike, seed: int) -> np.ndarray:
    """The checked reference array (and seed) of one run."""
    ref = np.ascontiguousarray(reference_m, dtype=np.float64)
    if ref.ndim != 1:
        raise _core.ConfigError(
            f"reference_m = array of shape {ref.shape} is invalid: expected a 1-D array"
        )
    _check_samples(ref.size, "reference_m (length)", ref.size)
    if not 0 <= seed < 2**64:
        raise _core.ConfigError(f"seed = {seed} is invalid: expected an integer in [0, 2**64)")
    return ref


def _trace(system: System, out: dict[str, Any]) -> Trace:
    """The :class:`Trace` of one run from the core's dict."""
    if out["interferometer_m"].size == 0:
        out["interferometer_m"] = None
    ctl = system.controller
    if isinstance(ctl, FpgaPid):
        unit_v, limit_v = ctl.output_unit_v, system.output_stage.amplifier_limit_v
    else:
        unit_v, limit_v = 1.0, ctl.saturation_v
    return Trace(
        **out,
        count_m=system.encoder.count_m,
        sample_period_s=ctl.sample_period_s,
        output_unit_v=unit_v,
        amplifier_limit_v=limit_v,
    )


def simulate_step(
    system: System, step_m: float, *, duration_s: float, start_s: float = 0.01
) -> Trace:
    """Closed-loop step response (a convenience over :func:`step_reference` + :func:`simulate`).

    Examples
    --------
    >>> import nanostage
    >>> s = nanostage.presets.seed(1e-3)
    >>> tr = nanostage.simulate_step(s, 1e-3, duration_s=0.5)
    >>> abs(tr.encoder_counts[-1] - tr.reference_counts[-1]) <= 1
    True
    """
    ref = step_reference(
        step_m,
        duration_s=duration_s,
        sample_period_s=system.controller.sample_period_s,
        start_s=start_s,
    )
    return simulate(system, ref)


def simulate_plant(
    plant: Plant,
    voltage_v: npt.ArrayLike,
    *,
    sample_period_s: float,
    integrator: IntegratorOptions | None = None,
) -> OpenLoopTrace:
    """Drive the plant alone: ``voltage_v[k]`` held on ``[k·T, (k+1)·T)``; starts at rest.

    Returns ``n + 1`` samples at ``t_k = k·T`` (including t = 0).
    """
    u = np.ascontiguousarray(voltage_v, dtype=np.float64)
    if u.ndim != 1:
        raise _core.ConfigError(
            f"voltage_v = array of shape {u.shape} is invalid: expected a 1-D array"
        )
    _check_samples(u.size, "voltage_v (length)", u.size)
    out = _core.simulate_open_loop(
        plant, integrator or IntegratorOptions(), u, float(sample_period_s), stop=_interrupt_stop
    )
    return OpenLoopTrace(**out)


@dataclass(frozen=True, slots=True, kw_only=True)
class DriveOpenLoopTrace:
    """The component plant driven open loop; ``n + 1`` samples including t = 0."""

    time_s: FloatArray
    position_m: FloatArray
    motor_position_m: FloatArray
    velocity_m_per_s: FloatArray
    motor_friction_force_n: FloatArray
    table_friction_force_n: FloatArray
    stuck: BoolArray
    stats: dict[str, int]


def simulate_open_loop(
    system: System,
    voltage_v: npt.ArrayLike,
    *,
    sample_period_s: float,
    force_n: npt.ArrayLike | None = None,
) -> DriveOpenLoopTrace:
    """Drive the plant of ``system`` with all its effects, without the controller:
    ``voltage_v[k]`` (motor voltage, or drive command of a force drive) and ``force_n[k]``
    (on the table, +x) held on ``[k·T, (k+1)·T)``; starts at rest. Always runs the component
    plant (``rust/src/model/component.rs``)."""
    u = np.ascontiguousarray(voltage_v, dtype=np.float64)
    if u.ndim != 1:
        raise _core.ConfigError(
            f"voltage_v = array of shape {u.shape} is invalid: expected a 1-D array"
        )
    _check_samples(u.size, "voltage_v (length)", u.size)
    out = _core.simulate_system_open_loop(
        system,
        u,
        float(sample_period_s),
        _series(force_n, "force_n", u.size),
        stop=_interrupt_stop,
    )
    return DriveOpenLoopTrace(**out)
