"""The ``nanostage`` command line.

Conventions of every command:

* exit code 0 on success; 2 on any input, option or output-folder error, with one line on
  stderr naming the file or option, the value and what is valid (no traceback;
  ``nanostage --debug COMMAND ...`` shows it); 1 on an unexpected internal error (one line,
  ``--debug`` for the traceback); 130 on Ctrl-C and 143 on SIGTERM (one line, after the
  running work has stopped and the clean-up has run);
* ``--out DIR`` is checked before any work and written whole or not at all
  (:mod:`nanostage.output`): it must be new, empty, or a folder an earlier nanostage run
  wrote, which a successful run replaces; an interrupted or failed run leaves it as it was.
"""

from __future__ import annotations

import argparse
import importlib.util
import signal
import sys
import threading
import traceback
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from pathlib import Path
from types import FrameType
from typing import Any, Final, NoReturn, cast

from . import iso230_2
from ._core import ConfigError, SimulationError, __version__
from .output import check_output_dir, staged_output

#: Exit codes.
EXIT_OK: Final = 0
EXIT_INTERNAL: Final = 1
EXIT_ERROR: Final = 2
EXIT_INTERRUPTED: Final = 130
EXIT_TERMINATED: Final = 143

#: Errors that are the user's input (the message says what is wrong): one line, exit 2.
#: ``ValueError`` covers ``ConfigError``, ``ManifestError``, ``OutputError``, the readers'
#: errors and ``UnicodeDecodeError``.
_USER_ERRORS: Final = (ValueError, OSError, SimulationError)
#: Longest error line printed [characters].
_MAX_MESSAGE: Final = 1000


class Terminated(KeyboardInterrupt):
    """SIGTERM, raised in the main thread like Ctrl-C so that the same clean-up runs
    (campaigns stopped, executor futures cancelled, staged output removed)."""


def _on_sigterm(signum: int, frame: FrameType | None) -> None:
    raise Terminated


@contextmanager
def _signals() -> Iterator[None]:
    """SIGTERM raises :class:`Terminated` while a command runs (main thread only; a SIGTERM
    the caller ignores or handles itself is left alone). The previous handler is restored."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.getsignal(signal.SIGTERM)
    install = previous in (signal.SIG_DFL, None)
    if install:
        signal.signal(signal.SIGTERM, _on_sigterm)
    try:
        yield
    finally:
        if install:
            signal.signal(signal.SIGTERM, previous)


def _log_line(msg: str) -> None:
    """A progress line on stderr in one write, so that a signal handled between the text and
    its newline (``print`` writes them separately) cannot glue the error line to it."""
    sys.stderr.write(msg + "\n")
    sys.stderr.flush()


def _one_line(text: str) -> str:
    line = " ".join(str(text).split())
    return line if len(line) <= _MAX_MESSAGE else line[: _MAX_MESSAGE - 1] + "…"


def _describe(exc: BaseException) -> str:
    """One line for an error: the exception's message, with the file of an ``OSError``."""
    if isinstance(exc, UnicodeDecodeError):
        return (
            f"input is not {exc.encoding} text: byte 0x{exc.object[exc.start]:02x} at offset "
            f"{exc.start} cannot be decoded ({exc.reason})"
        )
    if isinstance(exc, OSError) and exc.filename is not None:
        what = exc.strerror or type(exc).__name__
        other = f" -> {exc.filename2}" if exc.filename2 is not None else ""
        return f"{exc.filename}{other}: {what}"
    text = str(exc)
    return text if text else type(exc).__name__


class _Parser(argparse.ArgumentParser):
    """Usage errors on one line: ``nanostage tune: error: argument --trials: ...``."""

    def error(self, message: str) -> NoReturn:
        self.exit(EXIT_ERROR, f"{self.prog}: error: {_one_line(message)} (see --help)\n")


def _integer(text: str) -> int:
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"invalid value {text!r}: expected an integer") from None


def _number(text: str) -> float:
    try:
        return float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"invalid value {text!r}: expected a number") from None


def _wrote(out: str | Path, names: Sequence[str]) -> str:
    return "wrote " + ", ".join(str(Path(out) / n) for n in names)


# --------------------------------------------------------------------------------------------
# Commands
# --------------------------------------------------------------------------------------------


