"""Off-line tuning of the FPGA PID: gains (and anti-windup) that minimise a robust objective.

The paper tuned its PID gains by hand for each step size (Table 1). :func:`tune` searches the
gains in the controller's fixed-point gain format (whole numbers by default, or any value the
format holds) and, optionally, the anti-windup option, with scipy's differential evolution
and the Rust closed loop in the loop. *Robust* means the objective is a statistic over a Monte
Carlo campaign (:func:`nanostage.campaign.run_campaign`): ``n_trials`` trials of a test cycle,
each with its own stochastic-friction draw. Every candidate sees the same draws (the campaign
seed is fixed: common random numbers), so the objective is a deterministic function of the
gains and the search is reproducible from ``seed``.

What a candidate is scored on, per approach of the cycle (each measured target approach) and
per trial, from the positions inside the approach's *window* (from the sample at which the
reference reaches the target to the measurement instant at the end of the dwell):

* settling time: from the start of the window until the encoder error stays within
  ``±band_counts`` counts to the end of the window; an approach that has not settled by the
  end of the window counts as twice the window's length (so a candidate is pushed towards
  settling, and a limit cycle is never better than a slow settle);
* overshoot: largest travel of the true table position past the target, in the approach
  direction (≥ 0);
* final error: |target − position| at the measurement instant;
* ISO 230-2 A↑ and R↑ of the campaign, all completed trials' measurements pooled as runs of
  one test (:meth:`CampaignResult.evaluate` with ``trial=None``): with a per-trial friction
  level, this is the scatter the friction distribution causes.

The per-approach figures are reduced over all approaches of all trials by ``statistic``
(mean, 95th percentile or maximum). The objective is::

    J = settling_weight_per_s · T_settle + accuracy_weight_per_m · A↑
        + repeatability_weight_per_m · R↑ + final_error_weight_per_m · |e_final|
        + overshoot penalty

with the overshoot penalty ``1e3 · (overshoot / overshoot_max_m − 1)`` when the overshoot
statistic exceeds ``overshoot_max_m``. A failed trial (numerical failure) makes the candidate
``FAILED_OBJECTIVE``.

Example::

    system = with_friction_spread(presets.seed(100e-6), 0.2)
    cycle = tuning_cycle(100e-6)    # one step per trial, dwell 0.31 s
    res = tune(system, cycle, objective=Objective.mix(), n_trials=200, seed=1)
    res.best.kp, res.best.ki, res.best.kd, res.best.anti_windup
"""

from __future__ import annotations

import math
import os
import sys
import time
from collections.abc import Callable, Sequence
from concurrent.futures import Executor
from dataclasses import asdict, dataclass, replace
from typing import Any, Final, Literal

import numpy as np
import numpy.typing as npt
from scipy.optimize import differential_evolution

from ._core import ConfigError
from .campaign import CampaignResult, run_campaign, watch_parent
from .checks import int_arg
from .config import AntiWindup, FpgaPid, System
from .cycles import Cycle, step_cycle
from .effects import StochasticFriction
from .output import ProgressBar

__all__ = [
    "ANTI_WINDUP_OPTIONS",
    "FAILED_OBJECTIVE",
    "Candidate",
    "GainSpace",
    "Objective",
    "RobustMetrics",
    "TuneResult",
    "check_search",
    "evaluate_gains",
    "pareto_front",
    "tune",
    "tuning_cycle",
    "with_friction_spread",
]

FloatArray = npt.NDArray[np.float64]

#: The anti-windup options of the FPGA PID, in the order the search encodes them.
ANTI_WINDUP_OPTIONS: Final[tuple[AntiWindup, ...]] = ("none", "clamp", "conditional")
#: Objective value of a candidate with a failed trial.
FAILED_OBJECTIVE: Final[float] = 1e9
#: Weight of the relative overshoot-bound violation.
_OVERSHOOT_PENALTY: Final[float] = 1e3
Statistic = Literal["mean", "p95", "max"]
Reading = Literal["position", "encoder"]


def _bad(name: str, value: object, valid: str) -> ConfigError:
    return ConfigError(f"{name} = {value!r} is invalid: expected {valid}")


def _finite_nonneg(name: str, value: object) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float, np.floating, np.integer)):
        raise _bad(name, value, "a finite number >= 0")
    v = float(value)
    if not (math.isfinite(v) and v >= 0.0):
        raise _bad(name, value, "a finite number >= 0")
    return v


