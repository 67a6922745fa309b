"""The fit objective: the gap between measured and simulated readings, aligned per hold.


The gap
    For each sample, measured feedback reading minus the simulated mean reading
    ``x_sim − q/2`` (``q`` the encoder count: a floor quantiser reads on average half a count
    low). Using the mean reading keeps the fit objective smooth in the parameters; its floor
    for a perfect model is the quantisation noise ``q/√12`` plus sensor noise plus the
    trial-to-trial friction scatter. Experiments are weighted equally (each contributes its
    mean square).

Also the simulation cache the fits share, and the noise floors the selection compares
against.
"""

from __future__ import annotations

import itertools
import math
import threading
from collections import OrderedDict
from collections.abc import Mapping, Sequence
from dataclasses import replace
from typing import Final

import numpy as np
import numpy.typing as npt
from scipy import signal

from ..config import CascadeController, FpgaPid, System
from ..experiment import Experiment
from ..simulate import simulate_batch
from .segments import limit_cycle
from .settings import FloatArray

#: The flanks a backlash whose initial flank is open may rest against at the start of a
#: run (:func:`simulate_readings_and_commands`), in the order a tie is decided.
BACKLASH_FLANKS: tuple[float, float] = (1.0, -1.0)

__all__ = [
    "MICRO_STEP_MAX_COUNTS",
    "SimulationCache",
    "align_holds",
    "apply_gap_plan",
    "autocorrelation_time",
    "channel_units",
    "command_floors_v",
    "command_plan",
    "command_problems",
    "experiment_floors_m",
    "experiment_kind",
    "floors_m",
    "gap_plan",
    "gap_residual",
    "hold_intervals",
    "hunting_ramps",
    "move_units",
    "noise_floor_m",
    "output_limit_v",
    "proportional_gain_v_per_m",
    "ramp_intervals",
    "reading_quantum",
    "repeat_pairs",
    "rms_of",
    "simulate_reading_and_command",
    "simulate_readings_and_commands",
    "simulated_mean_reading",
]


def hold_intervals(reference_m: npt.ArrayLike, min_samples: int = 20) -> list[tuple[int, int]]:
    """(start, stop) of each stretch of at least ``min_samples`` where the reference is
    constant (after a step, or a rest between ramps)."""
    ref = np.asarray(reference_m, dtype=np.float64)
    const = np.r_[False, np.diff(ref) == 0]
    out = []
    k, n = 0, len(ref)
    while k < n:
        if const[k]:
            a = k - 1 if k > 0 else 0
            while k < n and const[k]:
                k += 1
            if k - a >= min_samples:
                out.append((a, k))
        else:
            k += 1
    return out


#: A hold is *unsettled* at its end when the measured position still spans more than this
#: many quanta (the smallest changes between samples: an encoder count) over its last
#: :data:`SETTLE_WINDOW` samples, and more than :data:`UNSETTLED_STEP_FRACTION` of the step
#: into it.
UNSETTLED_QUANTA = 4.0
UNSETTLED_STEP_FRACTION = 0.02
SETTLE_WINDOW = 50


def move_units(reference_m: npt.ArrayLike) -> list[tuple[int, int]]:
    """The experiment cut into its moves, (start, stop) each: a new unit starts where the
    reference settles at a new value (each hold after the first); the rest before the first
    move belongs to the first unit. A reference without holds is one unit."""
    ref = np.asarray(reference_m, dtype=np.float64)
    starts = [a for a, _ in hold_intervals(ref) if a > 0]
    bounds = [0, *starts[1:], len(ref)] if starts else [0, len(ref)]
    return list(itertools.pairwise(bounds))


def reading_quantum(m: npt.ArrayLike) -> float:
    """The smallest change between samples of a reading: one count for encoder data."""
    d = np.abs(np.diff(np.asarray(m, dtype=np.float64)))
    d = d[d > 0]
    # The 5th percentile of the nonzero changes: one count for encoder data however fast
    # the axis moves, the noise level for a continuous sensor.
    return float(np.percentile(d, 5.0)) if d.size else 0.0


