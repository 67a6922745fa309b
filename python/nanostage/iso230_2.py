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

Only numpy is required; matplotlib is imported lazily by :func:`plot` and is optional.
"""

from __future__ import annotations

import argparse
import codecs
import csv
import functools
import itertools
import json
import math
import sys
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, Final

import numpy as np
import numpy.typing as npt

if TYPE_CHECKING:
    from matplotlib.axes import Axes

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
    "ReportFiles",
    "add_cli",
    "evaluate",
    "evaluate_records",
    "plot",
    "read_measurement_csv",
    "run_cli",
    "write_measurement_csv",
    "write_report",
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
_UNITS_FIX: Final[str] = (
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

_UM_PER_M: Final[float] = 1e6
_MM_PER_M: Final[float] = 1e3

JSON_NAME: Final[str] = "iso230_2.json"
MARKDOWN_NAME: Final[str] = "iso230_2.md"
PNG_NAME: Final[str] = "iso230_2.png"


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


def _readonly(a: npt.ArrayLike) -> FloatArray:
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
            lines.append(f"| {symbol} | {_md_escape(description)} | {_fmt_um(values[key])} |")
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
            return _fmt_um(None if arr is None else float(arr[i]))

        for i in range(self.n_targets):
            cells = [
                str(i + 1),
                _fmt_mm(float(self.targets_m[i])),
                str(int(n_up[i])),
                "—" if n_down is None else str(int(n_down[i])),
            ]
            cells += [cell(getattr(self, name), i) for name in _PER_TARGET_FIELDS]
            lines.append("| " + " | ".join(cells) + " |")
        return "\n".join(lines) + "\n"


def _fmt_um(value_m: float | None) -> str:
    if value_m is None:
        return "—"
    return f"{round(value_m * _UM_PER_M, 4) + 0.0:.4f}"  # + 0.0 turns -0.0 into 0.0


def _fmt_mm(value_m: float) -> str:
    return f"{value_m * _MM_PER_M:.6g}"


# --------------------------------------------------------------------------------------------
# Evaluation
# --------------------------------------------------------------------------------------------


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
        return None if a is None else _readonly(a)

    return Iso230Result(
        coverage_factor=k,
        targets_m=_readonly(targets_m),
        deviations_up_m=tuple(_readonly(r) for r in up),
        deviations_down_m=None if down is None else tuple(_readonly(r) for r in down),
        mean_deviation_up_m=_readonly(mean_up),
        mean_deviation_down_m=ro(mean_down),
        mean_bidirectional_deviation_m=ro(mean_bi),
        reversal_at_target_m=ro(reversal_i),
        std_up_m=_readonly(std_up),
        std_down_m=ro(std_down),
        repeatability_at_target_up_m=_readonly(rep_up_i),
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


def _parse_direction(value: object) -> str | None:
    s = str(value).strip()
    return s if s in ("+", "-") else None


def _group_records(
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
        d = _parse_direction(dirs_in[i])
        if d is None:
            raise fail(i, "direction", f"unknown direction {str(dirs_in[i])!r}; use '+' or '-'")
        dirs.append(d)
        if not (math.isfinite(runs_f[i]) and runs_f[i] == math.floor(runs_f[i])):
            raise fail(i, "run", f"run number {runs_f[i]!r} is not an integer")
        if not math.isfinite(actual[i]):
            raise fail(i, "actual_m", f"value {actual[i]!r} is not a finite number")
        if check_units:
            _check_units(float(targets[i]), float(actual[i]), functools.partial(fail, i))
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


def _check_units(
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
            f"the value looks like millimetres, but the column must be in metres: {_UNITS_FIX}",
        )
    limit = MAX_PLAUSIBLE_DEVIATION_M * max(1.0, abs(target))
    deviation = actual - target
    if abs(deviation) > limit:
        raise fail(
            columns[1],
            f"deviation actual - target = {deviation:.6g} m exceeds the plausibility limit "
            f"{limit:.3g} m; mixed units (millimetres in a metre column)?",
        )


def _check_target_spacing(
    targets_m: Sequence[float], fail: Callable[[str], Iso230InputError]
) -> None:
    """Raise if targets read as metres span a long travel with too few targets for an
    ISO 230-2 test (:data:`MM_HEURISTIC_SPAN_M`, :data:`MM_HEURISTIC_INTERVAL_M`): a test of
    a short stroke written in millimetres."""
    t = np.unique(np.asarray(targets_m, dtype=np.float64))
    if t.size < 2:
        return
    span = float(t[-1] - t[0])
    interval = span / (t.size - 1)
    if span >= MM_HEURISTIC_SPAN_M and interval > MM_HEURISTIC_INTERVAL_M:
        raise fail(
            f"{t.size} targets over {span:.6g} m, {interval:.3g} m apart on average: an "
            "ISO 230-2 test has at least five targets per metre (at most "
            f"{MM_HEURISTIC_INTERVAL_M:g} m apart), so the values look like millimetres of a "
            f"{span:.6g} mm stroke (read as metres every deviation would be 1000 times too "
            f"large); {_UNITS_FIX}; pass --units m (units='m') if they are metres"
        )


class _Utf8Error(Exception):
    """Where a file stops being UTF-8: 0-based byte offset, 1-based line, the byte."""

    def __init__(self, offset: int, line: int, byte: int, reason: str) -> None:
        super().__init__(offset, line, byte, reason)
        self.offset, self.line, self.byte, self.reason = offset, line, byte, reason


def _find_utf8_error(path: Path, chunk_bytes: int = 1 << 20) -> _Utf8Error | None:
    """The first byte of ``path`` that is not UTF-8, read in chunks (no whole-file copy)."""
    decoder = codecs.getincrementaldecoder("utf-8")()
    pos = 0
    lines = 0
    with path.open("rb") as fh:
        while True:
            chunk = fh.read(chunk_bytes)
            pending = decoder.getstate()[0]
            try:
                decoder.decode(chunk, final=not chunk)
            except UnicodeDecodeError as exc:
                data = pending + chunk
                offset = pos - len(pending) + exc.start
                line = lines + data[: exc.start].count(b"\n") + 1
                return _Utf8Error(offset, line, data[exc.start], exc.reason)
            if not chunk:
                return None
            pos += len(chunk)
            lines += chunk.count(b"\n")


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
    targets, up, down = _group_records(
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

        targets, up, down = _group_records(
            self.target_m,
            self.direction,
            self.run,
            self.actual_m,
            locate=locate,
            target_tolerance_m=float(target_tolerance_m),
            check_units=False,
        )
        return _compute(targets, up, down, k)


# --------------------------------------------------------------------------------------------
# CSV input/output
# --------------------------------------------------------------------------------------------


def _skip_row(row: Sequence[str]) -> bool:
    return not any(c.strip() for c in row) or row[0].lstrip().startswith("#")


def read_measurement_csv(
    path: str | Path,
    *,
    check_units: bool = True,
    target_tolerance_m: float = 1e-9,
    units: str | None = None,
) -> MeasurementRecords:
    """Read and validate a measurement CSV file.

    The file has a header row with (at least) the columns ``target_m``, ``direction``,
    ``run`` and ``actual_m``, in any order; other columns are ignored. Each following row is
    one approach: target position [m], ``+`` or ``-``, run number (integer) and the measured
    actual position [m]. A file in millimetres names its length columns ``target_mm`` and
    ``actual_mm`` (each length column may carry its own unit), or is read with
    ``units="mm"``. Blank lines and lines starting with ``#`` (before or after the header)
    are skipped, so metadata can be kept as comments. Line numbers in errors are physical,
    1-based line numbers of the file. The records are returned in metres.

    **Unit heuristic** (``check_units=True``). Files in millimetres read as metres are a
    common mistake that would silently give results 1000 times too large. A row is rejected
    when

    * ``|target_m| > 10 m`` (no positioner this module is meant for has such a travel; a
      millimetre target of 10.5 mm read as metres would be 10.5 m), or
    * ``|actual_m - target_m| > 1e-3 m * max(1, |target_m| / 1 m)``: a positional deviation
      above 1 mm (or 1 mm per metre of target for long axes) is implausible for a positioning
      test, and is what one gets when one of the two columns is in millimetres and the other
      in metres;

    and, for columns named in metres without an explicit ``units``, the whole file is
    rejected when its targets span at least 0.5 m with fewer targets than ISO 230-2 asks
    for (at least five per metre, at most 0.25 m apart on average): targets 0, 1, ... 10
    with sub-micrometre-looking deviations are a 10 mm stroke in millimetres, not a 10 m
    axis. A file written *entirely* in millimetres with a stroke under 0.5 mm, or with
    targets at most 0.25 mm apart, cannot be told apart from a metre file; the heuristic
    cannot catch that case.

    Parameters
    ----------
    path : str or Path
        The CSV file (UTF-8, optional BOM, comma separated).
    check_units : bool, default True
        Apply the unit heuristic above.
    target_tolerance_m : float, default 1e-9
        Targets closer than this [m] are the same target position.
    units : {"m", "mm"}, optional
        The unit of both length columns whatever their names say (default: from the names).

    Returns
    -------
    MeasurementRecords
        The records, with ``source`` and per-record ``line`` numbers. Pass them to
        :meth:`MeasurementRecords.evaluate` or to :func:`evaluate_records`.

    Raises
    ------
    Iso230InputError
        With a message ``"<file>, line <n>, column '<name>': <reason>"`` for: a missing or
        duplicated required column, an empty, NaN/infinite or unparseable value, an unknown
        direction, a non-integer or duplicate run number, fewer than 2 runs at a target in a
        direction, a row with more fields than the header, text that is not UTF-8 (with the
        byte offset), an unknown ``units``, and (with ``check_units``) values that look like
        millimetres.
    OSError
        If the file cannot be read.
    """
    src = str(path)
    if units is not None and units not in LENGTH_UNITS:
        raise Iso230InputError(
            f"units = {units!r} is invalid: expected one of {', '.join(LENGTH_UNITS)}"
        )
    try:
        return _read_measurement_csv(Path(path), src, check_units, float(target_tolerance_m), units)
    except UnicodeDecodeError:
        bad = _find_utf8_error(Path(path))
        if bad is None:  # pragma: no cover - the decoder failed, so the scan finds it
            raise
        raise Iso230InputError(
            f"not UTF-8 text: byte 0x{bad.byte:02x} at byte offset {bad.offset} cannot be "
            f"decoded ({bad.reason}); save the file as UTF-8",
            source=src,
            line=bad.line,
        ) from None


def _read_measurement_csv(
    path: Path, src: str, check_units: bool, target_tolerance_m: float, units: str | None
) -> MeasurementRecords:
    targets: list[float] = []
    dirs: list[str] = []
    runs: list[int] = []
    actuals: list[float] = []
    lines: list[int] = []
    with path.open(newline="", encoding="utf-8-sig") as fh:
        reader = csv.reader(fh)
        header: list[str] | None = None
        header_line = 1
        for row in reader:
            if not _skip_row(row):
                header = [c.strip() for c in row]
                header_line = reader.line_num
                break
        if header is None:
            raise Iso230InputError(
                "no header row; expected columns " + ", ".join(REQUIRED_COLUMNS),
                source=src,
                line=max(reader.line_num, 1),
            )
        # The length columns: target_m or target_mm, actual_m or actual_mm.
        names: dict[str, str] = {}
        scale: dict[str, float] = {}
        for name in REQUIRED_COLUMNS:
            base = name.removesuffix("_m")
            present = (
                [f"{base}_{u}" for u in LENGTH_UNITS if f"{base}_{u}" in header]
                if base != name
                else ([name] if name in header else [])
            )
            if not present:
                also = " (lengths may be in mm: target_mm, actual_mm)" if base != name else ""
                raise Iso230InputError(
                    f"missing required column (header has: {', '.join(header)}){also}",
                    source=src,
                    line=header_line,
                    column=name,
                )
            if len(present) > 1:
                raise Iso230InputError(
                    f"both {' and '.join(present)} in the header; give one",
                    source=src,
                    line=header_line,
                    column=name,
                )
            names[name] = present[0]
            if base != name:
                unit = units if units is not None else present[0].rsplit("_", 1)[1]
                scale[name] = LENGTH_UNITS[unit]
        index: dict[str, int] = {}
        for name, col in names.items():
            if header.count(col) > 1:
                raise Iso230InputError(
                    "column appears more than once in the header",
                    source=src,
                    line=header_line,
                    column=col,
                )
            index[name] = header.index(col)
        length_cols = (names["target_m"], names["actual_m"])

        for row in reader:
            if _skip_row(row):
                continue
            ln = reader.line_num

            def fail(column: str, message: str, ln: int = ln) -> Iso230InputError:
                return Iso230InputError(message, source=src, line=ln, column=column)

            if len(row) > len(header) and any(c.strip() for c in row[len(header) :]):
                raise Iso230InputError(
                    f"row has {len(row)} fields but the header has {len(header)}",
                    source=src,
                    line=ln,
                )

            def cell(name: str, row: list[str] = row) -> str:
                j = index[name]
                value = row[j].strip() if j < len(row) else ""
                if not value:
                    raise fail(names[name], "empty value")
                return value

            t = _parse_float(cell("target_m"), names["target_m"], fail) * scale["target_m"]
            d_raw = cell("direction")
            d = _parse_direction(d_raw)
            if d is None:
                raise fail("direction", f"unknown direction {d_raw!r}; use '+' or '-'")
            r = _parse_int(cell("run"), fail)
            a = _parse_float(cell("actual_m"), names["actual_m"], fail) * scale["actual_m"]
            if check_units:
                _check_units(t, a, fail, length_cols)
            targets.append(t)
            dirs.append(d)
            runs.append(r)
            actuals.append(a)
            lines.append(ln)

    if not targets:
        raise Iso230InputError(
            "no data rows after the header", source=src, line=header_line, column=None
        )
    if check_units and units is None and length_cols == ("target_m", "actual_m"):
        _check_target_spacing(
            targets,
            lambda message: Iso230InputError(
                message, source=src, line=header_line, column="target_m"
            ),
        )
    line_arr = np.array(lines, dtype=np.int64)

    def locate(i: int) -> dict[str, Any]:
        return {"source": src, "line": int(line_arr[i])}

    # Validate the grouping (runs per target and direction, duplicates) with line numbers.
    _group_records(
        targets,
        dirs,
        runs,
        actuals,
        locate=locate,
        target_tolerance_m=target_tolerance_m,
        check_units=False,
    )
    t_arr = _readonly(targets)
    a_arr = _readonly(actuals)
    d_arr = np.array(dirs, dtype=np.str_)
    r_arr = np.array(runs, dtype=np.int64)
    for arr in (d_arr, r_arr, line_arr):
        arr.flags.writeable = False
    return MeasurementRecords(
        target_m=t_arr, direction=d_arr, run=r_arr, actual_m=a_arr, source=src, line=line_arr
    )


def _parse_float(text: str, column: str, fail: Callable[[str, str], Iso230InputError]) -> float:
    try:
        value = float(text)
    except ValueError:
        raise fail(column, f"cannot parse {text!r} as a number") from None
    if not math.isfinite(value):
        raise fail(column, f"value {text!r} is not a finite number (NaN/inf)")
    return value


def _parse_int(text: str, fail: Callable[[str, str], Iso230InputError]) -> int:
    try:
        return int(text)
    except ValueError:
        pass
    try:
        value = float(text)
    except ValueError:
        raise fail("run", f"cannot parse {text!r} as an integer run number") from None
    if not (math.isfinite(value) and value == math.floor(value)):
        raise fail("run", f"run number {text!r} is not an integer")
    return int(value)


def write_measurement_csv(
    path: str | Path,
    target_m: npt.ArrayLike,
    direction: Sequence[str] | npt.ArrayLike,
    run: npt.ArrayLike,
    actual_m: npt.ArrayLike,
) -> Path:
    """Write flat measurement records as a CSV file readable by :func:`read_measurement_csv`.

    Floats are written with ``repr`` so that reading the file back gives the same values
    bit for bit.

    Parameters
    ----------
    path : str or Path
        Output file; its parent directory must exist.
    target_m, direction, run, actual_m
        As in :func:`evaluate_records` (metres, ``'+'``/``'-'``, integers, metres).

    Returns
    -------
    Path
        ``path``.
    """
    t = np.asarray(target_m, dtype=np.float64).reshape(-1)
    d = [str(v) for v in np.asarray(direction).reshape(-1)]
    r = np.asarray(run).reshape(-1)
    a = np.asarray(actual_m, dtype=np.float64).reshape(-1)
    if not (t.shape[0] == len(d) == r.shape[0] == a.shape[0]):
        raise Iso230InputError("record arrays differ in length")
    out = Path(path)
    with out.open("w", newline="", encoding="utf-8") as fh:
        writer = csv.writer(fh, lineterminator="\n")
        writer.writerow(REQUIRED_COLUMNS)
        for i in range(t.shape[0]):
            writer.writerow([repr(float(t[i])), d[i], str(int(r[i])), repr(float(a[i]))])
    return out


# --------------------------------------------------------------------------------------------
# Plot and report
# --------------------------------------------------------------------------------------------


def _draw(result: Iso230Result, ax: Axes, title: str | None) -> None:
    k = result.coverage_factor
    x = result.targets_m * _MM_PER_M
    um = _UM_PER_M
    series: list[tuple[str, str, FloatArray, FloatArray]] = [
        ("C0", r"\uparrow", result.mean_deviation_up_m, result.std_up_m)
    ]
    if result.mean_deviation_down_m is not None and result.std_down_m is not None:
        series.append(("C3", r"\downarrow", result.mean_deviation_down_m, result.std_down_m))
    for color, arrow, mean, std in series:
        ax.fill_between(
            x,
            (mean - k * std) * um,
            (mean + k * std) * um,
            color=color,
            alpha=0.15,
            linewidth=0,
            label=rf"$\bar{{x}}_i{arrow} \pm {k:g}\,s_i{arrow}$",
        )
        ax.plot(x, (mean + k * std) * um, color=color, linewidth=0.8, linestyle="--")
        ax.plot(x, (mean - k * std) * um, color=color, linewidth=0.8, linestyle="--")
        ax.errorbar(
            x,
            mean * um,
            yerr=k * std * um,
            color=color,
            marker="o",
            markersize=4,
            capsize=3,
            linewidth=1.5,
            label=rf"$\bar{{x}}_i{arrow}$",
        )
    if result.mean_bidirectional_deviation_m is not None:
        ax.plot(
            x,
            result.mean_bidirectional_deviation_m * um,
            color="k",
            linestyle=":",
            marker=".",
            linewidth=1.2,
            label=r"$\bar{x}_i$",
        )
    ax.axhline(0.0, color="0.6", linewidth=0.6)
    ax.set_xlabel("Target position [mm]")
    ax.set_ylabel("Positional deviation [µm]")
    ax.grid(True, linewidth=0.4, alpha=0.6)
    ax.legend(loc="best", fontsize="small")
    keys: tuple[str, ...]
    names: tuple[str, ...]
    if result.bidirectional:
        keys = ("systematic_deviation_m", "repeatability_m", "accuracy_m", "reversal_m")
        names = ("E", "R", "A", "B")
    else:
        keys = ("systematic_deviation_up_m", "repeatability_up_m", "accuracy_up_m")
        names = (r"E$\uparrow$", r"R$\uparrow$", r"A$\uparrow$")
    values = result.axis_parameters()
    text = "\n".join(f"{n} = {_fmt_um(values[key])} µm" for n, key in zip(names, keys, strict=True))
    ax.text(
        0.01,
        0.02,
        text,
        transform=ax.transAxes,
        fontsize="small",
        va="bottom",
        ha="left",
        bbox={"boxstyle": "round", "facecolor": "white", "alpha": 0.8, "edgecolor": "0.7"},
    )
    ax.set_title(title or f"ISO 230-2 positional deviations (k = {k:g})")


def plot(
    result: Iso230Result,
    path: str | Path | None = None,
    *,
    ax: Axes | None = None,
    title: str | None = None,
    dpi: float = 150.0,
) -> Axes:
    """Draw the standard ISO 230-2 plot: mean deviations vs target with ±k·s bands.

    Shows :math:`\\bar x_i↑`, :math:`\\bar x_i↓` (with error bars and shaded bands of
    ±k·sᵢ per target and direction) and :math:`\\bar x_i` against the target position
    [mm], deviations in µm, plus a box with E, R, A (and B). matplotlib is imported here,
    not at module import; a new figure uses the Agg canvas directly (no pyplot, no global
    backend change).

    Parameters
    ----------
    result : Iso230Result
        The evaluation to plot.
    path : str or Path, optional
        If given, save the figure there (PNG at ``dpi``).
    ax : matplotlib.axes.Axes, optional
        Draw into this axes instead of a new figure.
    title : str, optional
        Axes title; a default naming k is used otherwise.
    dpi : float, default 150
        Resolution of the saved file [dots per inch].

    Returns
    -------
    matplotlib.axes.Axes
        The axes drawn into.

    Raises
    ------
    ImportError
        If matplotlib is not installed.
    """
    import matplotlib  # noqa: F401  (raises ImportError early if matplotlib is missing)
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    if ax is None:
        fig = Figure(figsize=(8.0, 5.0), layout="constrained")
        FigureCanvasAgg(fig)
        ax = fig.add_subplot()
    _draw(result, ax, title)
    if path is not None:
        root = ax.figure
        if not isinstance(root, Figure):  # a SubFigure: save its top-level figure
            root = root.figure
        root.savefig(Path(path), dpi=dpi)
    return ax


@dataclass(frozen=True, slots=True, kw_only=True)
class ReportFiles:
    """Paths written by :func:`write_report`.

    Attributes
    ----------
    json : Path
        ``iso230_2.json`` (the :meth:`Iso230Result.to_dict` data plus title/conditions).
    markdown : Path
        ``iso230_2.md``.
    png : Path or None
        ``iso230_2.png``, or ``None`` when matplotlib is not installed.
    """

    json: Path
    markdown: Path
    png: Path | None


def _md_escape(text: str) -> str:
    return text.replace("|", "\\|").replace("\n", " ")


def _deviation_table(rows: Sequence[FloatArray], targets_m: FloatArray) -> str:
    n_max = max(r.shape[0] for r in rows)
    head = ["i", "Target [mm]"] + [f"j = {j + 1} [µm]" for j in range(n_max)]
    lines = ["| " + " | ".join(head) + " |", "| " + " | ".join(["---:"] * len(head)) + " |"]
    for i, r in enumerate(rows):
        cells = [str(i + 1), _fmt_mm(float(targets_m[i]))]
        cells += [_fmt_um(float(v)) for v in r] + [""] * (n_max - r.shape[0])
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def write_report(
    result: Iso230Result,
    out_dir: str | Path,
    *,
    title: str = "ISO 230-2 positioning test",
    conditions: Mapping[str, str] | None = None,
) -> ReportFiles:
    """Write the ISO 230-2 report files into a directory.

    Writes ``iso230_2.json`` (SI units), ``iso230_2.md`` (parameter table, per-target
    table and the raw deviations; targets in mm, other values in µm) and ``iso230_2.png``
    (see :func:`plot`). If matplotlib is not installed the PNG is skipped and the markdown
    says so in a warning line.

    Parameters
    ----------
    result : Iso230Result
        The evaluation to report.
    out_dir : str or Path
        Output directory; created (with parents) if needed. Existing files are replaced.
    title : str, default "ISO 230-2 positioning test"
        Report title (markdown heading, plot title, JSON ``title``).
    conditions : mapping of str to str, optional
        Test conditions to list (machine, axis, date, instrument, feed, dwell,
        temperatures, ...), as ISO 230-2 asks a report to state.

    Returns
    -------
    ReportFiles
        Paths of the files written.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    json_path = out / JSON_NAME
    md_path = out / MARKDOWN_NAME
    png_path: Path | None = out / PNG_NAME

    data = {"title": title, "conditions": dict(conditions or {}), **result.to_dict()}
    json_path.write_text(json.dumps(data, indent=2, ensure_ascii=False) + "\n", encoding="utf-8")

    plot_note: str
    try:
        plot(result, png_path, title=title)
        plot_note = f"![ISO 230-2 positional deviations]({PNG_NAME})\n"
    except ImportError:
        png_path = None
        plot_note = (
            f"> **Warning:** matplotlib is not installed; the plot {PNG_NAME} was not written.\n"
        )

    k = result.coverage_factor
    n_up = sorted({int(v) for v in result.n_runs_up})
    n_down_arr = result.n_runs_down
    runs = f"{'/'.join(map(str, n_up))} (↑)"
    if n_down_arr is not None:
        runs += f", {'/'.join(str(v) for v in sorted({int(v) for v in n_down_arr}))} (↓)"
    md: list[str] = [
        f"# {_md_escape(title)}\n",
        (
            "Evaluation with the ISO 230-2 formulas (editions 1997/2006/2014), "
            f"coverage factor k = {k:g}, {result.n_targets} target position(s), "
            f"runs per target: {runs}, "
            f"{'bidirectional' if result.bidirectional else 'unidirectional (↑ only)'}. "
            "Positional deviation = actual - target. Targets in mm, all other values in µm.\n"
        ),
    ]
    if conditions:
        md.append("## Test conditions\n")
        md.append(
            "| Item | Value |\n| --- | --- |\n"
            + "".join(
                f"| {_md_escape(str(key))} | {_md_escape(str(v))} |\n"
                for key, v in conditions.items()
            )
        )
    md.append("## Axis parameters\n")
    md.append(result.summary_table_markdown())
    md.append("## Per-target results\n")
    md.append(result.per_target_table_markdown())
    md.append("## Positional deviations, positive direction (↑)\n")
    md.append(_deviation_table(result.deviations_up_m, result.targets_m))
    if result.deviations_down_m is not None:
        md.append("## Positional deviations, negative direction (↓)\n")
        md.append(_deviation_table(result.deviations_down_m, result.targets_m))
    md.append("## Plot\n")
    md.append(plot_note)
    md_path.write_text("\n".join(md), encoding="utf-8")
    return ReportFiles(json=json_path, markdown=md_path, png=png_path)


