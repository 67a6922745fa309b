"""The ISO 230-2 plot and report files (JSON, Markdown, PNG).

matplotlib is imported lazily by :func:`plot` and is optional."""

from __future__ import annotations

import json
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Final

from .evaluation import (
    MM_PER_M,
    UM_PER_M,
    FloatArray,
    Iso230Result,
    fmt_mm,
    fmt_um,
    md_escape,
)

if TYPE_CHECKING:
    from matplotlib.axes import Axes

__all__ = ["ReportFiles", "plot", "write_report"]

JSON_NAME: Final[str] = "iso230_2.json"
MARKDOWN_NAME: Final[str] = "iso230_2.md"
PNG_NAME: Final[str] = "iso230_2.png"


# --------------------------------------------------------------------------------------------
# Plot and report
# --------------------------------------------------------------------------------------------


def _draw(result: Iso230Result, ax: Axes, title: str | None) -> None:
    k = result.coverage_factor
    x = result.targets_m * MM_PER_M
    um = UM_PER_M
    series: list[tuple[str, str, FloatArray, FloatArray]] = [
        ("C0", r"\uparrow", result.mean_deviation_up_m, result.std_up_m)
    ]
    if result.mean_deviation_down_m is not None and result.std_down_m is not None:
        series.append(("C3", r"\downarrow", result.mean_deviation_down_m, result.std_down_m))
    for color, arrow, mean, std in series:
        ax.fill_between(
            x,
            (mean - k * std) * um,
            (mean + k * std) * um,
            color=color,
            alpha=0.15,
            linewidth=0,
            label=rf"$\bar{{x}}_i{arrow} \pm {k:g}\,s_i{arrow}$",
        )
        ax.plot(x, (mean + k * std) * um, color=color, linewidth=0.8, linestyle="--")
        ax.plot(x, (mean - k * std) * um, color=color, linewidth=0.8, linestyle="--")
        ax.errorbar(
            x,
            mean * um,
            yerr=k * std * um,
            color=color,
            marker="o",
            markersize=4,
            capsize=3,
            linewidth=1.5,
            label=rf"$\bar{{x}}_i{arrow}$",
        )
    if result.mean_bidirectional_deviation_m is not None:
        ax.plot(
            x,
            result.mean_bidirectional_deviation_m * um,
            color="k",
            linestyle=":",
            marker=".",
            linewidth=1.2,
            label=r"$\bar{x}_i$",
        )
    ax.axhline(0.0, color="0.6", linewidth=0.6)
    ax.set_xlabel("Target position [mm]")
    ax.set_ylabel("Positional deviation [µm]")
    ax.grid(True, linewidth=0.4, alpha=0.6)
    ax.legend(loc="best", fontsize="small")
    keys: tuple[str, ...]
    names: tuple[str, ...]
    if result.bidirectional:
        keys = ("systematic_deviation_m", "repeatability_m", "accuracy_m", "reversal_m")
        names = ("E", "R", "A", "B")
    else:
        keys = ("systematic_deviation_up_m", "repeatability_up_m", "accuracy_up_m")
        names = (r"E$\uparrow$", r"R$\uparrow$", r"A$\uparrow$")
    values = result.axis_parameters()
    text = "\n".join(f"{n} = {fmt_um(values[key])} µm" for n, key in zip(names, keys, strict=True))
    ax.text(
        0.01,
        0.02,
        text,
        transform=ax.transAxes,
        fontsize="small",
        va="bottom",
        ha="left",
        bbox={"boxstyle": "round", "facecolor": "white", "alpha": 0.8, "edgecolor": "0.7"},
    )
    ax.set_title(title or f"ISO 230-2 positional deviations (k = {k:g})")


def plot(
    result: Iso230Result,
    path: str | Path | None = None,
    *,
    ax: Axes | None = None,
    title: str | None = None,
    dpi: float = 150.0,
) -> Axes:
    """Draw the standard ISO 230-2 plot: mean deviations vs target with ±k·s bands.

    Shows :math:`\\bar x_i↑`, :math:`\\bar x_i↓` (with error bars and shaded bands of
    ±k·sᵢ per target and direction) and :math:`\\bar x_i` against the target position
    [mm], deviations in µm, plus a box with E, R, A (and B). matplotlib is imported here,
    not at module import; a new figure uses the Agg canvas directly (no pyplot, no global
    backend change).

    Parameters
    ----------
    result : Iso230Result
        The evaluation to plot.
    path : str or Path, optional
        If given, save the figure there (PNG at ``dpi``).
    ax : matplotlib.axes.Axes, optional
        Draw into this axes instead of a new figure.
    title : str, optional
        Axes title; a default naming k is used otherwise.
    dpi : float, default 150
        Resolution of the saved file [dots per inch].

    Returns
    -------
    matplotlib.axes.Axes
        The axes drawn into.

    Raises
    ------
    ImportError
        If matplotlib is not installed.
    """
    import matplotlib  # noqa: F401  (raises ImportError early if matplotlib is missing)
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    if ax is None:
        fig = Figure(figsize=(8.0, 5.0), layout="constrained")
        FigureCanvasAgg(fig)
        ax = fig.add_subplot()
    _draw(result, ax, title)
    if path is not None:
        root = ax.figure
        if not isinstance(root, Figure):  # a SubFigure: save its top-level figure
            root = root.figure
        root.savefig(Path(path), dpi=dpi)
    return ax


