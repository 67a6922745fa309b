"""Read measured experiments (CSV, ``.npz``, MATLAB ``.mat``) as :class:`Experiment` objects.

Every problem in a trace file is reported *before* anything is fitted, as a
:class:`TraceError` that names the file and, when it applies, the 1-based line (CSV), the
0-based sample index (``.npz``/``.mat``) and the column as it is spelled in the file.

File formats
------------
CSV
    A header row naming the columns, then one row per sample; comma separated, UTF-8
    (optional BOM). Blank lines and lines starting with ``#`` are skipped (before or after
    the header), so metadata can be kept in comments. Line numbers in errors are physical
    line numbers of the file. Extra columns are ignored.
``.npz``
    One 1-D array per column (``numpy.savez``); ``(n, 1)`` and ``(1, n)`` arrays are
    accepted as 1-D.
``.mat``
    MATLAB files up to v7.2 (``scipy.io.loadmat``; v7.3 files are HDF5 and are rejected
    with a hint), one ``n × 1`` or ``1 × n`` numeric variable per column.

Columns are the standard names of :mod:`nanostage.experiment` (SI units):
``time_s``, ``reference_m``, ``position_m`` (required) and ``command_v``,
``interferometer_m``, ``disturbance_v``, ``disturbance_n`` (optional). A *column map*
``{standard name: name in the file}`` reads files that use other names, e.g.
``{"time_s": "t", "reference_m": "qg", "position_m": "qm", "command_v": "vir"}`` for the
EMPS data set.

Checks (each raises :class:`TraceError`)
----------------------------------------
* unknown standard names in the column map, and mapped names the file does not have;
* missing required columns (the message lists the missing ones and the ones found);
* non-numeric or empty cells, rows with too many fields (file, line, column);
* NaN or infinite values (first offending line or sample, and column);
* unequal column lengths (``.npz``/``.mat``), non-1-D arrays;
* time not strictly increasing (the line or sample where it first fails);
* fewer than :data:`MIN_SAMPLES` samples;
* a reference that never moves (peak-to-peak 0), unless a known disturbance column
  (``disturbance_v``, ``disturbance_n``) drives the experiment (an open-loop or
  disturbance test);
* values that look like millimetres: a position-like column (reference, position,
  interferometer) with a peak-to-peak above :data:`MAX_TRAVEL_M` (the axes have at most
  0.5 m of travel), or a position/reference (or interferometer/position) scale ratio of
  about 1000;
* a time window that is empty, reversed or outside the trace.
"""

from __future__ import annotations

import csv
import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any, Final

import numpy as np
import numpy.typing as npt

from ..experiment import OPTIONAL_COLUMNS, REQUIRED_COLUMNS, Experiment

__all__ = [
    "ALL_COLUMNS",
    "MAX_TRAVEL_M",
    "MIN_SAMPLES",
    "POSITION_COLUMNS",
    "TraceError",
    "cut_window",
    "read_trace",
    "write_trace_csv",
]

FloatArray = npt.NDArray[np.float64]

#: Every standard column name, in file order.
ALL_COLUMNS: Final[tuple[str, ...]] = REQUIRED_COLUMNS + OPTIONAL_COLUMNS
#: Columns that hold positions in metres (checked for millimetre mix-ups).
POSITION_COLUMNS: Final[tuple[str, ...]] = ("reference_m", "position_m", "interferometer_m")
#: Fewest samples an experiment may have.
MIN_SAMPLES: Final[int] = 10
#: A position-like column whose peak-to-peak exceeds this, m, is taken for millimetres.
MAX_TRAVEL_M: Final[float] = 1.0
#: A scale ratio between two position columns inside this range is taken for mm vs m.
_MM_RATIO_RANGE: Final[tuple[float, float]] = (300.0, 3000.0)
#: Least correlation for "reference looks like millimetres" (the position must follow it).
_MM_MIN_CORRELATION: Final[float] = 0.5


