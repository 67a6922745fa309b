"""The ``nanostage`` command line."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from . import iso230_2


def _reproduce(args: argparse.Namespace) -> int:
    from .reproduce import reproduce

    summary = reproduce(args.out, plot=not args.no_plot)
    print(summary["table_markdown"])
    slew = summary["slew_at_voltage_limit"]
    assert isinstance(slew, dict)
    print(
        f"\nPredicted slew speed at the {slew['voltage_v']:g} V limit: "
        f"{slew['predicted_velocity_m_per_s'] * 1e3:.2f} mm/s (force balance; see summary.json)"
    )
    print(
        f"compute time: {summary['compute_time_s']:.3f} s; wrote {args.out}/summary.json"
        + ("" if args.no_plot else f" and {args.out}/steps.png")
    )
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``nanostage`` command."""
    parser = argparse.ArgumentParser(prog="nanostage", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)
    rep = sub.add_parser("reproduce", help="simulate the paper's four step experiments")
    rep.add_argument("--out", default="out", help="output directory (default: out)")
    rep.add_argument("--no-plot", action="store_true", help="skip steps.png")
    rep.set_defaults(func=_reproduce)
    iso230_2.add_cli(sub)
    args = parser.parse_args(argv)
    return int(args.func(args))


if __name__ == "__main__":
    sys.exit(main())
