"""Positioning test cycles: reference trajectories with labelled measurement instants.

A :class:`Cycle` is what a positioning test commands and when it reads the position: the
reference position at every control sample (one value per sample, metres, the input of
:func:`nanostage.simulate`) and the sample indices at which the position is measured, each
labelled with its target, approach direction and run, i.e. the labels the ISO 230-2
evaluator (:mod:`nanostage.iso230_2`) groups by. A simulated or measured campaign is then
evaluated in one line::

    cycle = step_cycle(step_m=100e-6, repeats=5, dwell_s=0.5, return_s=0.5,
                       sample_period_s=1e-3)
    trace = nanostage.simulate(nanostage.presets.seed(100e-6), cycle.reference_m)
    result = cycle.evaluate(cycle.at_measurements(trace.position_m))

Two cycles are provided:

* :func:`standard_test_cycle`: the ISO 230-2 standard test cycle (linear axis): random
  non-uniformly spaced targets over the measurement travel, each approached ``runs`` times
  (5 in the standard) in each direction, with an overrun past both ends of the travel so that
  every approach to a target comes from the same side (docs/DOMAIN.md section 1.4).
* :func:`step_cycle`: the seed paper's repeated unidirectional steps from one start position
  (docs/SEED.md, "The experiments"): one ISO target approached ``repeats`` times from the
  same side. This is *not* the standard cycle (ISO 230-2 Annex B's step cycle is also
  different); its ISO numbers are the ISO formulas applied to a non-standard cycle.

How the reference travels between two points is a :class:`MoveProfile`: a jump (``"step"``,
what the paper's FPGA does) or a trapezoidal velocity profile sampled at the control period.

Sample conventions (the same as :mod:`nanostage.simulate`): ``reference_m[n]`` is the
reference at ``t_n = n · T``. Every move ends with its *arrival sample*, the first sample at
which the reference equals the new point (for a step this is the sample of the jump). At a
measured stop the reference then stays constant for the dwell, and the position is read at
``measure_index = arrival + round(dwell_s / T)``, the last sample before the reference
leaves; the plant has then been commanded to the target for at least ``dwell_s``. The next
move starts at the following sample. Every cycle starts with ``reference_m[0] == start_m``
(the axis is assumed to rest there).

Units are SI and appear in the names. Invalid arguments raise :class:`nanostage.ConfigError`
(a :class:`ValueError`) naming the argument, the value and the valid range, before anything
is built; arguments of the wrong type raise :class:`TypeError`.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Final, Literal

import numpy as np
import numpy.typing as npt

from . import iso230_2
from ._core import ConfigError
from .checks import int_arg
from .simulate import MAX_SAMPLES

__all__ = [
    "MAX_DWELL_S",
    "MAX_N_TARGETS",
    "MAX_TRAVEL_M",
    "MIN_TARGETS",
    "TARGETS_PER_METRE",
    "Cycle",
    "MoveProfile",
    "min_targets",
    "standard_test_cycle",
    "step_cycle",
]

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

#: ISO 230-2: at least this many target positions per metre of travel (and at least 5).
TARGETS_PER_METRE: Final[int] = 5
#: ISO 230-2: at least this many target positions in all.
MIN_TARGETS: Final[int] = 5
#: Longest measurement travel of the standard cycle [m]; longer axes follow other ISO rules.
MAX_TRAVEL_M: Final[float] = 2.0
#: Most target positions a standard cycle may have.
MAX_N_TARGETS: Final[int] = 10_000
#: Longest dwell or hold time [s].
MAX_DWELL_S: Final[float] = 60.0
#: Largest position magnitude [m] (start, targets) a cycle accepts.
MAX_POSITION_M: Final[float] = 10.0
#: Longest control period [s].
MAX_SAMPLE_PERIOD_S: Final[float] = 1.0
#: Relative tolerance when checking that the target intervals are pairwise different.
_INTERVAL_TOLERANCE: Final[float] = 1e-9
#: Redraws of the random offsets before giving up on pairwise different intervals.
_MAX_DRAWS: Final[int] = 100


# --------------------------------------------------------------------------------------------
# Argument checks
# --------------------------------------------------------------------------------------------


def _real(name: str, value: object) -> float:
    """``value`` as a float; TypeError naming ``name`` if it is not a real number."""
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise TypeError(f"{name} must be a real number, got {value!r}")
    return float(value)


def _integer(name: str, value: object) -> int:
    """``value`` as an int; TypeError naming ``name`` if it is not an integer."""
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        raise TypeError(f"{name} must be an integer, got {value!r}")
    return int(value)


def _outside(name: str, value: object, valid: str) -> ConfigError:
    return ConfigError(f"{name} = {value!r} is outside {valid}")


def _in_range(
    name: str,
    value: object,
    lo: float,
    hi: float,
    unit: str,
    *,
    lo_open: bool = False,
    hi_open: bool = False,
    lo_text: str | None = None,
) -> float:
    """Check ``lo <(=) value <(=) hi`` (finite); return the value as a float."""
    v = _real(name, value)
    ok = math.isfinite(v)
    ok = ok and (v > lo if lo_open else v >= lo)
    ok = ok and (v < hi if hi_open else v <= hi)
    if not ok:
        lo_s = lo_text if lo_text is not None else f"{lo:g}"
        valid = f"{'(' if lo_open else '['}{lo_s}, {hi:g}{')' if hi_open else ']'} {unit}".rstrip()
        raise _outside(name, value, valid)
    return v


def _samples(value_s: float, sample_period_s: float) -> int:
    """Number of control samples ``round(value_s / T)``, at least 1 (already range-checked)."""
    return max(1, round(value_s / sample_period_s))


def _check_total(n_samples: int, what: str) -> None:
    if n_samples > MAX_SAMPLES:
        raise ConfigError(
            f"{what} would have {n_samples} samples, more than 2**24 = {MAX_SAMPLES}; "
            "use fewer runs or targets, shorter dwells, faster moves or a longer sample period"
        )


# --------------------------------------------------------------------------------------------
# Move profile
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True, kw_only=True)
class MoveProfile:
    """How the reference travels from one point to the next.

    Attributes
    ----------
    kind : {"step", "trapezoid"}
        ``"step"``: the reference jumps to the new point in one sample (as the seed paper's
        FPGA does). ``"trapezoid"``: a trapezoidal velocity profile (constant acceleration,
        cruise at ``max_velocity_m_per_s``, constant deceleration; triangular when the move
        is too short to reach the cruise velocity), starting and ending at rest, sampled at
        the control period. Sampling a profile with ``|v| <= v_max`` and ``|a| <= a_max``
        keeps the first difference of the reference within ``v_max · T`` and the second
        within ``a_max · T²``, including the joins with the holds before and after.
    max_velocity_m_per_s : float or None
        Cruise velocity of a trapezoid [m/s], finite and > 0; ``None`` for a step.
    acceleration_m_per_s2 : float or None
        Acceleration and deceleration of a trapezoid [m/s²], finite and > 0; ``None`` for a
        step.

    Raises
    ------
    ConfigError
        On an unknown kind, a missing or out-of-range trapezoid parameter, or a trapezoid
        parameter given for a step.
    """

    kind: Literal["step", "trapezoid"] = "step"
    max_velocity_m_per_s: float | None = None
    acceleration_m_per_s2: float | None = None

    def __post_init__(self) -> None:
        if self.kind == "step":
            for name in ("max_velocity_m_per_s", "acceleration_m_per_s2"):
                value = getattr(self, name)
                if value is not None:
                    raise ConfigError(
                        f"{name} = {value!r} is invalid for kind = 'step': expected None "
                        "(a step has no velocity or acceleration limit)"
                    )
        elif self.kind == "trapezoid":
            for name, unit in (
                ("max_velocity_m_per_s", "m/s"),
                ("acceleration_m_per_s2", "m/s²"),
            ):
                value = getattr(self, name)
                if value is None:
                    raise ConfigError(
                        f"{name} = None is invalid for kind = 'trapezoid': expected a finite "
                        f"value > 0 {unit}"
                    )
                _in_range(name, value, 0.0, math.inf, unit, lo_open=True, hi_open=True)
        else:
            raise ConfigError(f"kind = {self.kind!r} is invalid: expected 'step' or 'trapezoid'")

    def move_samples(self, distance_m: float, sample_period_s: float) -> int:
        """Samples a move over ``distance_m`` takes, up to and including the arrival sample.

        Parameters
        ----------
        distance_m : float
            Length of the move [m] (sign ignored).
        sample_period_s : float
            Control period [s] (> 0).

        Returns
        -------
        int
            1 for a step or a zero-length move, ``ceil(t_move / T)`` for a trapezoid.
        """
        d = abs(float(distance_m))
        if self.kind == "step" or d == 0.0:
            return 1
        t_move = self._timing(d)[2]
        return max(1, math.ceil(t_move / sample_period_s))

    def _timing(self, distance_m: float) -> tuple[float, float, float, float]:
        """``(t_acc, t_const, t_move, v_peak)`` of a trapezoid over ``distance_m`` > 0."""
        v = float(self.max_velocity_m_per_s or 0.0)
        a = float(self.acceleration_m_per_s2 or 0.0)
        d = distance_m
        if d >= v * v / a:
            t_acc = v / a
            t_const = (d - v * v / a) / v
            v_peak = v
        else:
            t_acc = math.sqrt(d / a)
            t_const = 0.0
            v_peak = a * t_acc
        return t_acc, t_const, 2.0 * t_acc + t_const, v_peak

    def samples(self, from_m: float, to_m: float, sample_period_s: float) -> FloatArray:
        """The reference samples of one move, after the sample at ``from_m``.

        Parameters
        ----------
        from_m, to_m : float
            Start and end of the move [m]; the reference is at rest at ``from_m`` before.
        sample_period_s : float
            Control period [s] (> 0).

        Returns
        -------
        ndarray, shape (move_samples,)
            Reference [m] at ``T, 2T, ...`` after the move starts; the last entry is exactly
            ``to_m`` (the arrival sample). Monotone from ``from_m`` to ``to_m``. (For a
            trapezoid, floating-point rounding can make a sample just before the last one
            equal ``to_m`` already.)
        """
        n = self.move_samples(to_m - from_m, sample_period_s)
        out = np.full(n, float(to_m), dtype=np.float64)
        if n == 1:
            return out
        d = abs(to_m - from_m)
        sign = 1.0 if to_m > from_m else -1.0
        a = float(self.acceleration_m_per_s2 or 0.0)
        t_acc, t_const, t_move, v_peak = self._timing(d)
        t = np.arange(1, n, dtype=np.float64) * sample_period_s
        s = np.where(
            t < t_acc,
            0.5 * a * t * t,
            np.where(
                t < t_acc + t_const,
                0.5 * a * t_acc * t_acc + v_peak * (t - t_acc),
                d - 0.5 * a * np.square(np.maximum(t_move - t, 0.0)),
            ),
        )
        pos = from_m + sign * s
        # Rounding must not make the move overshoot or step back by an ulp at a phase join.
        if sign > 0:
            pos = np.minimum(np.maximum.accumulate(np.maximum(pos, from_m)), to_m)
        else:
            pos = np.maximum(np.minimum.accumulate(np.minimum(pos, from_m)), to_m)
        out[:-1] = pos
        return out


_STEP: Final[MoveProfile] = MoveProfile()


# --------------------------------------------------------------------------------------------
# Cycle
# --------------------------------------------------------------------------------------------


def _frozen(a: npt.ArrayLike, dtype: type[np.float64] | type[np.int64]) -> npt.NDArray[np.generic]:
    out = np.array(a, dtype=dtype, copy=True)
    out.flags.writeable = False
    return out


@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class Cycle:
    """A positioning test: the reference trajectory and the labelled measurement instants.

    All arrays are read-only copies. Compares by identity (``eq=False``).

    Attributes
    ----------
    reference_m : ndarray of float64, shape (n_samples,)
        Reference position at each control sample ``t_n = n · sample_period_s`` [m].
    sample_period_s : float
        Control period ``T`` [s].
    measure_index : ndarray of int64, shape (n_measurements,)
        Sample indices at which the position is read, strictly increasing.
    target_m : ndarray of float64, shape (n_measurements,)
        Target position of each measurement [m] (equal to ``reference_m[measure_index]``).
    direction : ndarray of int64, shape (n_measurements,)
        Approach direction of each measurement: ``+1`` (↑, from below) or ``-1`` (↓).
    run : ndarray of int64, shape (n_measurements,)
        1-based run number of each measurement.

    Raises
    ------
    ConfigError
        If the arrays are inconsistent (lengths, indices out of range or not increasing,
        labels not matching the reference, unknown directions, runs < 1).
    """

    reference_m: FloatArray
    sample_period_s: float
    measure_index: IntArray
    target_m: FloatArray
    direction: IntArray
    run: IntArray

    def __post_init__(self) -> None:
        t = _in_range(
            "sample_period_s",
            self.sample_period_s,
            0.0,
            MAX_SAMPLE_PERIOD_S,
            "s",
            lo_open=True,
        )
        object.__setattr__(self, "sample_period_s", t)
        ref = _frozen(self.reference_m, np.float64)
        if ref.ndim != 1 or not 1 <= ref.shape[0] <= MAX_SAMPLES:
            raise ConfigError(
                f"reference_m = array of shape {ref.shape} is invalid: expected a 1-D array "
                f"of 1 to {MAX_SAMPLES} samples"
            )
        if not np.all(np.isfinite(ref)):
            raise ConfigError("reference_m = array with non-finite values is invalid")
        idx = _frozen(self.measure_index, np.int64)
        n = idx.shape[0] if idx.ndim == 1 else -1
        fields = {
            "measure_index": idx,
            "target_m": _frozen(self.target_m, np.float64),
            "direction": _frozen(self.direction, np.int64),
            "run": _frozen(self.run, np.int64),
        }
        for name, arr in fields.items():
            if arr.ndim != 1 or arr.shape[0] != n:
                raise ConfigError(
                    f"{name} = array of shape {arr.shape} is invalid: expected a 1-D array "
                    f"as long as measure_index ({n})"
                )
        if n > 0 and (idx[0] < 0 or idx[-1] >= ref.shape[0] or np.any(np.diff(idx) <= 0)):
            raise ConfigError(
                "measure_index is invalid: expected strictly increasing indices in "
                f"[0, {ref.shape[0] - 1}]"
            )
        if not np.array_equal(fields["target_m"], ref[idx]):
            raise ConfigError("target_m is invalid: expected reference_m[measure_index]")
        if not np.all(np.isin(fields["direction"], (-1, 1))):
            raise ConfigError("direction is invalid: expected +1 or -1 per measurement")
        if n > 0 and np.min(fields["run"]) < 1:
            raise ConfigError("run is invalid: expected run numbers >= 1")
        object.__setattr__(self, "reference_m", ref)
        for name, arr in fields.items():
            object.__setattr__(self, name, arr)

    @property
    def n_samples(self) -> int:
        """Number of control samples."""
        return int(self.reference_m.shape[0])

    @property
    def n_measurements(self) -> int:
        """Number of measurements (approaches)."""
        return int(self.measure_index.shape[0])

    @property
    def duration_s(self) -> float:
        """Length of the reference, ``n_samples · T`` [s]."""
        return self.n_samples * self.sample_period_s

    @property
    def targets_m(self) -> FloatArray:
        """The distinct target positions, ascending [m]."""
        out: FloatArray = np.unique(self.target_m)
        return out

    @property
    def time_s(self) -> FloatArray:
        """Sample instants ``n · T`` [s], shape ``(n_samples,)``."""
        out: FloatArray = np.arange(self.n_samples, dtype=np.float64) * self.sample_period_s
        return out

    @property
    def measure_time_s(self) -> FloatArray:
        """Measurement instants ``measure_index · T`` [s], shape ``(n_measurements,)``."""
        out: FloatArray = self.measure_index.astype(np.float64) * self.sample_period_s
        return out

    def at_measurements(self, signal: npt.ArrayLike) -> FloatArray:
        """Pick a per-sample signal at the measurement instants.

        Parameters
        ----------
        signal : array_like, shape (n_samples,)
            One value per control sample of this cycle, e.g. ``Trace.position_m`` (the true
            table position, as an interferometer reads it) or ``Trace.encoder_position_m``.

        Returns
        -------
        ndarray of float64, shape (n_measurements,)
            ``signal[measure_index]``.

        Raises
        ------
        ConfigError
            If ``signal`` is not a 1-D array of ``n_samples`` values.
        """
        arr = np.asarray(signal, dtype=np.float64)
        if arr.shape != (self.n_samples,):
            raise ConfigError(
                f"signal = array of shape {arr.shape} is invalid: expected shape "
                f"({self.n_samples},), one value per sample of the cycle"
            )
        out: FloatArray = arr[self.measure_index]
        return out

    def _actual(self, actual_m: npt.ArrayLike) -> FloatArray:
        try:
            actual = np.asarray(actual_m, dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise iso230_2.Iso230InputError(
                f"not a numeric array: {exc}", column="actual_m"
            ) from None
        if actual.shape != (self.n_measurements,):
            raise iso230_2.Iso230InputError(
                f"expected shape ({self.n_measurements},), one position per measurement, "
                f"got {actual.shape}",
                column="actual_m",
            )
        return actual

    def records(self, actual_m: npt.ArrayLike) -> iso230_2.MeasurementRecords:
        """The measurements as ISO 230-2 records (the evaluator's input).

        Parameters
        ----------
        actual_m : array_like, shape (n_measurements,)
            Position read at each measurement instant [m], e.g.
            ``cycle.at_measurements(trace.position_m)``.

        Returns
        -------
        iso230_2.MeasurementRecords
            One record per measurement: ``target_m``, ``direction`` (``'+'``/``'-'``),
            ``run`` and ``actual_m``. Call ``.evaluate()`` on it.

        Raises
        ------
        iso230_2.Iso230InputError
            If ``actual_m`` does not have one value per measurement.
        """
        actual = self._actual(actual_m)
        d = np.where(self.direction > 0, "+", "-").astype(np.str_)
        a = np.array(actual, dtype=np.float64, copy=True)
        for arr in (d, a):
            arr.flags.writeable = False
        return iso230_2.MeasurementRecords(
            target_m=self.target_m, direction=d, run=self.run, actual_m=a
        )

    def evaluate(
        self, actual_m: npt.ArrayLike, *, coverage_factor: float = 2.0
    ) -> iso230_2.Iso230Result:
        """Evaluate the measured positions with ISO 230-2 (``records(actual_m).evaluate()``).

        Parameters
        ----------
        actual_m : array_like, shape (n_measurements,)
            Position read at each measurement instant [m].
        coverage_factor : float, default 2.0
            Coverage factor ``k`` [-].

        Returns
        -------
        iso230_2.Iso230Result
            Unidirectional when the cycle has only ``+1`` approaches.

        Raises
        ------
        iso230_2.Iso230InputError
            On a wrong ``actual_m`` or data the evaluator rejects (e.g. a cycle with only
            ``-1`` approaches: the evaluator takes unidirectional data as ↑ only).
        """
        return self.records(actual_m).evaluate(coverage_factor=coverage_factor)

    def to_csv_rows(self, actual_m: npt.ArrayLike) -> list[tuple[str, str, str, str]]:
        """Rows of a measurement CSV (the format :func:`iso230_2.read_measurement_csv` reads).

        Parameters
        ----------
        actual_m : array_like, shape (n_measurements,)
            Position read at each measurement instant [m].

        Returns
        -------
        list of tuple of str
            The header ``("target_m", "direction", "run", "actual_m")`` followed by one row
            per measurement; floats are written with ``repr`` so they read back bit for bit.
            Pass the rows to ``csv.writer(...).writerows``.
        """
        actual = self._actual(actual_m)
        header = iso230_2.REQUIRED_COLUMNS
        rows: list[tuple[str, str, str, str]] = [(header[0], header[1], header[2], header[3])]
        for t, d, r, a in zip(self.target_m, self.direction, self.run, actual, strict=True):
            rows.append((repr(float(t)), "+" if d > 0 else "-", str(int(r)), repr(float(a))))
        return rows

    def write_csv(self, path: str | Path, actual_m: npt.ArrayLike) -> Path:
        """Write the measurements as a CSV file (see :func:`iso230_2.write_measurement_csv`).

        Parameters
        ----------
        path : str or Path
            Output file; its parent directory must exist.
        actual_m : array_like, shape (n_measurements,)
            Position read at each measurement instant [m].

        Returns
        -------
        Path
            ``path``.
        """
        actual = self._actual(actual_m)
        d = ["+" if v > 0 else "-" for v in self.direction]
        return iso230_2.write_measurement_csv(path, self.target_m, d, self.run, actual)


# --------------------------------------------------------------------------------------------
# Building
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class _Stop:
    """Move to ``position_m`` and stay there ``samples`` samples (arrival sample included).

    ``direction`` is 0 for a stop without measurement; otherwise the position is measured
    at the last of the ``samples``.
    """

    position_m: float
    samples: int
    direction: int = 0


def _count(start_m: float, stops: Sequence[_Stop], move: MoveProfile, period_s: float) -> int:
    n = 0
    here = start_m
    for stop in stops:
        n += move.move_samples(stop.position_m - here, period_s) + stop.samples - 1
        here = stop.position_m
    return n


def _build(
    start_m: float, stops: Sequence[_Stop], move: MoveProfile, period_s: float
) -> tuple[FloatArray, IntArray, FloatArray, IntArray]:
    """Reference samples after a sample at ``start_m``; local measurement indices and labels."""
    parts: list[FloatArray] = []
    index: list[int] = []
    target: list[float] = []
    direction: list[int] = []
    n = 0
    here = start_m
    for stop in stops:
        samples = move.samples(here, stop.position_m, period_s)
        hold = np.full(stop.samples - 1, stop.position_m, dtype=np.float64)
        parts += [samples, hold]
        n += samples.shape[0] + hold.shape[0]
        if stop.direction != 0:
            index.append(n - 1)
            target.append(stop.position_m)
            direction.append(stop.direction)
        here = stop.position_m
    return (
        np.concatenate(parts) if parts else np.empty(0, dtype=np.float64),
        np.array(index, dtype=np.int64),
        np.array(target, dtype=np.float64),
        np.array(direction, dtype=np.int64),
    )


def _assemble(
    *,
    start_m: float,
    initial_samples: int,
    prefix: Sequence[_Stop],
    block: Sequence[_Stop],
    runs: int,
    move: MoveProfile,
    sample_period_s: float,
    what: str,
) -> Cycle:
    """``initial_samples`` at ``start_m``, the prefix stops, then ``runs`` copies of the block.

    The block must end where it starts (the last stop of the prefix).
    """
    block_start = prefix[-1].position_m if prefix else start_m
    if block[-1].position_m != block_start:  # pragma: no cover - internal invariant
        raise AssertionError("a repeated block must end where it starts")
    n_prefix = _count(start_m, prefix, move, sample_period_s)
    n_block = _count(block_start, block, move, sample_period_s)
    _check_total(initial_samples + n_prefix + runs * n_block, what)

    pre_ref, _, _, _ = _build(start_m, prefix, move, sample_period_s)
    blk_ref, blk_idx, blk_target, blk_dir = _build(block_start, block, move, sample_period_s)
    offset = initial_samples + pre_ref.shape[0]
    reference = np.concatenate(
        [np.full(initial_samples, start_m, dtype=np.float64), pre_ref, np.tile(blk_ref, runs)]
    )
    run_no = np.repeat(np.arange(1, runs + 1, dtype=np.int64), blk_idx.shape[0])
    measure_index = offset + (run_no - 1) * blk_ref.shape[0] + np.tile(blk_idx, runs)
    return Cycle(
        reference_m=reference,
        sample_period_s=sample_period_s,
        measure_index=measure_index,
        target_m=np.tile(blk_target, runs),
        direction=np.tile(blk_dir, runs),
        run=run_no,
    )


def _check_move(move: object) -> MoveProfile:
    if not isinstance(move, MoveProfile):
        raise TypeError(f"move must be a MoveProfile, got {move!r}")
    return move


def _check_common(
    sample_period_s: float, dwell_s: float, start_m: float
) -> tuple[float, float, float]:
    t = _in_range("sample_period_s", sample_period_s, 0.0, MAX_SAMPLE_PERIOD_S, "s", lo_open=True)
    dwell = _in_range("dwell_s", dwell_s, t, MAX_DWELL_S, "s", lo_text=f"sample_period_s = {t:g}")
    start = _in_range("start_m", start_m, -MAX_POSITION_M, MAX_POSITION_M, "m")
    return t, dwell, start


def min_targets(travel_m: float) -> int:
    """ISO 230-2's least number of targets for a travel: ``max(5, ceil(5 per metre))``.

    Parameters
    ----------
    travel_m : float
        Measurement travel [m] (> 0).

    Returns
    -------
    int
        The least number of target positions.
    """
    per_metre = math.ceil(TARGETS_PER_METRE * float(travel_m) * (1.0 - 1e-12))
    return max(MIN_TARGETS, per_metre)


def _draw_targets(
    rng: np.random.Generator, start_m: float, travel_m: float, n: int, fraction: float
) -> FloatArray:
    """``P_i = start + (i - 1)·p + r_i`` with pairwise different intervals, within the travel."""
    p = travel_m / (n - 1)
    nominal = start_m + np.arange(n, dtype=np.float64) * p
    lo = np.full(n, -fraction * p)
    hi = np.full(n, fraction * p)
    lo[0] = 0.0  # the first target stays at or above the start of the travel
    hi[-1] = 0.0  # the last one at or below its end
    for _ in range(_MAX_DRAWS):
        targets = nominal + rng.uniform(lo, hi)
        targets[0] = max(targets[0], start_m)
        targets[-1] = min(targets[-1], start_m + travel_m)
        gaps = np.diff(np.sort(np.diff(targets)))
        if gaps.shape[0] == 0 or float(np.min(gaps)) > _INTERVAL_TOLERANCE * p:
            return targets
    raise RuntimeError(  # pragma: no cover - probability ~ 0
        f"could not draw {n} targets with pairwise different intervals in {_MAX_DRAWS} draws"
    )


def standard_test_cycle(
    *,
    travel_m: float,
    start_m: float = 0.0,
    n_targets: int | None = None,
    runs: int = 5,
    overrun_m: float,
    dwell_s: float,
    move: MoveProfile,
    sample_period_s: float,
    seed: int,
    bidirectional: bool = True,
    overrun_dwell_s: float | None = None,
    offset_fraction: float = 0.25,
) -> Cycle:
    """The ISO 230-2 standard test cycle of a linear axis (docs/DOMAIN.md section 1.4).

    **Targets.** ``m = n_targets`` positions ``P_i = start_m + (i - 1)·p + r_i`` over the
    measurement travel ``[start_m, start_m + travel_m]``, with the uniform interval
    ``p = travel_m / (m - 1)`` and a different random offset ``r_i`` per target, drawn
    uniformly from ``±offset_fraction · p`` (only inward at the two ends, so that every
    target lies within the travel), so that the intervals are not equal and periodic errors
    (screw lead, scale pitch) are not sampled at a fixed phase. The draws are redone (from
    the same generator) until all intervals differ pairwise. ISO 230-2 asks for at least 5
    targets per metre of travel and at least 5 in all; the allowed range of ``r`` is not
    known here (DOMAIN.md marks it [U]); ``offset_fraction < 0.5`` keeps the targets
    strictly increasing, at least ``(1 - 2·offset_fraction)·p`` apart.

    **Cycle.** The reference starts at ``start_m`` (held for one dwell), moves to the lower
    reversal point ``P_1 - overrun_m`` and holds. Each run then approaches
    ``P_1, ..., P_m`` upwards, stopping at each for ``dwell_s`` and measuring at the end of
    the dwell (↑, ``direction = +1``), runs past the last target to ``P_m + overrun_m``,
    holds, approaches ``P_m, ..., P_1`` downwards the same way (↓, ``-1``), runs past the
    first target to ``P_1 - overrun_m`` and holds. So every target is approached ``runs``
    times (5 in the standard) from below and from above, each time from the same side, and
    every reversal happens outside the measurement travel (the axis needs room for
    ``[P_1 - overrun_m, P_m + overrun_m]``). With ``bidirectional=False`` the way down has
    no stops (a unidirectional ↑ test).

    Parameters
    ----------
    travel_m : float
        Measurement travel [m], in ``[1e-6, 2]`` (ISO 230-2 treats axes above 2 m
        differently).
    start_m : float, default 0.0
        Lower end of the measurement travel, where the axis rests at ``t = 0`` [m], in
        ``[-10, 10]``.
    n_targets : int, optional
        Number of target positions, in ``[max(5, ceil(5 · travel_m / 1 m)), 10000]``; the
        least allowed number by default.
    runs : int, default 5
        Approaches per target and direction, in ``[2, 10000]`` (the standard uses 5).
    overrun_m : float
        Distance run past the first and last target before reversing [m], in
        ``(0, travel_m]``; long enough for normal reversal behaviour (backlash take-up).
    dwell_s : float
        Time the reference rests at a target before the measurement [s], in
        ``[sample_period_s, 60]``; rounded to ``round(dwell_s / T)`` samples.
    move : MoveProfile
        How the reference travels between points.
    sample_period_s : float
        Control period ``T`` [s], in ``(0, 1]``.
    seed : int
        Seed of the :class:`numpy.random.Generator` that draws the offsets, ``>= 0``; the
        same seed gives the same cycle.
    bidirectional : bool, default True
        Measure on the way down too.
    overrun_dwell_s : float, optional
        Hold at the reversal points [s], in ``[sample_period_s, 60]``; ``dwell_s`` by
        default.
    offset_fraction : float, default 0.25
        Largest random offset as a fraction of ``p``, in ``(0, 0.5)``.

    Returns
    -------
    Cycle
        Measurements ordered in time; runs numbered from 1.

    Raises
    ------
    ConfigError
        An argument outside its range (the message names it, its value and the range), or a
        cycle of more than 2**24 samples.
    TypeError
        An argument of the wrong type.

    Examples
    --------
    >>> c = standard_test_cycle(travel_m=0.02, overrun_m=1e-3, dwell_s=0.2,
    ...                         move=MoveProfile(), sample_period_s=1e-3, seed=1)
    >>> c.targets_m.shape, c.n_measurements
    ((5,), 50)
    """
    t, dwell, start = _check_common(sample_period_s, dwell_s, start_m)
    travel = _in_range("travel_m", travel_m, 1e-6, MAX_TRAVEL_M, "m")
    if start + travel > MAX_POSITION_M:
        raise _outside(
            "travel_m", travel_m, f"[1e-06, {MAX_POSITION_M - start:g}] m for start_m = {start:g}"
        )
    n_min = min_targets(travel)
    n = (
        n_min
        if n_targets is None
        else int_arg("n_targets", n_targets, n_min, MAX_N_TARGETS, wording="outside")
    )
    n_runs = int_arg("runs", runs, iso230_2.MIN_RUNS, 10_000, wording="outside")
    overrun = _in_range("overrun_m", overrun_m, 0.0, travel, "m", lo_open=True)
    move = _check_move(move)
    seed_value = _integer("seed", seed)
    if seed_value < 0:
        raise _outside("seed", seed, "[0, inf)")
    if not isinstance(bidirectional, bool):
        raise TypeError(f"bidirectional must be a bool, got {bidirectional!r}")
    reversal_s = (
        dwell
        if overrun_dwell_s is None
        else _in_range(
            "overrun_dwell_s",
            overrun_dwell_s,
            t,
            MAX_DWELL_S,
            "s",
            lo_text=f"sample_period_s = {t:g}",
        )
    )
    fraction = _in_range(
        "offset_fraction", offset_fraction, 0.0, 0.5, "", lo_open=True, hi_open=True
    )
    n_dwell = _samples(dwell, t)
    n_reversal = _samples(reversal_s, t)
    # Cheap lower bound before drawing anything: every measurement takes n_dwell + 1 samples.
    per_run = (2 if bidirectional else 1) * n * (n_dwell + 1)
    _check_total(n_runs * per_run, "the standard test cycle")

    targets = _draw_targets(np.random.default_rng(seed_value), start, travel, n, fraction)
    low = float(targets[0]) - overrun
    high = float(targets[-1]) + overrun
    block = [_Stop(float(p), n_dwell + 1, +1) for p in targets]
    block.append(_Stop(high, n_reversal))
    if bidirectional:
        block += [_Stop(float(p), n_dwell + 1, -1) for p in targets[::-1]]
    block.append(_Stop(low, n_reversal))
    return _assemble(
        start_m=start,
        initial_samples=n_dwell,
        prefix=[_Stop(low, n_reversal)],
        block=block,
        runs=n_runs,
        move=move,
        sample_period_s=t,
        what="the standard test cycle",
    )


def step_cycle(
    *,
    step_m: float,
    repeats: int,
    start_m: float = 0.0,
    dwell_s: float,
    return_s: float,
    sample_period_s: float,
    direction: int = +1,
    move: MoveProfile = _STEP,
) -> Cycle:
    """The seed paper's repeated unidirectional steps from one start position.

    The reference rests at ``start_m`` for ``return_s``, steps by ``direction · step_m`` to
    the target, rests there for ``dwell_s`` and the position is measured at the end of the
    dwell; it then returns to ``start_m`` and rests ``return_s`` again; ``repeats`` times,
    ending at the start. All measurements are at the one target and approach it from the
    same side (from below for ``direction = +1``): one ISO target with ``repeats`` runs, as
    in the paper's 100 µm and 1 mm tests (docs/SEED.md).

    The return approaches the start from the other side, and no attempt is made to approach
    it from a fixed side (no overrun): the start is not a measured position, and the paper's
    steps are repeated "from the same start position". The backlash and presliding state at
    the start therefore differ from run to run; that variation is part of what such a test
    measures.

    This is not ISO 230-2's standard test cycle (see :func:`standard_test_cycle`), so its
    ISO numbers are the ISO formulas applied to a non-standard cycle.

    Parameters
    ----------
    step_m : float
        Step size [m], in ``(0, 1]``.
    repeats : int
        Number of steps (runs), in ``[2, 16777216]``.
    start_m : float, default 0.0
        Start position [m], in ``[-10, 10]``; where the axis rests at ``t = 0``.
    dwell_s : float
        Rest at the target before the measurement [s], in ``[sample_period_s, 60]``;
        rounded to ``round(dwell_s / T)`` samples.
    return_s : float
        Rest at the start before each step [s], in ``[sample_period_s, 60]``; rounded to
        ``round(return_s / T)`` samples.
    sample_period_s : float
        Control period ``T`` [s], in ``(0, 1]``.
    direction : {+1, -1}, default +1
        Direction of the steps. The measurements are labelled with it; note that the ISO
        evaluator takes unidirectional data as ↑ only, so it rejects a ``-1`` cycle.
    move : MoveProfile, default step
        How the reference travels (a jump by default, as the paper's FPGA does).

    Returns
    -------
    Cycle
        ``repeats`` measurements at ``start_m + direction · step_m``, runs ``1..repeats``.

    Raises
    ------
    ConfigError
        An argument outside its range, or a cycle of more than 2**24 samples.
    TypeError
        An argument of the wrong type.

    Examples
    --------
    >>> c = step_cycle(step_m=100e-6, repeats=3, dwell_s=0.3, return_s=0.2,
    ...                sample_period_s=1e-3)
    >>> c.n_samples, c.measure_index.tolist(), c.run.tolist()
    (1703, [500, 1001, 1502], [1, 2, 3])
    """
    t, dwell, start = _check_common(sample_period_s, dwell_s, start_m)
    step = _in_range("step_m", step_m, 0.0, 1.0, "m", lo_open=True)
    n_repeats = int_arg("repeats", repeats, iso230_2.MIN_RUNS, MAX_SAMPLES, wording="outside")
    back_s = _in_range(
        "return_s", return_s, t, MAX_DWELL_S, "s", lo_text=f"sample_period_s = {t:g}"
    )
    sign = _integer("direction", direction)
    if sign not in (-1, 1):
        raise _outside("direction", direction, "{+1, -1}")
    move = _check_move(move)
    target = start + sign * step
    if abs(target) > MAX_POSITION_M:
        raise _outside(
            "step_m", step_m, f"(0, {MAX_POSITION_M - sign * start:g}] m for start_m = {start:g}"
        )
    n_dwell = _samples(dwell, t)
    n_return = _samples(back_s, t)
    _check_total(n_return + n_repeats * (n_dwell + 1 + n_return), "the step cycle")
    return _assemble(
        start_m=start,
        initial_samples=n_return,
        prefix=[],
        block=[_Stop(target, n_dwell + 1, sign), _Stop(start, n_return)],
        runs=n_repeats,
        move=move,
        sample_period_s=t,
        what="the step cycle",
    )
