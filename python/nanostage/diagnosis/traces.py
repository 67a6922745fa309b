"""Read measured experiments (CSV, ``.npz``, MATLAB ``.mat``, LabVIEW ``.tdms``) as
:class:`Experiment` objects.

Every problem in a trace file is reported *before* anything is fitted, as a
:class:`TraceError` that names the file and, when it applies, the 1-based line (CSV), the
0-based sample index (``.npz``/``.mat``) and the column as it is spelled in the file.
Messages quote nothing of a file but a short, escaped list of its column names (and a
short, escaped bad cell), so a file that is not a trace is never echoed.

File formats
------------
CSV
    A header row naming the columns, then one row per sample; comma separated, UTF-8
    (optional BOM). Blank lines and lines starting with ``#`` are skipped (before or after
    the header), so metadata can be kept in comments. Line numbers in errors are physical
    line numbers of the file. Extra columns are ignored (the trace of ``nanostage
    predict``, :func:`read_prediction_trace`, rejects them instead: it has no column a
    diagnosis trace could leave unread). A file that is not
    UTF-8 is an error naming the byte offset of the first undecodable byte.
``.npz``
    One 1-D array per column (``numpy.savez``); ``(n, 1)`` and ``(1, n)`` arrays are
    accepted as 1-D.
``.mat``
    MATLAB files up to v7.2 (``scipy.io.loadmat``; v7.3 files are HDF5 and are rejected
    with a hint), one ``n × 1`` or ``1 × n`` numeric variable per column.
``.tdms``
    LabVIEW TDMS files (npTDMS, the ``tdms`` extra: ``pip install "nanostage[tdms]"``),
    one channel per column. The column map names a channel ``"Group/Channel"``, or by its
    name alone, looked up in the group given by ``group=`` or else in every group (it must
    be in exactly one). Time is a ``time_s`` channel or, without one, comes from the
    waveform properties ``wf_start_offset + k · wf_increment`` (s) of the channels read,
    which must agree. Channel lengths are checked from the metadata before any data is
    read.

Columns are the standard names of :mod:`nanostage.experiment` (SI units):
``time_s``, ``reference_m``, ``position_m`` (required) and ``command_v``,
``interferometer_m``, ``disturbance_v``, ``disturbance_n`` (optional). A *column map*
``{standard name: name in the file}`` reads files that use other names, e.g.
``{"time_s": "t", "reference_m": "qg", "position_m": "qm", "command_v": "vir"}`` for the
EMPS data set. *Column units* ``units`` read files whose lengths (``reference_m``,
``position_m``, ``interferometer_m``) or time are not in metres and seconds: ``"mm"``
for every length column, or ``{"position_m": "um", "time_s": "ms"}`` per column
(:data:`LENGTH_UNITS`, :data:`TIME_UNITS`); the values are converted to SI on reading.

Size limits (:class:`TraceLimits`)
----------------------------------
A trace may hold at most ``max_samples_per_trace`` samples (2 000 000 by default: 33 min
at 1 kHz) in a file of at most ``max_bytes_per_trace`` bytes. The file size is checked
first, then (CSV) the number of rows estimated from the newlines in 16 blocks spread over
the file, then the rows are counted while they are read, so a file above the limit is
never read whole; ``.npz``/``.mat`` arrays are sized from their headers before they are
loaded. A CSV file is parsed in blocks of rows into float arrays, so reading takes about
8 bytes per sample and column kept.

Checks (each raises :class:`TraceError`)
----------------------------------------
* unknown standard names in the column map, and mapped names the file does not have;
  unknown column units;
* missing required columns (the message lists the missing ones and the ones found);
* a file above a size limit; a file that is not UTF-8 text (CSV);
* non-numeric or empty cells, rows with too many fields (file, line, column);
* NaN or infinite values (first offending line or sample, and column);
* unequal column lengths (``.npz``/``.mat``), non-1-D arrays;
* time not strictly increasing (the line or sample where it first fails);
* a gap (or jitter) in time: a step more than :data:`MAX_STEP_DEVIATION` (50 %) away from
  the median step. The simulation takes one sample per controller period, so a missing
  stretch of samples would silently shift everything after it;
* fewer than :data:`MIN_SAMPLES` samples;
* a reference that never moves (peak-to-peak 0), unless a known disturbance column
  (``disturbance_v``, ``disturbance_n``) drives the experiment (an open-loop or
  disturbance test);
* values that look like millimetres: a position-like column (reference, position,
  interferometer) with a peak-to-peak above the axis travel (``travel_m``; without one
  :data:`MAX_TRAVEL_M`), or a value farther than :data:`ABS_POSITION_TRAVELS` travels from
  the origin, or a position/reference (or interferometer/position) scale ratio of about
  1000. The message names the fix: convert, or declare the unit (``units = "mm"``);
* a time window that is empty, reversed or outside the trace.
"""

from __future__ import annotations

import csv
import dataclasses
import math
import zipfile
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from types import MappingProxyType
from typing import Any, Final

import numpy as np
import numpy.typing as npt

from .._core import ConfigError
from ..config import did_you_mean
from ..csvfile import find_utf8_error, open_csv, read_header, skip_row, too_wide
from ..experiment import OPTIONAL_COLUMNS, REQUIRED_COLUMNS, Experiment

__all__ = [
    "ABS_POSITION_TRAVELS",
    "ALL_COLUMNS",
    "LENGTH_UNITS",
    "MAX_STEP_DEVIATION",
    "MAX_TRAVEL_M",
    "MIN_SAMPLES",
    "POSITION_COLUMNS",
    "PREDICTION_COLUMNS",
    "PREDICTION_MAX_SAMPLES_TOTAL",
    "TIME_UNITS",
    "TraceError",
    "TraceLimits",
    "cut_window",
    "escaped",
    "read_prediction_trace",
    "read_trace",
    "short_names",
    "write_trace_csv",
]