@dataclass(frozen=True, slots=True, kw_only=True)
class ReportFiles:
    """Paths written by :func:`write_report`.

    Attributes
    ----------
    json : Path
        ``iso230_2.json`` (the :meth:`Iso230Result.to_dict` data plus title/conditions).
    markdown : Path
        ``iso230_2.md``.
    png : Path or None
        ``iso230_2.png``, or ``None`` when matplotlib is not installed.
    """

    json: Path
    markdown: Path
    png: Path | None


def _deviation_table(rows: Sequence[FloatArray], targets_m: FloatArray) -> str:
    n_max = max(r.shape[0] for r in rows)
    head = ["i", "Target [mm]"] + [f"j = {j + 1} [µm]" for j in range(n_max)]
    lines = ["| " + " | ".join(head) + " |", "| " + " | ".join(["---:"] * len(head)) + " |"]
    for i, r in enumerate(rows):
        cells = [str(i + 1), fmt_mm(float(targets_m[i]))]
        cells += [fmt_um(float(v)) for v in r] + [""] * (n_max - r.shape[0])
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def write_report(
    result: Iso230Result,
    out_dir: str | Path,
    *,
    title: str = "ISO 230-2 positioning test",
    conditions: Mapping[str, str] | None = None,
) -> ReportFiles:
    """Write the ISO 230-2 report files into a directory.

    Writes ``iso230_2.json`` (SI units), ``iso230_2.md`` (parameter table, per-target
    table and the raw deviations; targets in mm, other values in µm) and ``iso230_2.png``
    (see :func:`plot`). If matplotlib is not installed the PNG is skipped and the markdown
    says so in a warning line.

    Parameters
    ----------
    result : Iso230Result
        The evaluation to report.
    out_dir : str or Path
        Output directory; created (with parents) if needed. Existing files are replaced.
    title : str, default "ISO 230-2 positioning test"
        Report title (markdown heading, plot title, JSON ``title``).
    conditions : mapping of str to str, optional
        Test conditions to list (machine, axis, date, instrument, feed, dwell,
        temperatures, ...), as ISO 230-2 asks a report to state.

    Returns
    -------
    ReportFiles
        Paths of the files written.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    json_path = out / JSON_NAME
    md_path = out / MARKDOWN_NAME
    png_path: Path | None = out / PNG_NAME

    data = {"title": title, "conditions": dict(conditions or {}), **result.to_dict()}
    json_path.write_text(json.dumps(data, indent=2, ensure_ascii=False) + "\n", encoding="utf-8")

    plot_note: str
    try:
        plot(result, png_path, title=title)
        plot_note = f"![ISO 230-2 positional deviations]({PNG_NAME})\n"
    except ImportError:
        png_path = None
        plot_note = (
            f"> **Warning:** matplotlib is not installed; the plot {PNG_NAME} was not written.\n"
        )

    k = result.coverage_factor
    n_up = sorted({int(v) for v in result.n_runs_up})
    n_down_arr = result.n_runs_down
    runs = f"{'/'.join(map(str, n_up))} (↑)"
    if n_down_arr is not None:
        runs += f", {'/'.join(str(v) for v in sorted({int(v) for v in n_down_arr}))} (↓)"
    md: list[str] = [
        f"# {md_escape(title)}\n",
        (
            "Evaluation with the ISO 230-2 formulas (editions 1997/2006/2014), "
            f"coverage factor k = {k:g}, {result.n_targets} target position(s), "
            f"runs per target: {runs}, "
            f"{'bidirectional' if result.bidirectional else 'unidirectional (↑ only)'}. "
            "Positional deviation = actual - target. Targets in mm, all other values in µm.\n"
        ),
    ]
    if conditions:
        md.append("## Test conditions\n")
        md.append(
            "| Item | Value |\n| --- | --- |\n"
            + "".join(
                f"| {md_escape(str(key))} | {md_escape(str(v))} |\n"
                for key, v in conditions.items()
            )
        )
    md.append("## Axis parameters\n")
    md.append(result.summary_table_markdown())
    md.append("## Per-target results\n")
    md.append(result.per_target_table_markdown())
    md.append("## Positional deviations, positive direction (↑)\n")
    md.append(_deviation_table(result.deviations_up_m, result.targets_m))
    if result.deviations_down_m is not None:
        md.append("## Positional deviations, negative direction (↓)\n")
        md.append(_deviation_table(result.deviations_down_m, result.targets_m))
    md.append("## Plot\n")
    md.append(plot_note)
    md_path.write_text("\n".join(md), encoding="utf-8")
    return ReportFiles(json=json_path, markdown=md_path, png=png_path)