def gap_residual(
    measured_m: npt.ArrayLike, simulated_m: npt.ArrayLike, reference_m: npt.ArrayLike
) -> FloatArray:
    """The gap of one experiment: measured − simulated, sample by sample, except where the
    reference is constant from the moment the measured position first reaches it (or from
    the second half of that stretch, if it never does): there the *sorted* values are
    compared — the distribution of positions (mean, overshoot amplitude, limit-cycle
    amplitude) but not the phase of an oscillation, which no model reproduces sample by
    sample once it is chaotic (backlash hunting, stick-slip). On a constant-velocity ramp
    whose measured tracking error (position − reference) hunts (:func:`hunting_ramps`), the
    sorted tracking errors are compared, for the same reason.

    A move that starts while the measured position is still hunting (the previous hold is
    unsettled at its end, see :data:`UNSETTLED_QUANTA`) starts from the phase of that
    oscillation, which no model reproduces either: its transient is compared after the time
    shift of at most :data:`SETTLE_WINDOW` samples that fits best (the minimum over shifts
    is still a continuous function of the model). A hold that starts where a hunting ramp
    ends (within :data:`AFTER_RAMP_SAMPLES`) starts where the cycle left the axis stuck (a
    stick-slip or a backlash's hunting stops at a random point of its cycle): its level, in
    the position and in the command that holds it there, is no more predictable than the
    cycle's phase, so its sorted values are compared less each signal's own mean over the
    hold (the spread about the level: a limit cycle that goes on, a creep). Which samples
    are compared how depends on the measured data only.

    An experiment whose reference never moves is driven by a known input (an open-loop
    pulse or a disturbance test): its response is compared sample by sample throughout."""
    return apply_gap_plan(gap_plan(measured_m, reference_m), measured_m, simulated_m)


#: How :func:`gap_residual` compares one window: ``(a, h, b, aligned, order, trend,
#: centred)``: samples ``[a, h)`` sample by sample (after the best time shift when
#: ``aligned``), ``[h, b)`` as sorted values (``order``: the measured samples' ranks there)
#: less ``trend`` (None for a hold; the reference over ``[h, b)`` for a hunting ramp, whose
#: tracking errors are compared), and with ``centred`` less each signal's own mean over
#: ``[h, b)`` (a hold after a hunting ramp, where the axis stuck at a random point of the
#: cycle: only the spread about the level is compared).
HoldPlan = tuple[int, int, int, bool, npt.NDArray[np.intp], FloatArray | None, bool]

#: A hold follows a ramp when it starts within this many samples of the ramp's end (a
#: hold's first sample is the last sample of the move into it).
AFTER_RAMP_SAMPLES = 2

#: A window hunts when its error spans more than this many reading quanta and repeats
#: itself: autocorrelation at the cycle's period at least
#: :data:`LIMIT_CYCLE_MIN_CORRELATION` (the segmentation's :func:`.segments.limit_cycle`).
HUNTING_QUANTA = 4.0
LIMIT_CYCLE_MIN_CORRELATION = 0.5
#: Shortest constant-velocity stretch of a reference counted as a ramp, samples.
MIN_RAMP_SAMPLES = 40


#: The largest move of a micro-step, in encoder counts: one that shows breakaway and
#: presliding rather than a slew.
MICRO_STEP_MAX_COUNTS = 10.0


def ramp_intervals(reference_m: npt.ArrayLike) -> list[tuple[int, int, float]]:
    """(start, stop, velocity per sample) of each constant-velocity stretch of the
    reference with a nonzero velocity and at least :data:`MIN_RAMP_SAMPLES` samples."""
    ref = np.asarray(reference_m, dtype=np.float64)
    d = np.diff(ref)
    out = []
    k, n = 0, len(d)
    while k < n:
        if d[k] == 0.0:
            k += 1
            continue
        j = k
        tol = 1e-6 * abs(d[k])
        while j + 1 < n and abs(d[j + 1] - d[k]) <= tol:
            j += 1
        if j + 1 - k >= MIN_RAMP_SAMPLES:
            out.append((k + 1, j + 2, float(np.mean(d[k : j + 1]))))
        k = j + 1
    return out


