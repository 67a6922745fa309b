"""ISO 230-2 evaluation of the positioning accuracy and repeatability of a single axis.

The formulas are those of ISO 230-2:1997/2006/2014 (they did not change between these
editions), with the coverage factor ``k`` as a parameter (``k = 2`` is the standard; ``k = 3``
reproduces the pre-1997 "3 sigma" convention). Notation (see ``docs/DOMAIN.md`` section 1):

* target positions :math:`P_i`, ``i = 1..m``; runs ``j = 1..n`` per direction;
* positional deviation :math:`x_{ij} = P_{ij} - P_i` (actual minus target), in metres;
* ``up`` / ``↑`` is the approach in the positive direction, ``down`` / ``↓`` the negative one.

Per target position::

    x̄ᵢ↑ = mean_j xᵢⱼ↑                      x̄ᵢ↓ likewise
    x̄ᵢ  = (x̄ᵢ↑ + x̄ᵢ↓) / 2
    Bᵢ  = x̄ᵢ↑ - x̄ᵢ↓                         (signed)
    sᵢ↑ = sample standard deviation of xᵢⱼ↑ (n - 1 divisor)
    Rᵢ↑ = 2k·sᵢ↑                             Rᵢ↓ likewise
    Rᵢ  = max(k·sᵢ↑ + k·sᵢ↓ + |Bᵢ|, Rᵢ↑, Rᵢ↓)

Per axis::

    B  = maxᵢ |Bᵢ|            B̄ = meanᵢ Bᵢ (signed)
    R↑ = maxᵢ Rᵢ↑             R↓ likewise            R = maxᵢ Rᵢ
    E↑ = maxᵢ x̄ᵢ↑ - minᵢ x̄ᵢ↑   E↓ likewise
    E  = max(x̄ᵢ↑, x̄ᵢ↓) - min(x̄ᵢ↑, x̄ᵢ↓)     (extrema over all i and both directions)
    M  = maxᵢ x̄ᵢ - minᵢ x̄ᵢ
    A↑ = maxᵢ(x̄ᵢ↑ + k·sᵢ↑) - minᵢ(x̄ᵢ↑ - k·sᵢ↑)   A↓ likewise
    A  = max(x̄ᵢ↑ + k·sᵢ↑, x̄ᵢ↓ + k·sᵢ↓) - min(x̄ᵢ↑ - k·sᵢ↑, x̄ᵢ↓ - k·sᵢ↓)

Everything is computed and stored in SI units (metres); only the human-readable report
(:func:`write_report`, :meth:`Iso230Result.summary_table_markdown`) shows micrometres.

Only numpy is required.
"""

from __future__ import annotations

import functools
import itertools
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, Final

import numpy as np
import numpy.typing as npt

__all__ = [
    "AXIS_PARAMETERS",
    "LENGTH_UNITS",
    "MAX_PLAUSIBLE_DEVIATION_M",
    "MAX_PLAUSIBLE_TARGET_M",
    "MIN_RUNS",
    "REQUIRED_COLUMNS",
    "Iso230InputError",
    "Iso230Result",
    "MeasurementRecords",
    "evaluate",
    "evaluate_records",
]

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

#: Columns a measurement CSV must have (any order; extra columns are ignored).
REQUIRED_COLUMNS: Final[tuple[str, ...]] = ("target_m", "direction", "run", "actual_m")

#: Minimum number of runs per target and direction (ISO 230-2's standard cycle uses 5).
MIN_RUNS: Final[int] = 2

#: Unit plausibility heuristic: a target beyond this magnitude [m] is taken for millimetres.
MAX_PLAUSIBLE_TARGET_M: Final[float] = 10.0

#: Unit plausibility heuristic: a deviation beyond ``this * max(1, |target| / 1 m)`` [m] is
#: taken for a value in millimetres in a metre column.
MAX_PLAUSIBLE_DEVIATION_M: Final[float] = 1e-3

#: Length units a measurement CSV may be written in, with their size in metres: the columns
#: ``target_m``/``actual_m`` hold metres, ``target_mm``/``actual_mm`` millimetres (or
#: ``units=`` / ``--units`` says so for the whole file).
LENGTH_UNITS: Final[dict[str, float]] = {"m": 1.0, "mm": 1e-3}

