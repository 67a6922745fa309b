"""Figures (matplotlib is an optional extra, imported lazily; nothing calls ``plt.show``)."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from .simulate import Trace


def _figure(nrows: int, ncols: int, size: tuple[float, float]) -> tuple[Any, Any]:
    try:
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
    except ImportError as e:  # pragma: no cover - exercised only without the extra
        raise ImportError("plotting needs matplotlib: pip install 'nanostage[plot]'") from e
    fig = Figure(figsize=size, layout="constrained")
    FigureCanvasAgg(fig)
    axes = fig.subplots(nrows, ncols, sharex="col", squeeze=False)
    return fig, axes


def plot_steps(
    traces: Sequence[Trace], titles: Sequence[str], path: str | Path | None = None
) -> Any:
    """Step responses like the paper's figure: position and reference vs time (top), the
    controller output and the motor voltage (bottom), one column per trace.

    Returns the matplotlib ``Figure``; saves it as PNG when ``path`` is given.
    """
    fig, axes = _figure(2, len(traces), (5.2 * len(traces), 6.0))
    for col, (tr, title) in enumerate(zip(traces, titles, strict=True)):
        top, bottom = axes[0, col], axes[1, col]
        t_ms = tr.time_s * 1e3
        top.plot(t_ms, tr.reference_m * 1e6, "k--", lw=1.0, label="reference")
        top.plot(t_ms, tr.position_m * 1e6, lw=1.4, label="table position (true)")
        top.step(
            t_ms,
            tr.encoder_position_m * 1e6,
            where="post",
            lw=0.8,
            alpha=0.7,
            label="encoder reading",
        )
        top.set_ylabel("position [µm]")
        top.set_title(title)
        top.grid(alpha=0.3)
        top.legend(loc="lower right", fontsize=8)
        bottom.step(
            t_ms, tr.command * tr.output_unit_v, where="post", lw=1.0, label="controller output [V]"
        )
        bottom.step(
            t_ms, tr.motor_voltage_v, where="post", lw=1.0, alpha=0.8, label="motor voltage [V]"
        )
        lim = tr.amplifier_limit_v
        for y in (lim, -lim):
            bottom.axhline(y, color="r", lw=0.6, ls=":")
        bottom.set_ylabel("voltage [V]")
        bottom.set_xlabel("time [ms]")
        bottom.grid(alpha=0.3)
        bottom.legend(loc="upper right", fontsize=8)
    if path is not None:
        fig.savefig(path, dpi=130)
    return fig