def _load_model_option(args: argparse.Namespace) -> Any:
    """The System of ``--model FILE`` (None without it), loaded and validated; a bad file is
    a :class:`~nanostage.ModelFileError` naming the file and the key."""
    if getattr(args, "model", None) is None:
        return None
    from .model_file import load_model

    return load_model(args.model)


def _preset_option(name: str, label: str) -> Any:
    """The System of the preset ``name`` given as ``label`` (the option or argument as the
    user typed it: ``--preset``, ``preset``); an unknown name is a ConfigError naming it, the
    nearest preset and every preset (:func:`nanostage.presets.check_preset_name`)."""
    from .presets import check_preset_name, preset_system

    check_preset_name(name, label)
    return preset_system(name)


def _table1_model(args: argparse.Namespace) -> Any:
    """``--model`` for the Table 1 studies: loaded, and checked to be a Table 1 axis; and
    ``--gains``, checked to go with it."""
    from .presets import table1_system
    from .studies.reproduce import study_system

    model = _load_model_option(args)
    if model is not None:
        try:
            table1_system(1e-3, model)
        except ValueError as exc:
            raise ValueError(f"--model {args.model}: {exc}") from None
    study_system(1e-3, model, args.gains)
    return model


def _reproduce(args: argparse.Namespace) -> int:
    from .studies.paper_campaigns import CampaignSettings, check_threads, write_paper_campaigns_into
    from .studies.reproduce import reproduce_into

    # Every argument and the output folder are checked before any work.
    model = _table1_model(args)
    campaigns = None
    if args.campaigns:
        campaigns = CampaignSettings(
            n_trials=args.campaign_trials,
            seed=args.campaign_seed,
            backlash_width_m=args.campaign_backlash_m,
        )
        check_threads(args.threads)
    check_output_dir(args.out)
    plot = not args.no_plot
    if plot and importlib.util.find_spec("matplotlib") is None:
        plot = False
        print(
            "warning: matplotlib is not installed; steps.png not written (pip install "
            '"nanostage[plot]" for the figures)',
            file=sys.stderr,
        )
    names = ["summary.json", "steps.png"] if plot else ["summary.json"]
    with staged_output(args.out, "reproduce") as folder:
        summary = reproduce_into(folder, plot=plot, model=model, gains=args.gains)
        print(summary["table_markdown"])
        slew = summary["slew_at_voltage_limit"]
        assert isinstance(slew, dict)
        print(
            f"\nPredicted slew speed at the {slew['voltage_v']:g} V limit: "
            f"{slew['predicted_velocity_m_per_s'] * 1e3:.2f} mm/s (force balance; see "
            "summary.json)"
        )
        print(f"compute time: {summary['compute_time_s']:.3f} s")
        if campaigns is not None:
            res = write_paper_campaigns_into(
                folder,
                campaigns,
                threads=args.threads,
                log=None if args.quiet else _log_line,
                model=model,
                gains=args.gains,
                model_name=None if model is None else f"file {args.model}",
            )
            print()
            print(res["markdown"])
            names += ["campaigns.json", "campaigns.md"]
    print(_wrote(args.out, names))
    return EXIT_OK


def _add_input_options(p: argparse.ArgumentParser) -> None:
    """Options of the commands that read a manifest's trace files (docs/diagnosis.md)."""
    p.add_argument(
        "--model",
        default=None,
        metavar="FILE",
        help="the nominal model as a model file (nanostage model export, save_model; "
        "docs/model-file.md), in place of the manifest's [model] preset or model file; the "
        "manifest's overrides and controller gains apply to it",
    )
    p.add_argument(
        "--trace-root",
        default=None,
        metavar="DIR",
        help="allow files named in the manifest to lie inside DIR (default: only inside the "
        "manifest's folder, after symbolic links)",
    )
    p.add_argument(
        "--max-trace-samples",
        type=_integer,
        default=None,
        metavar="N",
        help="most samples per trace file (default 2000000; the file-size limit is 512 "
        "bytes per sample)",
    )
    p.add_argument(
        "--max-total-samples",
        type=_integer,
        default=None,
        metavar="N",
        help="most samples of all the experiments together (default: diagnose 200000, "
        "predict 10000000)",
    )