FloatArray = npt.NDArray[np.float64]

#: Every standard column name, in file order.
ALL_COLUMNS: Final[tuple[str, ...]] = REQUIRED_COLUMNS + OPTIONAL_COLUMNS
#: Columns of a ``nanostage predict`` trace: time and reference (required), known
#: disturbances and a measured position to compare with (optional).
PREDICTION_COLUMNS: Final[tuple[str, ...]] = (
    "time_s",
    "reference_m",
    "disturbance_v",
    "disturbance_n",
    "position_m",
)
#: Columns that hold positions in metres (checked for millimetre mix-ups).
POSITION_COLUMNS: Final[tuple[str, ...]] = ("reference_m", "position_m", "interferometer_m")
#: Fewest samples an experiment may have.
MIN_SAMPLES: Final[int] = 10
#: A position-like column whose peak-to-peak exceeds this, m, is taken for millimetres
#: when no axis travel is given.
MAX_TRAVEL_M: Final[float] = 1.0
#: A position-like value farther than this many axis travels from the origin is taken for
#: millimetres (an encoder's zero may lie outside the travel, but not this far).
ABS_POSITION_TRAVELS: Final[float] = 10.0
#: A time step farther than this fraction of the median step from it is a gap or jitter.
MAX_STEP_DEVIATION: Final[float] = 0.5
#: Units a length column may be declared in, and their factor to metres.
LENGTH_UNITS: Final[Mapping[str, float]] = MappingProxyType(
    {"m": 1.0, "mm": 1e-3, "um": 1e-6, "µm": 1e-6, "nm": 1e-9}
)
#: Units ``time_s`` may be declared in, and their factor to seconds.
TIME_UNITS: Final[Mapping[str, float]] = MappingProxyType(
    {"s": 1.0, "ms": 1e-3, "us": 1e-6, "µs": 1e-6}
)
#: A scale ratio between two position columns inside this range is taken for mm vs m.
_MM_RATIO_RANGE: Final[tuple[float, float]] = (300.0, 3000.0)
#: Least correlation for "reference looks like millimetres" (the position must follow it).
_MM_MIN_CORRELATION: Final[float] = 0.5
#: Bytes per allowed sample of the default byte limit of a trace file.
BYTES_PER_SAMPLE_ALLOWANCE: Final[int] = 512
#: ``max_samples_total`` of ``nanostage predict`` by default: it simulates one experiment at
#: a time (about 200 bytes per sample) and holds only the inputs of the others (40 bytes).
PREDICTION_MAX_SAMPLES_TOTAL: Final[int] = 10_000_000
#: Rows parsed into floats at a time (bounds the memory of the text form of a CSV file).
_CHUNK_ROWS: Final[int] = 65_536
#: Blocks (and their size) sampled to estimate the rows of a CSV file from its newlines.
_PROBE_BLOCKS: Final[int] = 16
_PROBE_BYTES: Final[int] = 4096
#: A CSV file whose estimated rows exceed the limit by this factor is rejected unread (the
#: estimate's error is far smaller; near the limit the rows are counted instead).
_ESTIMATE_MARGIN: Final[float] = 1.5
#: The CLI option that sets each limit.
_LIMIT_OPTION: Final[Mapping[str, str]] = MappingProxyType(
    {
        "max_samples_per_trace": "--max-trace-samples",
        "max_samples_total": "--max-total-samples",
        "max_bytes_per_trace": "--max-trace-samples (512 bytes per sample)",
    }
)


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
            parts.append(f"column {escaped(column)}")
        super().__init__(f"{', '.join(parts)}: {message}")


@dataclass(frozen=True, slots=True, kw_only=True)
class TraceLimits:
    """Size limits of the trace files one command reads (docs/diagnosis.md, *Size limits*).

    Far above any real use at kHz sampling (a diagnosis of about ten experiments holds
    about 10 000 samples, the whole EMPS data set 24 841), they exist so that a wrong file
    (a log of hours, a file that is not a trace) ends with an error naming the limit
    instead of exhausting the memory.

    Attributes
    ----------
    max_samples_per_trace : int
        Most samples (rows) one trace file may hold: 2 000 000 (33 min at 1 kHz, 3.3 min
        at 10 kHz; 16 MB per column kept). A long log can be read and cut into experiments
        by windows.
    max_samples_total : int
        Most samples all the experiments of one manifest may hold together (after their
        windows): 200 000 (8 times the EMPS data set). A diagnosis holds about 27 kB per
        sample at its peak, the batched simulations of its scans and fits (measured without
        the simulation cache, which adds up to its 512 MB: 0.27 GB for 9 430 samples,
        0.81 GB for 31 930, 2.56 GB for 94 930), so the default bounds it to about 6 GB.
        ``nanostage predict`` simulates one experiment at a time and defaults to
        :data:`PREDICTION_MAX_SAMPLES_TOTAL`.
    max_bytes_per_trace : int or None
        Largest trace file, bytes; None: :data:`BYTES_PER_SAMPLE_ALLOWANCE` (512) bytes per
        allowed sample, 1.02 GB by default (a CSV row of seven columns at 17 significant
        digits takes about 170 bytes).

    Raises
    ------
    nanostage.ConfigError
        A limit that is not an integer ≥ :data:`MIN_SAMPLES` (bytes: ≥ 1).
    """

    max_samples_per_trace: int = 2_000_000
    max_samples_total: int = 200_000
    max_bytes_per_trace: int | None = None

    def __post_init__(self) -> None:
        for name in ("max_samples_per_trace", "max_samples_total", "max_bytes_per_trace"):
            v = getattr(self, name)
            if v is None and name == "max_bytes_per_trace":
                continue
            least = 1 if name == "max_bytes_per_trace" else MIN_SAMPLES
            if isinstance(v, bool) or not isinstance(v, int) or v < least:
                raise ConfigError(
                    f"TraceLimits.{name} = {v!r} is invalid: expected an integer ≥ {least}"
                )

    @property
    def bytes_per_trace(self) -> int:
        """The byte limit in force (:attr:`max_bytes_per_trace` or its default)."""
        if self.max_bytes_per_trace is not None:
            return self.max_bytes_per_trace
        return BYTES_PER_SAMPLE_ALLOWANCE * self.max_samples_per_trace

    @staticmethod
    def how_to_raise(field: str) -> str:
        """How to change the limit ``field``: the settings field and the CLI option."""
        return (
            f"raise it with TraceLimits({field}=...) (the limits= keyword of read_trace, "
            f"load_manifest and predict) or the CLI option {_LIMIT_OPTION[field]}"
        )