class TraceError(ValueError):
    """A trace file that cannot be used, with the location of the problem.

    The message reads ``"<file>, line <n>, column '<name>': <reason>"`` (the parts that are
    not known are left out; ``.npz``/``.mat`` files give ``sample <i>`` instead of a line).

    Attributes
    ----------
    file : str
        The file (or the experiment's source) the problem is in.
    line : int or None
        1-based physical line number in a CSV file.
    column : str or None
        The column as it is named in the file (the mapped name when a column map is used).
    sample : int or None
        0-based sample index (``.npz``/``.mat`` files, and CSV rows).
    reason : str
        The message without the location.
    """

    def __init__(
        self,
        message: str,
        *,
        file: str,
        line: int | None = None,
        column: str | None = None,
        sample: int | None = None,
    ) -> None:
        self.reason = message
        self.file = file
        self.line = line
        self.column = column
        self.sample = sample
        parts = [file]
        if line is not None:
            parts.append(f"line {line}")
        elif sample is not None:
            parts.append(f"sample {sample}")
        if column is not None:
            parts.append(f"column {column!r}")
        super().__init__(f"{', '.join(parts)}: {message}")


class _Table:
    """Parsed columns (standard name → array) plus how to point at a sample or column."""

    def __init__(
        self,
        file: str,
        data: dict[str, FloatArray],
        names: dict[str, str],
        lines: npt.NDArray[np.int64] | None,
    ) -> None:
        self.file = file
        self.data = data
        self.names = names  # standard name -> name in the file
        self.lines = lines  # physical line of each sample (CSV) or None

    def label(self, std: str) -> str:
        """``'qm' (position_m)`` for a mapped column, ``'position_m'`` otherwise."""
        fname = self.names[std]
        return repr(fname) if fname == std else f"{fname!r} ({std})"

    def error(self, message: str, *, column: str | None = None, k: int | None = None) -> TraceError:
        line = None if (k is None or self.lines is None) else int(self.lines[k])
        return TraceError(
            message,
            file=self.file,
            line=line,
            column=None if column is None else self.names.get(column, column),
            sample=k,
        )


def _check_map(file: str, columns: Mapping[str, str] | None) -> dict[str, str]:
    """The column map, validated: standard name → name in the file (identity if absent)."""
    out = {c: c for c in ALL_COLUMNS}
    if columns is None:
        return out
    for std, fname in columns.items():
        if std not in ALL_COLUMNS:
            raise TraceError(
                f"unknown column {std!r} in the column map; the standard columns are "
                f"{', '.join(ALL_COLUMNS)} (the map is {{standard name: name in the file}})",
                file=file,
                column=std,
            )
        if not isinstance(fname, str) or not fname:
            raise TraceError(
                f"column map entry {std!r} must be a non-empty column name, got {fname!r}",
                file=file,
                column=std,
            )
        out[std] = fname
    seen: dict[str, str] = {}
    for std, fname in out.items():
        if fname in seen:
            raise TraceError(
                f"the column map reads both {seen[fname]} and {std} from this column",
                file=file,
                column=fname,
            )
        seen[fname] = std
    return out


def _select(
    file: str,
    available: Sequence[str],
    names: dict[str, str],
    columns: Mapping[str, str] | None,
    line: int | None = None,
) -> dict[str, str]:
    """Standard name → file name for the columns the file has; checks the required ones."""
    have = set(available)
    mapped = set(columns or {})
    for std in sorted(mapped):
        if names[std] not in have:
            raise TraceError(
                f"the column map reads {std} from {names[std]!r}, which the file does not "
                f"have; found: {', '.join(available) or '(none)'}",
                file=file,
                line=line,
                column=names[std],
            )
    missing = [s for s in REQUIRED_COLUMNS if names[s] not in have]
    if missing:
        wanted = [s if names[s] == s else f"{s} (mapped to {names[s]!r})" for s in missing]
        raise TraceError(
            f"missing required column(s) {', '.join(wanted)}; found: "
            f"{', '.join(available) or '(none)'}; map other names with columns="
            "{standard name: name in the file}",
            file=file,
            line=line,
        )
    return {s: names[s] for s in ALL_COLUMNS if names[s] in have}


def _skip_row(row: Sequence[str]) -> bool:
    return not any(c.strip() for c in row) or row[0].lstrip().startswith("#")


