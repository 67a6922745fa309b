"""The blind check of the ISO-level diagnosis (``nanostage iso-diagnose-benchmark``).

Each case is a synthetic measured ISO test written by :mod:`nanostage.iso_truth` (its own
formulas, none of nanostage's chain or effects) with one hidden effect, out of the loop or in
it, or none;
the diagnosis reads it from its CSV file alone and is scored: top-1 (the hidden effect is
the verdict; also counted up to the candidates the report names as indistinguishable from
the verdict), false alarms (an effect named on a no-effect case), how far the figure gap
shrinks (rms over the ISO axis quantities, the model against the verdict's prediction),
the confusion matrix and the time per case. Docs: docs/iso-diagnosis.md.
"""

from __future__ import annotations

import itertools
import json
import math
import sys
import time
from collections.abc import Callable, Sequence
from concurrent.futures import Executor
from pathlib import Path
from typing import Any, Final

import numpy as np

from .checks import int_arg
from .iso_diagnosis import IsoDiagnosisSettings, diagnose_iso
from .iso_truth import EFFECTS, TRAVEL_M, check_scale, draw_case, write_case
from .measurement import read_iso_measurement
from .output import ProgressBar, staged_output, write_json
from .presets import preset_system

__all__ = [
    "MAX_CASES",
    "SIZE_BINS_COUNTS",
    "detection_by_size",
    "detection_markdown",
    "pooled_rows",
    "run_iso_benchmark",
]

#: Most cases of one benchmark.
MAX_CASES: Final[int] = 10_000