def escaped(name: str, width: int = 32) -> str:
    """A file's column name or cell (or a path) for a message: quoted, escaped, at most
    ``width`` characters of it."""
    text = repr(name[:width])
    return text + "…" if len(name) > width else text


def short_names(names: Sequence[str], most: int = 12) -> str:
    """Column names found in a file, for a message: each escaped and shortened
    (:func:`escaped`, unquoted when plain), at most ``most`` of them."""
    out = []
    for n in names[:most]:
        plain = n.isprintable() and len(n) <= 32 and "'" not in n and "," not in n
        out.append(n if plain and n else escaped(n))
    if len(names) > most:
        out.append(f"… ({len(names) - most} more)")
    return ", ".join(out) or "(none)"


@dataclass(frozen=True, slots=True)
class _Schema:
    """Which standard columns a reader takes: required, optional, and whether other
    columns in a file are ignored or an error."""

    required: tuple[str, ...]
    optional: tuple[str, ...]
    ignore_extra: bool

    @property
    def columns(self) -> tuple[str, ...]:
        return self.required + self.optional


def _named_arrays(schema: _Schema) -> _Schema:
    """The schema for ``.npz``/``.mat`` files: other named arrays (a MATLAB file's gains,
    say) are not columns and are left alone."""
    return dataclasses.replace(schema, ignore_extra=True)


_TRACE: Final = _Schema(REQUIRED_COLUMNS, OPTIONAL_COLUMNS, True)
_PREDICTION: Final = _Schema(("time_s", "reference_m"), PREDICTION_COLUMNS[2:], False)


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
        self.derived_time = False  # time_s from waveform properties (TDMS), in s

    def label(self, std: str) -> str:
        """``'qm' (position_m)`` for a mapped column, ``'position_m'`` otherwise."""
        fname = self.names[std]
        return repr(fname) if fname == std else f"{escaped(fname)} ({std})"

    def error(self, message: str, *, column: str | None = None, k: int | None = None) -> TraceError:
        line = None if (k is None or self.lines is None) else int(self.lines[k])
        return TraceError(
            message,
            file=self.file,
            line=line,
            column=None if column is None else self.names.get(column, column),
            sample=k,
        )