def _read_csv(path: Path, columns: Mapping[str, str] | None) -> _Table:
    file = str(path)
    names = _check_map(file, columns)
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
            raise TraceError(
                "no header row; expected a first row naming the columns "
                + ", ".join(REQUIRED_COLUMNS),
                file=file,
            )
        for j, h in enumerate(header):
            if header.index(h) != j:
                raise TraceError(
                    "column appears more than once in the header",
                    file=file,
                    line=header_line,
                    column=h,
                )
        selected = _select(file, header, names, columns, header_line)
        idx = [header.index(f) for f in selected.values()]
        rows: list[list[str]] = []
        lines: list[int] = []
        width = len(header)
        for row in reader:
            if _skip_row(row):
                continue
            if len(row) > width and any(c.strip() for c in row[width:]):
                raise TraceError(
                    f"row has {len(row)} fields but the header has {width}",
                    file=file,
                    line=reader.line_num,
                )
            rows.append([row[j].strip() if j < len(row) else "" for j in idx])
            lines.append(reader.line_num)
    line_arr = np.array(lines, dtype=np.int64)
    table = _Table(file, {}, selected, line_arr)
    stds = list(selected)
    try:
        values = np.array(rows, dtype=np.float64).reshape(len(rows), len(stds))
    except ValueError:
        values = None
    if values is None:  # locate the first bad cell
        for k, row in enumerate(rows):
            for j, cell in enumerate(row):
                try:
                    float(cell)
                except ValueError:
                    what = "empty cell" if not cell else f"cannot parse {cell!r} as a number"
                    raise table.error(what, column=stds[j], k=k) from None
        raise AssertionError(
            "unreachable: numpy rejected a table Python parses"
        )  # pragma: no cover
    table.data = {s: np.ascontiguousarray(values[:, j]) for j, s in enumerate(stds)}
    return table


def _as_column(file: str, fname: str, value: Any) -> FloatArray:
    arr = np.asarray(value)
    if arr.ndim == 2 and 1 in arr.shape:
        arr = arr.reshape(-1)
    if arr.ndim != 1:
        raise TraceError(
            f"expected a 1-D array (or n × 1 / 1 × n), got shape {arr.shape}",
            file=file,
            column=fname,
        )
    if arr.dtype.kind not in "biuf":
        raise TraceError(f"expected numbers, got dtype {arr.dtype}", file=file, column=fname)
    out: FloatArray = np.ascontiguousarray(arr, dtype=np.float64)
    return out


def _from_arrays(file: str, arrays: Mapping[str, Any], columns: Mapping[str, str] | None) -> _Table:
    names = _check_map(file, columns)
    selected = _select(file, list(arrays), names, columns)
    data = {s: _as_column(file, f, arrays[f]) for s, f in selected.items()}
    n = len(data["time_s"])
    lengths = {selected[s]: len(a) for s, a in data.items()}
    for s, a in data.items():
        if len(a) != n:
            raise TraceError(
                f"has {len(a)} samples but {selected['time_s']!r} (time_s) has {n}; "
                f"lengths: {lengths}",
                file=file,
                column=selected[s],
            )
    return _Table(file, data, selected, None)


def _read_npz(path: Path, columns: Mapping[str, str] | None) -> _Table:
    file = str(path)
    try:
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
    except ValueError as exc:  # object arrays need pickle
        raise TraceError(f"cannot read the .npz file: {exc}", file=file) from None
    return _from_arrays(file, arrays, columns)


def _read_mat(path: Path, columns: Mapping[str, str] | None) -> _Table:
    file = str(path)
    try:
        from scipy.io import loadmat
    except ImportError as exc:  # pragma: no cover - scipy is installed with the tests
        raise TraceError("reading .mat files needs scipy: pip install scipy", file=file) from exc
    try:
        raw: dict[str, Any] = loadmat(str(path))
    except NotImplementedError:
        raise TraceError(
            "MATLAB v7.3 (HDF5) files are not supported; save with -v7 or export a CSV",
            file=file,
        ) from None
    except (ValueError, TypeError, OSError) as exc:
        raise TraceError(f"cannot read the MATLAB file: {exc}", file=file) from None
    arrays = {k: v for k, v in raw.items() if not k.startswith("__")}
    return _from_arrays(file, arrays, columns)


def _peak_to_peak(a: FloatArray) -> float:
    return float(np.max(a) - np.min(a))