# --------------------------------------------------------------------------------------------
# Objective, search space, metrics
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True, kw_only=True)
class Objective:
    """What a candidate's gains are scored on (see the module docs for the formula).

    Attributes
    ----------
    settling_weight_per_s : float
        Weight of the settling-time statistic [1/s], >= 0.
    accuracy_weight_per_m : float
        Weight of the pooled ISO 230-2 A↑ [1/m], >= 0.
    repeatability_weight_per_m : float
        Weight of the pooled ISO 230-2 R↑ [1/m], >= 0.
    final_error_weight_per_m : float
        Weight of the |final error| statistic [1/m], >= 0.
    overshoot_max_m : float or None
        Bound on the overshoot statistic [m], > 0; ``None``: no bound.
    band_counts : int
        Half-width of the settling band, encoder counts, in [0, 1000].
    statistic : {"mean", "p95", "max"}
        Reduction over all approaches of all trials of the per-approach figures.
    reading : {"position", "encoder"}
        Which position the ISO figures and the final error use (default: the true table
        position, as the paper's interferometer measured it). Settling always uses the
        encoder (what the controller sees).

    At least one weight must be > 0.
    """

    settling_weight_per_s: float = 0.0
    accuracy_weight_per_m: float = 0.0
    repeatability_weight_per_m: float = 0.0
    final_error_weight_per_m: float = 0.0
    overshoot_max_m: float | None = None
    band_counts: int = 1
    statistic: Statistic = "p95"
    reading: Reading = "position"

    def __post_init__(self) -> None:
        weights = (
            "settling_weight_per_s",
            "accuracy_weight_per_m",
            "repeatability_weight_per_m",
            "final_error_weight_per_m",
        )
        for name in weights:
            _finite_nonneg(name, getattr(self, name))
        if all(float(getattr(self, n)) == 0.0 for n in weights):
            raise ConfigError(
                "Objective weights = all 0 is invalid: expected at least one weight > 0"
            )
        if self.overshoot_max_m is not None:
            v = _finite_nonneg("overshoot_max_m", self.overshoot_max_m)
            if v == 0.0:
                raise _bad("overshoot_max_m", self.overshoot_max_m, "None or a number > 0 [m]")
        b = self.band_counts
        if isinstance(b, bool) or not isinstance(b, (int, np.integer)) or not 0 <= b <= 1000:
            raise _bad("band_counts", b, "an integer in [0, 1000]")
        if self.statistic not in ("mean", "p95", "max"):
            raise _bad("statistic", self.statistic, "'mean', 'p95' or 'max'")
        if self.reading not in ("position", "encoder"):
            raise _bad("reading", self.reading, "'position' or 'encoder'")

    @classmethod
    def settling(cls, *, overshoot_max_m: float | None = None, band_counts: int = 1) -> Objective:
        """Settling time to ±``band_counts`` counts (95th percentile), optionally with an
        overshoot bound."""
        return cls(
            settling_weight_per_s=1.0, overshoot_max_m=overshoot_max_m, band_counts=band_counts
        )

    @classmethod
    def accuracy(cls) -> Objective:
        """Pooled ISO 230-2 A↑ alone."""
        return cls(accuracy_weight_per_m=1.0)

    @classmethod
    def repeatability(cls) -> Objective:
        """Pooled ISO 230-2 R↑ alone."""
        return cls(repeatability_weight_per_m=1.0)

    @classmethod
    def mix(
        cls,
        *,
        seconds_per_micrometre: float = 0.1,
        overshoot_max_m: float | None = None,
        band_counts: int = 1,
    ) -> Objective:
        """Settling time (95th percentile) plus A↑, with ``seconds_per_micrometre`` of settling
        time weighing as much as 1 µm of A↑ (default: 100 ms ≙ 1 µm)."""
        s = _finite_nonneg("seconds_per_micrometre", seconds_per_micrometre)
        if s == 0.0:
            raise _bad("seconds_per_micrometre", seconds_per_micrometre, "a number > 0")
        return cls(
            settling_weight_per_s=1.0,
            accuracy_weight_per_m=s / 1e-6,
            overshoot_max_m=overshoot_max_m,
            band_counts=band_counts,
        )

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict."""
        return asdict(self)


@dataclass(frozen=True, slots=True, kw_only=True)
class GainSpace:
    """The search space: bounds of Kp, Ki, Kd (in the controller's gain units: output units
    per count, per count·sample, per count of motion per sample), whole numbers or any value
    of the gain format, and the anti-windup options to try.

    Bounds must lie in the range of the controller's ``gain_format`` (checked by
    :func:`tune`).
    """

    kp_bounds: tuple[float, float] = (50.0, 2000.0)
    ki_bounds: tuple[float, float] = (0.0, 40.0)
    kd_bounds: tuple[float, float] = (0.0, 200.0)
    integer_gains: bool = True
    anti_windup: tuple[AntiWindup, ...] = ANTI_WINDUP_OPTIONS

    def __post_init__(self) -> None:
        for name in ("kp_bounds", "ki_bounds", "kd_bounds"):
            b = getattr(self, name)
            ok = (
                isinstance(b, tuple)
                and len(b) == 2
                and all(isinstance(v, (int, float)) and math.isfinite(float(v)) for v in b)
            )
            if not ok or float(b[0]) > float(b[1]):
                raise _bad(name, b, "a (low, high) pair of finite numbers with low <= high")
        if not isinstance(self.anti_windup, tuple) or not self.anti_windup:
            raise _bad(
                "anti_windup", self.anti_windup, f"a non-empty tuple of {ANTI_WINDUP_OPTIONS}"
            )
        for a in self.anti_windup:
            if a not in ANTI_WINDUP_OPTIONS:
                raise _bad("anti_windup", a, f"one of {ANTI_WINDUP_OPTIONS}")
        if len(set(self.anti_windup)) != len(self.anti_windup):
            raise _bad("anti_windup", self.anti_windup, "no repeated option")

    def check_format(self, controller: FpgaPid) -> None:
        """Raise :class:`ConfigError` if a bound lies outside the gain format's range."""
        f = controller.gain_format
        step = 2.0 ** (-f.frac_bits)
        if f.signed:
            lo, hi = -(2.0 ** (f.word_bits - 1)) * step, (2.0 ** (f.word_bits - 1) - 1) * step
        else:
            lo, hi = 0.0, (2.0**f.word_bits - 1) * step
        for name in ("kp_bounds", "ki_bounds", "kd_bounds"):
            a, b = getattr(self, name)
            if a < lo or b > hi:
                raise _bad(
                    name,
                    (a, b),
                    f"bounds within the gain format's range [{lo:g}, {hi:g}] "
                    f"(<{f.signed}, {f.word_bits}, {f.int_bits}>)",
                )

    def quantise(
        self, controller: FpgaPid, x: Sequence[float] | FloatArray
    ) -> tuple[float, float, float]:
        """The gains a search vector stands for: whole numbers, or values of the gain format
        (nearest representable, the format's resolution ``2**-frac_bits``), clipped to the
        bounds."""
        out = []
        step = 1.0 if self.integer_gains else 2.0 ** (-controller.gain_format.frac_bits)
        for v, (a, b) in zip(x, (self.kp_bounds, self.ki_bounds, self.kd_bounds), strict=True):
            q = round(float(v) / step) * step
            out.append(float(min(max(q, a), b)))
        return out[0], out[1], out[2]