def _trace_limits(args: argparse.Namespace, *, prediction: bool = False) -> Any:
    """The :class:`~nanostage.diagnosis.traces.TraceLimits` of the options above."""
    from .diagnosis.traces import PREDICTION_MAX_SAMPLES_TOTAL, TraceLimits

    given = {
        k: v
        for k, v in (
            ("max_samples_per_trace", args.max_trace_samples),
            ("max_samples_total", args.max_total_samples),
        )
        if v is not None
    }
    if prediction:
        given.setdefault("max_samples_total", PREDICTION_MAX_SAMPLES_TOTAL)
    return TraceLimits(**given)


#: Most worker processes ``nanostage diagnose --workers`` starts.
MAX_DIAGNOSIS_WORKERS: Final = 256


def _check_workers(workers: int | None) -> None:
    """``diagnose --workers``: None, or an integer in [1, MAX_DIAGNOSIS_WORKERS]."""
    if workers is not None and (
        isinstance(workers, bool) or not 1 <= workers <= MAX_DIAGNOSIS_WORKERS
    ):
        raise ConfigError(
            f"--workers = {workers!r} is invalid: expected an integer in "
            f"[1, {MAX_DIAGNOSIS_WORKERS}] (worker processes for the candidate fits)"
        )


@contextmanager
def _diagnosis_executor(workers: int | None, scheduler: str | None) -> Iterator[Any]:
    """The executor of ``diagnose --workers N`` (a pool of N spawned processes: a forked
    child of a process whose core has started its threads can wait for ever on a lock) or
    ``--scheduler ADDRESS`` (a Dask client of that scheduler), or None; closed after.
    ``workers`` is checked by the caller (:func:`_check_workers`) before any work."""
    if workers is not None:
        import multiprocessing
        from concurrent.futures import ProcessPoolExecutor

        with ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn")) as ex:
            yield ex
    elif scheduler is not None:
        try:
            from dask.distributed import Client
        except ImportError:
            raise ConfigError(
                f'--scheduler {scheduler!r} needs dask.distributed: pip install "nanostage[dask]"'
            ) from None
        with Client(scheduler) as client:  # type: ignore[no-untyped-call]
            yield client
    else:
        yield None


def _diagnose(args: argparse.Namespace) -> int:
    from .diagnosis.manifest import load_manifest
    from .diagnosis.run import diagnose

    _check_workers(args.workers)
    model = _load_model_option(args)
    check_output_dir(args.out)
    manifest = load_manifest(
        args.manifest, trace_root=args.trace_root, limits=_trace_limits(args), model=model
    )
    with _diagnosis_executor(args.workers, args.scheduler) as executor:
        d = diagnose(
            manifest,
            args.out,
            progress=not args.quiet,
            figures=not args.no_plot,
            executor=executor,
        )
    r = d.report
    before, after = r["gap_before"]["total_rms_m"], r["gap_after"]["total_rms_m"]
    print(
        f"validation gap {before * 1e9:.0f} nm → {after * 1e9:.0f} nm with "
        f"{', '.join(r['selected']) or 'no effect'} (noise floor "
        f"{r['noise_floor_rms_m'] * 1e9:.0f} nm); report in {Path(args.out) / 'report.md'}, "
        f"model in {Path(args.out) / 'model.toml'}"
    )
    return EXIT_OK


def _pct(v: float | None, spec: str) -> str:
    return "—" if v is None or v != v else format(v, spec)


def _benchmark(args: argparse.Namespace) -> int:
    from .diagnosis.benchmark import run_benchmark

    s = run_benchmark(
        args.out,
        cases=args.cases,
        seed=args.seed,
        progress=not args.quiet,
        truth_check=not args.no_truth_check,
        truth=args.truth,
        **({} if args.level_scatter is None else {"level_scatter": args.level_scatter}),
    )
    detect = (
        ""
        if s["detectable_cases"] is None
        else f" (top-1 {_pct(s['top1_detectable'], '.0%')} of the {s['detectable_cases']} "
        "cases the truth-started check finds detectable)"
    )
    print(
        f"top-1 {_pct(s['top1'], '.0%')}{detect}, false alarms "
        f"{_pct(s['false_alarm_rate'], '.0%')}, median shrink "
        f"{_pct(s['median_shrink'], '.1%')}"
        + (
            ""
            if s["median_crossfit_shrink"] is None
            else f", cross-fitted {_pct(s['median_crossfit_shrink'], '.1%')}"
        )
        + f" (the truth's own model: {_pct(s['median_oracle_shrink'], '.1%')}), median "
        f"{s['median_seconds_per_case']:.0f} s per "
        f"case; wrote {Path(args.out) / 'benchmark.md'}"
    )
    return EXIT_OK


