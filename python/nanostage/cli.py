"""The ``nanostage`` command line."""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from . import iso230_2


def _reproduce(args: argparse.Namespace) -> int:
    from .paper_campaigns import CampaignSettings, write_paper_campaigns
    from .reproduce import reproduce

    campaigns = None
    if args.campaigns:
        # Checked before any work.
        try:
            campaigns = CampaignSettings(
                n_trials=args.campaign_trials,
                seed=args.campaign_seed,
                backlash_width_m=args.campaign_backlash_m,
            )
        except ValueError as exc:
            print(f"nanostage reproduce: {exc}", file=sys.stderr)
            return 2
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
    if campaigns is not None:
        res = write_paper_campaigns(
            args.out,
            campaigns,
            threads=args.threads,
            log=None if args.quiet else (lambda msg: print(msg, file=sys.stderr)),
        )
        print()
        print(res["markdown"])
        print(f"wrote {args.out}/campaigns.json and {args.out}/campaigns.md")
    return 0


def _diagnose(args: argparse.Namespace) -> int:
    from .diagnosis.manifest import ManifestError
    from .diagnosis.run import diagnose

    try:
        d = diagnose(args.manifest, args.out, progress=not args.quiet, figures=not args.no_plot)
    except (ManifestError, ValueError) as exc:
        print(f"nanostage diagnose: {exc}", file=sys.stderr)
        return 2
    r = d.report
    before, after = r["gap_before"]["total_rms_m"], r["gap_after"]["total_rms_m"]
    print(
        f"validation gap {before * 1e9:.0f} nm → {after * 1e9:.0f} nm with "
        f"{', '.join(r['selected']) or 'no effect'} (noise floor "
        f"{r['noise_floor_rms_m'] * 1e9:.0f} nm); report in {args.out}/report.md"
    )
    return 0


def _benchmark(args: argparse.Namespace) -> int:
    from .diagnosis.benchmark import run_benchmark

    s = run_benchmark(
        args.out,
        cases=args.cases,
        seed=args.seed,
        progress=not args.quiet,
        truth_check=not args.no_truth_check,
    )
    detect = (
        ""
        if s["detectable_cases"] is None
        else f" (top-1 {s['top1_detectable']:.0%} of the {s['detectable_cases']} cases the "
        "truth-started check finds detectable)"
    )
    print(
        f"top-1 {s['top1']:.0%}{detect}, false alarms {s['false_alarm_rate']:.0%}, median "
        f"shrink {s['median_shrink']:.1%}"
        + (
            ""
            if s["median_crossfit_shrink"] is None
            else f", cross-fitted {s['median_crossfit_shrink']:.1%}"
        )
        + f" (the truth's own model: {s['median_oracle_shrink']:.1%}), median "
        f"{s['median_seconds_per_case']:.0f} s per "
        f"case; wrote {args.out}/benchmark.md"
    )
    return 0


def _predict(args: argparse.Namespace) -> int:
    from .predict import PredictError, predict

    try:
        s = predict(args.manifest, args.out)
    except PredictError as exc:
        print(f"nanostage predict: {exc}", file=sys.stderr)
        return 2
    for name, e in s["experiments"].items():
        extra = (
            f", position error {e['position_relative_error']:.3%} against the measurement"
            if "position_relative_error" in e
            else ""
        )
        print(f"{name}: {e['samples']} samples → {e['file']}{extra}")
    return 0


def _emps(args: argparse.Namespace) -> int:
    from .emps_study import emps_study

    r = emps_study(args.out, mat_path=args.mat)
    rows = [
        ("authors' reported (their simulation)", r["authors_reference"]),
        ("authors' symmetric model, nanostage loop", r["authors_symmetric"]),
        ("authors' asymmetric model, nanostage loop", r["authors_asymmetric"]),
        ("output-error fit", r["output_error"]["yardstick"]),
    ]
    print("relative error ‖measured − simulated‖/‖measured‖  position  velocity  force")
    for label, y in rows:
        print(f"{label:44s} {y['position']:8.4%} {y['velocity']:8.3%} {y['force']:7.2%}")
    print(f"wrote {args.out}/emps.json")
    return 0


