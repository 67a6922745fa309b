"""Response figures of a step run (pure numpy on a :class:`~nanostage.Trace`)."""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from .simulate import Trace

__all__ = ["StepMetrics", "step_metrics"]


@dataclass(frozen=True, slots=True, kw_only=True)
class StepMetrics:
    """Figures of one step response.

    Attributes
    ----------
    step_m : reference step, m.
    rise_time_s : 10 % → 90 % of the step on the true table position, s (NaN if not reached).
    overshoot_m : largest travel past the target in the step direction, m (≥ 0).
    settling_time_s : time from the step until the encoder error stays within ±1 count for
        the rest of the run, s (NaN if it never does).
    final_error_m : target − true position at the end of the run, m.
    final_error_counts : target − encoder reading at the end, counts.
    max_velocity_m_per_s : largest |table velocity|, m/s.
    time_at_voltage_limit_s : time the amplifier spent at its voltage limit, s.
    settled : whether the run ended inside the ±1 count band and stayed there.
    """

    step_m: float
    rise_time_s: float
    overshoot_m: float
    settling_time_s: float
    final_error_m: float
    final_error_counts: int
    max_velocity_m_per_s: float
    time_at_voltage_limit_s: float
    settled: bool

    def to_dict(self) -> dict[str, float | int | bool | None]:
        """JSON-ready dict (NaN becomes None)."""
        out: dict[str, float | int | bool | None] = {}
        for k, v in asdict(self).items():
            out[k] = None if isinstance(v, float) and math.isnan(v) else v
        return out


def _first_crossing(t: np.ndarray, x: np.ndarray, level: float) -> float:
    idx = np.flatnonzero(x >= level)
    if idx.size == 0:
        return math.nan
    k = int(idx[0])
    if k == 0:
        return float(t[0])
    # Linear interpolation between the samples around the crossing.
    x0, x1 = x[k - 1], x[k]
    return float(t[k - 1] + (level - x0) / (x1 - x0) * (t[k] - t[k - 1]))


def step_metrics(trace: Trace, *, band_counts: int = 1) -> StepMetrics:
    """Response figures of a step run whose reference jumps once from its first value.

    Parameters
    ----------
    trace : Trace
        A closed-loop run with a step reference.
    band_counts : int
        Half-width of the settling band, encoder counts (default 1).
    """
    t = trace.time_s
    r = trace.reference_m
    start_val = float(r[0])
    moved = np.flatnonzero(r != start_val)
    if moved.size == 0:
        raise ValueError("the reference never moves: not a step run")
    k0 = int(moved[0])
    target = float(r[-1])
    step = target - start_val
    sgn = 1.0 if step > 0 else -1.0
    # Normalised progress along the step direction.
    prog = (trace.position_m[k0:] - start_val) * sgn
    tt = t[k0:]
    t_step = float(t[k0])
    t10 = _first_crossing(tt, prog, 0.1 * abs(step))
    t90 = _first_crossing(tt, prog, 0.9 * abs(step))
    overshoot = max(0.0, float(np.max(prog)) - abs(step))
    err_counts = trace.reference_counts - trace.encoder_counts
    outside = np.flatnonzero(np.abs(err_counts[k0:]) > band_counts)
    if outside.size == 0:
        settling = 0.0
        settled = True
    elif int(outside[-1]) == err_counts.size - k0 - 1:
        settling = math.nan
        settled = False
    else:
        settling = float(tt[int(outside[-1]) + 1] - t_step)
        settled = True
    at_limit = np.abs(trace.motor_voltage_v) >= trace.amplifier_limit_v * (1 - 1e-12)
    return StepMetrics(
        step_m=step,
        rise_time_s=t90 - t10,
        overshoot_m=overshoot,
        settling_time_s=settling,
        final_error_m=target - float(trace.position_m[-1]),
        final_error_counts=int(err_counts[-1]),
        max_velocity_m_per_s=float(np.max(np.abs(trace.velocity_m_per_s))),
        time_at_voltage_limit_s=float(np.count_nonzero(at_limit)) * trace.sample_period_s,
        settled=settled,
    )
