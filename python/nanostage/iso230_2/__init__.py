"""ISO 230-2 evaluation of positioning tests.

* :mod:`.evaluation`: the formulas of ISO 230-2 (per target and per axis), the result type
  :class:`Iso230Result`, flat measurement records and the input error;
* :mod:`.records`: reading and writing the measurement CSV file;
* :mod:`.report`: the plot and the report files (JSON, Markdown, PNG);
* :mod:`.cli`: the ``nanostage iso230`` command.

Only numpy is required; matplotlib is imported lazily by :func:`plot` and is optional.
"""

from __future__ import annotations

from .cli import add_cli, run_cli
from .evaluation import (
    AXIS_PARAMETERS,
    LENGTH_UNITS,
    MAX_PLAUSIBLE_DEVIATION_M,
    MAX_PLAUSIBLE_TARGET_M,
    MIN_RUNS,
    REQUIRED_COLUMNS,
    Iso230InputError,
    Iso230Result,
    MeasurementRecords,
    evaluate,
    evaluate_records,
)
from .records import read_measurement_csv, write_measurement_csv
from .report import ReportFiles, plot, write_report

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