def _predict(args: argparse.Namespace) -> int:
    from .diagnosis.predict import predict

    model = _load_model_option(args)
    check_output_dir(args.out)
    s = predict(
        args.manifest,
        args.out,
        trace_root=args.trace_root,
        limits=_trace_limits(args, prediction=True),
        model=model,
    )
    for name, e in s["experiments"].items():
        extra = (
            f", position error {e['position_relative_error']:.3%} against the measurement"
            if e.get("position_relative_error") is not None
            else ""
        )
        print(f"{name}: {e['samples']} samples → {e['file']}{extra}")
    return EXIT_OK


def _emps(args: argparse.Namespace) -> int:
    from .studies.emps_study import emps_study

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
    print(_wrote(args.out, ["emps.json", "model.toml"]))
    return EXIT_OK


def _iso_gap(args: argparse.Namespace) -> int:
    from .studies.iso_gap import GapSettings, write_iso_gap
    from .studies.paper_campaigns import check_threads

    # Every argument and the output folder are checked before any work.
    settings = GapSettings(n_trials=args.trials, seed=args.seed)
    check_threads(args.threads)
    check_output_dir(args.out)
    res = write_iso_gap(
        args.out, settings, threads=args.threads, log=None if args.quiet else _log_line
    )
    print(res["markdown"])
    return 0


def _iso_diagnose(args: argparse.Namespace) -> int:
    from .iso_diagnosis import IsoDiagnosisSettings, write_iso_diagnosis
    from .measurement import read_iso_measurement
    from .presets import PRESET_TRAVEL_M
    from .studies.paper_campaigns import check_threads

    # Every argument, the model and the output folder are checked before any work; the
    # measurement is read whole before the campaign runs.
    settings = IsoDiagnosisSettings(n_trials=args.trials, seed=args.seed)
    check_threads(args.threads)
    travel = None if args.travel_m is None else (args.travel_m[0], args.travel_m[1])
    if args.model is not None:
        system = _load_model_option(args)
    else:
        system = _preset_option(args.preset, "--preset")
        if travel is None:
            travel = (0.0, PRESET_TRAVEL_M[args.preset])
    check_output_dir(args.out)
    meas = read_iso_measurement(args.measurement, travel_m=travel, units=args.units)
    rep = write_iso_diagnosis(
        args.out,
        meas,
        system,
        settings,
        source=str(args.measurement),
        threads=args.threads,
        progress=not args.quiet,
        figure=not args.no_plot,
    )
    tied = ", ".join(t["candidate"] for t in rep["indistinguishable"])
    print(
        f"verdict: {rep['verdict']}"
        + (f" (indistinguishable: {tied})" if tied else "")
        + f"; ISO gap {rep['gap_before']['iso_gap']:.2f} → {rep['gap_after']['iso_gap']:.2f}, "
        f"figure gap {rep['gap_before']['figure_gap_rms_m'] * 1e6:.3f} → "
        f"{rep['gap_after']['figure_gap_rms_m'] * 1e6:.3f} µm"
    )
    if "figure_note" in rep:
        print(f"warning: {rep['figure_note']}", file=sys.stderr)
    print(_wrote(args.out, rep["files"]))
    return EXIT_OK


