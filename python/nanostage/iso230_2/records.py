"""Measurement CSV files for ISO 230-2: reading with validation (file, line and column in
every error, the millimetre heuristic) and writing."""

from __future__ import annotations

import csv
import math
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import numpy.typing as npt

from ..csvfile import find_utf8_error, open_csv, read_header, skip_row, too_wide
from .evaluation import (
    LENGTH_UNITS,
    MM_HEURISTIC_INTERVAL_M,
    MM_HEURISTIC_SPAN_M,
    REQUIRED_COLUMNS,
    UNITS_FIX,
    Iso230InputError,
    MeasurementRecords,
    check_record_units,
    group_records,
    parse_direction,
    readonly,
)

__all__ = ["read_measurement_csv", "write_measurement_csv"]


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
            f"large); {UNITS_FIX}; pass --units m (units='m') if they are metres"
        )


# --------------------------------------------------------------------------------------------
# CSV input/output
# --------------------------------------------------------------------------------------------


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
        bad = find_utf8_error(Path(path))
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
    with open_csv(path) as fh:
        reader = csv.reader(fh)
        header, header_line = read_header(reader)
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
            if skip_row(row):
                continue
            ln = reader.line_num

            def fail(column: str, message: str, ln: int = ln) -> Iso230InputError:
                return Iso230InputError(message, source=src, line=ln, column=column)

            if too_wide(row, len(header)):
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
            d = parse_direction(d_raw)
            if d is None:
                raise fail("direction", f"unknown direction {d_raw!r}; use '+' or '-'")
            r = _parse_int(cell("run"), fail)
            a = _parse_float(cell("actual_m"), names["actual_m"], fail) * scale["actual_m"]
            if check_units:
                check_record_units(t, a, fail, length_cols)
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
    group_records(
        targets,
        dirs,
        runs,
        actuals,
        locate=locate,
        target_tolerance_m=target_tolerance_m,
        check_units=False,
    )
    t_arr = readonly(targets)
    a_arr = readonly(actuals)
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
