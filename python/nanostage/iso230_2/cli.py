"""The ``nanostage iso230`` command: ISO 230-2 evaluation of a measurement CSV file."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from .evaluation import (
    LENGTH_UNITS,
    Iso230InputError,
)
from .records import read_measurement_csv
from .report import write_report

__all__ = ["add_cli", "run_cli"]


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
    from ..output import OutputError, check_output_dir, staged_output

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
        print(
            'warning: matplotlib is not installed; no plot written (pip install "nanostage[plot]" '
            "for the figures)",
            file=sys.stderr,
        )
    return 0