def _iso_diagnose_benchmark(args: argparse.Namespace) -> int:
    from .checks import int_arg
    from .iso_diagnosis_benchmark import MAX_CASES, run_iso_benchmark
    from .iso_truth import check_scale

    int_arg("cases", args.cases, 1, MAX_CASES)
    int_arg("seed", args.seed, 0, 2**32 - 1)
    check_scale(args.scale)
    check_output_dir(args.out)
    s = run_iso_benchmark(
        args.out,
        cases=args.cases,
        seed=args.seed,
        progress=not args.quiet,
        log=None if args.quiet else _log_line,
        encoder=args.encoder,
        scale=args.scale,
    )
    print(
        f"top-1 {_pct(s['top1'], '.0%')} (up to ties {_pct(s['top1_up_to_ties'], '.0%')}), "
        f"false alarms {s['false_alarms']} of {s['none_cases']}, median shrink "
        f"{_pct(s['median_shrink'], '.0%')}, median {s['median_seconds_per_case']:.1f} s per "
        f"case; wrote {Path(args.out) / 'benchmark.md'}"
    )
    return EXIT_OK


def _tune(args: argparse.Namespace) -> int:
    from .campaign import MAX_TRIALS
    from .checks import int_arg
    from .studies.paper_campaigns import check_threads
    from .studies.reproduce import study_system
    from .studies.table1 import markdown, tune_table1, write_tune_report
    from .tune import Objective, check_search, tuning_cycle, with_friction_spread

    # Every argument and the output folder are checked before any work.
    model = _table1_model(args)
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
    for step in steps:
        with_friction_spread(study_system(step, model, args.gains), args.spread)
        tuning_cycle(step)
    check_search(args.trials, args.seed, args.popsize, args.maxiter)
    if args.eval_trials is not None:
        int_arg("eval_trials", args.eval_trials, 1, MAX_TRIALS)
    check_threads(args.threads)
    check_output_dir(args.out)
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
        log=None if args.quiet else _log_line,
        model=model,
        gains=args.gains,
    )
    files = write_tune_report(args.out, report, plot=not args.no_plot)
    print(markdown(report))
    print("wrote " + ", ".join(str(f) for f in files.values()))
    return EXIT_OK


def _model_export(args: argparse.Namespace) -> int:
    """Write a preset as a model file whose provenance is the shipped file's, whole
    (:func:`nanostage.presets.preset_provenance`), naming the preset, the command and the
    version."""
    from .model_file import save_model
    from .presets import preset_provenance

    system = _preset_option(args.preset, "preset")
    out = Path(args.out)
    if out.is_dir():
        raise ValueError(f"--out {out} is a folder: expected a file name (e.g. model.toml)")
    if not out.parent.is_dir():
        raise ValueError(f"--out {out}: the folder {out.parent} does not exist")
    save_model(
        system,
        out,
        provenance={
            **preset_provenance(args.preset),
            "preset": args.preset,
            "command": f"nanostage model export {args.preset}",
            "version": __version__,
        },
    )
    print(f"wrote {out}")
    return EXIT_OK


# --------------------------------------------------------------------------------------------
# The parser and the entry point
# --------------------------------------------------------------------------------------------


_TABLE1_MODEL_HELP: Final = (
    "the axis as a model file (nanostage model export, save_model; docs/model-file.md): "
    "plant, effects, controller formats and timing, encoder, output stage and integrator "
    "are the model's; the PID gains are Table 1's for each step size (the seed preset's) "
    "unless --gains model. The model must have a rigid_axis plant and an fpga_pid "
    "controller (default: the seed preset)"
)
_GAINS_HELP: Final = (
    "the PID gains Kp, Ki, Kd of the axis: table1, the paper's Table 1 gains of each step "
    "size (default); model, the --model file's own gains at every step size (the anti-windup "
    "is the model's either way)"
)


def _add_gains_option(p: argparse.ArgumentParser, also: str = "") -> None:
    p.add_argument(
        "--gains", choices=("table1", "model"), default="table1", help=_GAINS_HELP + also
    )