# --------------------------------------------------------------------------------------------
# Command line
# --------------------------------------------------------------------------------------------


def add_cli(
    subparsers: argparse._SubParsersAction[argparse.ArgumentParser],
) -> argparse.ArgumentParser:
    """Register the ``iso230`` subcommand.

    ``iso230 FILE.csv [--out DIR] [--coverage-factor K] [--title TEXT] [--no-unit-check]``
    reads a measurement CSV (see :func:`read_measurement_csv`), evaluates it and writes the
    report (see :func:`write_report`). The parser's default ``func`` is :func:`run_cli`, so a
    caller can dispatch with ``args.func(args)``.

    Parameters
    ----------
    subparsers
        The object returned by ``ArgumentParser.add_subparsers()``.

    Returns
    -------
    argparse.ArgumentParser
        The new subcommand parser.
    """
    p = subparsers.add_parser(
        "iso230",
        help="evaluate a positioning test with ISO 230-2 and write a report",
        description=(
            "Evaluate a positioning test (CSV with columns target_m, direction, run, "
            "actual_m; metres) with the ISO 230-2 formulas and write iso230_2.json, "
            "iso230_2.md and iso230_2.png."
        ),
    )
    p.add_argument("file", metavar="FILE.csv", type=Path, help="measurement CSV file")
    p.add_argument(
        "--out",
        metavar="DIR",
        type=Path,
        default=None,
        help="output directory (default: FILE_iso230_2 next to FILE.csv)",
    )
    p.add_argument(
        "--coverage-factor",
        metavar="K",
        type=float,
        default=2.0,
        help="coverage factor k; repeatability = 2k*s (default: 2)",
    )
    p.add_argument("--title", default=None, help="report title (default: from the file name)")
    p.add_argument(
        "--units",
        choices=sorted(LENGTH_UNITS),
        default=None,
        help="unit of the length columns whatever their names say (default: from the "
        "names: target_m/actual_m in metres, target_mm/actual_mm in millimetres)",
    )
    p.add_argument(
        "--no-unit-check",
        action="store_true",
        help="do not reject values that look like millimetres",
    )
    p.set_defaults(func=run_cli)
    return p