def _tune(args: argparse.Namespace) -> int:
    from ._core import ConfigError
    from .tune import Objective, markdown, tune_table1, write_tune_report

    try:
        overshoot = None if args.overshoot_max_um is None else args.overshoot_max_um * 1e-6
        if args.objective == "mix":
            obj = Objective.mix(
                seconds_per_micrometre=args.seconds_per_um,
                overshoot_max_m=overshoot,
                band_counts=args.band_counts,
            )
        elif args.objective == "settling":
            obj = Objective.settling(overshoot_max_m=overshoot, band_counts=args.band_counts)
        elif args.objective == "accuracy":
            obj = Objective.accuracy()
        else:
            obj = Objective.repeatability()
        steps = [s * 1e-6 for s in (args.step_um or [100.0, 500.0, 1000.0, 10000.0])]
        report = tune_table1(
            steps,
            objective=obj,
            level_spread=args.spread,
            n_trials=args.trials,
            eval_trials=args.eval_trials,
            seed=args.seed,
            popsize=args.popsize,
            maxiter=args.maxiter,
            threads=args.threads,
            progress=not args.quiet,
            log=None if args.quiet else (lambda msg: print(msg, file=sys.stderr)),
        )
    except (ConfigError, TypeError) as exc:
        print(f"nanostage tune: {exc}", file=sys.stderr)
        return 2
    files = write_tune_report(args.out, report, plot=not args.no_plot)
    print(markdown(report))
    print("wrote " + ", ".join(str(f) for f in files.values()))
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``nanostage`` command."""
    parser = argparse.ArgumentParser(prog="nanostage", description=__doc__)
    sub = parser.add_subparsers(dest="command", required=True)
    rep = sub.add_parser("reproduce", help="simulate the paper's four step experiments")
    rep.add_argument("--out", default="out", help="output directory (default: out)")
    rep.add_argument("--no-plot", action="store_true", help="skip steps.png")
    rep.add_argument(
        "--campaigns",
        action="store_true",
        help="also run the ISO 230-2 step campaigns: calibrate the stochastic friction spread "
        "on the 100 µm figure, predict 1 mm (about 30 s; campaigns.json, campaigns.md)",
    )
    rep.add_argument(
        "--campaign-trials",
        type=int,
        default=32,
        help="trials per campaign with --campaigns (default 32)",
    )
    rep.add_argument(
        "--campaign-seed", type=int, default=0, help="campaign seed with --campaigns (default 0)"
    )
    rep.add_argument(
        "--campaign-backlash-m",
        type=float,
        default=0.0,
        help="gearhead backlash width in the campaigns' model [m] (default 0: the paper's "
        "model; e.g. 5e-6)",
    )
    rep.add_argument(
        "--threads", type=int, default=None, help="threads of the campaigns (default: all cores)"
    )
    rep.add_argument("--quiet", action="store_true", help="no campaign progress on stderr")
    rep.set_defaults(func=_reproduce)
    iso230_2.add_cli(sub)
    dg = sub.add_parser(
        "diagnose", help="locate and explain the gap between a model and measured experiments"
    )
    dg.add_argument("manifest", help="TOML manifest (see docs/diagnosis.md)")
    dg.add_argument("--out", default="diagnosis", help="output directory (default: diagnosis)")
    dg.add_argument("--no-plot", action="store_true", help="skip the figures")
    dg.add_argument("--quiet", action="store_true", help="no progress on stderr")
    dg.set_defaults(func=_diagnose)
    bm = sub.add_parser(
        "diagnose-benchmark", help="blind check of the diagnosis on synthetic hidden effects"
    )
    bm.add_argument("--out", default="diagnose-benchmark", help="output directory")
    bm.add_argument("--cases", type=int, default=16, help="number of cases (default 16)")
    bm.add_argument("--seed", type=int, default=1, help="seed of the case draws (default 1)")
    bm.add_argument("--quiet", action="store_true", help="no per-case lines")
    bm.add_argument(
        "--no-truth-check",
        action="store_true",
        help="skip the truth-started check of each case (is the hidden effect detectable?)",
    )
    bm.set_defaults(func=_benchmark)
    pr = sub.add_parser("predict", help="simulate an identified model for given inputs")
    pr.add_argument("manifest", help="TOML manifest (see nanostage.predict)")
    pr.add_argument("--out", default="prediction", help="output directory")
    pr.set_defaults(func=_predict)
    em = sub.add_parser("emps", help="the EMPS real-data study (yardstick, identification)")
    em.add_argument("--out", default="emps", help="output directory")
    em.add_argument("--mat", default=None, help="DATA_EMPS.mat (default: ../shared)")
    em.set_defaults(func=_emps)
    tu = sub.add_parser(
        "tune",
        help="tune the FPGA PID off-line (robust over stochastic friction) against Table 1",
    )
    tu.add_argument(
        "--step-um",
        type=float,
        action="append",
        help="step size in µm (repeat for several; default: Table 1's 100, 500, 1000, 10000)",
    )
    tu.add_argument(
        "--objective",
        choices=["mix", "settling", "accuracy", "repeatability"],
        default="mix",
        help="mix: settling time p95 + A↑ (default); settling; accuracy (A↑); repeatability (R↑)",
    )
    tu.add_argument(
        "--seconds-per-um",
        type=float,
        default=0.1,
        help="mix: seconds of settling time that weigh as much as 1 µm of A↑ (default 0.1)",
    )
    tu.add_argument("--overshoot-max-um", type=float, default=None, help="overshoot bound, µm")
    tu.add_argument("--band-counts", type=int, default=1, help="settling band, ±counts (1)")
    tu.add_argument(
        "--spread", type=float, default=0.2, help="per-trial friction level spread (0.2)"
    )
    tu.add_argument("--trials", type=int, default=200, help="trials per candidate (200)")
    tu.add_argument(
        "--eval-trials", type=int, default=None, help="held-out trials of the comparison"
    )
    tu.add_argument("--popsize", type=int, default=5, help="population multiplier (5)")
    tu.add_argument("--maxiter", type=int, default=10, help="generations (10)")
    tu.add_argument("--seed", type=int, default=0, help="seed of the search (0)")
    tu.add_argument("--threads", type=int, default=None, help="threads (default: all cores)")
    tu.add_argument("--out", default="tune", help="output directory (default: tune)")
    tu.add_argument("--no-plot", action="store_true", help="skip pareto.png")
    tu.add_argument("--quiet", action="store_true", help="no progress on stderr")
    tu.set_defaults(func=_tune)
    args = parser.parse_args(argv)
    return int(args.func(args))


if __name__ == "__main__":
    sys.exit(main())