def _build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="nanostage", description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--debug",
        action="store_true",
        help="show the traceback of an error (also accepted after the command)",
    )
    sub = cast(
        "argparse._SubParsersAction[argparse.ArgumentParser]",
        parser.add_subparsers(dest="command", required=True),
    )
    rep = sub.add_parser("reproduce", help="simulate the paper's four step experiments")
    rep.add_argument("--out", default="out", help="output directory (default: out)")
    rep.add_argument("--no-plot", action="store_true", help="skip steps.png")
    rep.add_argument(
        "--model", default=None, metavar="FILE", help=_TABLE1_MODEL_HELP + "; also --campaigns"
    )
    _add_gains_option(rep, "; also --campaigns")
    rep.add_argument(
        "--campaigns",
        action="store_true",
        help="also run the ISO 230-2 step campaigns: calibrate the stochastic friction spread "
        "on the 100 µm figure, predict 1 mm (about 30 s; campaigns.json, campaigns.md)",
    )
    rep.add_argument(
        "--campaign-trials",
        type=_integer,
        default=32,
        help="trials per campaign with --campaigns (default 32)",
    )
    rep.add_argument(
        "--campaign-seed",
        type=_integer,
        default=0,
        help="campaign seed with --campaigns (default 0)",
    )
    rep.add_argument(
        "--campaign-backlash-m",
        type=_number,
        default=0.0,
        help="gearhead backlash width in the campaigns' model [m] (default 0: the paper's "
        "model; e.g. 5e-6)",
    )
    rep.add_argument(
        "--threads",
        type=_integer,
        default=None,
        help="threads of the campaigns (default: all cores)",
    )
    rep.add_argument("--quiet", action="store_true", help="no campaign progress on stderr")
    rep.set_defaults(
        func=_reproduce,
        options={
            "CampaignSettings.n_trials": "--campaign-trials",
            "CampaignSettings.seed": "--campaign-seed",
            "CampaignSettings.backlash_width_m": "--campaign-backlash-m",
            "threads": "--threads",
            "gains": "--gains",
        },
    )
    iso230_2.add_cli(sub)
    dg = sub.add_parser(
        "diagnose", help="locate and explain the gap between a model and measured experiments"
    )
    dg.add_argument("manifest", help="TOML manifest (see docs/diagnosis.md)")
    dg.add_argument("--out", default="diagnosis", help="output directory (default: diagnosis)")
    dg.add_argument("--no-plot", action="store_true", help="skip the figures")
    dg.add_argument("--quiet", action="store_true", help="no progress on stderr")
    _add_input_options(dg)
    where = dg.add_mutually_exclusive_group()
    where.add_argument(
        "--workers",
        type=_integer,
        default=None,
        metavar="N",
        help="fit each round's candidates in N spawned worker processes (default: two "
        "threads in this process); the report is the same to the last bit",
    )
    where.add_argument(
        "--scheduler",
        default=None,
        metavar="ADDRESS",
        help="fit each round's candidates on a Dask cluster, e.g. tcp://host:8786 (needs "
        'pip install "nanostage[dask]"); the report is the same to the last bit',
    )
    dg.set_defaults(func=_diagnose)
    bm = sub.add_parser(
        "diagnose-benchmark", help="blind check of the diagnosis on synthetic hidden effects"
    )
    bm.add_argument("--out", default="diagnose-benchmark", help="output directory")
    bm.add_argument("--cases", type=_integer, default=16, help="number of cases (default 16)")
    bm.add_argument("--seed", type=_integer, default=1, help="seed of the case draws (default 1)")
    bm.add_argument(
        "--truth",
        choices=("own", "independent"),
        default="own",
        help="truth family of the cases: nanostage's own core and effects (own), or a "
        "simulator written without nanostage's models (independent); default own",
    )
    bm.add_argument(
        "--level-scatter",
        type=float,
        default=None,
        metavar="SIGMA",
        help="diagnose every case with this run-to-run friction level scatter (relative, "
        "1 sigma; written into each case's manifest); default: the diagnosis's default, "
        "0.01; 0: left out",
    )
    bm.add_argument("--quiet", action="store_true", help="no per-case lines")
    bm.add_argument(
        "--no-truth-check",
        action="store_true",
        help="skip the truth-started check of each case (is the hidden effect detectable?)",
    )
    bm.set_defaults(
        func=_benchmark,
        options={"cases": "--cases", "seed": "--seed", "level_scatter": "--level-scatter"},
    )
    pr = sub.add_parser("predict", help="simulate an identified model for given inputs")
    pr.add_argument("manifest", help="TOML manifest (see nanostage.diagnosis.predict)")
    pr.add_argument("--out", default="prediction", help="output directory")
    _add_input_options(pr)
    pr.set_defaults(func=_predict)
    em = sub.add_parser("emps", help="the EMPS real-data study (yardstick, identification)")
    em.add_argument("--out", default="emps", help="output directory")
    em.add_argument(
        "--mat",
        default=None,
        help="DATA_EMPS.mat (default: $NANOSTAGE_EMPS_MAT, or ../shared/data/emps beside a "
        "source checkout)",
    )
    em.set_defaults(func=_emps)
    tu = sub.add_parser(
        "tune",
        help="tune the FPGA PID off-line (robust over stochastic friction) against Table 1",
    )
    tu.add_argument(
        "--step-um",
        type=_number,
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
        type=_number,
        default=0.1,
        help="mix: seconds of settling time that weigh as much as 1 µm of A↑ (default 0.1)",
    )
    tu.add_argument("--overshoot-max-um", type=_number, default=None, help="overshoot bound, µm")
    tu.add_argument("--band-counts", type=_integer, default=1, help="settling band, ±counts (1)")
    tu.add_argument(
        "--spread", type=_number, default=0.2, help="per-trial friction level spread (0.2)"
    )
    tu.add_argument("--trials", type=_integer, default=200, help="trials per candidate (200)")
    tu.add_argument(
        "--eval-trials", type=_integer, default=None, help="held-out trials of the comparison"
    )
    tu.add_argument("--popsize", type=_integer, default=5, help="population multiplier (5)")
    tu.add_argument("--maxiter", type=_integer, default=10, help="generations (10)")
    tu.add_argument("--seed", type=_integer, default=0, help="seed of the search (0)")
    tu.add_argument("--threads", type=_integer, default=None, help="threads (default: all cores)")
    tu.add_argument("--model", default=None, metavar="FILE", help=_TABLE1_MODEL_HELP)
    _add_gains_option(tu, "; the tuning starts from them and the report compares with them")
    tu.add_argument("--out", default="tune", help="output directory (default: tune)")
    tu.add_argument("--no-plot", action="store_true", help="skip pareto.png")
    tu.add_argument("--quiet", action="store_true", help="no progress on stderr")
    tu.set_defaults(
        func=_tune,
        options={
            "step_m": "--step-um",
            "seconds_per_micrometre": "--seconds-per-um",
            "overshoot_max_m": "--overshoot-max-um",
            "band_counts": "--band-counts",
            "level_spread": "--spread",
            "stochastic.level_spread": "--spread",
            "n_trials": "--trials",
            "eval_trials": "--eval-trials",
            "popsize": "--popsize",
            "maxiter": "--maxiter",
            "seed": "--seed",
            "threads": "--threads",
            "gains": "--gains",
        },
    )
    gap = sub.add_parser(
        "iso-gap",
        help="which out-of-loop effects reproduce the paper's ISO figures (docs/iso-gap.md)",
    )
    gap.add_argument("--trials", type=_integer, default=256, help="trials per campaign (256)")
    gap.add_argument("--seed", type=_integer, default=0, help="campaign seed (0)")
    gap.add_argument("--threads", type=_integer, default=None, help="threads (default: all)")
    gap.add_argument("--out", default="iso-gap", help="output directory (default: iso-gap)")
    gap.add_argument("--quiet", action="store_true", help="no progress on stderr")
    gap.set_defaults(
        func=_iso_gap,
        options={
            "GapSettings.n_trials": "--trials",
            "GapSettings.seed": "--seed",
            "threads": "--threads",
        },
    )
    idg = sub.add_parser(
        "iso-diagnose",
        help="which out-of-loop effects explain a measured ISO 230-2 test (docs/iso-diagnosis.md)",
    )
    idg.add_argument(
        "measurement",
        help="the measured test: target_m, direction, run, actual_m (the interferometer), "
        "optional time_s, encoder_m, temperature_k",
    )
    src = idg.add_mutually_exclusive_group()
    src.add_argument("--model", default=None, metavar="FILE", help="the model as a model file")
    src.add_argument("--preset", default="seed", help="the model as a preset (default: seed)")
    idg.add_argument(
        "--travel-m",
        type=_number,
        nargs=2,
        default=None,
        metavar=("LO", "HI"),
        help="the axis's travel [m]: a target outside is an error (default: the preset's, "
        "from 0; none with --model)",
    )
    idg.add_argument(
        "--units", choices=sorted(iso230_2.LENGTH_UNITS), default=None, help="file's length unit"
    )
    idg.add_argument("--trials", type=_integer, default=16, help="trials of the campaign (16)")
    idg.add_argument("--seed", type=_integer, default=0, help="campaign seed (0)")
    idg.add_argument("--threads", type=_integer, default=None, help="threads (default: all)")
    idg.add_argument("--out", default="iso-diagnosis", help="output directory")
    idg.add_argument("--no-plot", action="store_true", help="skip diagnosis.png")
    idg.add_argument("--quiet", action="store_true", help="no progress on stderr")
    idg.set_defaults(
        func=_iso_diagnose,
        options={"n_trials": "--trials", "seed": "--seed", "threads": "--threads"},
    )
    ibm = sub.add_parser(
        "iso-diagnose-benchmark",
        help="blind check of iso-diagnose on synthetic tests with a hidden effect",
    )
    ibm.add_argument("--cases", type=_integer, default=16, help="number of cases (default 16)")
    ibm.add_argument("--seed", type=_integer, default=1, help="seed of the cases (default 1)")
    ibm.add_argument("--out", default="iso-diagnose-benchmark", help="output directory")
    ibm.add_argument(
        "--encoder",
        action="store_true",
        help="write the encoder's readings (encoder_m) in the cases' files: the chain's "
        "candidates are then fitted on the interferometer minus the encoder, the in-loop "
        "ones on the encoder",
    )
    ibm.add_argument(
        "--scale",
        type=_number,
        default=1.0,
        help="each hidden effect's error at every reading times this factor, in (0, 1] "
        "(default 1: the drawn sizes; smaller: where detection ends)",
    )
    ibm.add_argument("--quiet", action="store_true", help="no per-case lines")
    ibm.set_defaults(
        func=_iso_diagnose_benchmark,
        options={"cases": "--cases", "seed": "--seed", "scale": "--scale"},
    )
    mo = sub.add_parser("model", help="model files (docs/model-file.md)")
    mo_sub = mo.add_subparsers(dest="action", required=True)
    ex = mo_sub.add_parser("export", help="write a preset as a model file")
    ex.add_argument("preset", metavar="PRESET", help="the preset (seed, emps, ...)")
    ex.add_argument("--out", required=True, metavar="FILE", help="the model file to write")
    ex.set_defaults(func=_model_export)
    for p in [*sub.choices.values(), ex]:
        p.add_argument(
            "--debug", action="store_true", default=argparse.SUPPRESS, help=argparse.SUPPRESS
        )
    return parser


