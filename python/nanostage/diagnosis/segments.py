"""Segment a positioning response into labelled phases, sample by sample.

The reference is split into *moves*: maximal stretches over which it changes monotonically
(one sample for a step, many for a ramp), each followed by the dwell until the next move.
Every sample gets exactly one phase (:data:`PHASES`, a partition of the samples):

``acceleration``
    From the start of a move until the slew phase (or, without one, the peak velocity).
``slew``
    Step moves: the measured speed within ``slew_tolerance`` (10 %) of the experiment's
    peak speed over at least ``min_slew_samples`` samples (the voltage/velocity limit).
    Ramp moves: the reference runs at constant velocity (its acceleration below
    ``slew_tolerance`` times its typical acceleration), again sustained.
``braking``
    After the slew (or the velocity peak) until the position first reaches the target, or
    stops (speed below the sliding threshold) short of it.
``overshoot``
    The first excursion beyond the target, from the crossing until the position comes back
    to the target; only if it exceeds the hold band.
``settling``
    Between braking/overshoot and hold.
``hold``
    From the moment the position stays within a band of its final value until the next
    move (and before the first move). The band is ``hold_band_m``, or by default 1.5 times
    the half range of the last quarter of the dwell (at least two position quanta and
    1 nm), so that a limit cycle in hold stays inside it. For each hold, the final position
    and error, and a limit cycle (periodic oscillation: autocorrelation peak ≥
    ``limit_cycle_min_correlation`` at a lag that fits three times in the hold) with its
    amplitude and period are reported in :class:`Move`.

For ramp moves the phases during the ramp follow the reference's kinematics (speeding up,
constant velocity, slowing down); after the reference stops they follow the measured
position as for steps.

Independently, each sample is labelled ``presliding``/``sliding`` (speed below/above
``sliding_threshold_m_per_s``, default 0.1 mm/s), by direction (``+``, ``-``, ``rest``, the
same threshold) and by position bin (``n_position_bins`` equal bins over the measured
travel). The velocity is a Savitzky–Golay derivative (quadratic, ``smoothing_window``
samples) of the measured position at the median sample period.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Final, Literal

import numpy as np
import numpy.typing as npt

from ..experiment import Experiment

__all__ = [
    "DIRECTION_LABELS",
    "MOTION_LABELS",
    "PHASES",
    "LimitCycle",
    "Move",
    "Segmentation",
    "estimate_velocity",
    "segment",
    "segment_arrays",
    "segment_summary",
]

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]
BoolArray = npt.NDArray[np.bool_]

#: Phase names, in the order of a move; the phases partition the samples.
PHASES: Final[tuple[str, ...]] = (
    "acceleration",
    "slew",
    "braking",
    "overshoot",
    "settling",
    "hold",
)
#: Motion labels (by speed).
MOTION_LABELS: Final[tuple[str, ...]] = ("presliding", "sliding")
#: Direction labels.
DIRECTION_LABELS: Final[tuple[str, ...]] = ("+", "-", "rest")

_ACC, _SLEW, _BRAKE, _OVER, _SETTLE, _HOLD = range(6)


@dataclass(frozen=True, slots=True, kw_only=True)
class LimitCycle:
    """A periodic oscillation in hold.

    Attributes
    ----------
    amplitude_m : float
        Half the peak-to-peak position in hold, m.
    period_s : float
        Period, s (autocorrelation peak, parabolic interpolation).
    correlation : float
        Normalised autocorrelation at the period, in (0, 1].
    """

    amplitude_m: float
    period_s: float
    correlation: float


@dataclass(frozen=True, slots=True, kw_only=True)
class Move:
    """One move of the reference and the response to it (sample indices into the trace).

    Attributes
    ----------
    index : int
        0-based move number.
    kind : {"step", "ramp"}
        ``step`` if the reference jumps within two samples, else ``ramp``.
    start : int
        First sample with the new reference value.
    reference_stop : int
        First sample with the reference at the target.
    stop : int
        End of the move (exclusive): the next move's start or the trace length.
    start_m, target_m : float
        Reference before and after the move, m.
    direction : int
        +1 or -1.
    hold_start : int
        First hold sample (``stop`` if there is no hold).
    hold_band_m : float
        Half-width of the hold band, m.
    final_start : int
        First of the samples the final position is taken over (the hold, or the last
        quarter of the dwell without one; ``stop`` if the move has no dwell).
    final_position_m : float
        Median measured position over ``[final_start, stop)``, m (NaN without a dwell).
    final_error_m : float
        ``target_m - final_position_m``, m.
    settling_time_s : float
        Time from ``start`` to ``hold_start``, s (NaN without a hold).
    overshoot_m : float
        Largest travel beyond the target in the move direction, m (≥ 0).
    peak_speed_m_per_s : float
        Largest speed in the move direction, m/s.
    limit_cycle : LimitCycle or None
        The oscillation in hold, if one is detected.
    """

    index: int
    kind: Literal["step", "ramp"]
    start: int
    reference_stop: int
    stop: int
    start_m: float
    target_m: float
    direction: int
    hold_start: int
    hold_band_m: float
    final_start: int
    final_position_m: float
    final_error_m: float
    settling_time_s: float
    overshoot_m: float
    peak_speed_m_per_s: float
    limit_cycle: LimitCycle | None

    @property
    def step_m(self) -> float:
        """Signed move distance, m."""
        return self.target_m - self.start_m


@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class Segmentation:
    """Per-sample labels of one response (see the module docstring).

    Attributes
    ----------
    time_s, reference_m, position_m : ndarray, shape (n,)
        The inputs.
    velocity_m_per_s : ndarray, shape (n,)
        Estimated velocity of the measured position, m/s.
    phase : ndarray of int64, shape (n,)
        Index into :data:`PHASES` per sample.
    sliding : ndarray of bool, shape (n,)
        Speed above the sliding threshold.
    direction : ndarray of int64, shape (n,)
        +1, -1 or 0 (rest) per sample.
    position_bin : ndarray of int64, shape (n,)
        Position bin per sample, ``0 .. n_bins - 1``.
    position_bin_edges_m : ndarray, shape (n_bins + 1,)
        Bin edges, m.
    moves : tuple of Move
    peak_speed_m_per_s : float
        Largest measured speed in the experiment, m/s.
    sliding_threshold_m_per_s : float
        The presliding/sliding threshold used, m/s.
    """

    time_s: FloatArray
    reference_m: FloatArray
    position_m: FloatArray
    velocity_m_per_s: FloatArray
    phase: IntArray
    sliding: BoolArray
    direction: IntArray
    position_bin: IntArray
    position_bin_edges_m: FloatArray
    moves: tuple[Move, ...]
    peak_speed_m_per_s: float
    sliding_threshold_m_per_s: float

    @property
    def n_samples(self) -> int:
        """Number of samples."""
        return int(self.time_s.shape[0])

    def masks(self) -> dict[str, BoolArray]:
        """Phase name → boolean mask, for every name in :data:`PHASES` (a partition)."""
        return {name: self.phase == i for i, name in enumerate(PHASES)}

    def motion_masks(self) -> dict[str, BoolArray]:
        """``presliding``/``sliding`` → mask (a partition)."""
        return {"presliding": ~self.sliding, "sliding": self.sliding.copy()}

    def direction_masks(self) -> dict[str, BoolArray]:
        """``+``/``-``/``rest`` → mask (a partition)."""
        return {"+": self.direction > 0, "-": self.direction < 0, "rest": self.direction == 0}

    def position_masks(self) -> dict[str, BoolArray]:
        """Position bin label (``"[a, b) mm"``) → mask (a partition)."""
        e = self.position_bin_edges_m * 1e3
        out: dict[str, BoolArray] = {}
        for i in range(len(e) - 1):
            close = "]" if i == len(e) - 2 else ")"
            out[f"[{e[i]:.4g}, {e[i + 1]:.4g}{close} mm"] = self.position_bin == i
        return out

    def partitions(self) -> dict[str, dict[str, BoolArray]]:
        """All partitions: ``phase``, ``motion``, ``direction``, ``position``."""
        return {
            "phase": self.masks(),
            "motion": self.motion_masks(),
            "direction": self.direction_masks(),
            "position": self.position_masks(),
        }

    def labels(self) -> npt.NDArray[np.str_]:
        """Phase name per sample."""
        out: npt.NDArray[np.str_] = np.asarray(PHASES, dtype=np.str_)[self.phase]
        return out

    def intervals(self) -> list[tuple[str, int, int]]:
        """Contiguous phase runs ``(phase, first, end_exclusive)`` in time order."""
        p = self.phase
        cuts = np.flatnonzero(np.diff(p)) + 1
        starts = np.concatenate(([0], cuts))
        ends = np.concatenate((cuts, [p.size]))
        return [(PHASES[int(p[s])], int(s), int(e)) for s, e in zip(starts, ends, strict=True)]


# --------------------------------------------------------------------------------------------
# Helpers
# --------------------------------------------------------------------------------------------


def estimate_velocity(
    time_s: npt.ArrayLike, position_m: npt.ArrayLike, *, smoothing_window: int = 7
) -> FloatArray:
    """Velocity of a sampled position by a Savitzky–Golay derivative (quadratic fit).

    Parameters
    ----------
    time_s : array_like, shape (n,)
        Sample instants, s (about uniform; the median period is used).
    position_m : array_like, shape (n,)
        Position, m.
    smoothing_window : int
        Window length in samples (odd, ≥ 3; shortened for short traces).

    Returns
    -------
    ndarray, shape (n,)
        Velocity, m/s.
    """
    from scipy.signal import savgol_filter

    t = np.asarray(time_s, dtype=np.float64)
    x = np.asarray(position_m, dtype=np.float64)
    n = x.shape[0]
    if n < 3:
        return np.zeros(n) if n < 2 else np.gradient(x, t)
    w = max(3, int(smoothing_window))
    w = min(w if w % 2 else w + 1, n if n % 2 else n - 1)
    dt = float(np.median(np.diff(t)))
    v = savgol_filter(x, window_length=w, polyorder=min(2, w - 1), deriv=1, delta=dt, mode="interp")
    return np.asarray(v, dtype=np.float64)


def _runs(mask: BoolArray) -> list[tuple[int, int]]:
    """``[start, end)`` of the runs of True."""
    m = np.concatenate(([False], mask, [False])).astype(np.int8)
    d = np.diff(m)
    return list(
        zip(
            (int(i) for i in np.flatnonzero(d == 1)),
            (int(i) for i in np.flatnonzero(d == -1)),
            strict=True,
        )
    )


def _first(mask: BoolArray, offset: int) -> int | None:
    idx = np.flatnonzero(mask)
    return None if idx.size == 0 else offset + int(idx[0])


def _quantum(x: FloatArray) -> float:
    """Smallest non-zero step between samples (the sensor resolution for quantised data)."""
    d = np.abs(np.diff(x))
    d = d[d > 1e-12 * max(1e-3, float(np.max(np.abs(x))))]
    return float(np.min(d)) if d.size else 0.0


def _reference_moves(ref: FloatArray) -> list[tuple[int, int]]:
    """Runs ``(k0, k1)`` of sample intervals over which the reference moves one way."""
    d = np.diff(ref)
    scale = max(float(np.max(np.abs(ref))), float(np.ptp(ref)), 1e-300)
    sgn = np.where(np.abs(d) > 1e-12 * scale, np.sign(d), 0.0)
    out: list[tuple[int, int]] = []
    k = 0
    n = sgn.size
    while k < n:
        if sgn[k] == 0.0:
            k += 1
            continue
        j = k
        while j < n and sgn[j] == sgn[k]:
            j += 1
        out.append((k, j))
        k = j
    return out


def limit_cycle(
    y: FloatArray, dt: float, min_correlation: float, quantum: float
) -> LimitCycle | None:
    """The periodic oscillation in the samples ``y`` (every ``dt`` s) of a hold: the
    autocorrelation's first peak after its first zero, at a lag that fits three times in the
    samples and correlates at least ``min_correlation``; None when there is none (or the
    samples span less than half a ``quantum``)."""
    from scipy.signal import correlate

    n = y.size
    if n < 12:
        return None
    y = y - float(np.mean(y))
    span = float(np.ptp(y))
    if span <= 0.0 or span < 0.5 * quantum:
        return None
    ac = np.asarray(correlate(y, y, mode="full", method="fft"), dtype=np.float64)[n - 1 :]
    ac = ac / (n - np.arange(n))
    if ac[0] <= 0.0:
        return None
    ac = ac / ac[0]
    max_lag = n // 3
    neg = np.flatnonzero(ac[: max_lag + 1] < 0.0)
    if neg.size == 0:
        return None
    z = int(neg[0])
    p = z + int(np.argmax(ac[z : max_lag + 1]))
    if p < 2 or ac[p] < min_correlation:
        return None
    lag = float(p)
    if 0 < p < n - 1:
        a, b, c = ac[p - 1], ac[p], ac[p + 1]
        den = a - 2.0 * b + c
        if den < 0.0:
            lag += 0.5 * (a - c) / den
    return LimitCycle(amplitude_m=0.5 * span, period_s=lag * dt, correlation=float(ac[p]))


def _hold(
    x: FloatArray,
    rs: int,
    b: int,
    *,
    band_m: float | None,
    band_min_m: float,
    quantum_m: float,
    min_hold: int,
) -> tuple[int, float, int]:
    """Hold start, band and the start of the final-value samples for the dwell ``[rs, b)``."""
    dwell = b - rs
    if dwell < min_hold:
        return b, band_min_m if band_m is None else band_m, b
    tail_len = max(min_hold, dwell // 4)
    # Shrink the tail while its older half moves much more than its newer half (a decaying
    # transient in a short dwell), so that the band reflects the steady state.
    while tail_len // 2 >= min_hold:
        half = tail_len // 2
        older = float(np.ptp(x[b - tail_len : b - half]))
        newer = float(np.ptp(x[b - half : b]))
        if older <= 2.0 * newer + quantum_m:
            break
        tail_len = half
    tail = x[b - tail_len : b]
    lo, hi = float(np.min(tail)), float(np.max(tail))
    centre = 0.5 * (lo + hi)
    band = max(band_min_m, 1.5 * 0.5 * (hi - lo)) if band_m is None else band_m
    outside = np.flatnonzero(np.abs(x[rs:b] - centre) > band)
    h = rs if outside.size == 0 else rs + int(outside[-1]) + 1
    if b - h < 2:  # the band was given and the tail is outside it: no hold
        return b, band, b - tail_len
    return h, band, h


# --------------------------------------------------------------------------------------------
# Segmentation
# --------------------------------------------------------------------------------------------


def segment_arrays(
    time_s: npt.ArrayLike,
    reference_m: npt.ArrayLike,
    position_m: npt.ArrayLike,
    *,
    sliding_threshold_m_per_s: float = 1e-4,
    slew_tolerance: float = 0.1,
    min_slew_samples: int = 5,
    smoothing_window: int = 7,
    hold_band_m: float | None = None,
    min_hold_samples: int = 10,
    n_position_bins: int = 10,
    limit_cycle_min_correlation: float = 0.5,
) -> Segmentation:
    """Segment a response given as arrays (see the module docstring for the phases).

    Parameters
    ----------
    time_s, reference_m, position_m : array_like, shape (n,)
        Sample instants (s, increasing), reference and measured position (m).
    sliding_threshold_m_per_s : float
        Speed separating presliding from sliding (and rest from ±), m/s.
    slew_tolerance : float
        Relative tolerance of the slew criteria (0.1 = within 10 %).
    min_slew_samples : int
        Shortest slew stretch, samples.
    smoothing_window : int
        Savitzky–Golay window for the velocity, samples.
    hold_band_m : float, optional
        Hold band half-width, m (default: from the end of each dwell, see above).
    min_hold_samples : int
        Shortest dwell that can hold, samples.
    n_position_bins : int
        Number of position bins over the measured travel.
    limit_cycle_min_correlation : float
        Least normalised autocorrelation at the period for a limit cycle.

    Returns
    -------
    Segmentation
    """
    t = np.ascontiguousarray(time_s, dtype=np.float64)
    ref = np.ascontiguousarray(reference_m, dtype=np.float64)
    x = np.ascontiguousarray(position_m, dtype=np.float64)
    n = t.shape[0]
    if t.ndim != 1 or ref.shape != t.shape or x.shape != t.shape:
        raise ValueError(
            f"time_s, reference_m and position_m must be 1-D of one length; got shapes "
            f"{t.shape}, {ref.shape}, {x.shape}"
        )
    if n < 2:
        raise ValueError(f"need at least 2 samples, got {n}")
    if not (0.0 <= slew_tolerance < 1.0):
        raise ValueError(f"slew_tolerance = {slew_tolerance} is invalid: expected [0, 1)")
    if n_position_bins < 1:
        raise ValueError(f"n_position_bins = {n_position_bins} is invalid: expected >= 1")
    thr = float(sliding_threshold_m_per_s)
    dt = float(np.median(np.diff(t)))
    v = estimate_velocity(t, x, smoothing_window=smoothing_window)
    speed = np.abs(v)
    peak_speed = float(np.max(speed))
    quantum = _quantum(x)
    band_min = max(2.0 * quantum, 1e-9)
    min_slew = max(1, int(min_slew_samples))
    min_hold = max(2, int(min_hold_samples))

    phase = np.full(n, _HOLD, dtype=np.int64)
    runs = _reference_moves(ref)
    # Reference kinematics for ramp moves.
    v_ref = np.gradient(ref, t)
    a_ref = np.gradient(v_ref, t)
    ramp_samples = np.zeros(n, dtype=bool)
    for k0, k1 in runs:
        if k1 - k0 > 2:
            ramp_samples[k0 + 1 : k1] = True
    a_floor = 64.0 * np.finfo(np.float64).eps * max(float(np.max(np.abs(ref))), 1e-300) / dt**2
    a_typ = float(np.percentile(np.abs(a_ref[ramp_samples]), 95)) if ramp_samples.any() else 0.0
    a_tol = max(slew_tolerance * a_typ, a_floor)

    moves: list[Move] = []
    for i, (k0, k1) in enumerate(runs):
        a = k0 + 1
        rs = k1
        b = runs[i + 1][0] + 1 if i + 1 < len(runs) else n
        start_m = float(ref[k0])
        target = float(ref[k1])
        s = 1 if target > start_m else -1
        kind: Literal["step", "ramp"] = "step" if k1 - k0 <= 2 else "ramp"
        h, band, final_start = _hold(
            x, rs, b, band_m=hold_band_m, band_min_m=band_min, quantum_m=quantum, min_hold=min_hold
        )
        prog = s * (x - target)  # > 0 beyond the target
        u = s * v
        if kind == "step":
            c = _first(prog[a:b] >= 0.0, a)
            lim = c if c is not None else h
            acc_end = slew_end = a
            if lim > a:
                seg = u[a:lim]
                cand = [
                    r
                    for r in _runs(seg >= (1.0 - slew_tolerance) * peak_speed)
                    if r[1] - r[0] >= min_slew
                ]
                if cand and peak_speed > thr:
                    r0, r1 = max(cand, key=lambda r: r[1] - r[0])
                    acc_end, slew_end = a + r0, a + r1
                else:
                    acc_end = slew_end = a + int(np.argmax(seg)) + 1
            post = slew_end
        else:
            _label_ramp(phase, a, rs, a_ref, s, a_tol, min_slew)
            c = _first(prog[rs:b] >= 0.0, rs)
            acc_end = slew_end = rs
            post = rs
        if c is not None:
            brake_end = c
            back = _first(prog[c + 1 : b] <= 0.0, c + 1)
            e = back if back is not None else b
            over_end = e if float(np.max(prog[c:e])) > band else c
        else:
            stopped = _first(speed[post:b] < thr, post)
            brake_end = stopped if stopped is not None else b
            over_end = brake_end
        if kind == "step":
            bounds = np.array([a, acc_end, slew_end, brake_end, over_end, h, b])
        else:
            bounds = np.array([rs, rs, rs, brake_end, over_end, h, b])
        bounds[1:6] = np.minimum(bounds[1:6], h)
        bounds = np.maximum.accumulate(bounds)
        first_phase = _ACC if kind == "step" else _BRAKE
        for ph in range(first_phase, _HOLD + 1):
            phase[bounds[ph] : bounds[ph + 1]] = ph
        final = float(np.median(x[final_start:b])) if final_start < b else math.nan
        cycle = None
        if h < b:
            cycle = limit_cycle(x[h:b], dt, limit_cycle_min_correlation, quantum)
        moves.append(
            Move(
                index=i,
                kind=kind,
                start=a,
                reference_stop=rs,
                stop=b,
                start_m=start_m,
                target_m=target,
                direction=s,
                hold_start=h,
                hold_band_m=band,
                final_start=final_start,
                final_position_m=final,
                final_error_m=target - final,
                settling_time_s=float(t[h] - t[a]) if h < b else math.nan,
                overshoot_m=max(0.0, float(np.max(prog[a:b]))),
                peak_speed_m_per_s=max(0.0, float(np.max(u[a:b]))),
                limit_cycle=cycle,
            )
        )

    direction = np.where(v > thr, 1, np.where(v < -thr, -1, 0)).astype(np.int64)
    lo, hi = float(np.min(x)), float(np.max(x))
    edges = np.linspace(lo, hi if hi > lo else lo + 1e-12, n_position_bins + 1)
    bins = np.clip(np.digitize(x, edges) - 1, 0, n_position_bins - 1).astype(np.int64)
    return Segmentation(
        time_s=t,
        reference_m=ref,
        position_m=x,
        velocity_m_per_s=v,
        phase=phase,
        sliding=speed > thr,
        direction=direction,
        position_bin=bins,
        position_bin_edges_m=edges,
        moves=tuple(moves),
        peak_speed_m_per_s=peak_speed,
        sliding_threshold_m_per_s=thr,
    )


def _label_ramp(
    phase: IntArray, a: int, rs: int, a_ref: FloatArray, s: int, a_tol: float, min_slew: int
) -> None:
    """Label ``[a, rs)`` by the reference's kinematics (speeding up / constant / slowing)."""
    acc = s * a_ref[a:rs]
    lab = np.where(np.abs(acc) <= a_tol, _SLEW, np.where(acc > 0.0, _ACC, _BRAKE))
    # Constant-velocity stretches shorter than min_slew take the label of their neighbour.
    for r0, r1 in _runs(lab == _SLEW):
        if r1 - r0 < min_slew:
            if r0 > 0:
                lab[r0:r1] = lab[r0 - 1]
            elif r1 < lab.size:
                lab[r0:r1] = lab[r1]
            else:
                lab[r0:r1] = _ACC
    phase[a:rs] = lab