def _check_map(file: str, columns: Mapping[str, str] | None, schema: _Schema) -> dict[str, str]:
    """The column map, validated: standard name → name in the file (identity if absent)."""
    valid = schema.columns
    out = {c: c for c in valid}
    if columns is None:
        return out
    for std, fname in columns.items():
        if std not in valid:
            raise TraceError(
                f"unknown column {std!r} in the column map{did_you_mean(std, valid)}; the standard "
                f"columns are {', '.join(valid)} (the map is {{standard name: name in the "
                "file}})",
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


def _check_units(
    file: str, units: str | Mapping[str, str] | None, schema: _Schema
) -> dict[str, float]:
    """Column units, validated: standard name → factor to SI (only factors other than 1)."""
    if units is None:
        return {}
    lengths = [c for c in POSITION_COLUMNS if c in schema.columns]
    if isinstance(units, str):
        if units not in LENGTH_UNITS:
            raise TraceError(
                f"unknown length unit {units!r}{did_you_mean(units, list(LENGTH_UNITS))}; valid: "
                f"{', '.join(LENGTH_UNITS)} (applies to {', '.join(lengths)})",
                file=file,
            )
        f = LENGTH_UNITS[units]
        return {c: f for c in lengths} if f != 1.0 else {}
    out: dict[str, float] = {}
    for std, unit in units.items():
        if std == "time_s":
            table = TIME_UNITS
        elif std in lengths:
            table = LENGTH_UNITS
        else:
            valid = ["time_s", *lengths]
            raise TraceError(
                f"no unit can be declared for {std!r}{did_you_mean(std, valid)}; units apply to "
                f"{', '.join(valid)} (other columns are in the unit their name says)",
                file=file,
                column=std,
            )
        if not isinstance(unit, str) or unit not in table:
            raise TraceError(
                f"unknown unit {unit!r} for {std}{did_you_mean(str(unit), list(table))}; valid: "
                f"{', '.join(table)}",
                file=file,
                column=std,
            )
        if table[unit] != 1.0:
            out[std] = table[unit]
    return out


def _select(
    file: str,
    available: Sequence[str],
    names: dict[str, str],
    columns: Mapping[str, str] | None,
    schema: _Schema,
    line: int | None = None,
) -> dict[str, str]:
    """Standard name → file name for the columns the file has; checks the required ones
    (and, for a schema that does not ignore them, that there are no others)."""
    have = set(available)
    mapped = set(columns or {})
    for std in sorted(mapped):
        if names[std] not in have:
            raise TraceError(
                f"the column map reads {std} from {escaped(names[std])}, which the file does "
                f"not have; found: {short_names(available)}",
                file=file,
                line=line,
                column=names[std],
            )
    missing = [s for s in schema.required if names[s] not in have]
    if missing:
        wanted = [s if names[s] == s else f"{s} (mapped to {escaped(names[s])})" for s in missing]
        raise TraceError(
            f"missing required column(s) {', '.join(wanted)}; found: "
            f"{short_names(available)}; map other names with columns="
            "{standard name: name in the file}",
            file=file,
            line=line,
        )
    if not schema.ignore_extra:
        used = set(names.values())
        unknown = [a for a in available if a not in used]
        if unknown:
            raise TraceError(
                f"unknown column(s) {short_names(unknown)}"
                f"{did_you_mean(unknown[0], schema.columns)}; "
                f"valid: {', '.join(schema.columns)}",
                file=file,
                line=line,
                column=unknown[0],
            )
    return {s: names[s] for s in schema.columns if names[s] in have}


def _limit_error(file: str, what: str, limit: int, unit: str, field: str) -> TraceError:
    return TraceError(
        f"{what}, above the limit of {limit} {unit} per trace; split the file, or "
        f"{TraceLimits.how_to_raise(field)}",
        file=file,
    )


def _check_bytes(path: Path, file: str, limits: TraceLimits) -> int:
    """The file's size, checked against the byte limit."""
    size = path.stat().st_size
    cap = limits.bytes_per_trace
    if size > cap:
        raise _limit_error(file, f"the file has {size} bytes", cap, "bytes", "max_bytes_per_trace")
    return size


def _estimate_rows(path: Path, size: int) -> int | None:
    """Rows of a text file estimated from the newlines in :data:`_PROBE_BLOCKS` blocks
    spread over it; None for a small file (counted exactly while read) or one without
    newlines in the blocks."""
    if size <= _PROBE_BLOCKS * _PROBE_BYTES:
        return None
    newlines = 0
    seen = 0
    with path.open("rb") as fh:
        for i in range(_PROBE_BLOCKS):
            fh.seek(i * (size - _PROBE_BYTES) // (_PROBE_BLOCKS - 1))
            block = fh.read(_PROBE_BYTES)
            newlines += block.count(b"\n")
            seen += len(block)
    if newlines == 0:
        return None
    return int(size * newlines / seen)


def _utf8_error(path: Path, file: str) -> TraceError:
    bad = find_utf8_error(path)
    if bad is None:  # pragma: no cover - only called after a decode error
        raise AssertionError(f"{file}: a UTF-8 decode error but no undecodable byte")
    return TraceError(
        f"not UTF-8 text: the byte at offset {bad.offset} cannot be decoded; save the file as "
        "UTF-8 (plain ASCII numbers are UTF-8)",
        file=file,
        line=bad.line,
    )


def _parse_rows(
    file: str,
    rows: list[list[str]],
    lines: list[int],
    stds: list[str],
    names: dict[str, str],
    first: int,
) -> FloatArray:
    """Rows of cells → a float array; the first bad cell raises (line, column)."""
    try:
        values: FloatArray = np.array(rows, dtype=np.float64).reshape(len(rows), len(stds))
        return values
    except ValueError:
        pass
    for k, row in enumerate(rows):
        for j, cell in enumerate(row):
            try:
                float(cell)
            except ValueError:
                what = "empty cell" if not cell else f"cannot parse {escaped(cell, 20)} as a number"
                raise TraceError(
                    what, file=file, line=lines[k], column=names[stds[j]], sample=first + k
                ) from None
    raise AssertionError("unreachable: numpy rejected a table Python parses")  # pragma: no cover


def _read_csv(
    path: Path, columns: Mapping[str, str] | None, schema: _Schema, limits: TraceLimits
) -> _Table:
    file = str(path)
    names = _check_map(file, columns, schema)
    size = _check_bytes(path, file, limits)
    cap = limits.max_samples_per_trace
    estimate = _estimate_rows(path, size)
    if estimate is not None and estimate > _ESTIMATE_MARGIN * cap:
        raise _limit_error(
            file,
            f"about {estimate} rows (estimated from its {size} bytes)",
            cap,
            "samples",
            "max_samples_per_trace",
        )
    reader: Any = None
    try:
        with open_csv(path) as fh:
            reader = csv.reader(fh)
            header, header_line = read_header(reader)
            if header is None:
                raise TraceError(
                    "no header row; expected a first row naming the columns "
                    + ", ".join(schema.required),
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
            selected = _select(file, header, names, columns, schema, header_line)
            stds = list(selected)
            idx = [header.index(f) for f in selected.values()]
            width = len(header)
            blocks: list[FloatArray] = []
            line_blocks: list[npt.NDArray[np.int64]] = []
            rows: list[list[str]] = []
            lines: list[int] = []
            n = 0
            for row in reader:
                if skip_row(row):
                    continue
                if too_wide(row, width):
                    raise TraceError(
                        f"row has {len(row)} fields but the header has {width}",
                        file=file,
                        line=reader.line_num,
                    )
                rows.append([row[j].strip() if j < len(row) else "" for j in idx])
                lines.append(reader.line_num)
                if len(rows) == _CHUNK_ROWS:
                    if n + len(rows) > cap:
                        break
                    blocks.append(_parse_rows(file, rows, lines, stds, selected, n))
                    line_blocks.append(np.array(lines, dtype=np.int64))
                    n += len(rows)
                    rows, lines = [], []
            if n + len(rows) > cap:
                raise _limit_error(
                    file, f"more than {cap} rows", cap, "samples", "max_samples_per_trace"
                )
            if rows or not blocks:
                blocks.append(_parse_rows(file, rows, lines, stds, selected, n))
                line_blocks.append(np.array(lines, dtype=np.int64))
    except UnicodeDecodeError:
        raise _utf8_error(path, file) from None
    except csv.Error as exc:
        raise TraceError(
            f"not a readable CSV file ({exc})",
            file=file,
            line=None if reader is None else reader.line_num,
        ) from None
    values = blocks[0] if len(blocks) == 1 else np.concatenate(blocks)
    line_arr = line_blocks[0] if len(line_blocks) == 1 else np.concatenate(line_blocks)
    table = _Table(file, {}, selected, line_arr)
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


def _check_elements(file: str, fname: str, n: int | None, limits: TraceLimits) -> None:
    """An array's element count (from its header), checked before it is loaded."""
    cap = limits.max_samples_per_trace
    if n is not None and n > cap:
        raise TraceError(
            f"{n} values, above the limit of {cap} samples per trace; split the file, or "
            f"{TraceLimits.how_to_raise('max_samples_per_trace')}",
            file=file,
            column=fname,
        )


def _from_arrays(
    file: str,
    selected: dict[str, str],
    arrays: Mapping[str, Any],
) -> _Table:
    data = {s: _as_column(file, f, arrays[f]) for s, f in selected.items()}
    n = len(data["time_s"])
    lengths = {escaped(selected[s]): len(a) for s, a in data.items()}
    for s, a in data.items():
        if len(a) != n:
            raise TraceError(
                f"has {len(a)} samples but {escaped(selected['time_s'])} (time_s) has {n}; "
                f"lengths: {', '.join(f'{k}: {v}' for k, v in lengths.items())}",
                file=file,
                column=selected[s],
            )
    return _Table(file, data, selected, None)


def _npy_elements(zf: zipfile.ZipFile, key: str) -> int | None:
    """Elements of one array of an ``.npz`` archive, from its header (None: unknown)."""
    try:
        with zf.open(key + ".npy") as fh:
            version = np.lib.format.read_magic(fh)
            if version == (1, 0):
                shape = np.lib.format.read_array_header_1_0(fh)[0]
            elif version == (2, 0):
                shape = np.lib.format.read_array_header_2_0(fh)[0]
            else:
                return None
    except (KeyError, ValueError, OSError, zipfile.BadZipFile):
        return None
    return math.prod(shape)


def _read_npz(
    path: Path, columns: Mapping[str, str] | None, schema: _Schema, limits: TraceLimits
) -> _Table:
    file = str(path)
    names = _check_map(file, columns, schema)
    _check_bytes(path, file, limits)
    try:
        z = np.load(path, allow_pickle=False)
    except (ValueError, OSError, EOFError, zipfile.BadZipFile) as exc:
        raise TraceError(f"cannot read the .npz file: {exc}", file=file) from None
    if not isinstance(z, np.lib.npyio.NpzFile):
        raise TraceError(
            "not an .npz archive (a single array); save the columns with numpy.savez", file=file
        )
    with z:
        selected = _select(file, list(z.files), names, columns, _named_arrays(schema))
        zf = z.zip
        for f in selected.values():
            _check_elements(file, f, None if zf is None else _npy_elements(zf, f), limits)
        try:
            arrays = {f: z[f] for f in selected.values()}
        except (ValueError, OSError, EOFError, zipfile.BadZipFile) as exc:
            raise TraceError(f"cannot read the .npz file: {exc}", file=file) from None
    return _from_arrays(file, selected, arrays)


def _read_mat(
    path: Path, columns: Mapping[str, str] | None, schema: _Schema, limits: TraceLimits
) -> _Table:
    file = str(path)
    names = _check_map(file, columns, schema)
    _check_bytes(path, file, limits)
    try:
        from scipy.io import loadmat, whosmat
    except ImportError as exc:  # pragma: no cover - scipy is installed with the tests
        raise TraceError("reading .mat files needs scipy: pip install scipy", file=file) from exc
    try:
        info = whosmat(str(path))
        selected = _select(file, [v[0] for v in info], names, columns, _named_arrays(schema))
        shapes = {v[0]: v[1] for v in info}
        for f in selected.values():
            _check_elements(file, f, math.prod(shapes[f]), limits)
        raw: dict[str, Any] = loadmat(str(path), variable_names=list(selected.values()))
    except NotImplementedError:
        raise TraceError(
            "MATLAB v7.3 (HDF5) files are not supported; save with -v7 or export a CSV",
            file=file,
        ) from None
    except TraceError:
        raise
    except (ValueError, TypeError, OSError) as exc:
        raise TraceError(f"cannot read the MATLAB file: {exc}", file=file) from None
    return _from_arrays(file, selected, raw)


#: Channel properties of a LabVIEW waveform: the sample period (s) and the first time (s).
_WF_INCREMENT: Final[str] = "wf_increment"
_WF_START: Final[str] = "wf_start_offset"


def _import_tdms(file: str) -> Any:
    """npTDMS's ``TdmsFile``, or a one-line error saying how to install it."""
    try:
        from nptdms import TdmsFile
    except ImportError:
        raise TraceError(
            'reading .tdms files needs npTDMS: pip install "nanostage[tdms]"', file=file
        ) from None
    return TdmsFile


def _tdms_channel(
    file: str,
    std: str,
    fname: str | None,
    channels: Mapping[str, Sequence[str]],
    group: str | None,
) -> tuple[str, str] | None:
    """The ``(group, channel)`` a standard column is read from (None: an unmapped column
    the file does not have). ``fname`` is the mapped name (``"Group/Channel"`` or a bare
    channel name), None for an unmapped column (looked up under its standard name)."""
    name = std if fname is None else fname
    if fname is not None:
        for g, chans in channels.items():
            if name.startswith(g + "/") and name[len(g) + 1 :] in chans:
                return g, name[len(g) + 1 :]
    where = f"group {escaped(group)} does not have" if group is not None else "no group has"
    if "/" in name and fname is not None:
        g, c = name.split("/", 1)
        if g not in channels:
            raise TraceError(
                f"the column map reads {std} from group {escaped(g)}, which the file does not "
                f"have{did_you_mean(g, list(channels))}; groups: {short_names(list(channels))}",
                file=file,
                column=name,
            )
        chans = list(channels[g])
        raise TraceError(
            f"the column map reads {std} from channel {escaped(c)} of group {escaped(g)}, which "
            f"the group does not have{did_you_mean(c, chans)}; its channels: {short_names(chans)}",
            file=file,
            column=name,
        )
    found = [g for g, chans in channels.items() if (group is None or g == group) and name in chans]
    if len(found) == 1:
        return found[0], name
    if len(found) > 1:
        raise TraceError(
            f"channel {escaped(name)} ({std}) is in several groups ({short_names(found)}); name "
            f'the group: columns = {{ {std} = "{found[0]}/{name}" }}, or group = "{found[0]}"',
            file=file,
            column=name,
        )
    if fname is None:
        return None
    pool = [c for g, chans in channels.items() if group is None or g == group for c in chans]
    raise TraceError(
        f"the column map reads {std} from channel {escaped(name)}, which {where}"
        f"{did_you_mean(name, pool)}; channels: {short_names(pool)} (name a channel "
        '"Group/Channel")',
        file=file,
        column=name,
    )


def _waveform_time(
    file: str, meta: Any, selected: Mapping[str, tuple[str, str]], n: int
) -> FloatArray:
    """``time_s`` from the waveform properties of the selected channels (all must agree)."""
    props: dict[str, tuple[float, float]] = {}
    for g, c in selected.values():
        pr = meta[g][c].properties
        if _WF_INCREMENT in pr:
            props[f"{g}/{c}"] = (pr[_WF_INCREMENT], pr.get(_WF_START, 0.0))
    if not props:
        raise TraceError(
            f"no time: no time_s channel (map one with columns = {{ time_s = "
            f'"Group/Channel" }}) and no {_WF_INCREMENT} property on the channels read '
            f"({short_names([f'{g}/{c}' for g, c in selected.values()])})",
            file=file,
            column="time_s",
        )
    first, (inc, start) = next(iter(props.items()))
    for name, (inc_k, start_k) in props.items():
        if (inc_k, start_k) != (inc, start):
            raise TraceError(
                f"waveform timing {_WF_INCREMENT} = {inc_k!r} s, {_WF_START} = {start_k!r} s "
                f"differs from that of {escaped(first)} ({inc!r} s, {start!r} s); the channels "
                "of one trace must share their sampling",
                file=file,
                column=name,
            )
    try:
        inc_f, start_f = float(inc), float(start)
    except (TypeError, ValueError):
        inc_f = start_f = math.nan
    if not (math.isfinite(inc_f) and inc_f > 0.0 and math.isfinite(start_f)):
        raise TraceError(
            f"waveform timing {_WF_INCREMENT} = {inc!r}, {_WF_START} = {start!r} is invalid: "
            "expected a finite step > 0 s and a finite start",
            file=file,
            column=first,
        )
    t: FloatArray = start_f + inc_f * np.arange(n, dtype=np.float64)
    return t


def _read_tdms(
    path: Path,
    columns: Mapping[str, str] | None,
    schema: _Schema,
    limits: TraceLimits,
    group: str | None,
) -> _Table:
    """A LabVIEW TDMS file: channels found by the column map (``"Group/Channel"``, or a
    channel name looked up in ``group`` or in every group); time from a ``time_s`` channel
    or the waveform properties. Lengths are checked from the metadata before any data is
    read."""
    file = str(path)
    _check_map(file, columns, schema)
    _check_bytes(path, file, limits)
    tdms_file = _import_tdms(file)
    try:
        meta = tdms_file.read_metadata(file)
        channels = {g.name: [c.name for c in g.channels()] for g in meta.groups()}
    except (ValueError, OSError, KeyError, EOFError) as exc:
        raise TraceError(f"cannot read the TDMS file: {exc}", file=file) from None
    if group is not None and group not in channels:
        raise TraceError(
            f"no group {escaped(group)}{did_you_mean(group, list(channels))}; groups: "
            f"{short_names(list(channels))}",
            file=file,
        )
    mapped = columns or {}
    selected: dict[str, tuple[str, str]] = {}
    for std in schema.columns:
        where = _tdms_channel(file, std, mapped.get(std), channels, group)
        if where is not None:
            selected[std] = where
    missing = [s for s in schema.required if s not in selected and s != "time_s"]
    if missing:
        pool = [f"{g}/{c}" for g, chans in channels.items() for c in chans]
        raise TraceError(
            f"missing required column(s) {', '.join(missing)}; channels: {short_names(pool)}; "
            'map them with columns = {standard name = "Group/Channel"}',
            file=file,
        )
    for g, c in selected.values():
        _check_elements(file, f"{g}/{c}", len(meta[g][c]), limits)
    try:
        with tdms_file.open(file) as fh:
            arrays = {f"{g}/{c}": fh[g][c][:] for g, c in selected.values()}
    except (ValueError, OSError, KeyError, EOFError) as exc:
        raise TraceError(f"cannot read the TDMS file: {exc}", file=file) from None
    derived = "time_s" not in selected
    if derived:
        ref = selected["reference_m"]
        n = len(arrays[f"{ref[0]}/{ref[1]}"])
        arrays["time_s"] = _waveform_time(file, meta, selected, n)
    fnames = {"time_s": "time_s"} if derived else {}
    fnames.update({s: f"{g}/{c}" for s, (g, c) in selected.items()})
    table = _from_arrays(file, fnames, arrays)
    table.derived_time = derived
    return table


def _peak_to_peak(a: FloatArray) -> float:
    return float(np.max(a) - np.min(a))


def _mm_fix(column: str) -> str:
    return (
        f'convert to metres or declare the unit (units = "mm", or units = {{ {column} = "mm" }}'
        " in the manifest's [[experiment]])"
    )


def _validate(table: _Table, *, travel_m: float | None = None, needs_move: bool = True) -> None:
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
    del stacked
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
    median = float(np.median(dt))
    off = np.abs(dt - median) > MAX_STEP_DEVIATION * median
    if np.any(off):
        k = int(np.flatnonzero(off)[0]) + 1
        prev = f"line {table.lines[k - 1]}" if table.lines is not None else f"sample {k - 1}"
        raise table.error(
            f"time steps by {dt[k - 1]:.6g} s from {t[k - 1]!r} s ({prev}), "
            f"{dt[k - 1] / median:.3g} times the median step {median:.6g} s: a gap or jitter "
            f"in the sampling (allowed: ±{MAX_STEP_DEVIATION:.0%}); the simulation takes one "
            "sample per controller period: cut the trace at the gap (window_s) or resample it",
            column="time_s",
            k=k,
        )
    present = [c for c in POSITION_COLUMNS if c in data]
    travel = MAX_TRAVEL_M if travel_m is None else travel_m
    for c in present:
        p2p = _peak_to_peak(data[c])
        if p2p > travel:
            what = (
                f"exceeds {MAX_TRAVEL_M:g} m (the axes travel at most 0.5 m)"
                if travel_m is None
                else f"m exceeds the axis travel of {travel_m:g} m (model.travel_m)"
            )
            raise table.error(
                f"peak-to-peak {p2p:.6g} {what}: the column looks like millimetres; {_mm_fix(c)}",
                column=c,
            )
    for c in present:
        far = float(np.max(np.abs(data[c])))
        if far > ABS_POSITION_TRAVELS * travel:
            raise table.error(
                f"value {far:.6g} m lies more than {ABS_POSITION_TRAVELS:g} axis travels "
                f"({ABS_POSITION_TRAVELS * travel:g} m) from the origin: the column looks like "
                f"millimetres; {_mm_fix(c)}",
                column=c,
            )
    if needs_move:
        ref_p2p = _peak_to_peak(data["reference_m"])
        if ref_p2p == 0.0 and not _driven(data):
            raise table.error(
                f"the reference never moves (constant {data['reference_m'][0]!r} m); an "
                "experiment needs at least one move, or a known disturbance column "
                "(disturbance_v, disturbance_n) that drives it",
                column="reference_m",
            )
    if "position_m" in data:
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
        f"the column looks like millimetres; {_mm_fix(big)}",
        column=big,
    )


def _window_keep(
    t: FloatArray, sample_period_s: float, window_s: Sequence[float], file: str
) -> tuple[float, float]:
    """``(start_s, stop_s)`` of a window, checked against the trace's time span."""
    if len(window_s) != 2:
        raise TraceError(
            f"window_s must be (start_s, stop_s), got {tuple(window_s)!r}",
            file=file,
            column="time_s",
        )
    start, stop = float(window_s[0]), float(window_s[1])
    tol = sample_period_s
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
    return start, stop


def _few_in_window(n: int, start: float, stop: float, file: str) -> TraceError:
    return TraceError(
        f"window [{start:g}, {stop:g}) s holds {n} sample(s); an experiment needs at least "
        f"{MIN_SAMPLES}",
        file=file,
        column="time_s",
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
    start, stop = _window_keep(exp.time_s, exp.sample_period_s, window_s, file)
    out = exp.window(start, stop, name=exp.name)
    if out.n_samples < MIN_SAMPLES:
        raise _few_in_window(out.n_samples, start, stop, file)
    inputs = {c: getattr(out, c) for c in DRIVING_COLUMNS if getattr(out, c) is not None}
    if _peak_to_peak(out.reference_m) == 0.0 and not _driven(inputs):
        raise TraceError(
            f"the reference never moves inside the window [{start:g}, {stop:g}) s, and no "
            "known disturbance drives the experiment there",
            file=file,
            column="reference_m",
        )
    return out


def _read_table(
    path: str | Path,
    schema: _Schema,
    *,
    columns: Mapping[str, str] | None,
    units: str | Mapping[str, str] | None,
    travel_m: float | None,
    limits: TraceLimits | None,
    needs_move: bool,
    group: str | None = None,
) -> _Table:
    """Read, convert to SI and validate a trace file's columns."""
    p = Path(path)
    file = str(p)
    lim = limits if limits is not None else TraceLimits()
    if travel_m is not None and not (math.isfinite(travel_m) and travel_m > 0.0):
        raise TraceError(f"travel_m = {travel_m!r} is invalid: expected a length > 0 m", file=file)
    factors = _check_units(file, units, schema)
    if not p.is_file():
        raise TraceError("no such file" if not p.exists() else "not a regular file", file=file)
    suffix = p.suffix.lower()
    if group is not None and suffix != ".tdms":
        raise TraceError(
            f"group = {group!r} applies to .tdms files only (this file is {p.suffix or 'a file'} "
            "without groups)",
            file=file,
        )
    try:
        if suffix in (".csv", ".txt"):
            table = _read_csv(p, columns, schema, lim)
        elif suffix == ".npz":
            table = _read_npz(p, columns, schema, lim)
        elif suffix == ".mat":
            table = _read_mat(p, columns, schema, lim)
        elif suffix == ".tdms":
            table = _read_tdms(p, columns, schema, lim, group)
        else:
            raise TraceError(
                f"unknown trace format {p.suffix!r}; expected .csv, .npz, .mat or .tdms",
                file=file,
            )
    except OSError as exc:
        raise TraceError(f"cannot read the file ({exc.strerror or exc})", file=file) from None
    if table.derived_time and "time_s" in factors:
        raise TraceError(
            f"units declare time_s, but the time comes from the waveform property {_WF_INCREMENT},"
            " which is in seconds; leave time_s out of units (or map a time channel)",
            file=file,
            column="time_s",
        )
    for std, f in factors.items():
        if std in table.data:
            table.data[std] = table.data[std] * f
    _validate(table, travel_m=travel_m, needs_move=needs_move)
    return table


def read_trace(
    path: str | Path,
    *,
    columns: Mapping[str, str] | None = None,
    name: str | None = None,
    window_s: Sequence[float] | None = None,
    units: str | Mapping[str, str] | None = None,
    travel_m: float | None = None,
    limits: TraceLimits | None = None,
    group: str | None = None,
) -> Experiment:
    """Read and validate one experiment from a CSV, ``.npz``, ``.mat`` or ``.tdms`` file.

    Parameters
    ----------
    path : str or Path
        The trace file; the format follows the suffix (``.csv``/``.txt``, ``.npz``,
        ``.mat``, ``.tdms``).
    columns : mapping of str to str, optional
        Column map ``{standard name: name in the file}`` for files that use other names;
        unmapped columns are looked up under their standard names.
    name : str, optional
        Experiment name (default: the file stem).
    window_s : (float, float), optional
        Keep only the samples with ``start_s <= time_s < stop_s`` (time kept as is), e.g.
        to cut one long trace into experiments.
    units : str or mapping of str to str, optional
        Units of the file's columns when not SI: a length unit (:data:`LENGTH_UNITS`) for
        every length column, or ``{standard name: unit}`` (lengths, and ``time_s`` in
        :data:`TIME_UNITS`). Values are converted to metres and seconds.
    travel_m : float, optional
        The axis travel, m: a length column whose peak-to-peak exceeds it, or with a value
        beyond :data:`ABS_POSITION_TRAVELS` travels, is taken for millimetres (default:
        :data:`MAX_TRAVEL_M`).
    limits : TraceLimits, optional
        Size limits (default: ``TraceLimits()``).
    group : str, optional
        ``.tdms`` files only: the group whose channels are read under bare names (column
        map values without ``"Group/"`` and unmapped standard names); default: a channel
        name is looked up in every group and must be in exactly one.

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
    table = _read_table(
        p,
        _TRACE,
        columns=columns,
        units=units,
        travel_m=travel_m,
        limits=limits,
        needs_move=True,
        group=group,
    )
    exp = Experiment(name=name or p.stem, source=str(p), **table.data)
    if window_s is not None:
        exp = cut_window(exp, window_s)
    return exp


def read_prediction_trace(
    path: str | Path,
    *,
    columns: Mapping[str, str] | None = None,
    window_s: Sequence[float] | None = None,
    units: str | Mapping[str, str] | None = None,
    travel_m: float | None = None,
    limits: TraceLimits | None = None,
    group: str | None = None,
) -> dict[str, FloatArray]:
    """Read and validate the input trace of ``nanostage predict``.

    The columns are :data:`PREDICTION_COLUMNS`: ``time_s`` and ``reference_m`` required,
    ``disturbance_v``, ``disturbance_n`` and ``position_m`` optional; any other CSV column
    is an error (with a "did you mean"), so a misspelt disturbance is not silently left out
    (other arrays of an ``.npz``/``.mat`` file are left alone).
    Every check of :func:`read_trace` applies (format, size limits, UTF-8, cells, finite
    values, time strictly increasing and without gaps, at least :data:`MIN_SAMPLES`
    samples, millimetre checks against ``travel_m``) except that the reference may stay
    put (a hold is a valid prediction). Parameters as in :func:`read_trace`.

    Returns
    -------
    dict of str to ndarray
        Standard name → values in SI units, for the columns the file has.

    Raises
    ------
    TraceError
        Naming the file, the line or sample and the column.
    """
    p = Path(path)
    table = _read_table(
        p,
        _PREDICTION,
        columns=columns,
        units=units,
        travel_m=travel_m,
        limits=limits,
        needs_move=False,
        group=group,
    )
    data = table.data
    if window_s is not None:
        t = data["time_s"]
        period = float(np.median(np.diff(t)))
        start, stop = _window_keep(t, period, window_s, str(p))
        keep = (t >= start) & (t < stop)
        data = {k: v[keep] for k, v in data.items()}
        n = len(data["time_s"])
        if n < MIN_SAMPLES:
            raise _few_in_window(n, start, stop, str(p))
    return data


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