def _case_effect(i: int, seed: int) -> str:
    """The hidden effect of case ``i``: every effect (and none) in turn, from a seeded
    shuffle of each round."""
    k = len(EFFECTS)
    order = np.random.default_rng([seed, i // k, 0xBE9C]).permutation(k)
    return EFFECTS[int(order[i % k])]


def run_iso_benchmark(
    out: str | Path,
    *,
    cases: int,
    seed: int,
    settings: IsoDiagnosisSettings | None = None,
    threads: int | None = None,
    executor: Executor | Any | None = None,
    progress: bool = True,
    log: Callable[[str], None] | None = None,
    encoder: bool = False,
    scale: float = 1.0,
) -> dict[str, Any]:
    """Run ``cases`` blind cases from ``seed`` and write benchmark.json, benchmark.md and
    each case's measurement (cases/) to ``out`` (whole or not at all); with ``encoder``,
    the cases' files have the encoder's readings; ``scale`` (in (0, 1]) multiplies each
    hidden effect's error (:func:`~nanostage.iso_truth.draw_case`), for the detection
    limit. Returns the summary."""
    n = int_arg("cases", cases, 1, MAX_CASES)
    sd = int_arg("seed", seed, 0, 2**32 - 1)
    check_scale(scale)
    s = IsoDiagnosisSettings() if settings is None else settings
    system = preset_system("seed")
    rows: list[dict[str, Any]] = []
    bar = ProgressBar(n, sys.stderr if progress and log is None else None, "cases", unit="cases")
    with staged_output(out, "iso-diagnose-benchmark") as folder:
        (folder / "cases").mkdir()
        for i in range(n):
            hidden = _case_effect(i, sd)
            case = draw_case(hidden, sd * 100_000 + i, scale=scale)
            path = write_case(case, folder / "cases" / f"case_{i:04d}.csv", encoder=encoder)
            t0 = time.perf_counter()
            meas = read_iso_measurement(path, travel_m=(0.0, TRAVEL_M))
            rep = diagnose_iso(meas, system, s, threads=threads, executor=executor)
            seconds = time.perf_counter() - t0
            found = rep["verdict"]
            tied = [t["candidate"] for t in rep["indistinguishable"]]
            row = {
                "case": i,
                "hidden": hidden,
                "hidden_parameters": case.parameters,
                "hidden_size_counts": case.hidden_size_counts,
                "found": found,
                "found_parameters": next(
                    (c["parameters"] for c in rep["candidates"] if c["name"] == found), {}
                ),
                "tied_with": tied,
                "correct": found == hidden,
                "correct_up_to_tie": found == hidden or hidden in tied,
                "figure_gap_before_m": rep["gap_before"]["figure_gap_rms_m"],
                "figure_gap_after_m": rep["gap_after"]["figure_gap_rms_m"],
                "figure_gap_shrink": rep["figure_gap_shrink"],
                "iso_gap_before": rep["gap_before"]["iso_gap"],
                "iso_gap_after": rep["gap_after"]["iso_gap"],
                "seconds": seconds,
            }
            rows.append(row)
            if log is not None:
                log(
                    f"case {i}: hidden {hidden}, found {found}"
                    + (f" (tied: {', '.join(tied)})" if tied else "")
                    + f", shrink {row['figure_gap_shrink']:.0%}, {seconds:.1f} s"
                )
            bar.update(i + 1)
        bar.update(n, final=True)
        summary = _summary(rows, sd, s)
        summary["encoder_readings"] = bool(encoder)
        summary["magnitude_scale"] = float(scale)
        write_json(summary, folder / "benchmark.json")
        (folder / "benchmark.md").write_text(markdown(summary), encoding="utf-8")
    return summary


def _summary(rows: list[dict[str, Any]], seed: int, s: IsoDiagnosisSettings) -> dict[str, Any]:
    eff = [r for r in rows if r["hidden"] != "none"]
    nones = [r for r in rows if r["hidden"] == "none"]
    labels = [*EFFECTS]
    found_labels = sorted({r["found"] for r in rows} | set(labels), key=labels.index)
    confusion = {h: {f: 0 for f in found_labels} for h in labels}
    for r in rows:
        confusion[r["hidden"]][r["found"]] += 1
    per_effect = {
        h: {
            "cases": sum(r["hidden"] == h for r in rows),
            "top1": _mean([r["correct"] for r in rows if r["hidden"] == h]),
            "median_shrink": _median([r["figure_gap_shrink"] for r in rows if r["hidden"] == h]),
        }
        for h in labels
        if h != "none"
    }
    return {
        "seed": seed,
        "cases": len(rows),
        "effect_cases": len(eff),
        "none_cases": len(nones),
        "top1": _mean([r["correct"] for r in eff]),
        "top1_up_to_ties": _mean([r["correct_up_to_tie"] for r in eff]),
        "false_alarms": sum(r["found"] != "none" for r in nones),
        "false_alarm_rate": _mean([r["found"] != "none" for r in nones]),
        "missed": sum(r["found"] == "none" for r in eff),
        "median_shrink": _median([r["figure_gap_shrink"] for r in eff]),
        "median_seconds_per_case": _median([r["seconds"] for r in rows]),
        "max_seconds_per_case": max(r["seconds"] for r in rows),
        "confusion": confusion,
        "per_effect": per_effect,
        "by_size": detection_by_size(rows),
        "settings": {k: getattr(s, k) for k in s.__dataclass_fields__},
        "rows": rows,
    }


#: The bins of the hidden error's size (RMS about its mean, encoder counts) of
#: :func:`detection_by_size`: their lower edges.
SIZE_BINS_COUNTS: Final[tuple[float, ...]] = (0.0, 0.25, 0.5, 1.0, 2.0, 5.0)


def _size_bin(size: float) -> str:
    edges = [*SIZE_BINS_COUNTS, math.inf]
    for lo, hi in itertools.pairwise(edges):
        if lo <= size < hi:
            return f"{lo:g}–{hi:g}" if math.isfinite(hi) else f"≥ {lo:g}"
    return f"≥ {edges[-2]:g}"


def detection_by_size(rows: Sequence[dict[str, Any]]) -> dict[str, dict[str, list[int]]]:
    """Per hidden effect (no-effect cases left out) and bin of its size in encoder counts
    (:data:`SIZE_BINS_COUNTS`, the rows' ``hidden_size_counts``): [named, cases], where
    named counts the cases whose verdict is the hidden effect; ``"all"`` sums the effects."""
    out: dict[str, dict[str, list[int]]] = {}
    for r in rows:
        if r["hidden"] == "none":
            continue
        b = _size_bin(float(r["hidden_size_counts"]))
        for key in (r["hidden"], "all"):
            cell = out.setdefault(key, {}).setdefault(b, [0, 0])
            cell[0] += int(bool(r["correct"]))
            cell[1] += 1
    return out


def pooled_rows(folders: Sequence[str | Path]) -> list[dict[str, Any]]:
    """The case rows of several benchmark output folders (their benchmark.json), each with
    its run's ``magnitude_scale`` and ``hidden_size_counts`` (drawn again from the run's seed
    where a row lacks it: the draws are deterministic)."""
    out = []
    for folder in folders:
        path = Path(folder) / "benchmark.json"
        try:
            summary = json.loads(path.read_text(encoding="utf-8"))
        except (OSError, ValueError) as e:
            raise ValueError(f"{path}: not a benchmark's summary ({e})") from None
        if not isinstance(summary, dict) or not isinstance(summary.get("rows"), list):
            raise ValueError(f"{path}: not a benchmark's summary (no list of case rows)")
        scale = float(summary.get("magnitude_scale", 1.0))
        for r in summary["rows"]:
            row = dict(r, magnitude_scale=scale, benchmark=str(folder))
            if "hidden_size_counts" not in row:
                case = draw_case(r["hidden"], summary["seed"] * 100_000 + r["case"], scale=scale)
                row["hidden_size_counts"] = case.hidden_size_counts
            out.append(row)
    return out


def detection_markdown(rows: Sequence[dict[str, Any]]) -> str:
    """:func:`detection_by_size` of ``rows`` as a Markdown table (named / cases per bin)."""
    table = detection_by_size(rows)
    bins = [_size_bin(lo) for lo in SIZE_BINS_COUNTS]
    lines = [
        "| hidden \\ size [counts] | " + " | ".join(bins) + " |",
        "|---" * (len(bins) + 1) + "|",
    ]
    order = [e for e in EFFECTS if e in table] + ["all"] * ("all" in table)
    for h in order:
        cells = [f"{table[h][b][0]}/{table[h][b][1]}" if b in table[h] else "—" for b in bins]
        lines.append(f"| {h} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def _mean(values: list[bool]) -> float:
    return float(np.mean(values)) if values else math.nan


def _median(values: list[float]) -> float:
    return float(np.median(values)) if values else math.nan


def _pct(v: float) -> str:
    return "—" if not math.isfinite(v) else f"{v:.0%}"


def markdown(summary: dict[str, Any]) -> str:
    """The benchmark's summary in Markdown."""
    s = summary
    lines = [
        f"# ISO-level diagnosis: blind benchmark (seed {s['seed']}, {s['cases']} cases"
        + (", with the encoder's readings" if s.get("encoder_readings") else "")
        + (
            f", hidden effects at {s['magnitude_scale']:g} times their drawn size)"
            if s.get("magnitude_scale", 1.0) != 1.0
            else ")"
        ),
        "",
        f"- top-1 (hidden effect is the verdict): **{_pct(s['top1'])}** of "
        f"{s['effect_cases']}; counting a hidden effect named as indistinguishable: "
        f"{_pct(s['top1_up_to_ties'])}",
        f"- false alarms: **{s['false_alarms']} of {s['none_cases']}** no-effect cases; "
        f"effects missed (verdict none): {s['missed']}",
        f"- median shrink of the figure gap (effect cases): {_pct(s['median_shrink'])}",
        f"- time per case: median {s['median_seconds_per_case']:.1f} s, max "
        f"{s['max_seconds_per_case']:.1f} s",
        "",
        "## Confusion (rows: hidden, columns: verdict)",
        "",
    ]
    cols = list(next(iter(s["confusion"].values())).keys())
    lines.append("| hidden \\ found | " + " | ".join(cols) + " |")
    lines.append("|---" * (len(cols) + 1) + "|")
    for h, row in s["confusion"].items():
        lines.append(f"| {h} | " + " | ".join(str(row[c]) for c in cols) + " |")
    lines += [
        "",
        "## Named by size",
        "",
        "Cases whose verdict is the hidden effect, of the cases, by the hidden error's size "
        "(its RMS about its mean over the readings, in encoder counts).",
        "",
        detection_markdown(s["rows"]),
        "## Cases",
        "",
        "| case | hidden | size [counts] | found | tied with | shrink | s |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in s["rows"]:
        lines.append(
            f"| {r['case']} | {r['hidden']} | {r['hidden_size_counts']:.2f} | {r['found']} "
            f"| {', '.join(r['tied_with']) or '—'} | {_pct(r['figure_gap_shrink'])} "
            f"| {r['seconds']:.1f} |"
        )
    return "\n".join(lines) + "\n"


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m nanostage.iso_diagnosis_benchmark DIR [DIR ...]``: the cases of several
    benchmark runs (e.g. at several ``--scale``) pooled, named by the hidden error's size."""
    import argparse

    parser = argparse.ArgumentParser(
        prog="python -m nanostage.iso_diagnosis_benchmark",
        description="pool iso-diagnose-benchmark runs: cases named by the hidden error's size",
    )
    parser.add_argument("folders", nargs="+", metavar="DIR", help="benchmark output folders")
    args = parser.parse_args(argv)
    try:
        rows = pooled_rows(args.folders)
    except ValueError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(detection_markdown(rows), end="")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