def segment(
    experiment: Experiment,
    *,
    position_m: npt.ArrayLike | None = None,
    sliding_threshold_m_per_s: float = 1e-4,
    slew_tolerance: float = 0.1,
    min_slew_samples: int = 5,
    smoothing_window: int = 7,
    hold_band_m: float | None = None,
    min_hold_samples: int = 10,
    n_position_bins: int = 10,
    limit_cycle_min_correlation: float = 0.5,
) -> Segmentation:
    """Segment a measured experiment (options as in :func:`segment_arrays`).

    Parameters
    ----------
    experiment : Experiment
        The experiment (its time, reference and measured ``position_m``).
    position_m : array_like, optional
        Another position to segment on the experiment's time base (e.g. the
        interferometer, or a simulation), m.
    """
    return segment_arrays(
        experiment.time_s,
        experiment.reference_m,
        experiment.position_m if position_m is None else position_m,
        sliding_threshold_m_per_s=sliding_threshold_m_per_s,
        slew_tolerance=slew_tolerance,
        min_slew_samples=min_slew_samples,
        smoothing_window=smoothing_window,
        hold_band_m=hold_band_m,
        min_hold_samples=min_hold_samples,
        n_position_bins=n_position_bins,
        limit_cycle_min_correlation=limit_cycle_min_correlation,
    )


def segment_summary(seg: Segmentation) -> dict[str, object]:
    """JSON-ready summary: sample counts per phase and per-move figures."""
    counts = {k: int(np.count_nonzero(m)) for k, m in seg.masks().items()}
    moves: list[Mapping[str, object]] = []
    for m in seg.moves:
        moves.append(
            {
                "index": m.index,
                "kind": m.kind,
                "start_s": float(seg.time_s[m.start]),
                "step_m": m.step_m,
                "target_m": m.target_m,
                "final_error_m": m.final_error_m,
                "settling_time_s": m.settling_time_s,
                "overshoot_m": m.overshoot_m,
                "peak_speed_m_per_s": m.peak_speed_m_per_s,
                "hold_band_m": m.hold_band_m,
                "limit_cycle": None
                if m.limit_cycle is None
                else {
                    "amplitude_m": m.limit_cycle.amplitude_m,
                    "period_s": m.limit_cycle.period_s,
                    "correlation": m.limit_cycle.correlation,
                },
            }
        )
    return {"samples_per_phase": counts, "moves": moves}