def _with_option(message: str, options: dict[str, str]) -> str:
    """Prefix the command-line option to an API message that starts with its parameter."""
    for name, option in options.items():
        if message.startswith((f"{name} ", f"{name}=")):
            return f"{option}: {message}"
    return message


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``nanostage`` command; returns the exit code (see the module
    docstring)."""
    parser = _build_parser()
    try:
        args = parser.parse_args(argv)
    except SystemExit as exc:  # --help, or a usage error already printed on one line
        return exc.code if isinstance(exc.code, int) else EXIT_ERROR
    command = f"{parser.prog} {args.command}"
    debug = bool(getattr(args, "debug", False))
    options: dict[str, str] = getattr(args, "options", {})

    def say(message: str, exc: BaseException | None = None) -> None:
        if debug and exc is not None:
            traceback.print_exception(exc)
        print(f"{command}: {_one_line(message)}", file=sys.stderr)
        sys.stderr.flush()

    try:
        with _signals():
            return int(args.func(args))
    except KeyboardInterrupt as exc:
        if isinstance(exc, Terminated):
            say("terminated (SIGTERM)", exc)
            return EXIT_TERMINATED
        say("interrupted", exc)
        return EXIT_INTERRUPTED
    except _USER_ERRORS as exc:
        say(_with_option(_describe(exc), options), exc)
        return EXIT_ERROR
    except Exception as exc:
        say(
            f"internal error: {type(exc).__name__}: {_describe(exc)} (run with --debug for "
            "the traceback)",
            exc,
        )
        return EXIT_INTERNAL


if __name__ == "__main__":
    sys.exit(main())