def hunting_ramps(
    measured_m: npt.ArrayLike, reference_m: npt.ArrayLike, quantum_m: float
) -> list[tuple[int, int]]:
    """The constant-velocity ramps (:func:`ramp_intervals`) whose measured tracking error
    still hunts in their second half, past the transient of the ramp's start: it spans
    more than :data:`HUNTING_QUANTA` quanta about its straight-line trend there (a lag
    settling slowly is no cycle), in the last quarter too (a ringing that dies out is a
    transient, whose phase a model reproduces), and repeats itself (a limit cycle, e.g. a
    backlash hunting while the reference moves slowly). That half must itself be a ramp's
    length (:data:`MIN_RAMP_SAMPLES`): a short fast ramp is one transient."""
    m = np.asarray(measured_m, dtype=np.float64)
    ref = np.asarray(reference_m, dtype=np.float64)
    out = []
    for a, b, _ in ramp_intervals(ref):
        half = (b - a) // 2
        if half < MIN_RAMP_SAMPLES:
            continue
        err = m[b - half : b] - ref[b - half : b]
        k = np.arange(half, dtype=np.float64)
        err = err - np.polyval(np.polyfit(k, err, 1), k)
        span = HUNTING_QUANTA * quantum_m
        if (
            float(np.ptp(err)) > span
            and float(np.ptp(err[half // 2 :])) > span
            and (limit_cycle(err, 1.0, LIMIT_CYCLE_MIN_CORRELATION, quantum_m) is not None)
        ):
            out.append((a, b))
    return out


def gap_plan(measured_m: npt.ArrayLike, reference_m: npt.ArrayLike) -> list[HoldPlan]:
    """The part of :func:`gap_residual` that depends on the measured data only (computed
    once per experiment by the fits, which compare many simulations with it)."""
    m = np.asarray(measured_m, dtype=np.float64)
    ref = np.asarray(reference_m, dtype=np.float64)
    if ref.size == 0 or np.all(ref == ref[0]):
        return []
    q = reading_quantum(m)
    plan: list[HoldPlan] = []
    unsettled = False
    hunting = hunting_ramps(m, ref, q)
    ends = [b for _, b in hunting]
    for a, b in hold_intervals(ref):
        step = abs(ref[a] - ref[a - 1]) if a > 0 else 0.0
        if any(abs(a - e) <= AFTER_RAMP_SAMPLES for e in ends):
            # The axis stuck where the cycle left it: a level no model predicts.
            plan.append((a, a, b, False, np.argsort(m[a:b], kind="stable"), None, True))
        else:
            side = np.sign(m[a:b] - ref[a])
            start_side = side[0]
            crossed = np.flatnonzero(side != start_side) if start_side != 0 else np.array([0])
            h = a + int(crossed[0]) if crossed.size else a + (b - a) // 2
            plan.append(
                (a, h, b, unsettled and h > a, np.argsort(m[h:b], kind="stable"), None, False)
            )
        tail = m[max(a, b - SETTLE_WINDOW) : b]
        spread = float(np.ptp(tail)) if tail.size else 0.0
        unsettled = spread > UNSETTLED_QUANTA * q and spread > UNSETTLED_STEP_FRACTION * step
    for a, b in hunting:
        trend = ref[a:b].copy()
        plan.append((a, a, b, False, np.argsort(m[a:b] - trend, kind="stable"), trend, False))
    return plan


def apply_gap_plan(
    plan: Sequence[HoldPlan], measured_m: npt.ArrayLike, simulated_m: npt.ArrayLike
) -> FloatArray:
    """:func:`gap_residual` from its plan (:func:`gap_plan` of the same measured data)."""
    m = np.asarray(measured_m, dtype=np.float64)
    s = np.asarray(simulated_m, dtype=np.float64)
    r = m - s
    for a, h, b, aligned_move, order, trend, centred in plan:
        if aligned_move:
            r[a:h] = m[a:h] - _best_shift(m, s, a, h, SETTLE_WINDOW)
        if b - h > 1:
            aligned = np.empty(b - h)
            if centred:
                aligned[order] = np.sort(s[h:b])
                r[h:b] = (m[h:b] - float(np.mean(m[h:b]))) - (aligned - float(np.mean(aligned)))
            elif trend is None:
                aligned[order] = np.sort(s[h:b])
                r[h:b] = m[h:b] - aligned
            else:
                aligned[order] = np.sort(s[h:b] - trend)
                r[h:b] = (m[h:b] - trend) - aligned
    return r


def command_plan(plan: Sequence[HoldPlan], measured_v: npt.ArrayLike) -> list[HoldPlan]:
    """The plan of an experiment's command gap from its position gap's (:func:`gap_plan`):
    the same windows compared the same way (sample by sample, time-shifted after an
    unsettled hold, as sorted values in the settled part of each hold), the sorted
    comparison ranking the measured command's own values. A limit cycle's phase shows in
    the command as in the position, and no model predicts it. (A hunting ramp's command has
    no trend: its own values are sorted.)"""
    c = np.asarray(measured_v, dtype=np.float64)
    return [
        (a, h, b, aligned, np.argsort(c[h:b], kind="stable"), None, centred)
        for a, h, b, aligned, _, _, centred in plan
    ]


def channel_units(r: FloatArray, n: int, units: Sequence[tuple[int, int]]) -> list[float]:
    """Each unit's (``(start, stop)`` sample ranges of one channel of ``n`` samples) sum of
    squares of the residual ``r``, over every channel ``r`` stacks (the position gap, then
    the weighted command gap when the fit uses the command), divided by ``len(r)``: the
    units' shares of the experiment's mean square (they add up to it)."""
    k = len(r) // n if n else 1
    return [
        float(sum(np.sum(r[j * n + a : j * n + b] ** 2) for j in range(k))) / len(r)
        for a, b in units
    ]


def _best_shift(m: FloatArray, s: FloatArray, a: int, h: int, window: int) -> FloatArray:
    """``s`` over ``[a, h)`` delayed or advanced by the whole number of samples (at most
    ``window``) that matches ``m`` there best (indices clamped to the record). Ties go to no
    shift, then to the most negative shift."""
    shifts = np.arange(-window, window + 1)
    idx = np.clip(np.arange(a, h)[None, :] + shifts[:, None], 0, len(s) - 1)
    cands = s[idx]
    costs = np.sum((m[a:h][None, :] - cands) ** 2, axis=1)
    k = window if costs[window] <= costs.min() else int(np.argmin(costs))
    best: FloatArray = cands[k]
    return best


def align_holds(
    measured_m: npt.ArrayLike, simulated_m: npt.ArrayLike, reference_m: npt.ArrayLike
) -> FloatArray:
    """The simulated signal with the samples of each hold window re-ordered to rank-match
    the measured ones, so that ``measured − aligned`` is :func:`gap_residual`."""
    out: FloatArray = np.asarray(measured_m, dtype=np.float64) - gap_residual(
        measured_m, simulated_m, reference_m
    )
    return out


def autocorrelation_time(r: FloatArray, max_lag: int = 500) -> float:
    """Integrated autocorrelation time ``1 + 2·Σρ(k)``, summed over the lags ``k`` from 1
    while ρ(k) > 0 (to the first lag where it drops to 0 or below), below ``max_lag`` and
    half the length. The lag products come from one FFT (``scipy.signal.correlate``): a
    smooth residual stays correlated over all ``max_lag`` lags, and one NumPy call per lag,
    each waiting for the GIL behind the candidates' other fitting threads, cost about a
    second per fit (on a residual of 10–20 thousand samples)."""
    x = np.asarray(r, dtype=np.float64)
    x = x - float(np.mean(x))
    var = float(np.dot(x, x))
    n_lags = min(max_lag, len(x) // 2)
    if var <= 0.0 or len(x) < 4 or n_lags <= 1:
        return 1.0
    full = signal.correlate(x, x, mode="full", method="fft")
    rho = full[len(x) : len(x) + n_lags - 1] / var  # lags 1 … n_lags − 1
    stop = np.flatnonzero(rho <= 0.0)
    kept = rho[: int(stop[0])] if stop.size else rho
    return 1.0 + 2.0 * float(np.sum(kept))


def rms_of(res: Sequence[FloatArray]) -> float:
    return math.sqrt(float(np.mean([np.mean(r**2) for r in res])))


def simulate_reading_and_command(system: System, exp: Experiment) -> tuple[FloatArray, FloatArray]:
    """The simulated mean reading (true position of the sensor's side minus half a count)
    and the controller's output in volts, on the experiment's samples."""
    return simulate_readings_and_commands([system], [exp])[0]


def simulate_readings_and_commands(
    systems: Sequence[System], experiments: Sequence[Experiment], threads: int = 0
) -> list[tuple[FloatArray, FloatArray]]:
    """:func:`simulate_reading_and_command` for each (system, experiment) pair, simulated in
    one parallel batch of the core (``threads`` workers; 0: one per CPU).

    The run starts at rest where the measured trace starts. A backlash whose initial flank
    the system leaves open (``Backlash.initial_flank`` None) rests against one of its two
    flanks, the side of the last move before the run, which the trace does not record:
    both are simulated, and the one whose reading is closer to the measured one (the
    :func:`gap_residual`; +1 on a tie) is kept."""
    for system, exp in zip(systems, experiments, strict=True):
        t = system.sample_period_s
        if abs(exp.sample_period_s - t) > 1e-3 * t:
            raise ValueError(
                f"experiment {exp.name!r} ({exp.source}): sample period "
                f"{exp.sample_period_s:g} s differs from the controller's {t:g} s"
            )
    # Each pair's runs: the system itself, or its flank variants.
    runs: list[tuple[int, System]] = []
    for j, system in enumerate(systems):
        b = system.effects.backlash
        if b is not None and b.initial_flank is None:
            for flank in BACKLASH_FLANKS:
                fx = replace(system.effects, backlash=replace(b, initial_flank=flank))
                runs.append((j, replace(system, effects=fx)))
        else:
            runs.append((j, system))
    traces = simulate_batch(
        [s for _, s in runs],
        [experiments[j].reference_m for j, _ in runs],
        force_disturbances_n=[experiments[j].disturbance_n for j, _ in runs],
        command_disturbances_v=[experiments[j].disturbance_v for j, _ in runs],
        initial_positions_m=[
            float(experiments[j].position_m[0]) + 0.5 * s.encoder.count_m for j, s in runs
        ],
        threads=threads,
    )
    out: list[tuple[FloatArray, FloatArray] | None] = [None] * len(systems)
    best = [math.inf] * len(systems)
    for (j, system), tr in zip(runs, traces, strict=True):
        q = system.encoder.count_m
        x = tr.motor_position_m if system.encoder.side == "motor" else tr.position_m
        reading: FloatArray = x - 0.5 * q
        command: FloatArray = tr.command * tr.output_unit_v
        if system is systems[j]:
            out[j] = (reading, command)
            continue
        e = experiments[j]
        cost = float(np.sum(apply_gap_plan(_measured_plan(e), e.position_m, reading) ** 2))
        if out[j] is None or cost < best[j]:
            best[j], out[j] = cost, (reading, command)
    return [o for o in out if o is not None]


#: :func:`gap_plan` of the experiments whose backlash flank was chosen, by ``id`` of the
#: experiment (held with it, so that an id is not reused while its entry lives); cleared
#: when it holds :data:`_PLAN_MEMO_SIZE` experiments.
_PLAN_MEMO: dict[int, tuple[Experiment, list[HoldPlan]]] = {}
_PLAN_MEMO_SIZE: Final = 256


def _measured_plan(e: Experiment) -> list[HoldPlan]:
    """:func:`gap_plan` of an experiment's measured position, computed once per experiment
    (it depends on the measured data only; a backlash's two flanks are judged by it at
    every simulation)."""
    hit = _PLAN_MEMO.get(id(e))
    if hit is not None and hit[0] is e:
        return hit[1]
    plan = gap_plan(e.position_m, e.reference_m)
    if len(_PLAN_MEMO) >= _PLAN_MEMO_SIZE:
        _PLAN_MEMO.clear()
    _PLAN_MEMO[id(e)] = (e, plan)
    return plan


class _PairKey:
    """A (system, experiment) pair as a dictionary key, its hash computed once: a
    ``System``'s hash walks every field of its nested dataclasses, and a lookup hashes its
    key several times."""

    __slots__ = ("_hash", "experiment_id", "system")

    def __init__(self, system: System, experiment: Experiment) -> None:
        self.system = system
        self.experiment_id = id(experiment)
        self._hash = hash((system, self.experiment_id))

    def __hash__(self) -> int:
        return self._hash

    def __eq__(self, other: object) -> bool:
        return (
            isinstance(other, _PairKey)
            and self._hash == other._hash
            and self.experiment_id == other.experiment_id
            and self.system == other.system
        )


class SimulationCache:
    """The simulated reading and command (:func:`simulate_readings_and_commands`) of each
    (system, experiment) pair simulated so far, the least recently used dropped beyond
    ``max_bytes``. A simulation is a deterministic function of its system and experiment (the
    same trace bit for bit whatever the batch or thread count), so a pair seen before is
    looked up instead of simulated: the results are those without the cache. Within a
    diagnosis a candidate's refit repeats its screening's scan and local fits from the same
    starts, and a discrete candidate's fits repeat its setting's start.

    Systems are compared by value (``System`` is a frozen dataclass), experiments by
    identity; an entry keeps its experiment alive. By value means ``0.0 == -0.0``: two
    systems differing only in the sign of a zero share an entry (their simulations could
    differ in the last bit where that sign reaches the arithmetic). Thread-safe
    (candidates are fitted on several Python threads); a batch's misses are simulated as one
    batch, outside the lock. The stored arrays are read-only."""

    def __init__(self, max_bytes: float) -> None:
        if not max_bytes >= 0.0:
            raise ValueError(f"SimulationCache max_bytes = {max_bytes!r}: must be ≥ 0")
        self.max_bytes = max_bytes
        self.n_bytes = 0
        self.hits = 0
        self.misses = 0
        self._lock = threading.Lock()
        self._entries: OrderedDict[_PairKey, tuple[Experiment, FloatArray, FloatArray]] = (
            OrderedDict()
        )

    def __len__(self) -> int:
        return len(self._entries)

    def simulate(
        self, systems: Sequence[System], experiments: Sequence[Experiment], threads: int = 0
    ) -> list[tuple[FloatArray, FloatArray]]:
        """:func:`simulate_readings_and_commands` of the pairs, the ones seen before looked
        up; a pair repeated within the call is simulated once."""
        keys = [_PairKey(s, e) for s, e in zip(systems, experiments, strict=True)]
        found: dict[_PairKey, tuple[FloatArray, FloatArray]] = {}
        with self._lock:
            for key in keys:
                hit = self._entries.get(key)
                if hit is not None and key not in found:
                    self._entries.move_to_end(key)
                    found[key] = (hit[1], hit[2])
        todo: dict[_PairKey, int] = {}
        for j, key in enumerate(keys):
            if key not in found and key not in todo:
                todo[key] = j
        with self._lock:
            self.hits += len(keys) - len(todo)
            self.misses += len(todo)
        if todo:
            idx = list(todo.values())
            sims = simulate_readings_and_commands(
                [systems[j] for j in idx], [experiments[j] for j in idx], threads
            )
            with self._lock:
                for key, j, (reading, command) in zip(todo, idx, sims, strict=True):
                    reading.setflags(write=False)
                    command.setflags(write=False)
                    found[key] = (reading, command)
                    if key not in self._entries:
                        self._entries[key] = (experiments[j], reading, command)
                        self.n_bytes += reading.nbytes + command.nbytes
                while self.n_bytes > self.max_bytes and self._entries:
                    _, (_, r, c) = self._entries.popitem(last=False)
                    self.n_bytes -= r.nbytes + c.nbytes
        return [found[key] for key in keys]


def simulated_mean_reading(system: System, exp: Experiment) -> FloatArray:
    """The simulated true position of the sensor's side minus half a count."""
    return simulate_reading_and_command(system, exp)[0]


def experiment_kind(reference_m: npt.ArrayLike, count_m: float) -> tuple[int, ...]:
    """What makes two experiments comparable in scatter: the sizes of their reference's
    steps in counts, in order, whatever the direction and the start (a 300 nm breakaway test
    and a 1 mm step scatter very differently; a +100 µm and a −100 µm step alike)."""
    d = np.diff(np.asarray(reference_m, dtype=float))
    return tuple(round(abs(float(x)) / count_m) for x in d[d != 0.0])


def _sensor_floor_var(experiments: Sequence[Experiment], count_m: float) -> float:
    """Quantisation ``q²/12`` plus the white sensor noise estimated from the second
    differences of the measured readings where the reference is at rest, m²."""
    noise_var = []
    for e in experiments:
        rest = np.r_[False, np.diff(e.reference_m) == 0] & np.r_[np.diff(e.reference_m) == 0, False]
        d2 = np.diff(e.position_m, 2)
        m = rest[1:-1]
        if np.count_nonzero(m) > 20:
            mad = float(np.median(np.abs(d2[m] - np.median(d2[m]))))
            noise_var.append((1.4826 * mad) ** 2 / 6.0)
    return count_m**2 / 12.0 + (float(np.median(noise_var)) if noise_var else 0.0)


def _command_sensor_var(experiments: Sequence[Experiment]) -> float:
    """The white floor of the measured command, V²: its resolution ``Δ²/12`` (Δ the
    smallest change between samples, :func:`reading_quantum`) plus the white noise estimated from
    its second differences where the reference is at rest (the median over experiments)."""
    noise_var = []
    quanta = []
    for e in experiments:
        if e.command_v is None:
            continue
        quanta.append(reading_quantum(np.asarray(e.command_v, dtype=np.float64)))
        rest = np.r_[False, np.diff(e.reference_m) == 0] & np.r_[np.diff(e.reference_m) == 0, False]
        d2 = np.diff(e.command_v, 2)
        m = rest[1:-1]
        if np.count_nonzero(m) > 20:
            mad = float(np.median(np.abs(d2[m] - np.median(d2[m]))))
            noise_var.append((1.4826 * mad) ** 2 / 6.0)
    q = float(np.median(quanta)) if quanta else 0.0
    return q**2 / 12.0 + (float(np.median(noise_var)) if noise_var else 0.0)


#: A measured command is *clipped* when it sits at its rails (within 1 % of the largest
#: magnitude it reaches, that magnitude within 2 % of the controller's output limit) for
#: more than this share of its samples.
CLIPPED_SHARE = 0.5
#: A measured command reaching more than this many times the controller's output limit is
#: in the wrong unit (millivolts: 1000×).
WRONG_UNIT_FACTOR = 10.0


def output_limit_v(system: System) -> float | None:
    """The largest command the controller can give, V (None for another controller)."""
    c = system.controller
    if isinstance(c, FpgaPid):
        return max(abs(c.output_min), abs(c.output_max)) * c.output_unit_v
    if isinstance(c, CascadeController):
        return abs(c.saturation_v)
    return None


def command_problems(
    experiments: Sequence[Experiment], systems: Mapping[str, System]
) -> tuple[list[str], dict[str, str]]:
    """Checks of the measured commands before any fitting: the errors (a command beyond
    :data:`WRONG_UNIT_FACTOR` times the controller's output limit: in the wrong unit), and
    the warnings by experiment name (a constant command, or one clipped at the rails for
    most of the experiment, :data:`CLIPPED_SHARE`: such a command tells nothing of the
    plant, and the gap leaves it out). Each message names the experiment, its source, the
    value and the valid range."""
    errors: list[str] = []
    warnings: dict[str, str] = {}
    for e in experiments:
        if e.command_v is None:
            continue
        c = np.asarray(e.command_v, dtype=np.float64)
        where = f"experiment {e.name!r}" + (f" ({e.source})" if e.source else "")
        peak = float(np.max(np.abs(c))) if c.size else 0.0
        limit = output_limit_v(systems[e.name]) if e.name in systems else None
        if limit is not None and peak > WRONG_UNIT_FACTOR * limit:
            errors.append(
                f"{where}: command_v reaches {peak:.6g} V, beyond {WRONG_UNIT_FACTOR:g}× the "
                f"controller's output limit of ±{limit:.6g} V: the command must be in volts "
                "(in millivolts, divide by 1000)"
            )
        elif c.size == 0 or float(np.ptp(c)) == 0.0:
            warnings[e.name] = (
                f"{where}: command_v is constant ({c[0] if c.size else 0.0:.6g} V): it tells "
                "nothing of the plant and is left out of the gap"
            )
        elif limit is not None and peak >= 0.98 * limit:
            share = float(np.mean(np.abs(c) >= 0.99 * peak))
            if share > CLIPPED_SHARE:
                warnings[e.name] = (
                    f"{where}: command_v sits at the rails (±{peak:.6g} V, output limit "
                    f"±{limit:.6g} V) for {share:.0%} of the samples (more than "
                    f"{CLIPPED_SHARE:.0%}: saturated moves, or a limit cycle between the "
                    "rails): it tells little of the plant and is left out of the gap; moves "
                    "the amplifier can follow tell more"
                )
    return errors, warnings


def proportional_gain_v_per_m(system: System) -> float:
    """The controller's proportional gain, volts of command per metre of position error:
    ``kp·output_unit_v/count`` for the FPGA PID, ``kp·kv`` for the cascade; 0 for another
    controller."""
    c = system.controller
    if isinstance(c, FpgaPid):
        return abs(c.kp * c.output_unit_v / system.encoder.count_m)
    if isinstance(c, CascadeController):
        return abs(c.kp_per_s * c.kv_v_s_per_m)
    return 0.0


def command_floors_v(
    experiments: Sequence[Experiment],
    count_m: float,
    position_floors_m: Mapping[str, float],
    gains_v_per_m: Mapping[str, float],
) -> dict[str, float]:
    """Each experiment's noise floor of the measured command, V: its position floor
    (``position_floors_m``, :func:`experiment_floors_m`) through the controller's
    proportional gain (``gains_v_per_m``, :func:`proportional_gain_v_per_m`: the command the
    reading's noise alone makes), raised to the spread of the repeated experiments of its
    kind compared as the command gap is, and to the command's white floor
    (:func:`_command_sensor_var`). 0 for an experiment without a command, or whose
    controller has no proportional path and no repeats (nothing to scale it by)."""
    sensor = _command_sensor_var(experiments)
    by_kind: dict[tuple[int, ...], list[float]] = {}
    for kind, v in _repeat_spreads(experiments, count_m, command=True):
        by_kind.setdefault(kind, []).append(v)
    out = {}
    for e in experiments:
        vs = by_kind.get(experiment_kind(e.reference_m, count_m))
        through = gains_v_per_m.get(e.name, 0.0) * position_floors_m.get(e.name, 0.0)
        spread = math.sqrt(float(np.mean(vs))) if vs else 0.0
        floor = max(through, spread)
        out[e.name] = 0.0 if e.command_v is None or floor == 0.0 else max(floor, sensor**0.5)
    return out


def _repeat_spreads(
    experiments: Sequence[Experiment], count_m: float, *, command: bool = False
) -> list[tuple[tuple[int, ...], float]]:
    """Half the mean-square difference of each pair of repeated experiments (the same
    reference at the same positions: the same step elsewhere on the travel is not a repeat,
    since position-dependent friction makes it differ), with the pair's kind. Measured like
    the gap itself: sample by sample, but in holds as sorted values, so a limit cycle's
    phase (which no model predicts) is not scatter. ``command``: the spread of the measured
    commands instead (pairs with both commands only)."""
    spreads = []
    for a, b in repeat_pairs(experiments, count_m):
        if command:
            if a.command_v is None or b.command_v is None:
                continue
            plan = command_plan(gap_plan(a.position_m, a.reference_m), a.command_v)
            r = apply_gap_plan(plan, a.command_v, b.command_v)
        else:
            r = gap_residual(a.position_m, b.position_m, a.reference_m)
        spreads.append((experiment_kind(a.reference_m, count_m), float(np.mean(r**2)) / 2.0))
    return spreads


def repeat_pairs(
    experiments: Sequence[Experiment], count_m: float
) -> list[tuple[Experiment, Experiment]]:
    """The pairs of repeated experiments (consecutive within each group of the same
    reference at the same positions, to a tenth of a count): the same step elsewhere on the
    travel is not a repeat, since position-dependent friction makes it differ."""
    groups: dict[tuple[int, float], list[Experiment]] = {}
    for e in experiments:
        key = (len(e.reference_m), round(float(e.reference_m[0]) / count_m))
        groups.setdefault(key, []).append(e)
    return [
        (a, b)
        for g in groups.values()
        for a, b in itertools.pairwise(g)
        if np.allclose(a.reference_m, b.reference_m, rtol=0.0, atol=count_m / 10)
    ]


def noise_floor_m(experiments: Sequence[Experiment], count_m: float) -> float:
    """The gap a perfect model would leave, m: quantisation ``q/√12`` plus the white sensor
    noise estimated from the second differences of the measured readings where the
    reference is at rest, raised to the spread of repeated experiments (the same reference
    at the same positions), if any. The spread of two repeats is measured with
    :func:`gap_residual`, as the gap is."""
    return floors_m(experiments, count_m)[0]


def floors_m(experiments: Sequence[Experiment], count_m: float) -> tuple[float, dict[str, float]]:
    """:func:`noise_floor_m` and :func:`experiment_floors_m` from one pass over the repeats."""
    sensor = _sensor_floor_var(experiments, count_m)
    spreads = _repeat_spreads(experiments, count_m)
    var = sensor
    if spreads:
        # The mean over pairs, like the gap's mean over experiments: experiment types differ
        # in scatter (a chaotic breakaway test far more than a settled step), and a median
        # would report the quiet ones only.
        var = max(var, float(np.mean([v for _, v in spreads])))
    overall = math.sqrt(var)
    by_kind: dict[tuple[int, ...], list[float]] = {}
    for kind, v in spreads:
        by_kind.setdefault(kind, []).append(v)
    own = {}
    for e in experiments:
        vs = by_kind.get(experiment_kind(e.reference_m, count_m))
        own[e.name] = math.sqrt(max(sensor, float(np.mean(vs)))) if vs else overall
    return overall, own


def experiment_floors_m(experiments: Sequence[Experiment], count_m: float) -> dict[str, float]:
    """Each experiment's own noise floor, m: the spread of the repeated experiments of its
    kind (:func:`experiment_kind`; the mean over the kind's repeat pairs), never below the
    sensor floor; an experiment of a kind without repeats gets :func:`noise_floor_m`.

    Experiment types differ in scatter by an order of magnitude (a breakaway test of three
    counts scatters by tens of nm, a 1 mm step or a reversal by hundreds), so one floor for
    all either hides an effect that shows in the quiet experiments only (a rising static
    friction in the breakaway tests) or lets noise in the loud ones pass for an effect."""
    return floors_m(experiments, count_m)[1]
