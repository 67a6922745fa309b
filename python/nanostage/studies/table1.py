"""The paper's Table 1 tuning study: tune the seed axis for each step size of Table 1 and
compare the tuned gains with the paper's on held-out friction draws (``nanostage tune``).

The tuning itself is the library's (:mod:`nanostage.tune`); this module runs it over the
paper's step sizes, writes the report (JSON, markdown, Pareto figure) and formats it.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from concurrent.futures import Executor
from pathlib import Path
from typing import Any

import numpy as np

from ..config import System
from ..output import staged_output, write_json
from ..tune import (
    Objective,
    TuneResult,
    evaluate_gains,
    pareto_front,
    tune,
    tuning_cycle,
    with_friction_spread,
)
from .reproduce import GainSource, study_system

__all__ = ["markdown", "plot_pareto", "tune_table1", "write_tune_report"]


def tune_table1(
    steps_m: Sequence[float] = (100e-6, 500e-6, 1e-3, 10e-3),
    *,
    objective: Objective | None = None,
    level_spread: float = 0.2,
    n_trials: int = 200,
    eval_trials: int | None = None,
    seed: int = 0,
    popsize: int = 5,
    maxiter: int = 10,
    threads: int | None = None,
    executor: Executor | Any | None = None,
    progress: bool = True,
    log: Callable[[str], None] | None = None,
    model: System | None = None,
    gains: GainSource = "table1",
) -> dict[str, Any]:
    """Tune the seed axis for each step size and compare with the paper's Table 1 gains.

    ``model`` (a :class:`~nanostage.System`, e.g. from :func:`nanostage.load_model`):
    tune that axis instead (plant, effects, controller formats and timing, encoder, output
    stage, integrator), starting each step size from the Table 1 gains in place of the
    model's (:func:`nanostage.presets.table1_system`), or with ``gains="model"`` from the
    model's own gains, which the report then compares the tuned ones with
    (:func:`nanostage.studies.reproduce.study_system`); checked before any search. The
    report's ``gains`` names the starting gains and is the key of their figures in each
    step's row (``table1`` or ``model``, beside ``tuned``).

    The search uses campaign seed ``seed``; the comparison re-runs both gain sets on
    ``eval_trials`` (default ``n_trials``) *other* draws (campaign seed ``seed + 1``), the
    same draws for both, so the comparison is not the search's own sample.
    """
    objective = Objective.mix() if objective is None else objective
    eval_n = n_trials if eval_trials is None else eval_trials
    rows: list[dict[str, Any]] = []
    results: dict[float, TuneResult] = {}
    systems = [study_system(step, model, gains) for step in steps_m]
    for step, base in zip(steps_m, systems, strict=True):
        system = with_friction_spread(base, level_spread)
        cycle = tuning_cycle(step)
        if log:
            log(f"tuning the {step * 1e6:g} µm step ({n_trials} trials per candidate)")
        r = tune(
            system,
            cycle,
            objective=objective,
            n_trials=n_trials,
            seed=seed,
            popsize=popsize,
            maxiter=maxiter,
            threads=threads,
            executor=executor,
            progress=progress,
        )
        results[step] = r
        held = {}
        for name, c in ((gains, r.start), ("tuned", r.best)):
            held[name] = evaluate_gains(
                system,
                cycle,
                objective=objective,
                n_trials=eval_n,
                seed=seed + 1,
                kp=c.kp,
                ki=c.ki,
                kd=c.kd,
                anti_windup=c.anti_windup,
                threads=threads,
                per_trial=True,
            ).to_dict()
        rows.append(
            {
                "step_m": step,
                "search": {
                    "wall_s": r.wall_s,
                    "n_evaluations": r.n_evaluations,
                    "n_distinct": len(r.history),
                    "message": r.message,
                    "settings": r.settings,
                },
                gains: held[gains],
                "tuned": held["tuned"],
                "pareto": [c.to_dict() for c in pareto_front(r.history)],
                "history": [c.to_dict() for c in r.history],
            }
        )
    return {
        "objective": objective.to_dict(),
        "level_spread": level_spread,
        "n_trials": n_trials,
        "eval_trials": eval_n,
        "seed": seed,
        "eval_seed": seed + 1,
        "gains": gains,
        "steps": rows,
    }


def _start(report: dict[str, Any]) -> tuple[str, str]:
    """The key of the starting gains in a report's rows and their label."""
    key = str(report.get("gains", "table1"))
    return key, "Table 1" if key == "table1" else "model"


def _fmt(v: float | None, scale: float, digits: int = 1) -> str:
    return "—" if v is None else f"{v * scale:.{digits}f}"