@dataclass(frozen=True, slots=True, kw_only=True)
class RobustMetrics:
    """A candidate's figures over a campaign (lengths in m, times in s).

    ``settling_time_s``, ``overshoot_m`` and ``final_error_m`` are the objective's statistic
    over all approaches of all completed trials; ``*_mean`` are means. ``accuracy_up_m`` and
    ``repeatability_up_m`` are the pooled ISO 230-2 A↑ and R↑; ``*_trial_mean_m`` the mean
    of the per-trial figures (only filled by :func:`evaluate_gains` with ``per_trial=True``).
    """

    settling_time_s: float
    settling_time_mean_s: float
    settled_fraction: float
    overshoot_m: float
    overshoot_mean_m: float
    final_error_m: float
    final_error_mean_m: float
    accuracy_up_m: float
    repeatability_up_m: float
    n_trials: int
    n_failed: int
    objective: float
    accuracy_up_trial_mean_m: float = math.nan
    repeatability_up_trial_mean_m: float = math.nan

    def to_dict(self) -> dict[str, float | int | None]:
        """JSON-ready dict (NaN and inf become None)."""
        return {
            k: (None if isinstance(v, float) and not math.isfinite(v) else v)
            for k, v in asdict(self).items()
        }


@dataclass(frozen=True, slots=True, kw_only=True)
class Candidate:
    """One evaluated set of gains and its figures."""

    kp: float
    ki: float
    kd: float
    anti_windup: AntiWindup
    metrics: RobustMetrics

    @property
    def objective(self) -> float:
        """The objective value."""
        return self.metrics.objective

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict."""
        return {
            "kp": self.kp,
            "ki": self.ki,
            "kd": self.kd,
            "anti_windup": self.anti_windup,
            **self.metrics.to_dict(),
        }


@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class TuneResult:
    """What :func:`tune` found.

    Attributes
    ----------
    best : Candidate
        The lowest objective among every evaluated candidate.
    start : Candidate
        The system's own gains under the same draws (the baseline).
    history : tuple of Candidate
        Every distinct candidate evaluated, in order of first evaluation.
    n_evaluations : int
        Objective calls (including repeats served from the cache).
    wall_s : float
        Wall time of the search [s].
    message : str
        The optimiser's final message.
    settings : dict
        The search settings (trials, seed, population, generations, objective, space).
    """

    best: Candidate
    start: Candidate
    history: tuple[Candidate, ...]
    n_evaluations: int
    wall_s: float
    message: str
    settings: dict[str, Any]

    def system(self, base: System) -> System:
        """``base`` with the tuned gains and anti-windup."""
        return _with_candidate(
            base, self.best.kp, self.best.ki, self.best.kd, self.best.anti_windup
        )


# --------------------------------------------------------------------------------------------
# Building blocks
# --------------------------------------------------------------------------------------------


def with_friction_spread(
    system: System, level_spread: float, distribution: str = "lognormal"
) -> System:
    """``system`` with a per-trial stochastic friction level (:class:`StochasticFriction`),
    the trial-to-trial scatter the robust objective averages over."""
    st = StochasticFriction(level_spread=level_spread, distribution=distribution)  # type: ignore[arg-type]
    return replace(system, effects=replace(system.effects, stochastic=st))


def tuning_cycle(
    step_m: float,
    *,
    repeats: int = 1,
    dwell_s: float | None = None,
    return_s: float = 0.1,
    sample_period_s: float = 1e-3,
) -> Cycle:
    """``repeats`` unidirectional ``step_m`` steps from 0, each after ``return_s`` at rest,
    measured at the end of a dwell long enough to settle: by default ``0.3 s + 100 s/m ·
    step_m`` (0.31 s for 100 µm, 0.4 s for 1 mm, 1.3 s for 10 mm: the seed axis slews at
    about 14 mm/s).

    With ``repeats >= 2`` this is :func:`~nanostage.cycles.step_cycle`. The default, one step
    per trial, is that cycle cut after its first measurement: with a per-trial friction draw
    the trials are the runs that matter (the pooled ISO figures take every trial's step as a
    run), and a second step at the same draw would double the cost for little information.
    """
    dwell = 0.3 + 100.0 * float(step_m) if dwell_s is None else dwell_s
    if isinstance(repeats, bool) or not isinstance(repeats, (int, np.integer)) or repeats < 1:
        raise _bad("repeats", repeats, "an integer >= 1")
    full = step_cycle(
        step_m=step_m,
        repeats=max(int(repeats), 2),
        dwell_s=dwell,
        return_s=return_s,
        sample_period_s=sample_period_s,
    )
    if repeats >= 2:
        return full
    k = int(full.measure_index[0])
    return Cycle(
        reference_m=full.reference_m[: k + 1],
        sample_period_s=full.sample_period_s,
        measure_index=full.measure_index[:1],
        target_m=full.target_m[:1],
        direction=full.direction[:1],
        run=full.run[:1],
    )


def _fpga(system: System) -> FpgaPid:
    """The system's FPGA PID, or a ConfigError (tuning searches the FPGA PID's gains)."""
    ctl = system.controller
    if not isinstance(ctl, FpgaPid):
        raise ConfigError(
            f"system.controller = {type(ctl).__name__} is invalid: expected an FpgaPid "
            "(tuning searches the FPGA PID's gains)"
        )
    return ctl


def _with_candidate(system: System, kp: float, ki: float, kd: float, aw: AntiWindup) -> System:
    ctl = replace(_fpga(system), kp=kp, ki=ki, kd=kd, anti_windup=aw)
    return replace(system, controller=ctl)


def _windows(cycle: Cycle) -> list[tuple[int, int]]:
    """Per measurement, the samples [a, b] from the reference reaching the target to the
    measurement instant."""
    ref = cycle.reference_m
    out = []
    prev_end = -1
    for k, target in zip(cycle.measure_index.tolist(), cycle.target_m.tolist(), strict=True):
        a = k
        while a - 1 > prev_end and ref[a - 1] == target:
            a -= 1
        out.append((a, k))
        prev_end = k
    return out


@dataclass(frozen=True, slots=True)
class _Dense:
    """The cycle re-labelled so that the campaign records every sample of every window."""

    cycle: Cycle
    dense: Cycle
    window_cols: tuple[tuple[int, int], ...]  # columns [a, b) of each window in `dense`
    final_cols: npt.NDArray[np.int64]  # column of each measurement instant in `dense`


def _dense(cycle: Cycle) -> _Dense:
    idx: list[int] = []
    runs: list[int] = []
    dirs: list[int] = []
    cols: list[tuple[int, int]] = []
    for m, (a, b) in enumerate(_windows(cycle)):
        c0 = len(idx)
        idx.extend(range(a, b + 1))
        runs.extend([int(cycle.run[m])] * (b - a + 1))
        dirs.extend([int(cycle.direction[m])] * (b - a + 1))
        cols.append((c0, len(idx)))
    index = np.asarray(idx, dtype=np.int64)
    dense = Cycle(
        reference_m=cycle.reference_m,
        sample_period_s=cycle.sample_period_s,
        measure_index=index,
        target_m=cycle.reference_m[index],
        direction=np.asarray(dirs, dtype=np.int64),
        run=np.asarray(runs, dtype=np.int64),
    )
    finals = np.asarray([b - 1 for _, b in cols], dtype=np.int64)
    return _Dense(cycle=cycle, dense=dense, window_cols=tuple(cols), final_cols=finals)


def _reduce(values: FloatArray, statistic: Statistic) -> float:
    if values.size == 0:
        return math.nan
    if statistic == "mean":
        return float(np.mean(values))
    if statistic == "p95":
        return float(np.percentile(values, 95.0))
    return float(np.max(values))


def _score(
    d: _Dense,
    res: CampaignResult,
    system: System,
    objective: Objective,
    *,
    per_trial: bool,
) -> RobustMetrics:
    cyc = d.cycle
    count_m = system.encoder.count_m
    period = cyc.sample_period_s
    ok = res.ok
    n_failed = res.n_failed
    # Measured positions in the original cycle's layout → ISO figures (pooled over trials).
    finals = CampaignResult(
        cycle=cyc,
        seed=res.seed,
        position_m=res.position_m[:, d.final_cols],
        encoder_m=res.encoder_m[:, d.final_cols],
        status=res.status,
        failures=res.failures,
        compute_s=res.compute_s,
    )
    if not np.any(ok):
        nan = math.nan
        return RobustMetrics(
            settling_time_s=nan,
            settling_time_mean_s=nan,
            settled_fraction=0.0,
            overshoot_m=nan,
            overshoot_mean_m=nan,
            final_error_m=nan,
            final_error_mean_m=nan,
            accuracy_up_m=nan,
            repeatability_up_m=nan,
            n_trials=res.n_trials,
            n_failed=n_failed,
            objective=FAILED_OBJECTIVE,
        )
    pos = res.position_m[ok]
    enc_counts = np.rint(res.encoder_m[ok] / count_m)
    settle: list[FloatArray] = []
    settled: list[npt.NDArray[np.bool_]] = []
    over: list[FloatArray] = []
    for m, (c0, c1) in enumerate(d.window_cols):
        target = float(cyc.target_m[m])
        sgn = float(cyc.direction[m])
        ref_counts = round(target / count_m)  # the host's conversion: nearest, ties to even
        err = np.abs(ref_counts - enc_counts[:, c0:c1]) > objective.band_counts
        n = c1 - c0
        # Index of the last sample outside the band (−1: never outside).
        last_out = np.where(err.any(axis=1), n - 1 - np.argmax(err[:, ::-1], axis=1), -1)
        is_settled = last_out < n - 1
        t = np.where(is_settled, (last_out + 1) * period, 2.0 * n * period)
        settle.append(t)
        settled.append(is_settled)
        over.append(np.maximum(0.0, np.max((pos[:, c0:c1] - target) * sgn, axis=1)))
    t_all = np.concatenate(settle)
    o_all = np.concatenate(over)
    actual = finals.actual_m(objective.reading)[ok]
    e_all = np.abs(cyc.target_m[None, :] - actual).ravel()
    iso = finals.evaluate(reading=objective.reading)
    a_up = float(iso.accuracy_up_m) if iso.accuracy_up_m is not None else math.nan
    r_up = float(iso.repeatability_up_m) if iso.repeatability_up_m is not None else math.nan
    st = objective.statistic
    t_stat, o_stat, e_stat = _reduce(t_all, st), _reduce(o_all, st), _reduce(e_all, st)
    j = (
        objective.settling_weight_per_s * t_stat
        + objective.accuracy_weight_per_m * a_up
        + objective.repeatability_weight_per_m * r_up
        + objective.final_error_weight_per_m * e_stat
    )
    if objective.overshoot_max_m is not None and o_stat > objective.overshoot_max_m:
        j += _OVERSHOOT_PENALTY * (o_stat / objective.overshoot_max_m - 1.0)
    if n_failed or not math.isfinite(j):
        j = FAILED_OBJECTIVE
    trial_a = trial_r = math.nan
    if per_trial and int(np.max(cyc.run)) >= 2:  # a per-trial test needs two runs
        dist = finals.distribution(reading=objective.reading)
        trial_a = float(np.nanmean(dist["accuracy_up_m"]))
        trial_r = float(np.nanmean(dist["repeatability_up_m"]))
    return RobustMetrics(
        settling_time_s=t_stat,
        settling_time_mean_s=float(np.mean(t_all)),
        settled_fraction=float(np.mean(np.concatenate(settled))),
        overshoot_m=o_stat,
        overshoot_mean_m=float(np.mean(o_all)),
        final_error_m=e_stat,
        final_error_mean_m=float(np.mean(e_all)),
        accuracy_up_m=a_up,
        repeatability_up_m=r_up,
        n_trials=res.n_trials,
        n_failed=n_failed,
        objective=float(j),
        accuracy_up_trial_mean_m=trial_a,
        repeatability_up_trial_mean_m=trial_r,
    )


def evaluate_gains(
    system: System,
    cycle: Cycle,
    *,
    objective: Objective,
    n_trials: int,
    seed: int,
    kp: float | None = None,
    ki: float | None = None,
    kd: float | None = None,
    anti_windup: AntiWindup | None = None,
    threads: int | None = None,
    per_trial: bool = False,
) -> Candidate:
    """Score one set of gains (default: the system's own) over ``n_trials`` trials of
    ``cycle`` with campaign seed ``seed``: the same draws for any gains."""
    ctl = _fpga(system)
    kp = ctl.kp if kp is None else kp
    ki = ctl.ki if ki is None else ki
    kd = ctl.kd if kd is None else kd
    aw: AntiWindup = ctl.anti_windup if anti_windup is None else anti_windup
    return _Evaluator(system, _dense(cycle), objective, n_trials, seed, threads, per_trial)(
        (kp, ki, kd, aw)
    )


class _Evaluator:
    """The objective as a picklable callable of (kp, ki, kd, anti_windup) → Candidate."""

    def __init__(
        self,
        system: System,
        dense: _Dense,
        objective: Objective,
        n_trials: int,
        seed: int,
        threads: int | None,
        per_trial: bool = False,
    ) -> None:
        self.system = system
        self.dense = dense
        self.objective = objective
        self.n_trials = n_trials
        self.seed = seed
        self.threads = threads
        self.per_trial = per_trial
        # The process running the search: a pool worker it started exits when it is gone.
        self.parent_pid = os.getpid()

    def __call__(self, key: tuple[float, float, float, AntiWindup]) -> Candidate:
        watch_parent(self.parent_pid)
        kp, ki, kd, aw = key
        sys_c = _with_candidate(self.system, kp, ki, kd, aw)
        res = run_campaign(
            sys_c,
            self.dense.dense,
            n_trials=self.n_trials,
            seed=self.seed,
            threads=self.threads,
            progress=False,
        )
        m = _score(self.dense, res, sys_c, self.objective, per_trial=self.per_trial)
        return Candidate(kp=kp, ki=ki, kd=kd, anti_windup=aw, metrics=m)


def pareto_front(
    candidates: Sequence[Candidate],
    x: Callable[[Candidate], float] = lambda c: c.metrics.settling_time_s,
    y: Callable[[Candidate], float] = lambda c: c.metrics.accuracy_up_m,
) -> list[Candidate]:
    """The candidates no other candidate beats in both ``x`` and ``y`` (default: settling
    time and A↑; lower is better), sorted by ``x``. Candidates with a non-finite figure or a
    failed trial are left out."""
    pts = [
        c
        for c in candidates
        if math.isfinite(x(c)) and math.isfinite(y(c)) and c.metrics.n_failed == 0
    ]
    pts.sort(key=lambda c: (x(c), y(c)))
    front: list[Candidate] = []
    best_y = math.inf
    for c in pts:
        if y(c) < best_y:
            front.append(c)
            best_y = y(c)
    return front


# --------------------------------------------------------------------------------------------
# The search
# --------------------------------------------------------------------------------------------


def check_search(n_trials: int, seed: int, popsize: int, maxiter: int) -> tuple[int, int, int, int]:
    """Check the search settings of :func:`tune` (before any work); returns them as ints.

    Raises
    ------
    ConfigError
        A setting outside its range (see :func:`tune`).
    """
    return (
        int_arg("n_trials", n_trials, 1, 100_000),
        int_arg("seed", seed, 0, 2**32 - 1),
        int_arg("popsize", popsize, 4, 100),
        int_arg("maxiter", maxiter, 1, 10_000),
    )


def tune(
    system: System,
    cycle: Cycle,
    *,
    objective: Objective,
    space: GainSpace | None = None,
    n_trials: int = 200,
    seed: int = 0,
    campaign_seed: int | None = None,
    popsize: int = 5,
    maxiter: int = 10,
    tol: float = 1e-3,
    threads: int | None = None,
    executor: Executor | Any | None = None,
    progress: bool = True,
    x0_from_system: bool = True,
) -> TuneResult:
    """Search the FPGA PID's gains (and anti-windup option) of ``system`` that minimise
    ``objective`` over ``n_trials`` trials of ``cycle``.

    Parameters
    ----------
    system : System
        The loop, with an :class:`~nanostage.FpgaPid`. Its random effects (stochastic friction,
        encoder noise, jitter) make the trials differ; without any, every trial is the same.
    cycle : Cycle
        The test each trial runs (:func:`tuning_cycle` for one step size, or any
        :func:`~nanostage.cycles.standard_test_cycle`).
    objective : Objective
        What to minimise.
    space : GainSpace, optional
        Bounds, integrality and anti-windup options (default :class:`GainSpace`).
    n_trials : int, default 200
        Trials per candidate, in [1, 100000].
    seed : int, default 0
        Seed of the optimiser, in [0, 2**32).
    campaign_seed : int, optional
        Campaign seed of every candidate's trials (common random numbers); default ``seed``.
    popsize : int, default 5
        scipy's population multiplier (population = ``popsize ·`` number of variables),
        in [4, 100].
    maxiter : int, default 10
        Generations, in [1, 10000].
    tol : float, default 1e-3
        scipy's relative convergence tolerance, in [0, 1].
    threads : int, optional
        Threads of each candidate's campaign (local run); default all cores.
    executor : concurrent.futures.Executor or dask.distributed.Client, optional
        Evaluate the candidates of a generation on its workers (each with one thread).
    progress : bool, default True
        A progress bar on stderr (evaluations, best objective).
    x0_from_system : bool, default True
        Start the population from the system's own gains (clipped to the bounds) besides the
        random members, so the search is never worse than where it started.

    Returns
    -------
    TuneResult

    Raises
    ------
    ConfigError
        Invalid settings or bounds outside the gain format, before any simulation.
    """
    space = GainSpace() if space is None else space
    if not isinstance(objective, Objective):
        raise TypeError(f"objective must be an Objective, not {type(objective).__name__}")
    if not isinstance(space, GainSpace):
        raise TypeError(f"space must be a GainSpace, not {type(space).__name__}")
    ctl = _fpga(system)
    space.check_format(ctl)
    n_trials, seed, popsize, maxiter = check_search(n_trials, seed, popsize, maxiter)
    cseed = seed if campaign_seed is None else int_arg("campaign_seed", campaign_seed, 0, 2**64 - 1)
    tol_v = _finite_nonneg("tol", tol)
    if tol_v > 1.0:
        raise _bad("tol", tol, "a number in [0, 1]")
    if not isinstance(cycle, Cycle):
        raise TypeError(f"cycle must be a Cycle, not {type(cycle).__name__}")
    dense = _dense(cycle)
    per_eval_threads = 1 if executor is not None else threads
    evaluator = _Evaluator(system, dense, objective, n_trials, cseed, per_eval_threads)

    bounds = [space.kp_bounds, space.ki_bounds, space.kd_bounds]
    n_aw = len(space.anti_windup)
    if n_aw > 1:
        bounds.append((0.0, float(n_aw - 1)))
    integrality = [space.integer_gains] * 3 + ([True] if n_aw > 1 else [])

    def key_of(x: Sequence[float] | FloatArray) -> tuple[float, float, float, AntiWindup]:
        kp, ki, kd = space.quantise(ctl, x[:3])
        aw = space.anti_windup[round(float(x[3])) if n_aw > 1 else 0]
        return kp, ki, kd, aw

    cache: dict[tuple[float, float, float, AntiWindup], Candidate] = {}
    order: list[tuple[float, float, float, AntiWindup]] = []
    n_calls = 0
    total = popsize * len(bounds) * (maxiter + 1) + 1
    bar = ProgressBar(total, sys.stderr if progress else None, "tune", unit="candidates")

    def remember(c: Candidate) -> Candidate:
        key = (c.kp, c.ki, c.kd, c.anti_windup)
        if key not in cache:
            cache[key] = c
            order.append(key)
        return c

    def report() -> None:
        best = min(cache.values(), key=lambda c: c.objective) if cache else None
        extra = f", best J {best.objective:.4g}" if best is not None else ""
        bar.update(n_calls, suffix=extra)

    def objective_fn(x: FloatArray) -> float:
        nonlocal n_calls
        n_calls += 1
        key = key_of(x)
        c = cache.get(key) or remember(evaluator(key))
        report()
        return c.objective

    def mapper(fn: Callable[[FloatArray], float], xs: Any) -> list[float]:
        # Evaluate the new keys of a generation on the executor, then answer from the cache.
        nonlocal n_calls
        xs = list(xs)
        keys = [key_of(x) for x in xs]
        new = list(dict.fromkeys(k for k in keys if k not in cache))
        futures = [executor.submit(evaluator, k) for k in new]  # type: ignore[union-attr]
        try:
            for f in futures:
                remember(f.result())
        except BaseException:
            for f in futures:
                f.cancel()
            raise
        n_calls += len(xs)
        report()
        return [cache[k].objective for k in keys]

    t0 = time.perf_counter()
    start_key = (ctl.kp, ctl.ki, ctl.kd, ctl.anti_windup)
    start = remember(evaluator(start_key))
    n_calls += 1
    x0 = None
    if x0_from_system:
        x0_list = [
            float(min(max(v, a), b)) for v, (a, b) in zip(start_key[:3], bounds[:3], strict=True)
        ]
        if n_aw > 1:
            aw_i = (
                space.anti_windup.index(ctl.anti_windup)
                if ctl.anti_windup in space.anti_windup
                else 0
            )
            x0_list.append(float(aw_i))
        x0 = np.asarray(x0_list)
    kwargs: dict[str, Any] = {}
    if executor is not None:
        kwargs["workers"] = mapper
        kwargs["updating"] = "deferred"
    res = differential_evolution(
        objective_fn,
        bounds,
        seed=seed,
        popsize=popsize,
        maxiter=maxiter,
        tol=tol_v,
        polish=False,
        init="latinhypercube",
        integrality=integrality,
        x0=x0,
        **kwargs,
    )
    wall = time.perf_counter() - t0
    bar.update(n_calls, final=True)
    history = tuple(cache[k] for k in order)
    best = min(history, key=lambda c: c.objective)
    return TuneResult(
        best=best,
        start=start,
        history=history,
        n_evaluations=n_calls,
        wall_s=wall,
        message=str(res.message),
        settings={
            "n_trials": n_trials,
            "seed": seed,
            "campaign_seed": cseed,
            "popsize": popsize,
            "maxiter": maxiter,
            "tol": tol_v,
            "objective": objective.to_dict(),
            "space": {
                "kp_bounds": list(space.kp_bounds),
                "ki_bounds": list(space.ki_bounds),
                "kd_bounds": list(space.kd_bounds),
                "integer_gains": space.integer_gains,
                "anti_windup": list(space.anti_windup),
            },
            "cycle": {
                "n_samples": cycle.n_samples,
                "n_measurements": cycle.n_measurements,
                "duration_s": cycle.duration_s,
            },
        },
    )