def _validate(table: _Table) -> None:
    data = table.data
    # NaN/inf: the first offending sample, and in it the first column in file order.
    stacked = np.column_stack(list(data.values()))
    bad = np.argwhere(~np.isfinite(stacked))
    if bad.size:
        k, j = (int(v) for v in bad[0])
        std = list(data)[j]
        raise table.error(
            f"value {stacked[k, j]!r} is not a finite number (NaN/inf)", column=std, k=k
        )
    n = len(data["time_s"])
    if n < MIN_SAMPLES:
        raise table.error(f"only {n} sample(s); an experiment needs at least {MIN_SAMPLES}")
    t = data["time_s"]
    dt = np.diff(t)
    if np.any(dt <= 0.0):
        k = int(np.flatnonzero(dt <= 0.0)[0]) + 1
        prev = f"line {table.lines[k - 1]}" if table.lines is not None else f"sample {k - 1}"
        raise table.error(
            f"time is not strictly increasing: {t[k]!r} s follows {t[k - 1]!r} s ({prev})",
            column="time_s",
            k=k,
        )
    present = [c for c in POSITION_COLUMNS if c in data]
    for c in present:
        p2p = _peak_to_peak(data[c])
        if p2p > MAX_TRAVEL_M:
            raise table.error(
                f"peak-to-peak {p2p:.6g} exceeds {MAX_TRAVEL_M:g} m (the axes travel at most "
                "0.5 m): the column looks like millimetres; convert to metres",
                column=c,
            )
    ref_p2p = _peak_to_peak(data["reference_m"])
    if ref_p2p == 0.0 and not _driven(data):
        raise table.error(
            f"the reference never moves (constant {data['reference_m'][0]!r} m); an "
            "experiment needs at least one move, or a known disturbance column "
            "(disturbance_v, disturbance_n) that drives it",
            column="reference_m",
        )
    _check_scale(table, "position_m", "reference_m")
    if "interferometer_m" in data:
        _check_scale(table, "interferometer_m", "position_m")


#: Known inputs that can drive an experiment whose reference never moves.
DRIVING_COLUMNS = ("disturbance_v", "disturbance_n")


def _driven(data: Mapping[str, Any]) -> bool:
    """Whether a known disturbance column moves (an open-loop or disturbance test)."""
    return any(c in data and _peak_to_peak(data[c]) > 0.0 for c in DRIVING_COLUMNS)


def _check_scale(table: _Table, col: str, against: str) -> None:
    """Raise if ``col`` and ``against`` differ in scale by ~1000 (mm in a metre column)."""
    a, b = table.data[col], table.data[against]
    pa, pb = _peak_to_peak(a), _peak_to_peak(b)
    if pa == 0.0 or pb == 0.0:
        return
    lo, hi = _MM_RATIO_RANGE
    ratio = pa / pb
    if lo <= ratio <= hi:
        big, small = col, against
    elif lo <= 1.0 / ratio <= hi:
        # The smaller column could simply not have moved (a stuck stage): require that it
        # follows the larger one before blaming the larger one.
        with np.errstate(invalid="ignore", divide="ignore"):
            corr = float(np.corrcoef(a, b)[0, 1])
        if not (math.isfinite(corr) and corr >= _MM_MIN_CORRELATION):
            return
        big, small = against, col
    else:
        return
    raise table.error(
        f"peak-to-peak {_peak_to_peak(table.data[big]):.6g} is {max(ratio, 1 / ratio):.0f} "
        f"times that of {table.label(small)} ({_peak_to_peak(table.data[small]):.6g}): "
        "the column looks like millimetres; convert to metres",
        column=big,
    )