def markdown(report: dict[str, Any]) -> str:
    """The side-by-side table of :func:`tune_table1`'s report."""
    o = report["objective"]
    terms = [
        f"{o[k]:g}·{label}"
        for k, label in (
            ("settling_weight_per_s", "settling p95 [s]"),
            ("accuracy_weight_per_m", "A↑ [m]"),
            ("repeatability_weight_per_m", "R↑ [m]"),
            ("final_error_weight_per_m", "|final error| p95 [m]"),
        )
        if o[k]
    ]
    bound = o["overshoot_max_m"]
    objective_text = " + ".join(terms) + (
        f", overshoot ≤ {bound * 1e6:g} µm" if bound is not None else ""
    )
    lines = [
        f"Objective: J = {objective_text} (settling band ±{o['band_counts']} count, "
        f"statistic {o['statistic']}, reading {o['reading']}); stochastic friction level spread "
        f"{report['level_spread']} (log-normal, per trial); search on {report['n_trials']} "
        f"trials (seed {report['seed']}), figures below on {report['eval_trials']} other "
        f"trials (seed {report['eval_seed']}), the same draws for both gain sets.",
        "",
    ]
    start, start_label = _start(report)
    # Per-trial ISO figures exist only when each trial repeats the step.
    per_trial = any(
        row[n]["accuracy_up_trial_mean_m"] is not None
        for row in report["steps"]
        for n in (start, "tuned")
    )
    lines.append(
        "| step | gains | Kp, Ki, Kd | anti-windup | settling p95 [ms] | settled [%] | "
        "overshoot p95 [µm] | final error p95 [nm] | A↑ pooled [µm] | R↑ pooled [µm] | "
        + ("A↑ per trial, mean [µm] | " if per_trial else "")
        + "objective |"
    )
    lines.append("|---" * (11 + per_trial) + "|")
    for row in report["steps"]:
        for name in (start, "tuned"):
            c = row[name]
            trial = f"| {_fmt(c['accuracy_up_trial_mean_m'], 1e6, 3)} " if per_trial else ""
            lines.append(
                f"| {row['step_m'] * 1e6:g} µm | {start_label if name == start else 'tuned'} "
                f"| {c['kp']:g}, {c['ki']:g}, {c['kd']:g} | {c['anti_windup']} "
                f"| {_fmt(c['settling_time_s'], 1e3, 0)} | {c['settled_fraction'] * 100:.0f} "
                f"| {_fmt(c['overshoot_m'], 1e6)} | {_fmt(c['final_error_m'], 1e9, 0)} "
                f"| {_fmt(c['accuracy_up_m'], 1e6, 3)} | {_fmt(c['repeatability_up_m'], 1e6, 3)} "
                f"{trial}| {c['objective']:.4g} |"
            )
    lines.append("")
    lines.append(
        "Search cost: "
        + "; ".join(
            f"{r['step_m'] * 1e6:g} µm: {r['search']['wall_s']:.0f} s, "
            f"{r['search']['n_distinct']} distinct candidates"
            for r in report["steps"]
        )
    )
    return "\n".join(lines) + "\n"


def plot_pareto(report: dict[str, Any], path: str | Path) -> None:
    """Settling time against pooled A↑ of every evaluated candidate, the Pareto front, the
    starting (Table 1 or the model's) and the tuned gains; one panel per step size."""

    from matplotlib.figure import Figure
    from matplotlib.ticker import LogFormatter

    start, start_label = _start(report)
    steps = report["steps"]
    ncol = min(2, len(steps))
    nrow = math.ceil(len(steps) / ncol)
    fig = Figure(figsize=(5.2 * ncol, 4.0 * nrow))
    axes = fig.subplots(nrow, ncol, squeeze=False)
    flat = list(axes.ravel())
    for ax in flat[len(steps) :]:
        ax.set_visible(False)
    for ax, row in zip(flat, steps, strict=False):
        pts = [
            (h["settling_time_s"], h["accuracy_up_m"])
            for h in row["history"]
            if h["settling_time_s"] is not None and h["accuracy_up_m"] is not None
        ]
        if pts:
            xs, ys = zip(*pts, strict=True)
            ax.scatter(np.array(xs) * 1e3, np.array(ys) * 1e6, s=6, c="0.7", label="evaluated")
        front = row["pareto"]
        if front:
            ax.plot(
                [c["settling_time_s"] * 1e3 for c in front],
                [c["accuracy_up_m"] * 1e6 for c in front],
                "-o",
                ms=3,
                color="C0",
                label="Pareto front (search draws)",
            )
        for name, style, label in (
            (start, "s", f"{start_label} (held-out draws)"),
            ("tuned", "*", "tuned (held-out draws)"),
        ):
            c = row[name]
            if c["settling_time_s"] is not None and c["accuracy_up_m"] is not None:
                ax.plot(
                    c["settling_time_s"] * 1e3,
                    c["accuracy_up_m"] * 1e6,
                    style,
                    ms=10,
                    label=label,
                    color="C3" if name == start else "C2",
                )
        ax.set_xscale("log")
        ax.set_yscale("log")
        ax.xaxis.set_minor_formatter(LogFormatter(labelOnlyBase=False, minor_thresholds=(2, 1)))
        ax.set_xlabel(f"settling time to ±{report['objective']['band_counts']} count, p95 [ms]")
        ax.set_ylabel("A↑, trials pooled [µm]")
        ax.set_title(f"{row['step_m'] * 1e6:g} µm step")
        ax.grid(True, which="both", alpha=0.3)
    flat[0].legend(fontsize=7)
    fig.suptitle(
        f"Every evaluated candidate (search draws); {start_label} and tuned on held-out draws"
    )
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def write_tune_report(
    out_dir: str | Path, report: dict[str, Any], *, plot: bool = True
) -> dict[str, Path]:
    """Write ``tune.json``, ``tune.md`` and (with matplotlib) ``pareto.png`` to ``out_dir``.

    The folder is written whole or not at all (:func:`nanostage.output.staged_output`): it
    must be new, empty or an earlier run's folder. Returns the paths in ``out_dir``.
    """
    names = {"json": "tune.json", "markdown": "tune.md"}
    if plot:
        names["pareto"] = "pareto.png"
    with staged_output(out_dir, "tune") as folder:
        write_json(report, folder / names["json"], indent=1)
        title = "Table 1" if _start(report)[0] == "table1" else "The model's gains"
        (folder / names["markdown"]).write_text(
            f"# {title} against tuned gains\n\n" + markdown(report), encoding="utf-8"
        )
        if plot:
            plot_pareto(report, folder / names["pareto"])
    return {k: Path(out_dir) / n for k, n in names.items()}