def run_cli(args: argparse.Namespace) -> int:
    """Run the ``iso230`` subcommand parsed by the parser from :func:`add_cli`.

    Prints the axis parameter table and the written paths to stdout. The output folder is
    checked before the file is read and written whole or not at all
    (:func:`nanostage.output.staged_output`).

    Parameters
    ----------
    args : argparse.Namespace
        With ``file``, ``out``, ``coverage_factor`` and optionally ``title``, ``units`` and
        ``no_unit_check``.

    Returns
    -------
    int
        Exit status: 0 on success, 2 on invalid input data, a file that cannot be read or
        an output folder that cannot be used (one line on stderr).
    """
    from .output import OutputError, check_output_dir, staged_output

    path = Path(args.file)
    out = Path(args.out) if args.out is not None else path.with_name(f"{path.stem}_iso230_2")
    title = getattr(args, "title", None) or f"ISO 230-2 positioning test: {path.name}"
    try:
        check_output_dir(out)
        records = read_measurement_csv(
            path,
            check_units=not getattr(args, "no_unit_check", False),
            units=getattr(args, "units", None),
        )
        result = records.evaluate(coverage_factor=args.coverage_factor)
        with staged_output(out, "iso230") as folder:
            staged = write_report(result, folder, title=title)
    except (Iso230InputError, OutputError) as exc:
        print(f"nanostage iso230: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:
        where = f"{exc.filename}: " if exc.filename is not None else ""
        print(f"nanostage iso230: {where}{exc.strerror or exc}", file=sys.stderr)
        return 2
    print(result.summary_table_markdown(), end="")
    for f in (staged.json, staged.markdown, staged.png):
        if f is not None:
            print(f"wrote {out / f.name}")
    if staged.png is None:
        print("warning: matplotlib is not installed; no plot written", file=sys.stderr)
    return 0