def cut_window(exp: Experiment, window_s: Sequence[float]) -> Experiment:
    """The samples of ``exp`` with ``start_s <= time_s < stop_s`` (time kept as is), checked.

    Parameters
    ----------
    exp : Experiment
        A validated experiment (its ``source`` names the file in errors).
    window_s : (float, float)
        ``(start_s, stop_s)``, s.

    Returns
    -------
    Experiment
        The window, with the same name and ``source`` extended by the window.

    Raises
    ------
    TraceError
        If the window is not ``start_s < stop_s``, lies outside the trace (by more than one
        sample period), holds fewer than :data:`MIN_SAMPLES` samples, or the reference does
        not move inside it.
    """
    file = exp.source or exp.name
    if len(window_s) != 2:
        raise TraceError(
            f"window_s must be (start_s, stop_s), got {tuple(window_s)!r}",
            file=file,
            column="time_s",
        )
    start, stop = float(window_s[0]), float(window_s[1])
    t = exp.time_s
    tol = exp.sample_period_s
    if not (math.isfinite(start) and math.isfinite(stop) and start < stop):
        raise TraceError(
            f"window [{start:g}, {stop:g}) s is invalid: expected finite start_s < stop_s",
            file=file,
            column="time_s",
        )
    if start < t[0] - tol or stop > t[-1] + 1.5 * tol:
        raise TraceError(
            f"window [{start:g}, {stop:g}) s is outside the trace, which spans "
            f"[{t[0]:g}, {t[-1]:g}] s",
            file=file,
            column="time_s",
        )
    out = exp.window(start, stop, name=exp.name)
    if out.n_samples < MIN_SAMPLES:
        raise TraceError(
            f"window [{start:g}, {stop:g}) s holds {out.n_samples} sample(s); an experiment "
            f"needs at least {MIN_SAMPLES}",
            file=file,
            column="time_s",
        )
    inputs = {c: getattr(out, c) for c in DRIVING_COLUMNS if getattr(out, c) is not None}
    if _peak_to_peak(out.reference_m) == 0.0 and not _driven(inputs):
        raise TraceError(
            f"the reference never moves inside the window [{start:g}, {stop:g}) s, and no "
            "known disturbance drives the experiment there",
            file=file,
            column="reference_m",
        )
    return out


def read_trace(
    path: str | Path,
    *,
    columns: Mapping[str, str] | None = None,
    name: str | None = None,
    window_s: Sequence[float] | None = None,
) -> Experiment:
    """Read and validate one experiment from a CSV, ``.npz`` or ``.mat`` file.

    Parameters
    ----------
    path : str or Path
        The trace file; the format follows the suffix (``.csv``/``.txt``, ``.npz``,
        ``.mat``).
    columns : mapping of str to str, optional
        Column map ``{standard name: name in the file}`` for files that use other names;
        unmapped columns are looked up under their standard names.
    name : str, optional
        Experiment name (default: the file stem).
    window_s : (float, float), optional
        Keep only the samples with ``start_s <= time_s < stop_s`` (time kept as is), e.g.
        to cut one long trace into experiments.

    Returns
    -------
    Experiment
        The channels in SI units, ``source`` set to the file (and window).

    Raises
    ------
    TraceError
        For every problem listed in the module docstring; a :class:`ValueError`.

    Examples
    --------
    >>> exp = read_trace("DATA_EMPS.mat", columns={"time_s": "t", "reference_m": "qg",
    ...                  "position_m": "qm", "command_v": "vir"})  # doctest: +SKIP
    """
    p = Path(path)
    file = str(p)
    if not p.is_file():
        raise TraceError("no such file" if not p.exists() else "not a regular file", file=file)
    suffix = p.suffix.lower()
    if suffix in (".csv", ".txt"):
        table = _read_csv(p, columns)
    elif suffix == ".npz":
        table = _read_npz(p, columns)
    elif suffix == ".mat":
        table = _read_mat(p, columns)
    else:
        raise TraceError(
            f"unknown trace format {p.suffix!r}; expected .csv, .npz or .mat", file=file
        )
    _validate(table)
    exp = Experiment(name=name or p.stem, source=file, **table.data)
    if window_s is not None:
        exp = cut_window(exp, window_s)
    return exp


def write_trace_csv(exp: Experiment, path: str | Path) -> Path:
    """Write an experiment as a CSV trace that :func:`read_trace` reads back exactly.

    The header names the standard columns the experiment has; values are written with 17
    significant digits (lossless for ``float64``).

    Parameters
    ----------
    exp : Experiment
        The experiment.
    path : str or Path
        Output file (parent directories are created).

    Returns
    -------
    Path
        The written file.
    """
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    cols = [c for c in ALL_COLUMNS if getattr(exp, c) is not None]
    data = np.column_stack([np.asarray(getattr(exp, c), dtype=np.float64) for c in cols])
    np.savetxt(p, data, fmt="%.17g", delimiter=",", header=",".join(cols), comments="")
    return p