#: Whole-file unit heuristic: targets read as metres that span at least this [m] ...
MM_HEURISTIC_SPAN_M: Final[float] = 0.5
#: ... with a mean interval above this [m] are taken for millimetres: ISO 230-2 asks for at
#: least five target positions per metre on axes up to 2 m and an average interval of at
#: most 250 mm on longer ones, so such a file is a millimetre test of a short stroke.
MM_HEURISTIC_INTERVAL_M: Final[float] = 0.25

#: The fix named by the unit errors.
UNITS_FIX: Final[str] = (
    "if the file is in millimetres pass --units mm (units='mm'), or name the columns "
    "target_mm and actual_mm"
)

#: Axis parameters in report order: (symbol, attribute of :class:`Iso230Result`, description).
AXIS_PARAMETERS: Final[tuple[tuple[str, str, str], ...]] = (
    ("E↑", "systematic_deviation_up_m", "Unidirectional systematic positional deviation (↑)"),
    ("E↓", "systematic_deviation_down_m", "Unidirectional systematic positional deviation (↓)"),
    ("E", "systematic_deviation_m", "Bidirectional systematic positional deviation"),
    ("M", "mean_deviation_range_m", "Range of the mean bidirectional positional deviation"),
    ("R↑", "repeatability_up_m", "Unidirectional repeatability of positioning (↑)"),
    ("R↓", "repeatability_down_m", "Unidirectional repeatability of positioning (↓)"),
    ("R", "repeatability_m", "Bidirectional repeatability of positioning"),
    ("B", "reversal_m", "Reversal value of the axis, max |Bᵢ|"),
    ("B̄", "mean_reversal_m", "Mean reversal value of the axis (signed)"),
    ("A↑", "accuracy_up_m", "Unidirectional accuracy of positioning (↑)"),
    ("A↓", "accuracy_down_m", "Unidirectional accuracy of positioning (↓)"),
    ("A", "accuracy_m", "Bidirectional accuracy of positioning"),
)

_PER_TARGET_FIELDS: Final[tuple[str, ...]] = (
    "mean_deviation_up_m",
    "mean_deviation_down_m",
    "mean_bidirectional_deviation_m",
    "reversal_at_target_m",
    "std_up_m",
    "std_down_m",
    "repeatability_at_target_up_m",
    "repeatability_at_target_down_m",
    "repeatability_at_target_m",
)

UM_PER_M: Final[float] = 1e6
MM_PER_M: Final[float] = 1e3


# --------------------------------------------------------------------------------------------
# Errors
# --------------------------------------------------------------------------------------------


class Iso230InputError(ValueError):
    """Invalid ISO 230-2 input data.

    The message starts with the location of the problem when it is known: the file, the
    1-based line number and the column name for CSV input (``"meas.csv, line 7, column
    'actual_m': ..."``), or the 0-based record index and the column for
    :func:`evaluate_records`.

    Parameters
    ----------
    message : str
        What is wrong, without the location.
    source : str, optional
        File the data came from.
    line : int, optional
        1-based line number in ``source``.
    column : str, optional
        Name of the offending column (or argument).
    record : int, optional
        0-based index of the offending record when there is no file.

    Attributes
    ----------
    reason, source, line, column, record
        The constructor arguments (``reason`` is ``message``).
    """

    def __init__(
        self,
        message: str,
        *,
        source: str | None = None,
        line: int | None = None,
        column: str | None = None,
        record: int | None = None,
    ) -> None:
        self.reason = message
        self.source = source
        self.line = line
        self.column = column
        self.record = record
        parts: list[str] = []
        if source is not None:
            parts.append(source)
        if line is not None:
            parts.append(f"line {line}")
        if record is not None:
            parts.append(f"record {record}")
        if column is not None:
            parts.append(f"column {column!r}")
        prefix = ", ".join(parts)
        super().__init__(f"{prefix}: {message}" if prefix else message)


# --------------------------------------------------------------------------------------------
# Result
# --------------------------------------------------------------------------------------------


def readonly(a: npt.ArrayLike) -> FloatArray:
    out = np.array(a, dtype=np.float64, copy=True)
    out.flags.writeable = False
    return out


@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class Iso230Result:
    """Result of an ISO 230-2 evaluation; all lengths in metres.

    Per-target arrays have shape ``(n_targets,)`` and follow ``targets_m`` (ascending). They
    are read-only numpy arrays, so the object is immutable but compares by identity
    (``eq=False``). Bidirectional quantities are ``None`` for unidirectional data (only ``↑``
    approaches).

    Attributes
    ----------
    coverage_factor : float
        Coverage factor ``k`` [-] (2 in ISO 230-2:1997 and later).
    targets_m : ndarray, shape (n_targets,)
        Target positions :math:`P_i` [m], ascending.
    deviations_up_m : tuple of ndarray
        Positional deviations :math:`x_{ij}↑` [m]; entry ``i`` has shape ``(n_runs_up[i],)``,
        ordered by run.
    deviations_down_m : tuple of ndarray or None
        Positional deviations :math:`x_{ij}↓` [m], or ``None``.
    mean_deviation_up_m, mean_deviation_down_m : ndarray, shape (n_targets,)
        Mean unidirectional positional deviation :math:`\\bar x_i↑`, :math:`\\bar x_i↓` [m].
    mean_bidirectional_deviation_m : ndarray, shape (n_targets,) or None
        Mean bidirectional positional deviation :math:`\\bar x_i` [m].
    reversal_at_target_m : ndarray, shape (n_targets,) or None
        Signed reversal value :math:`B_i = \\bar x_i↑ - \\bar x_i↓` [m].
    std_up_m, std_down_m : ndarray, shape (n_targets,)
        Estimator of the unidirectional repeatability :math:`s_i` [m] (n - 1 divisor).
    repeatability_at_target_up_m, repeatability_at_target_down_m : ndarray, shape (n_targets,)
        Unidirectional repeatability at a position :math:`R_i = 2k s_i` [m].
    repeatability_at_target_m : ndarray, shape (n_targets,) or None
        Bidirectional repeatability at a position
        :math:`R_i = \\max(k s_i↑ + k s_i↓ + |B_i|, R_i↑, R_i↓)` [m].
    systematic_deviation_up_m, systematic_deviation_down_m, systematic_deviation_m : float
        E↑, E↓, E [m].
    mean_deviation_range_m : float or None
        M, range of the mean bidirectional positional deviation [m].
    repeatability_up_m, repeatability_down_m, repeatability_m : float
        R↑, R↓, R [m].
    reversal_m : float or None
        B = max |Bᵢ| [m].
    mean_reversal_m : float or None
        B̄ = mean Bᵢ [m], signed.
    accuracy_up_m, accuracy_down_m, accuracy_m : float
        A↑, A↓, A [m].
    """

    coverage_factor: float
    targets_m: FloatArray
    deviations_up_m: tuple[FloatArray, ...]
    deviations_down_m: tuple[FloatArray, ...] | None
    mean_deviation_up_m: FloatArray
    mean_deviation_down_m: FloatArray | None
    mean_bidirectional_deviation_m: FloatArray | None
    reversal_at_target_m: FloatArray | None
    std_up_m: FloatArray
    std_down_m: FloatArray | None
    repeatability_at_target_up_m: FloatArray
    repeatability_at_target_down_m: FloatArray | None
    repeatability_at_target_m: FloatArray | None
    systematic_deviation_up_m: float
    systematic_deviation_down_m: float | None
    systematic_deviation_m: float | None
    mean_deviation_range_m: float | None
    repeatability_up_m: float
    repeatability_down_m: float | None
    repeatability_m: float | None
    reversal_m: float | None
    mean_reversal_m: float | None
    accuracy_up_m: float
    accuracy_down_m: float | None
    accuracy_m: float | None

    @property
    def bidirectional(self) -> bool:
        """True when negative-direction (↓) data were evaluated."""
        return self.deviations_down_m is not None

    @property
    def n_targets(self) -> int:
        """Number of target positions ``m``."""
        return int(self.targets_m.shape[0])

    @property
    def n_runs_up(self) -> IntArray:
        """Number of ↑ runs per target, shape ``(n_targets,)``."""
        return np.array([d.shape[0] for d in self.deviations_up_m], dtype=np.int64)

    @property
    def n_runs_down(self) -> IntArray | None:
        """Number of ↓ runs per target, shape ``(n_targets,)``, or ``None``."""
        if self.deviations_down_m is None:
            return None
        return np.array([d.shape[0] for d in self.deviations_down_m], dtype=np.int64)

    def axis_parameters(self) -> dict[str, float | None]:
        """Axis parameters keyed by attribute name (see :data:`AXIS_PARAMETERS`).

        Returns
        -------
        dict of str to float or None
            Values in metres; ``None`` for bidirectional parameters of unidirectional data.
        """
        return {key: getattr(self, key) for _, key, _ in AXIS_PARAMETERS}

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready representation (plain floats, ints, lists, ``None``); lengths in metres.

        Returns
        -------
        dict
            Keys ``standard``, ``units``, ``coverage_factor``, ``bidirectional``,
            ``n_targets``, ``axis`` (attribute name → value [m]), ``symbols`` (attribute
            name → ISO symbol), ``per_target`` (one dict per target), ``deviations_up_m`` and
            ``deviations_down_m`` (list of per-target lists [m], or ``None``).
        """
        n_up = self.n_runs_up
        n_down = self.n_runs_down
        per_target: list[dict[str, Any]] = []
        for i in range(self.n_targets):
            row: dict[str, Any] = {
                "target_m": float(self.targets_m[i]),
                "n_runs_up": int(n_up[i]),
                "n_runs_down": None if n_down is None else int(n_down[i]),
            }
            for name in _PER_TARGET_FIELDS:
                arr: FloatArray | None = getattr(self, name)
                row[name] = None if arr is None else float(arr[i])
            per_target.append(row)
        return {
            "standard": "ISO 230-2",
            "units": "m",
            "coverage_factor": float(self.coverage_factor),
            "bidirectional": self.bidirectional,
            "n_targets": self.n_targets,
            "axis": self.axis_parameters(),
            "symbols": {key: symbol for symbol, key, _ in AXIS_PARAMETERS},
            "per_target": per_target,
            "deviations_up_m": [[float(v) for v in d] for d in self.deviations_up_m],
            "deviations_down_m": None
            if self.deviations_down_m is None
            else [[float(v) for v in d] for d in self.deviations_down_m],
        }

    def summary_table_markdown(self) -> str:
        """Markdown table of the axis parameters, values in micrometres.

        Returns
        -------
        str
            A pipe table with columns *Symbol*, *Parameter*, *Value [µm]*; bidirectional
            parameters of unidirectional data are shown as ``—``. Ends with a newline.
        """
        lines = ["| Symbol | Parameter | Value [µm] |", "| --- | --- | ---: |"]
        values = self.axis_parameters()
        for symbol, key, description in AXIS_PARAMETERS:
            lines.append(f"| {symbol} | {md_escape(description)} | {fmt_um(values[key])} |")
        return "\n".join(lines) + "\n"

    def per_target_table_markdown(self) -> str:
        """Markdown table of the per-target statistics, targets in mm, values in micrometres.

        Returns
        -------
        str
            A pipe table, one row per target position. Ends with a newline.
        """
        head = [
            "i",
            "Target [mm]",
            "n↑",
            "n↓",
            "x̄ᵢ↑ [µm]",
            "x̄ᵢ↓ [µm]",
            "x̄ᵢ [µm]",
            "Bᵢ [µm]",
            "sᵢ↑ [µm]",
            "sᵢ↓ [µm]",
            "Rᵢ↑ [µm]",
            "Rᵢ↓ [µm]",
            "Rᵢ [µm]",
        ]
        lines = ["| " + " | ".join(head) + " |", "| " + " | ".join(["---:"] * len(head)) + " |"]
        n_up = self.n_runs_up
        n_down = self.n_runs_down

        def cell(arr: FloatArray | None, i: int) -> str:
            return fmt_um(None if arr is None else float(arr[i]))

        for i in range(self.n_targets):
            cells = [
                str(i + 1),
                fmt_mm(float(self.targets_m[i])),
                str(int(n_up[i])),
                "—" if n_down is None else str(int(n_down[i])),
            ]
            cells += [cell(getattr(self, name), i) for name in _PER_TARGET_FIELDS]
            lines.append("| " + " | ".join(cells) + " |")
        return "\n".join(lines) + "\n"


def fmt_um(value_m: float | None) -> str:
    if value_m is None:
        return "—"
    return f"{round(value_m * UM_PER_M, 4) + 0.0:.4f}"  # + 0.0 turns -0.0 into 0.0


def fmt_mm(value_m: float) -> str:
    return f"{value_m * MM_PER_M:.6g}"


# --------------------------------------------------------------------------------------------
# Evaluation
# --------------------------------------------------------------------------------------------


def md_escape(text: str) -> str:
    return text.replace("|", "\\|").replace("\n", " ")


def _check_coverage_factor(coverage_factor: float) -> float:
    k = float(coverage_factor)
    if not (math.isfinite(k) and k > 0.0):
        raise Iso230InputError(
            f"must be a finite number > 0, got {coverage_factor!r}", column="coverage_factor"
        )
    return k


def _compute(
    targets_m: FloatArray,
    up: Sequence[FloatArray],
    down: Sequence[FloatArray] | None,
    k: float,
) -> Iso230Result:
    """Apply the ISO 230-2 formulas to validated, target-sorted data (one array per target)."""
    mean_up = np.array([float(np.mean(r)) for r in up])
    std_up = np.array([float(np.std(r, ddof=1)) for r in up])
    rep_up_i = 2.0 * k * std_up
    lo_up = mean_up - k * std_up
    hi_up = mean_up + k * std_up

    e_up = float(np.max(mean_up) - np.min(mean_up))
    r_up = float(np.max(rep_up_i))
    a_up = float(np.max(hi_up) - np.min(lo_up))

    mean_down = std_down = rep_down_i = mean_bi = reversal_i = rep_i = None
    e_down = e_bi = m_range = r_down = r_bi = b_axis = b_mean = a_down = a_bi = None
    if down is not None:
        mean_down = np.array([float(np.mean(r)) for r in down])
        std_down = np.array([float(np.std(r, ddof=1)) for r in down])
        rep_down_i = 2.0 * k * std_down
        lo_down = mean_down - k * std_down
        hi_down = mean_down + k * std_down
        mean_bi = 0.5 * (mean_up + mean_down)
        reversal_i = mean_up - mean_down
        rep_i = np.maximum(
            k * std_up + k * std_down + np.abs(reversal_i), np.maximum(rep_up_i, rep_down_i)
        )
        e_down = float(np.max(mean_down) - np.min(mean_down))
        e_bi = float(
            max(np.max(mean_up), np.max(mean_down)) - min(np.min(mean_up), np.min(mean_down))
        )
        m_range = float(np.max(mean_bi) - np.min(mean_bi))
        r_down = float(np.max(rep_down_i))
        r_bi = float(np.max(rep_i))
        b_axis = float(np.max(np.abs(reversal_i)))
        b_mean = float(np.mean(reversal_i))
        a_down = float(np.max(hi_down) - np.min(lo_down))
        a_bi = float(max(np.max(hi_up), np.max(hi_down)) - min(np.min(lo_up), np.min(lo_down)))

    def ro(a: FloatArray | None) -> FloatArray | None:
        return None if a is None else readonly(a)

    return Iso230Result(
        coverage_factor=k,
        targets_m=readonly(targets_m),
        deviations_up_m=tuple(readonly(r) for r in up),
        deviations_down_m=None if down is None else tuple(readonly(r) for r in down),
        mean_deviation_up_m=readonly(mean_up),
        mean_deviation_down_m=ro(mean_down),
        mean_bidirectional_deviation_m=ro(mean_bi),
        reversal_at_target_m=ro(reversal_i),
        std_up_m=readonly(std_up),
        std_down_m=ro(std_down),
        repeatability_at_target_up_m=readonly(rep_up_i),
        repeatability_at_target_down_m=ro(rep_down_i),
        repeatability_at_target_m=ro(rep_i),
        systematic_deviation_up_m=e_up,
        systematic_deviation_down_m=e_down,
        systematic_deviation_m=e_bi,
        mean_deviation_range_m=m_range,
        repeatability_up_m=r_up,
        repeatability_down_m=r_down,
        repeatability_m=r_bi,
        reversal_m=b_axis,
        mean_reversal_m=b_mean,
        accuracy_up_m=a_up,
        accuracy_down_m=a_down,
        accuracy_m=a_bi,
    )


def _as_deviation_matrix(value: npt.ArrayLike, name: str, n_targets: int) -> FloatArray:
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise Iso230InputError(f"not a numeric array: {exc}", column=name) from None
    if arr.ndim != 2 or arr.shape[0] != n_targets:
        raise Iso230InputError(
            f"must have shape (n_targets={n_targets}, n_runs), got {arr.shape}", column=name
        )
    if arr.shape[1] < MIN_RUNS:
        raise Iso230InputError(
            f"needs at least 2 runs per target (ISO 230-2 uses 5), got {arr.shape[1]}",
            column=name,
        )
    if not np.all(np.isfinite(arr)):
        bad = tuple(int(v) for v in np.argwhere(~np.isfinite(arr))[0])
        raise Iso230InputError(f"non-finite value at index {bad}", column=name)
    return arr


def evaluate(
    targets_m: npt.ArrayLike,
    deviations_up_m: npt.ArrayLike,
    deviations_down_m: npt.ArrayLike | None = None,
    *,
    coverage_factor: float = 2.0,
) -> Iso230Result:
    """Evaluate a positioning test with the ISO 230-2 formulas.

    Parameters
    ----------
    targets_m : array_like, shape (n_targets,)
        Target positions :math:`P_i` [m], distinct, finite, in any order (the result is
        sorted by target).
    deviations_up_m : array_like, shape (n_targets, n_runs_up)
        Positional deviations :math:`x_{ij}↑ = P_{ij}↑ - P_i` [m] (actual minus target) of
        the approaches in the positive direction; ``n_runs_up >= 2``.
    deviations_down_m : array_like, shape (n_targets, n_runs_down), optional
        Deviations [m] of the approaches in the negative direction. If omitted the test is
        unidirectional and all bidirectional quantities of the result are ``None``.
    coverage_factor : float, default 2.0
        Coverage factor ``k`` [-]; repeatability is ``2k·s``, accuracy bands are ``±k·s``.

    Returns
    -------
    Iso230Result
        All per-target and per-axis quantities, in metres.

    Raises
    ------
    Iso230InputError
        On wrong shapes, fewer than 2 runs, non-finite values, duplicate targets or a
        non-positive coverage factor. It is a :class:`ValueError`.

    Examples
    --------
    >>> import numpy as np
    >>> r = evaluate([0.0, 0.01], np.array([[1, 2, 3], [4, 6, 8]]) * 1e-6,
    ...              np.array([[-1, 0, 1], [3, 5, 7]]) * 1e-6)
    >>> round(r.systematic_deviation_m * 1e6, 9), round(r.repeatability_m * 1e6, 9)
    (6.0, 9.0)
    """
    k = _check_coverage_factor(coverage_factor)
    try:
        targets = np.asarray(targets_m, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise Iso230InputError(f"not a numeric array: {exc}", column="targets_m") from None
    if targets.ndim != 1 or targets.shape[0] < 1:
        raise Iso230InputError(
            f"must be a non-empty 1-D array, got shape {targets.shape}", column="targets_m"
        )
    if not np.all(np.isfinite(targets)):
        raise Iso230InputError("contains non-finite values", column="targets_m")
    m = targets.shape[0]
    up = _as_deviation_matrix(deviations_up_m, "deviations_up_m", m)
    down = (
        None
        if deviations_down_m is None
        else _as_deviation_matrix(deviations_down_m, "deviations_down_m", m)
    )
    order = np.argsort(targets, kind="stable")
    targets = targets[order]
    if m > 1 and np.any(np.diff(targets) == 0.0):
        dup = float(targets[1:][np.diff(targets) == 0.0][0])
        raise Iso230InputError(f"duplicate target {dup!r} m", column="targets_m")
    return _compute(
        targets,
        [up[i] for i in order],
        None if down is None else [down[i] for i in order],
        k,
    )


# --------------------------------------------------------------------------------------------
# Flat records
# --------------------------------------------------------------------------------------------

_Locate = Callable[[int], dict[str, Any]]


def _record_locator(i: int) -> dict[str, Any]:
    return {"record": i}


def parse_direction(value: object) -> str | None:
    s = str(value).strip()
    return s if s in ("+", "-") else None


def group_records(
    target_m: npt.ArrayLike,
    direction: Sequence[str] | npt.ArrayLike,
    run: npt.ArrayLike,
    actual_m: npt.ArrayLike,
    *,
    locate: _Locate,
    target_tolerance_m: float,
    check_units: bool,
) -> tuple[FloatArray, list[FloatArray], list[FloatArray] | None]:
    """Validate flat records and group them into per-target deviation arrays.

    Returns ``(targets_m, up, down)``: ascending targets and, per target, the deviations
    ordered by run number.
    """

    def fail(i: int, column: str, message: str) -> Iso230InputError:
        return Iso230InputError(message, column=column, **locate(i))

    try:
        targets = np.asarray(target_m, dtype=np.float64).reshape(-1)
        actual = np.asarray(actual_m, dtype=np.float64).reshape(-1)
        runs_f = np.asarray(run, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError) as exc:
        raise Iso230InputError(f"records are not numeric: {exc}") from None
    dirs_in = [direction] if isinstance(direction, str) else list(np.asarray(direction).ravel())
    n = targets.shape[0]
    lengths = {
        "target_m": n,
        "direction": len(dirs_in),
        "run": runs_f.shape[0],
        "actual_m": actual.shape[0],
    }
    if len(set(lengths.values())) != 1:
        raise Iso230InputError(f"record arrays differ in length: {lengths}")
    if n == 0:
        raise Iso230InputError("no measurement records")

    dirs: list[str] = []
    for i in range(n):
        if not math.isfinite(targets[i]):
            raise fail(i, "target_m", f"value {targets[i]!r} is not a finite number")
        d = parse_direction(dirs_in[i])
        if d is None:
            raise fail(i, "direction", f"unknown direction {str(dirs_in[i])!r}; use '+' or '-'")
        dirs.append(d)
        if not (math.isfinite(runs_f[i]) and runs_f[i] == math.floor(runs_f[i])):
            raise fail(i, "run", f"run number {runs_f[i]!r} is not an integer")
        if not math.isfinite(actual[i]):
            raise fail(i, "actual_m", f"value {actual[i]!r} is not a finite number")
        if check_units:
            check_record_units(float(targets[i]), float(actual[i]), functools.partial(fail, i))
    runs = runs_f.astype(np.int64)

    # Group targets: sort, start a new group when a target is more than the tolerance away
    # from the first target of the current group (no chaining of small steps).
    order = np.argsort(targets, kind="stable")
    groups: list[list[int]] = []
    start = math.nan
    for idx in order:
        t = float(targets[idx])
        if not groups or t - start > target_tolerance_m:
            groups.append([])
            start = t
        groups[-1].append(int(idx))

    has_down = "-" in dirs
    if "+" not in dirs:
        raise fail(
            0,
            "direction",
            "no '+' records: unidirectional data must be the positive direction (↑)",
        )

    group_targets = np.array([float(np.mean(targets[g])) for g in groups])
    up: list[FloatArray] = []
    down: list[FloatArray] = []
    for g, t_group in zip(groups, group_targets, strict=True):
        for sign, out in (("+", up), ("-", down)):
            if sign == "-" and not has_down:
                continue
            members = [i for i in g if dirs[i] == sign]
            if len(members) < MIN_RUNS:
                where = members[0] if members else g[0]
                column = "run" if members else "direction"
                raise fail(
                    where,
                    column,
                    f"target {t_group:.9g} m has {len(members)} run(s) in direction {sign!r}; "
                    "ISO 230-2 needs at least 2 (normally 5) per target and direction",
                )
            members.sort(key=lambda i: (int(runs[i]), i))
            for a, b in itertools.pairwise(members):
                if runs[a] == runs[b]:
                    raise fail(
                        b,
                        "run",
                        f"duplicate run {int(runs[b])} at target {t_group:.9g} m "
                        f"in direction {sign!r}",
                    )
            out.append(np.array([actual[i] - targets[i] for i in members], dtype=np.float64))
    return group_targets, up, (down if has_down else None)


def check_record_units(
    target: float,
    actual: float,
    fail: Callable[[str, str], Iso230InputError],
    columns: tuple[str, str] = ("target_m", "actual_m"),
) -> None:
    """Raise if a record looks like it holds millimetres in a metre column (see the CSV doc).
    ``target`` and ``actual`` in metres; ``columns``: their column names for the message."""
    if abs(target) > MAX_PLAUSIBLE_TARGET_M:
        raise fail(
            columns[0],
            f"target {target!r} m is beyond ±{MAX_PLAUSIBLE_TARGET_M:g} m; "
            f"the value looks like millimetres, but the column must be in metres: {UNITS_FIX}",
        )
    limit = MAX_PLAUSIBLE_DEVIATION_M * max(1.0, abs(target))
    deviation = actual - target
    if abs(deviation) > limit:
        raise fail(
            columns[1],
            f"deviation actual - target = {deviation:.6g} m exceeds the plausibility limit "
            f"{limit:.3g} m; mixed units (millimetres in a metre column)?",
        )


def evaluate_records(
    target_m: npt.ArrayLike,
    direction: Sequence[str] | npt.ArrayLike,
    run: npt.ArrayLike,
    actual_m: npt.ArrayLike,
    *,
    coverage_factor: float = 2.0,
    target_tolerance_m: float = 1e-9,
    check_units: bool = False,
) -> Iso230Result:
    """Evaluate flat measurement records (one row per approach) with ISO 230-2.

    Records are grouped by target position (targets closer than ``target_tolerance_m`` to
    the first target of a group belong to it) and direction, and ordered by run number. The
    deviation of each record is ``actual_m - target_m``. Targets may have different numbers
    of runs, but each needs at least 2 in each direction present. If there are no ``'-'``
    records the evaluation is unidirectional.

    Parameters
    ----------
    target_m : array_like, shape (n_records,)
        Commanded target position [m] of each approach.
    direction : sequence of str, shape (n_records,)
        ``'+'`` for an approach in the positive direction (↑), ``'-'`` for the negative one.
    run : array_like of int, shape (n_records,)
        Run (cycle) number; unique per target and direction.
    actual_m : array_like, shape (n_records,)
        Measured actual position [m].
    coverage_factor : float, default 2.0
        Coverage factor ``k`` [-].
    target_tolerance_m : float, default 1e-9
        Targets closer than this [m] are the same target position.
    check_units : bool, default False
        Apply the millimetre-in-metre-column heuristic of :func:`read_measurement_csv`.

    Returns
    -------
    Iso230Result
        See :func:`evaluate`.

    Raises
    ------
    Iso230InputError
        Naming the 0-based record index and the column: non-finite values, unknown
        direction, non-integer or duplicate run numbers, fewer than 2 runs at a target in a
        direction, no ``'+'`` records, or arrays of different lengths.
    """
    k = _check_coverage_factor(coverage_factor)
    targets, up, down = group_records(
        target_m,
        direction,
        run,
        actual_m,
        locate=_record_locator,
        target_tolerance_m=float(target_tolerance_m),
        check_units=check_units,
    )
    return _compute(targets, up, down, k)


@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class MeasurementRecords:
    """Flat measurement records as read from a CSV file (one row per approach).

    Attributes
    ----------
    target_m : ndarray of float64, shape (n_records,)
        Target position [m].
    direction : ndarray of str, shape (n_records,)
        ``'+'`` or ``'-'``.
    run : ndarray of int64, shape (n_records,)
        Run (cycle) number.
    actual_m : ndarray of float64, shape (n_records,)
        Measured actual position [m].
    source : str or None
        File the records came from.
    line : ndarray of int64, shape (n_records,), or None
        1-based line number of each record in ``source``.
    """

    target_m: FloatArray
    direction: npt.NDArray[np.str_]
    run: IntArray
    actual_m: FloatArray
    source: str | None = None
    line: IntArray | None = None

    def __len__(self) -> int:
        return int(self.target_m.shape[0])

    def evaluate(
        self, *, coverage_factor: float = 2.0, target_tolerance_m: float = 1e-9
    ) -> Iso230Result:
        """Evaluate these records; errors cite the file and line when known.

        Parameters
        ----------
        coverage_factor : float, default 2.0
            Coverage factor ``k`` [-].
        target_tolerance_m : float, default 1e-9
            Targets closer than this [m] are the same target position.

        Returns
        -------
        Iso230Result
            See :func:`evaluate`.
        """
        k = _check_coverage_factor(coverage_factor)
        line = self.line
        source = self.source

        def locate(i: int) -> dict[str, Any]:
            if line is None:
                return {"source": source, "record": i}
            return {"source": source, "line": int(line[i])}

        targets, up, down = group_records(
            self.target_m,
            self.direction,
            self.run,
            self.actual_m,
            locate=locate,
            target_tolerance_m=float(target_tolerance_m),
            check_units=False,
        )
        return _compute(targets, up, down, k)
