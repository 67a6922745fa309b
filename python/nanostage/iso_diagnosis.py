"""Which effect explains a measured ISO 230-2 test? (``nanostage iso-diagnose``)

The closed loop servoes the encoder; an ISO 230-2 test reads an interferometer at the
functional point. What lies between (the measurement chain of :mod:`nanostage.measurement`)
is invisible to the loop, so a trace diagnosis cannot find it. This module compares a
measured test with a model's Monte Carlo campaign of the *same* test (its targets, runs,
directions and order) and says which chain effect, or which in-loop effect, if any,
explains the difference.

Method (docs/iso-diagnosis.md):

1. **Features** of the measurement (:func:`iso_features`): mean deviation, scatter and
   reversal value per target, the trend of the deviations with time (or run order) within
   each target and direction, and the amplitude of a sinusoid of the per-target mean
   deviation at the scale's signal period and at the screw lead.
2. **One campaign** of the model on the measurement's test cycle
   (:func:`measurement_cycle`, :func:`nanostage.campaign.run_campaign`, Rust/rayon or an
   executor), read through the nominal interferometer noise. Its trials give the model's
   mean deviation per reading and its scatter.
3. **Fit** each candidate (:data:`CANDIDATES`) to the residual (measured minus the model's
   mean deviation per reading; with the file's encoder readings, the interferometer minus
   the encoder against the model's position minus its encoder): the chain's component is
   linear in its amplitudes, so its columns are the chain applied, at unit amplitudes, to
   the campaign's readings, and the amplitudes are a least-squares solution with a free
   zero offset and the loop's direction-dependent stop as a nuisance bounded within half
   an encoder count; a time constant is scanned on a grid and refined. The residual is
   Gaussian with a variance free within ``[1/scatter_tolerance, scatter_tolerance]`` times
   the model's (the model's own scatter is uncertain); a random component (noise, angular
   repeatability, a residual oscillation) frees the upper bound.
4. **Significance against the Monte Carlo noise**: each candidate's likelihood gain over
   "none" is compared with the gains the same fit finds on the campaign's own trials taken
   as measurements (a test of the model itself, read with the nominal noise and the
   loop's tolerance), and with a χ² bound for its number of parameters; its fitted effect
   must also exceed half an encoder count. "none" is the verdict when no candidate passes.
5. **Ranking by the ISO quantities**: each fitted candidate predicts tests (the campaign's
   trials plus its fitted error and scatter); its ISO gap is the rms of the z-scores of the
   measured E, A, R, B, M (per direction) and the per-target mean deviations against that
   prediction's spread over trials. Candidates the data cannot tell apart
   (:func:`_select`) are reported as *indistinguishable*, each with the experiment that
   would separate them (:data:`SEPARATING_TESTS`); the verdict is the one with the fewest
   parameters.

In-loop effects (:data:`IN_LOOP_CANDIDATES`: a backlash, a friction scatter) change where
the loop stops: each is fitted by campaigns of the model with the effect added, a scan of
its size with the model's seed (common random numbers), interpolated between the sizes and
refined between the best size's neighbours, on the encoder's deviations when the file has
them (a chain effect is not in them), else on the interferometer's; then judged by the
same significance and ranking. A size at which the loop stops more than a count apart on
the runs of one approach makes the loop hunt: there only the change per direction is
kept and the rest counts as scatter (a hunting table's place at the reading is a phase of
its limit cycle no other test repeats). The controller's gains are not covered
(:data:`NOT_COVERED`). The encoder's
interpolation error acts in the loop but its effect on where the table stops is, to first
order, ``−A·sin(2π x/λ + φ)`` at the target (docs/effects.md): it is fitted that way.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
import sys
import time
from collections.abc import Callable, Sequence
from concurrent.futures import Executor
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any, Final

import numpy as np
import numpy.typing as npt
from scipy.optimize import lsq_linear, minimize_scalar
from scipy.stats import chi2

from . import iso230_2
from ._core import ConfigError
from .campaign import CampaignResult, run_campaign
from .checks import int_arg
from .config import System
from .cycles import Cycle, MoveProfile
from .effects import Backlash, EncoderErrors, StochasticFriction
from .fitting import simplest_of_ties
from .measurement import (
    AbbeError,
    InterferometerEnvironment,
    IsoMeasurement,
    MeasurementChain,
    ScaleError,
    SettlingResidual,
    ThermalDrift,
    arrival_times,
)
from .output import ProgressBar, staged_output, write_json

__all__ = [
    "CANDIDATES",
    "IN_LOOP_CANDIDATES",
    "NOT_COVERED",
    "SEPARATING_TESTS",
    "InLoopCandidate",
    "IsoDiagnosisSettings",
    "diagnose_iso",
    "iso_features",
    "measurement_cycle",
    "write_iso_diagnosis",
]

FloatArray = npt.NDArray[np.float64]
IntArray = npt.NDArray[np.int64]

#: Time constants of the thermal drift's scan [s].
THERMAL_TIME_CONSTANTS_S: Final[tuple[float, ...]] = (150.0, 300.0, 600.0, 1200.0, 2400.0)
#: Time constants of the settling creep's scan [s].
CREEP_TIME_CONSTANTS_S: Final[tuple[float, ...]] = (0.05, 0.1, 0.2, 0.4, 0.8)
#: Relative ridge on the candidates' amplitudes (picks the smallest effect among equal fits).
_RIDGE: Final[float] = 1e-6
#: Least spread of a predicted ISO quantity in the z-scores [m].
_SD_FLOOR_M: Final[float] = 1e-9
#: Axis parameters of the ISO gap (the reversal's signed mean is left out: B covers it).
ISO_QUANTITIES: Final[tuple[str, ...]] = tuple(
    attr for _, attr, _ in iso230_2.AXIS_PARAMETERS if attr != "mean_reversal_m"
)

#: What the diagnosis does not fit, and why.
NOT_COVERED: Final[dict[str, str]] = {
    "backlash_hunting_pattern": "where a hunting loop (a backlash of 14 µm and more on the "
    "seed axis) is at each reading: a phase of its limit cycle no other test repeats, so "
    "only its offset per direction and its scatter are fitted, and its width only up to "
    "the scan's widest (the loop's swing hardly grows beyond): use nanostage diagnose on "
    "traces for the cycle itself",
    "controller_gains": "in the loop: use nanostage diagnose or nanostage tune",
}

#: The experiment that separates two candidates one test cannot (unordered pairs).
SEPARATING_TESTS: Final[dict[frozenset[str], str]] = {
    frozenset({"scale_error", "abbe"}): "a second measuring point (another Abbe offset): an "
    "Abbe error scales with the offset, a scale error does not",
    frozenset({"thermal_drift", "refractive_index_drift"}): "a repeat at a later time (a "
    "thermal rise levels off, an index drift goes on) with the air's temperature and "
    "pressure logged beside the structure's",
    frozenset({"interferometer_noise", "abbe"}): "a second measuring point: the angular "
    "repeatability scales with the Abbe offset, the interferometer's noise does not",
    frozenset({"interferometer_noise", "settling_residual"}): "a repeat with a longer dwell: a "
    "residual oscillation decays, the interferometer's noise does not",
    frozenset({"scale_error", "thermal_drift"}): "a repeat at a later time with the "
    "temperature logged: a thermal expansion changes with the temperature, a scale error "
    "does not",
    frozenset({"scale_error", "refractive_index_drift"}): "a repeat at a later time: an "
    "index drift grows with the time since the interferometer's zero, a scale error does not",
    frozenset({"abbe", "settling_residual"}): "a bidirectional cycle with other step lengths "
    "(a creep scales with the move, a tilt with the direction only) and a second measuring "
    "point",
    frozenset({"backlash", "abbe"}): "a bidirectional cycle with a longer dwell and the "
    "encoder's readings logged (the loop pulls a backlash's lost motion back given time and "
    "the table's encoder sees it; a direction-dependent tilt stays and the encoder does not "
    "see it)",
    frozenset({"backlash", "settling_residual"}): "a bidirectional cycle with a longer dwell "
    "and other step lengths (a creep scales with the move and decays, a backlash's lost "
    "motion follows the direction only)",
    frozenset({"backlash", "interpolation_error"}): "a bidirectional cycle at targets shifted "
    "by a fraction of the signal period (an interpolation error follows the position, a "
    "backlash the direction)",
    frozenset({"friction_scatter", "interferometer_noise"}): "the encoder's readings logged "
    "beside the interferometer's, or two readings at each stop (a scatter of the stops is in "
    "the encoder's readings and the same at both readings; the interferometer's noise is not)",
    frozenset({"backlash", "interferometer_noise"}): "the encoder's readings logged beside "
    "the interferometer's (a hunting loop's stops are in the encoder's readings; the "
    "interferometer's noise is not)",
    frozenset({"friction_scatter", "abbe"}): "a second measuring point (an angular "
    "repeatability scales with the Abbe offset, a scatter of the stops does not)",
    frozenset({"friction_scatter", "settling_residual"}): "a repeat with a longer dwell (a "
    "residual oscillation decays, a stop's scatter stays)",
    frozenset({"friction_scatter", "thermal_drift"}): "a repeat at a later time (a drift "
    "follows the time, a stop's scatter has no order)",
}
_DEFAULT_SEPARATION: Final[str] = (
    "a bidirectional cycle, a repeat at a later time and a second measuring point"
)


def separating_test(a: str, b: str) -> str:
    """The experiment that would separate candidates ``a`` and ``b``."""
    return SEPARATING_TESTS.get(frozenset({a, b}), _DEFAULT_SEPARATION)


# --------------------------------------------------------------------------------------------
# Settings
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True, kw_only=True)
class IsoDiagnosisSettings:
    """Settings of an ISO-level diagnosis (the test's timing where the file has none).

    Attributes
    ----------
    n_trials : int
        Trials of the model's campaign, in [4, 4096] (also the null tests of significance).
    seed : int
        Campaign seed, in [0, 2**32).
    dwell_s : float
        Rest at each target before the reading [s], in [0.001, 60].
    overrun_m : float
        Distance run past a target before reversing [m], in (0, 0.1].
    velocity_m_per_s, acceleration_m_per_s2 : float
        The trapezoidal move between targets [m/s] in (0, 10], [m/s²] in (0, 1000].
    reading_noise_m : float
        Nominal noise of the interferometer's reading [m], in [0, 1e-6] (docs/effects.md:
        1–10 nm rms).
    scatter_tolerance : float
        Factor the model's scatter (variance) is trusted within, in [1, 100].
    abbe_offset_m : float
        Abbe offset the fitted angles refer to [m], in (0, 1] (the fit finds offset × angle).
    loop_tolerance_m : float or None
        How far the model's stop at a target is trusted [m], in [0, 1e-5]: the loop ends
        within about one encoder count, so a model whose nominal parameters are off stops
        elsewhere within it. Adds ``tol²/12`` to the model's variance, and a candidate whose
        fitted effect (rms over the readings) is below ``tol / 2`` is not significant.
        Default: the model's encoder count.
    in_loop_trials : int
        Trials of each campaign of the in-loop candidates' scans, in [2, 4096] (the same
        seed as the model's campaign: common random numbers).
    backlash_widths_m : tuple of float
        The backlash scan's widths [m], ascending, each in (0, 1e-2] (the fit interpolates
        between them and the model without backlash at zero width).
    friction_spreads : tuple of float
        The friction scatter scan's spreads, ascending, each in (0, 0.5] (level and
        within-trial spread of :class:`nanostage.effects.StochasticFriction`).
    """

    n_trials: int = 16
    seed: int = 0
    dwell_s: float = 0.5
    overrun_m: float = 1e-3
    velocity_m_per_s: float = 5e-3
    acceleration_m_per_s2: float = 0.05
    reading_noise_m: float = 10e-9
    scatter_tolerance: float = 4.0
    abbe_offset_m: float = 0.02
    loop_tolerance_m: float | None = None
    in_loop_trials: int = 2
    backlash_widths_m: tuple[float, ...] = (6e-6, 8e-6, 10e-6, 12e-6, 14e-6, 20e-6)
    friction_spreads: tuple[float, ...] = (0.1, 0.2, 0.35, 0.5)

    def __post_init__(self) -> None:
        int_arg("n_trials", self.n_trials, 4, 4096, strict=True)
        int_arg("in_loop_trials", self.in_loop_trials, 2, 4096, strict=True)
        for name, hi, unit in (("backlash_widths_m", 1e-2, "m"), ("friction_spreads", 0.5, "")):
            grid = getattr(self, name)
            ok = isinstance(grid, tuple) and all(
                isinstance(v, (int, float)) and not isinstance(v, bool) and 0 < v <= hi
                for v in grid
            )
            if not ok or any(b <= a for a, b in itertools.pairwise(grid)):
                raise ConfigError(
                    f"{name} = {grid!r} is invalid: expected an ascending tuple of values in "
                    f"(0, {hi:g}] {unit}".rstrip()
                )
        int_arg("seed", self.seed, 0, 2**32 - 1, strict=True)
        for name, lo, hi, unit, lo_open in (
            ("dwell_s", 1e-3, 60.0, "s", False),
            ("overrun_m", 0.0, 0.1, "m", True),
            ("velocity_m_per_s", 0.0, 10.0, "m/s", True),
            ("acceleration_m_per_s2", 0.0, 1000.0, "m/s²", True),
            ("reading_noise_m", 0.0, 1e-6, "m", False),
            ("scatter_tolerance", 1.0, 100.0, "", False),
            ("abbe_offset_m", 0.0, 1.0, "m", True),
            ("loop_tolerance_m", 0.0, 1e-5, "m", False),
        ):
            v = getattr(self, name)
            if v is None and name == "loop_tolerance_m":
                continue
            ok = isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
            ok = ok and (v > lo if lo_open else v >= lo) and v <= hi
            if not ok:
                rng = f"{'(' if lo_open else '['}{lo:g}, {hi:g}]"
                raise ConfigError(f"{name} = {v!r} is invalid: expected a value in {rng} {unit}")

    @property
    def move(self) -> MoveProfile:
        """The move between targets."""
        return MoveProfile(
            kind="trapezoid",
            max_velocity_m_per_s=self.velocity_m_per_s,
            acceleration_m_per_s2=self.acceleration_m_per_s2,
        )


# --------------------------------------------------------------------------------------------
# The measurement's layout and features
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class _Layout:
    """Where each reading (in the order of the test) sits in the ISO matrices."""

    targets_m: FloatArray  # distinct targets, ascending
    target_index: IntArray  # per reading
    direction: IntArray  # per reading, ±1
    run_index: IntArray  # per reading, 0-based
    n_runs: int
    bidirectional: bool
    target_m: FloatArray  # per reading (the distinct target's exact value)


def _layout(meas: IsoMeasurement, tolerance_m: float = 1e-9) -> _Layout:
    rec = meas.records
    order = np.argsort(rec.target_m, kind="stable")
    tgt = np.asarray(rec.target_m, dtype=np.float64)
    index = np.empty(len(tgt), dtype=np.int64)
    distinct: list[float] = []
    for i in order:
        if not distinct or tgt[i] - distinct[-1] > tolerance_m:
            distinct.append(float(tgt[i]))
        index[i] = len(distinct) - 1
    direction = np.where(np.asarray(rec.direction) == "+", 1, -1).astype(np.int64)
    run = np.asarray(rec.run, dtype=np.int64)
    targets = np.asarray(distinct, dtype=np.float64)
    return _Layout(
        targets_m=targets,
        target_index=index,
        direction=direction,
        run_index=run - 1,
        n_runs=int(np.max(run)),
        bidirectional=bool(np.any(direction < 0)),
        target_m=targets[index],
    )


def _evaluate(lay: _Layout, deviation_m: FloatArray) -> iso230_2.Iso230Result:
    """ISO 230-2 of one test's deviations (one value per reading, in the test's order)."""
    n_t = lay.targets_m.shape[0]
    up = np.zeros((n_t, lay.n_runs))
    down = np.zeros((n_t, lay.n_runs))
    upm = lay.direction > 0
    up[lay.target_index[upm], lay.run_index[upm]] = deviation_m[upm]
    if lay.bidirectional:
        dm = ~upm
        down[lay.target_index[dm], lay.run_index[dm]] = deviation_m[dm]
    return iso230_2.evaluate(lay.targets_m, up, down if lay.bidirectional else None)


def _iso_vector(lay: _Layout, deviation_m: FloatArray) -> tuple[FloatArray, FloatArray]:
    """(axis quantities of :data:`ISO_QUANTITIES` (NaN where absent), per-target mean
    deviations ↑ then ↓) of one test."""
    r = _evaluate(lay, deviation_m)
    params = r.axis_parameters()
    axis = np.array([np.nan if params[q] is None else params[q] for q in ISO_QUANTITIES])
    means = [r.mean_deviation_up_m]
    if r.mean_deviation_down_m is not None:
        means.append(r.mean_deviation_down_m)
    return axis.astype(np.float64), np.concatenate(means)


def _sinusoid(x: FloatArray, y: FloatArray, period_m: float) -> dict[str, float]:
    """Least-squares ``y ≈ c + a·sin(2πx/λ) + b·cos(2πx/λ)``: amplitude, phase and the
    amplitude's standard error."""
    w = 2.0 * math.pi * x / period_m
    design = np.column_stack([np.ones_like(x), np.sin(w), np.cos(w)])
    coef, *_ = np.linalg.lstsq(design, y, rcond=None)
    dof = max(x.shape[0] - 3, 1)
    resid = y - design @ coef
    s2 = float(resid @ resid) / dof
    cov = s2 * np.linalg.pinv(design.T @ design)
    amp = math.hypot(coef[1], coef[2])
    # Standard error of the amplitude (delta method; the larger axis when amp ≈ 0).
    if amp > 0:
        g = np.array([0.0, coef[1] / amp, coef[2] / amp])
        se = math.sqrt(max(float(g @ cov @ g), 0.0))
    else:
        se = math.sqrt(max(float(cov[1, 1]), float(cov[2, 2]), 0.0))
    return {
        "period_m": period_m,
        "amplitude_m": amp,
        "amplitude_se_m": se,
        "phase_rad": math.atan2(coef[2], coef[1]),
    }


def iso_features(
    meas: IsoMeasurement,
    *,
    scale_pitch_m: float = EncoderErrors().cyclic_period_m,
    screw_lead_m: float | None = None,
) -> dict[str, Any]:
    """Per-target features of a measured ISO test.

    Returns
    -------
    dict
        ``targets_m``; ``mean_deviation_up_m``, ``mean_deviation_down_m`` (per target),
        ``std_up_m``, ``std_down_m`` (n − 1), ``reversal_m`` (x̄↑ − x̄↓ per target);
        ``trend``: the slope of the deviations against time (``time_s`` of the file, else the
        run number) after each target and direction's mean is removed, with its standard
        error (``per_s`` or ``per_run``); ``periodic``: the sinusoid of the per-target mean
        deviation (both directions averaged) at the scale pitch and the screw lead
        (amplitude, its standard error, phase).
    """
    lay = _layout(meas)
    dev = np.asarray(meas.records.actual_m, dtype=np.float64) - lay.target_m
    r = _evaluate(lay, dev)
    group = lay.target_index * 2 + (lay.direction < 0)
    resid = dev.copy()
    clock = (
        np.asarray(meas.time_s, dtype=np.float64)
        if meas.time_s is not None
        else lay.run_index.astype(np.float64) + 1.0
    )
    xc = clock.copy()
    for g in np.unique(group):
        m = group == g
        resid[m] -= resid[m].mean()
        xc[m] -= xc[m].mean()
    sxx = float(xc @ xc)
    slope = float(xc @ resid) / sxx if sxx > 0 else 0.0
    dof = max(dev.shape[0] - np.unique(group).shape[0] - 1, 1)
    s2 = float(((resid - slope * xc) ** 2).sum()) / dof
    slope_se = math.sqrt(s2 / sxx) if sxx > 0 else math.inf
    mean_bi = (
        r.mean_bidirectional_deviation_m
        if r.mean_bidirectional_deviation_m is not None
        else r.mean_deviation_up_m
    )
    periodic = {"scale_pitch": _sinusoid(r.targets_m, mean_bi, scale_pitch_m)}
    if screw_lead_m is not None:
        periodic["screw_lead"] = _sinusoid(r.targets_m, mean_bi, screw_lead_m)
    unit = "per_s" if meas.time_s is not None else "per_run"
    out: dict[str, Any] = {
        "targets_m": r.targets_m,
        "mean_deviation_up_m": r.mean_deviation_up_m,
        "mean_deviation_down_m": r.mean_deviation_down_m,
        "std_up_m": r.std_up_m,
        "std_down_m": r.std_down_m,
        "reversal_m": r.reversal_at_target_m,
        "trend": {
            "against": "time_s" if meas.time_s is not None else "run",
            f"slope_m_{unit}": slope,
            f"slope_se_m_{unit}": slope_se,
        },
        "periodic": periodic,
    }
    if meas.encoder_m is not None:
        out["interferometer_minus_encoder_mean_m"] = float(
            np.mean(np.asarray(meas.records.actual_m) - meas.encoder_m)
        )
    return out


# --------------------------------------------------------------------------------------------
# The test cycle of a measurement
# --------------------------------------------------------------------------------------------


def measurement_cycle(
    meas: IsoMeasurement, settings: IsoDiagnosisSettings, sample_period_s: float
) -> Cycle:
    """The cycle that reads the measurement's targets in the file's order, each approached
    from its direction: a reading whose direction needs the axis on the other side first
    runs past the target by ``overrun_m`` and holds there one dwell; each target is held for
    ``dwell_s`` and read at the end of the dwell."""
    lay = _layout(meas)
    move = settings.move
    dwell = max(1, round(settings.dwell_s / sample_period_s))
    tgt = lay.target_m
    d0 = int(lay.direction[0])
    cur = float(tgt[0]) - d0 * settings.overrun_m
    parts: list[FloatArray] = [np.full(dwell, cur)]
    n = dwell
    index = np.empty(tgt.shape[0], dtype=np.int64)
    for k in range(tgt.shape[0]):
        p = float(tgt[k])
        d = int(lay.direction[k])
        if (d > 0 and cur >= p) or (d < 0 and cur <= p):
            pre = p - d * settings.overrun_m
            seg = move.samples(cur, pre, sample_period_s)
            parts += [seg, np.full(dwell, pre)]
            n += seg.shape[0] + dwell
            cur = pre
        seg = move.samples(cur, p, sample_period_s)
        parts += [seg, np.full(dwell, p)]
        n += seg.shape[0] + dwell
        index[k] = n - 1
        cur = p
    ref = np.concatenate(parts)
    return Cycle(
        reference_m=ref,
        sample_period_s=sample_period_s,
        measure_index=index,
        target_m=ref[index],
        direction=lay.direction,
        run=lay.run_index + 1,
    )


# --------------------------------------------------------------------------------------------
# Candidates
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class _Context:
    """What the candidates' columns are built from."""

    campaign: CampaignResult
    rows: IntArray  # completed trials
    time_s: FloatArray  # reading times (the file's, else the cycle's)
    direction: IntArray
    move_m: FloatArray
    dwell_s: FloatArray
    target_m: FloatArray
    x_ref_m: float  # first target (the interferometer's zero)
    x_centre_m: float
    temperature_k: FloatArray | None
    scale_pitch_m: float
    settings: IsoDiagnosisSettings

    def apply(self, chain: MeasurementChain) -> FloatArray:
        """The chain's error at each reading, averaged over the campaign's trials."""
        err = chain.error_m(
            position_m=self.campaign.position_m[self.rows],
            time_s=self.time_s,
            direction=self.direction,
            move_m=self.move_m,
            dwell_s=self.dwell_s,
            seed=self.campaign.seed,
        )
        out: FloatArray = np.mean(err, axis=0)
        return out


@dataclass(frozen=True, slots=True, kw_only=True)
class Candidate:
    """One effect the diagnosis fits.

    Attributes
    ----------
    name : str
        Stable name (docs/iso-diagnosis.md).
    what : str
        The component and what it fits, in words.
    parameters : tuple of str
        Names of the fitted amplitudes (one column each), in the chain's units.
    random : bool
        It has a random part (adds scatter; frees the variance's upper bound).
    columns : callable
        ``columns(context)`` → list of (grid value or None, columns of shape (n, p), unit of
        each column's amplitude).
    """

    name: str
    what: str
    parameters: tuple[str, ...]
    random: bool
    columns: Callable[[_Context], list[tuple[float | None, FloatArray, FloatArray]]] = field(
        repr=False
    )
    refine: Callable[[_Context, float], tuple[FloatArray, FloatArray]] | None = field(
        default=None, repr=False
    )

    @property
    def dof(self) -> int:
        """Free parameters beyond the offset and the model's scatter."""
        grid = 1 if self.name in ("thermal_drift", "settling_residual") else 0
        return len(self.parameters) + int(self.random) + grid


def _stack(*cols: FloatArray) -> FloatArray:
    return np.column_stack(cols) if cols else np.zeros((0, 0))


def _scale_cols(c: _Context) -> list[tuple[float | None, FloatArray, FloatArray]]:
    col = c.apply(MeasurementChain(scale=ScaleError(linear_error_m_per_m=1e-6, datum_m=c.x_ref_m)))
    return [(None, _stack(col), np.array([1e-6]))]


def _abbe_cols(c: _Context) -> list[tuple[float | None, FloatArray, FloatArray]]:
    h = c.settings.abbe_offset_m
    units = np.array([1e-4, 1e-2, 1e-6])
    cols = [
        c.apply(
            MeasurementChain(abbe=(AbbeError(offset_m=h, centre_m=c.x_centre_m, **{k: float(u)}),))
        )
        for k, u in zip(
            ("slope_rad_per_m", "curvature_rad_per_m2", "reversal_rad"), units, strict=True
        )
    ]
    return [(None, _stack(*cols), units)]


def _thermal_at(c: _Context, tau: float) -> tuple[FloatArray, FloatArray]:
    """Columns of the thermal drift at time constant ``tau``: the structure's shift per
    kelvin and the scale's expansion per 1e-6 /K, for a 1 K rise."""
    s = c.apply(
        MeasurementChain(
            thermal=ThermalDrift(
                temperature_rise_k=1.0, time_constant_s=tau, structure_m_per_k=1e-6
            )
        )
    )
    a = c.apply(
        MeasurementChain(
            thermal=ThermalDrift(
                temperature_rise_k=1.0,
                time_constant_s=tau,
                scale_expansion_per_k=1e-6,
                scale_datum_m=c.x_ref_m,
            )
        )
    )
    return _stack(s, a), np.array([1e-6, 1e-6])


def _thermal_cols(c: _Context) -> list[tuple[float | None, FloatArray, FloatArray]]:
    units = np.array([1e-6, 1e-6])
    if c.temperature_k is not None:
        dt = c.temperature_k - c.temperature_k[0]
        return [(None, _stack(1e-6 * dt, 1e-6 * (c.target_m - c.x_ref_m) * dt), units)]
    return [(tau, *_thermal_at(c, tau)) for tau in THERMAL_TIME_CONSTANTS_S]


def _index_cols(c: _Context) -> list[tuple[float | None, FloatArray, FloatArray]]:
    rate = 1e-10
    along = c.apply(
        MeasurementChain(
            interferometer=InterferometerEnvironment(
                refractive_index_rate_per_s=rate, zero_position_m=c.x_ref_m
            )
        )
    )
    dead = c.apply(
        MeasurementChain(
            interferometer=InterferometerEnvironment(
                refractive_index_rate_per_s=rate, dead_path_m=1.0, zero_position_m=c.x_ref_m
            )
        )
    )
    # Columns: ṅ·(x − x_ref)·t, and ṅ·L·t per metre of dead path.
    return [(None, _stack(along, dead - along), np.array([rate, rate]))]


def _settling_at(c: _Context, tau: float) -> tuple[FloatArray, FloatArray]:
    """Column of the settling creep at time constant ``tau`` (fraction 1e-3)."""
    col = c.apply(
        MeasurementChain(
            settling=SettlingResidual(
                creep_fraction=1e-3, creep_time_constant_s=tau, phase_spread_rad=0.0
            )
        )
    )
    return _stack(col), np.array([1e-3])


def _settling_cols(c: _Context) -> list[tuple[float | None, FloatArray, FloatArray]]:
    return [(tau, *_settling_at(c, tau)) for tau in CREEP_TIME_CONSTANTS_S]


def _noise_cols(c: _Context) -> list[tuple[float | None, FloatArray, FloatArray]]:
    return [(None, np.zeros((c.target_m.shape[0], 0)), np.zeros(0))]


def _interpolation_cols(c: _Context) -> list[tuple[float | None, FloatArray, FloatArray]]:
    w = 2.0 * math.pi * c.target_m / c.scale_pitch_m
    # The table stops at about target − A·sin(2πx/λ + φ) (docs/effects.md).
    return [(None, _stack(-1e-7 * np.sin(w), -1e-7 * np.cos(w)), np.array([1e-7, 1e-7]))]


#: The candidates, in the order of the report.
CANDIDATES: Final[tuple[Candidate, ...]] = (
    Candidate(
        name="scale_error",
        what="ScaleError: linear error of the scale",
        parameters=("linear_error_m_per_m",),
        random=False,
        columns=_scale_cols,
    ),
    Candidate(
        name="abbe",
        what="AbbeError: pitch/yaw slope, curvature and direction-dependent tilt times the "
        "offset, and an angular repeatability",
        parameters=("slope_rad_per_m", "curvature_rad_per_m2", "reversal_rad"),
        random=True,
        columns=_abbe_cols,
    ),
    Candidate(
        name="thermal_drift",
        what="ThermalDrift: structure and scale expansion under a first-order rise (the "
        "file's temperatures when it has them)",
        parameters=("structure_m_per_k_times_rise_k", "scale_expansion_per_k_times_rise_k"),
        random=False,
        columns=_thermal_cols,
        refine=_thermal_at,
    ),
    Candidate(
        name="refractive_index_drift",
        what="InterferometerEnvironment: the air's index drifting over the path and the dead path",
        parameters=("refractive_index_rate_per_s", "rate_times_dead_path_m_per_s"),
        random=False,
        columns=_index_cols,
    ),
    Candidate(
        name="settling_residual",
        what="SettlingResidual: a creep after each move and a residual oscillation read at a "
        "random phase",
        parameters=("creep_fraction",),
        random=True,
        columns=_settling_cols,
        refine=_settling_at,
    ),
    Candidate(
        name="interferometer_noise",
        what="InterferometerEnvironment: noise of the reading beyond the nominal",
        parameters=(),
        random=True,
        columns=_noise_cols,
    ),
    Candidate(
        name="interpolation_error",
        what="EncoderErrors (in the loop, first order): where the table stops, −A·sin(2πx/λ+φ)",
        parameters=("sin_amplitude_m", "cos_amplitude_m"),
        random=False,
        columns=_interpolation_cols,
    ),
)


def _with_backlash(system: System, width_m: float) -> System:
    """The model with a gearhead backlash of ``width_m`` (the model's own contact stiffness
    and damping when it has a backlash, else the library's)."""
    old = system.effects.backlash
    bl = Backlash(width_m=width_m) if old is None else dataclasses.replace(old, width_m=width_m)
    return dataclasses.replace(system, effects=dataclasses.replace(system.effects, backlash=bl))


def _with_friction_scatter(system: System, spread: float) -> System:
    """The model with every friction level scattered by ``spread``: a per-trial level factor
    and a within-trial fluctuation of the same spread (the model's distribution and
    correlation time when it has them)."""
    old = system.effects.stochastic
    sf = (
        StochasticFriction(level_spread=spread, within_spread=spread)
        if old is None
        else dataclasses.replace(old, level_spread=spread, within_spread=spread)
    )
    return dataclasses.replace(system, effects=dataclasses.replace(system.effects, stochastic=sf))


@dataclass(frozen=True, slots=True, kw_only=True)
class InLoopCandidate:
    """An effect in the loop, fitted by campaigns of the model with the effect added.

    Attributes
    ----------
    name, what : str
        As :class:`Candidate`.
    parameter : str
        The effect's size the scan runs over.
    random : bool
        The effect scatters the stops: it is fitted by the scatter it adds (its mean change
        over a few trials is Monte Carlo noise); else by its mean change of the stops.
    grid : callable
        ``grid(settings)`` → the scan's sizes (ascending; zero is the model itself).
    with_effect : callable
        ``with_effect(system, size)`` → the model with the effect added.
    """

    name: str
    what: str
    parameter: str
    random: bool
    grid: Callable[[IsoDiagnosisSettings], tuple[float, ...]] = field(repr=False)
    with_effect: Callable[[System, float], System] = field(repr=False)

    @property
    def dof(self) -> int:
        """Free parameters beyond the offset and the model's scatter: the size."""
        return 1


#: The in-loop candidates (fitted on the interferometer's deviations: the loop's stop is
#: what they change, and the encoder on the table sees it too).
IN_LOOP_CANDIDATES: Final[tuple[InLoopCandidate, ...]] = (
    InLoopCandidate(
        name="backlash",
        what="Backlash in the loop: where the loop stops after closing the gearhead's dead band",
        parameter="width_m",
        random=False,
        grid=lambda s: s.backlash_widths_m,
        with_effect=_with_backlash,
    ),
    InLoopCandidate(
        name="friction_scatter",
        what="StochasticFriction in the loop: the scatter of the stops under a friction level "
        "that varies from trial to trial and within a trial",
        parameter="spread",
        random=True,
        grid=lambda s: s.friction_spreads,
        with_effect=_with_friction_scatter,
    ),
)


# --------------------------------------------------------------------------------------------
# Fitting
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class _Fit:
    nll: float  # −2 log L
    offset_m: float
    beta: FloatArray  # amplitudes in column units
    grid: float | None
    variance_m2: float
    mean_m: FloatArray  # fitted deterministic part per reading (offset included)
    effect_m: FloatArray  # the candidate's part of it
    loop_reversal_m: float  # the loop's direction-dependent stop, within the tolerance


def _fit(
    r: FloatArray,
    options: Sequence[tuple[float | None, FloatArray, FloatArray]],
    random: bool,
    v0: float,
    tol: float,
    direction: FloatArray,
    bound_m: float,
    refine: Callable[[float], tuple[FloatArray, FloatArray]] | None = None,
) -> tuple[_Fit, FloatArray]:
    """Least squares with a free offset; Gaussian likelihood with the variance profiled in
    ``[v0/tol, v0·tol]`` (no upper bound for a random candidate) and a direction-dependent
    offset of the loop's stops within ``±bound_m``. With ``refine``, the
    grid's best value is refined between its neighbours (bounded, in log). Returns the fit
    and the units of its amplitudes."""
    best, units = _fit_grid(r, options, random, v0, tol, direction, bound_m)
    grid = [float(g) for g, _, _ in options if g is not None]
    if refine is None or best.grid is None or len(grid) < 2:
        return best, units
    k = grid.index(best.grid)
    lo = math.log(grid[max(k - 1, 0)])
    hi = math.log(grid[min(k + 1, len(grid) - 1)])

    def nll(log_value: float) -> float:
        cols, u = refine(math.exp(log_value))
        opts = [(math.exp(log_value), cols, u)]
        return _fit_grid(r, opts, random, v0, tol, direction, bound_m)[0].nll

    res = minimize_scalar(nll, bounds=(lo, hi), method="bounded", options={"xatol": 0.02})
    if float(res.fun) < best.nll:
        value = math.exp(float(res.x))
        cols, u = refine(value)
        return _fit_grid(r, [(value, cols, u)], random, v0, tol, direction, bound_m)
    return best, units


def _fit_grid(
    r: FloatArray,
    options: Sequence[tuple[float | None, FloatArray, FloatArray]],
    random: bool,
    v0: float,
    tol: float,
    direction: FloatArray,
    bound_m: float,
) -> tuple[_Fit, FloatArray]:
    """The best of the options (one least-squares fit each, the loop's direction-dependent
    stop ``±bound_m`` as a bounded nuisance)."""
    n = r.shape[0]
    best: _Fit | None = None
    best_units = np.zeros(0)
    for grid, cols, unit in options:
        design = np.column_stack([np.ones(n), direction, cols])
        scale = np.sqrt(np.mean(design**2, axis=0))
        scale[scale == 0] = 1.0
        lo = np.full(design.shape[1], -np.inf)
        hi = np.full(design.shape[1], np.inf)
        lo[1], hi[1] = -bound_m * scale[1], bound_m * scale[1]
        if bound_m > 0:
            # A tiny ridge on the candidate's amplitudes: where they and the loop's nuisance
            # explain the same (a reversal), the nuisance takes what its bound allows.
            p = design.shape[1]
            ridge = np.zeros((p - 2, p))
            ridge[:, 2:] = np.eye(p - 2) * math.sqrt(_RIDGE * n)
            a = np.vstack([design / scale, ridge])
            b = np.concatenate([r, np.zeros(p - 2)])
            coef = lsq_linear(a, b, bounds=(lo, hi), method="bvls").x / scale
        else:
            coef, *_ = np.linalg.lstsq(design / scale, r, rcond=None)
            coef = coef / scale
            coef[1] = 0.0
        fitted = design @ coef
        rss = float(((r - fitted) ** 2).sum())
        var = rss / n
        var = max(var, v0 / tol) if random else min(max(var, v0 / tol), v0 * tol)
        nll = n * math.log(2.0 * math.pi * var) + rss / var
        if best is None or nll < best.nll:
            best = _Fit(
                nll=nll,
                offset_m=float(coef[0]),
                beta=np.asarray(coef[2:], dtype=np.float64),
                grid=grid,
                variance_m2=var,
                mean_m=fitted,
                effect_m=design[:, 2:] @ coef[2:],
                loop_reversal_m=2.0 * float(coef[1]),
            )
            best_units = unit
    assert best is not None
    return best, best_units


@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class _Scan:
    """An in-loop candidate's campaigns: per size (zero first: the model), the mean change
    of the stops against the model (zero for a random candidate) and the scatter added."""

    sizes: FloatArray
    effect_m: FloatArray  # (sizes, readings), on the fitted reading
    position_effect_m: FloatArray  # (sizes, readings), of the table's position
    extra_var_m2: FloatArray  # (sizes,), on the fitted reading
    failed_trials: list[int]
    seconds: float
    hunting: list[bool] = field(default_factory=list)  # per size (zero excluded)

    def _weights(self, size: float) -> tuple[int, float]:
        k = int(np.searchsorted(self.sizes, size, side="right")) - 1
        k = min(max(k, 0), self.sizes.shape[0] - 2)
        a, b = float(self.sizes[k]), float(self.sizes[k + 1])
        return k, min(max((size - a) / (b - a), 0.0), 1.0)

    def at(self, size: float) -> tuple[FloatArray, float]:
        """The effect on the fitted reading and the added variance, by linear interpolation
        between the scan's sizes (the last size beyond it)."""
        k, w = self._weights(size)
        eff: FloatArray = (1.0 - w) * self.effect_m[k] + w * self.effect_m[k + 1]
        return eff, float((1.0 - w) * self.extra_var_m2[k] + w * self.extra_var_m2[k + 1])

    def position_at(self, size: float) -> FloatArray:
        """The effect on the table's position, interpolated as :meth:`at`."""
        k, w = self._weights(size)
        out: FloatArray = (1.0 - w) * self.position_effect_m[k] + w * self.position_effect_m[k + 1]
        return out


def _scan(
    cand: InLoopCandidate,
    system: System,
    cycle: Cycle,
    base: CampaignResult,
    s: IsoDiagnosisSettings,
    threads: int | None,
    executor: Executor | Any | None,
    encoder: bool,
) -> _Scan:
    """Campaigns of the model with the effect at each of the scan's sizes, with the model's
    seed (common random numbers: trial ``i`` draws the same numbers at every size), each
    against the same trials of ``base`` (the model without the effect), on the encoder's
    reading with ``encoder``, else on the table's position (and always on the position, for
    the ISO prediction). A size whose campaign completes fewer than two trials ends the
    scan."""
    t0 = time.perf_counter()
    k = s.in_loop_trials
    target = cycle.target_m
    # The readings of one target and direction (the runs of one approach).
    _, group = np.unique(np.column_stack([target, cycle.direction]), axis=0, return_inverse=True)
    group = group.ravel()
    up = cycle.direction > 0
    count = float(system.encoder.count_m)
    base_dev = (base.encoder_m if encoder else base.position_m)[:k] - target[None, :]
    base_pos = base.position_m[:k] - target[None, :]
    base_ok = base.ok[:k]
    zero = np.zeros(target.shape[0])
    sizes, effects, positions, extra, failed = [0.0], [zero], [zero], [0.0], []
    hunting: list[bool] = []
    for size in cand.grid(s):
        camp = run_campaign(
            cand.with_effect(system, float(size)),
            cycle,
            n_trials=k,
            seed=s.seed,
            threads=threads,
            executor=executor,
            progress=False,
        )
        ok = camp.ok & base_ok
        failed.append(int(camp.n_failed))
        if int(ok.sum()) < 2:
            break
        dev = (camp.encoder_m if encoder else camp.position_m)[ok] - target[None, :]
        bdev = base_dev[ok]
        pos = camp.position_m[ok] - target[None, :] - base_pos[ok]
        eff = zero if cand.random else np.mean(dev - bdev, axis=0)
        peff = zero if cand.random else np.mean(pos, axis=0)
        v = float(np.mean(np.var(dev, axis=0, ddof=1)) - np.mean(np.var(bdev, axis=0, ddof=1)))
        # A loop that stops more than a count apart on the runs of one approach has not
        # settled: it hunts, and where a hunting table is at the reading is a phase of its
        # limit cycle that no other test repeats. Its mean change per direction is kept;
        # the rest is scatter.
        hunt = _within_rms(eff, group) > count
        if hunt:
            eff, spread = _direction_split(eff, up)
            peff, _ = _direction_split(peff, up)
            v += spread
        hunting.append(bool(hunt))
        effects.append(eff)
        positions.append(peff)
        extra.append(max(v, 0.0))
        sizes.append(float(size))
    if len(sizes) < 2:  # not one size completed: the model itself, twice
        sizes.append(1.0)
        effects.append(zero)
        positions.append(zero)
        extra.append(0.0)
    return _Scan(
        sizes=np.asarray(sizes),
        effect_m=np.asarray(effects),
        position_effect_m=np.asarray(positions),
        extra_var_m2=np.asarray(extra),
        failed_trials=failed,
        seconds=time.perf_counter() - t0,
        hunting=hunting,
    )


def _within_rms(effect_m: FloatArray, group: IntArray) -> float:
    """Rms of the effect about its mean over each group's readings."""
    means = np.bincount(group, weights=effect_m) / np.bincount(group)
    return float(np.sqrt(np.mean((effect_m - means[group]) ** 2)))


def _direction_split(effect_m: FloatArray, up: npt.NDArray[np.bool_]) -> tuple[FloatArray, float]:
    """The effect's mean per direction at each reading, and the mean square of the rest."""
    out = np.empty_like(effect_m)
    for m in (up, ~up):
        if np.any(m):
            out[m] = float(np.mean(effect_m[m]))
    return out, float(np.mean((effect_m - out) ** 2))


def _fit_in_loop(
    r: FloatArray,
    scan: _Scan,
    v0: float,
    tol: float,
    direction: FloatArray,
    bound_m: float,
) -> _Fit:
    """The in-loop candidate's best size: each scanned size (the residual minus the effect's
    change of the stops, the variance centred on the model's plus the scatter the effect
    adds, the offset and the loop's direction-dependent stop as for the chain's
    candidates), then a bounded search between the best size's neighbours on the
    interpolated scan."""
    empty = np.zeros((r.shape[0], 0))

    def at(size: float) -> _Fit:
        eff, extra = scan.at(size)
        f = _fit_grid(
            r - eff, [(size, empty, np.zeros(0))], False, v0 + extra, tol, direction, bound_m
        )[0]
        return _Fit(
            nll=f.nll,
            offset_m=f.offset_m,
            beta=np.array([size]),
            grid=size,
            variance_m2=f.variance_m2,
            mean_m=f.mean_m + eff,
            effect_m=eff,
            loop_reversal_m=f.loop_reversal_m,
        )

    sizes = [float(v) for v in scan.sizes[1:]]
    fits = [at(v) for v in sizes]
    k = int(np.argmin([f.nll for f in fits]))
    best = fits[k]
    grid = [float(scan.sizes[0]), *sizes]
    lo, hi = grid[k], grid[min(k + 2, len(grid) - 1)]
    if hi > lo:
        res = minimize_scalar(
            lambda v: at(float(v)).nll,
            bounds=(lo, hi),
            method="bounded",
            options={"xatol": 0.01 * (hi - lo)},
        )
        if float(res.fun) < best.nll:
            best = at(float(res.x))
    return best


def _physical(
    cand: Candidate, fit: _Fit, units: FloatArray, v0: float, s: IsoDiagnosisSettings
) -> dict[str, float]:
    """The fitted amplitudes in the chain's units (and the derived magnitudes)."""
    amps = fit.beta * units
    out = {p: float(a) for p, a in zip(cand.parameters, amps, strict=True)}
    extra_var = max(fit.variance_m2 - v0, 0.0)
    if cand.name == "abbe":
        out["abbe_offset_m"] = s.abbe_offset_m
        out["noise_std_rad"] = math.sqrt(extra_var) / s.abbe_offset_m
    elif cand.name == "thermal_drift":
        if fit.grid is not None:
            out["time_constant_s"] = fit.grid
    elif cand.name == "refractive_index_drift":
        rate = out["refractive_index_rate_per_s"]
        out["dead_path_m"] = out["rate_times_dead_path_m_per_s"] / rate if rate != 0 else math.nan
    elif cand.name == "settling_residual":
        if fit.grid is not None:
            out["creep_time_constant_s"] = fit.grid
        out["oscillation_rms_at_reading_m"] = math.sqrt(extra_var)
    elif cand.name == "interferometer_noise":
        out["noise_std_m"] = math.sqrt(extra_var + s.reading_noise_m**2)
    elif cand.name == "interpolation_error":
        a, b = out["sin_amplitude_m"], out["cos_amplitude_m"]
        out["cyclic_amplitude_m"] = math.hypot(a, b)
        out["cyclic_phase_rad"] = math.atan2(b, a)
    return out


# --------------------------------------------------------------------------------------------
# The diagnosis
# --------------------------------------------------------------------------------------------


def _scale_pitch(system: System) -> float:
    enc = getattr(system.effects, "encoder_errors", None)
    return float(enc.cyclic_period_m) if enc is not None else EncoderErrors().cyclic_period_m


def _screw_lead(system: System) -> float | None:
    screw = getattr(system.plant, "screw", None)
    lead = getattr(screw, "lead_m", None)
    return float(lead) if lead is not None else None


def _z_gap(
    meas_axis: FloatArray,
    meas_tgt: FloatArray,
    pred_axis: FloatArray,
    pred_tgt: FloatArray,
    model_sd_m: float,
) -> dict[str, float]:
    """ISO gap of a measured test against predicted tests (rows: trials); ``model_sd_m``:
    the model's systematic uncertainty, added in quadrature to the spread over trials."""
    ok = np.isfinite(meas_axis)
    mu_a = np.mean(pred_axis[:, ok], axis=0)
    sd_a = np.hypot(np.std(pred_axis[:, ok], axis=0, ddof=1), model_sd_m)
    sd_a = np.maximum(sd_a, _SD_FLOOR_M)
    za = (meas_axis[ok] - mu_a) / sd_a
    mu_t = np.mean(pred_tgt, axis=0)
    sd_t = np.hypot(np.std(pred_tgt, axis=0, ddof=1), model_sd_m)
    sd_t = np.maximum(sd_t, _SD_FLOOR_M)
    zt = (meas_tgt - mu_t) / sd_t
    ga = float(np.sqrt(np.mean(za**2)))
    gt = float(np.sqrt(np.mean(zt**2)))
    return {
        "iso_gap": math.sqrt(0.5 * (ga * ga + gt * gt)),
        "axis_z_rms": ga,
        "per_target_z_rms": gt,
        "figure_gap_rms_m": float(np.sqrt(np.mean((meas_axis[ok] - mu_a) ** 2))),
        "per_target_gap_rms_m": float(np.sqrt(np.mean((meas_tgt - mu_t) ** 2))),
    }


def _select(
    results: Sequence[dict[str, Any]],
    shapes: dict[str, tuple[FloatArray, float]],
    gap_noise: float,
    resolution_m: float,
    group: IntArray | None = None,
    within_resolution_m: float = math.inf,
) -> tuple[str, list[str]]:
    """The verdict and the candidates indistinguishable from it.

    Two candidates are *distinguishable* when their likelihood gains differ by more than
    the larger of their noise floors and their fitted effects differ: by at least
    ``resolution_m`` (rms over the readings, with the extra scatter), or, with ``group``
    (the readings' target and direction), by at least ``within_resolution_m`` in how they
    change from run to run at one target and direction (rms about each group's mean: the
    loop's tolerance is a stop per target and direction, the same in every run, so it
    cannot stand for such a change; a drift's course in time is one). The contenders are the
    significant candidates within the gap's noise band of the best ISO gap, those not
    distinguishable from the best, and those with a higher likelihood gain; a contender
    that another contender is distinguishable from and beats on likelihood drops out; of
    the rest, the one with the fewest parameters (then the lower ISO gap) is the verdict,
    the others are indistinguishable from it.
    """
    sig = [r for r in results if r["significant"]]
    if not sig:
        return "none", []

    def differ(a: dict[str, Any], b: dict[str, Any]) -> bool:
        pa, sa = shapes[a["name"]]
        pb, sb = shapes[b["name"]]
        d = math.sqrt(float(np.mean((pa - pb) ** 2)) + (sa - sb) ** 2)
        within = 0.0 if group is None else _within_rms(pa - pb, group)
        margin = max(a["noise_floor_gain"], b["noise_floor_gain"])
        apart = d >= resolution_m or within >= within_resolution_m
        return apart and abs(a["likelihood_gain"] - b["likelihood_gain"]) > margin

    best = min(sig, key=lambda r: r["iso_gap"])
    band = max(gap_noise, 0.1 * best["iso_gap"])
    contenders = [
        r
        for r in sig
        if r["iso_gap"] <= best["iso_gap"] + band
        or not differ(r, best)
        or r["likelihood_gain"] > best["likelihood_gain"]
    ]
    kept = [
        r
        for r in contenders
        if not any(differ(r, o) and o["likelihood_gain"] > r["likelihood_gain"] for o in contenders)
    ]
    top = simplest_of_ties(
        sorted(kept, key=lambda r: r["iso_gap"]), lambda r: True, lambda r: r["dof"]
    )
    tied = [r["name"] for r in contenders if r is not top and not differ(r, top)]
    return str(top["name"]), tied


def diagnose_iso(
    meas: IsoMeasurement,
    system: System,
    settings: IsoDiagnosisSettings | None = None,
    *,
    threads: int | None = None,
    executor: Executor | Any | None = None,
    progress: bool = False,
    candidates: Sequence[Candidate] = CANDIDATES,
    in_loop: Sequence[InLoopCandidate] = IN_LOOP_CANDIDATES,
) -> dict[str, Any]:
    """Diagnose a measured ISO 230-2 test against a model (see the module's docstring).

    Parameters
    ----------
    meas : IsoMeasurement
        From :func:`nanostage.measurement.read_iso_measurement` (checked whole).
    system : System
        The model (its loop runs the campaign).
    settings : IsoDiagnosisSettings, optional
    threads, executor :
        Passed to :func:`nanostage.campaign.run_campaign` (an executor, e.g. a Dask client,
        runs the campaign's chunks).
    progress : bool
        Progress on stderr.
    candidates, in_loop :
        The chain's candidates and the in-loop candidates (each scanned by campaigns).

    Returns
    -------
    dict
        The report (strict JSON with :func:`nanostage.output.write_json`).
    """
    s = IsoDiagnosisSettings() if settings is None else settings
    if not isinstance(meas, IsoMeasurement):
        raise ConfigError(
            f"meas = {type(meas).__name__} is invalid: expected a nanostage.measurement."
            "IsoMeasurement (read_iso_measurement)"
        )
    t_start = time.perf_counter()
    lay = _layout(meas)
    dev = np.asarray(meas.records.actual_m, dtype=np.float64) - lay.target_m
    period = system.controller.sample_period_s
    cycle = measurement_cycle(meas, s, period)
    pitch, lead = _scale_pitch(system), _screw_lead(system)
    features = iso_features(meas, scale_pitch_m=pitch, screw_lead_m=lead)
    camp = run_campaign(
        system,
        cycle,
        n_trials=s.n_trials,
        seed=s.seed,
        threads=threads,
        executor=executor,
        progress=progress,
    )
    t_campaign = time.perf_counter() - t_start
    rows = np.flatnonzero(camp.ok)
    if rows.size < 4:
        raise ConfigError(
            f"the model's campaign completed {rows.size} of {camp.n_trials} trials: expected at "
            "least 4 (see the campaign's failures)"
        )
    n_steps = len(candidates) + len(in_loop) + 2
    bar = ProgressBar(n_steps, sys.stderr if progress else None, "fit", unit="steps")
    rng = np.random.default_rng([s.seed, 0x150D])
    loop_dev = camp.position_m[rows] - lay.target_m[None, :]
    model_mean_iso = loop_dev.mean(axis=0)
    # The channel the candidates are fitted on: with the file's encoder readings, the
    # interferometer minus the encoder (what the loop saw is taken out, whatever count the
    # loop stopped at); else the interferometer's deviation.
    if meas.encoder_m is not None:
        channel = "interferometer_minus_encoder"
        fit_dev = np.asarray(meas.records.actual_m, dtype=np.float64) - meas.encoder_m
        fit_loop = camp.position_m[rows] - camp.encoder_m[rows]
    else:
        channel = "interferometer"
        fit_dev, fit_loop = dev, loop_dev
    nominal = s.reading_noise_m**2
    loop_tol = float(system.encoder.count_m) if s.loop_tolerance_m is None else s.loop_tolerance_m
    v_loop = float(np.mean(np.var(loop_dev, axis=0, ddof=1)))
    v0 = float(np.mean(np.var(fit_loop, axis=0, ddof=1))) + nominal + loop_tol**2 / 12.0
    n_rows = rows.size
    move_m, dwell_s = arrival_times(cycle.reference_m, cycle.measure_index, period)
    times = (
        np.asarray(meas.time_s, dtype=np.float64)
        - float(meas.time_s[0])
        + float(cycle.measure_time_s[0])
        if meas.time_s is not None
        else cycle.measure_time_s
    )
    ctx = _Context(
        campaign=camp,
        rows=rows,
        time_s=times,
        direction=lay.direction,
        move_m=move_m,
        dwell_s=dwell_s,
        target_m=lay.target_m,
        x_ref_m=float(lay.target_m[0]),
        x_centre_m=float(0.5 * (lay.targets_m[0] + lay.targets_m[-1])),
        temperature_k=None if meas.temperature_k is None else np.asarray(meas.temperature_k),
        scale_pitch_m=pitch,
        settings=s,
    )
    options = {c.name: c.columns(ctx) for c in candidates}
    # The in-loop candidates: campaigns of the model with the effect, on what the loop's stop
    # changes: the encoder's deviations when the file has them (the encoder is on the table;
    # the chain's effects are not in them), else the interferometer's.
    if meas.encoder_m is not None:
        in_channel = "encoder"
        in_dev = np.asarray(meas.encoder_m, dtype=np.float64) - lay.target_m
        in_loop_dev = camp.encoder_m[rows] - lay.target_m[None, :]
        in_nominal = 0.0
    else:
        in_channel, in_dev, in_loop_dev, in_nominal = "interferometer", dev, loop_dev, nominal
    base = camp
    if s.in_loop_trials > camp.n_trials and in_loop:
        base = run_campaign(
            system,
            cycle,
            n_trials=s.in_loop_trials,
            seed=s.seed,
            threads=threads,
            executor=executor,
        )
    scans = {
        c.name: _scan(c, system, cycle, base, s, threads, executor, in_channel == "encoder")
        for c in in_loop
    }
    v0_in = float(np.mean(np.var(in_loop_dev, axis=0, ddof=1))) + in_nominal + loop_tol**2 / 12.0
    refiners: dict[str, Callable[[float], tuple[FloatArray, FloatArray]] | None] = {
        c.name: (
            None
            if c.refine is None or (ctx.temperature_k is not None and c.name == "thermal_drift")
            else partial(c.refine, ctx)
        )
        for c in candidates
    }
    empty = [(None, np.zeros((dev.shape[0], 0)), np.zeros(0))]
    dirf = lay.direction.astype(np.float64)
    half = 0.5 * loop_tol
    bar.update(1)
    tol = s.scatter_tolerance

    # Pseudo-measurements: each trial read with the nominal noise, against the others' mean.
    # The loop's tolerance, half per target and direction, half per reading.
    group = lay.target_index * 2 + (lay.direction < 0)
    n_groups = 2 * lay.targets_m.shape[0]
    noise = rng.standard_normal(loop_dev.shape) * s.reading_noise_m
    noise += rng.uniform(-0.5, 0.5, loop_dev.shape) * loop_tol / math.sqrt(2.0)
    noise += rng.uniform(-0.5, 0.5, (n_rows, n_groups))[:, group] * loop_tol / math.sqrt(2.0)
    pseudo = loop_dev + noise
    total = fit_loop.sum(axis=0)
    null_gain: dict[str, list[float]] = {c.name: [] for c in candidates}
    for j in range(n_rows):
        mean_others = (total - fit_loop[j]) / (n_rows - 1)
        r = fit_loop[j] + noise[j] - mean_others
        none = _fit(r, empty, False, v0, tol, dirf, half)[0]
        for c in candidates:
            fit_c = _fit(r, options[c.name], c.random, v0, tol, dirf, half, refiners[c.name])[0]
            null_gain[c.name].append(none.nll - fit_c.nll)
    total_in = in_loop_dev.sum(axis=0)
    for j in range(n_rows):
        r = in_loop_dev[j] + noise[j] - (total_in - in_loop_dev[j]) / (n_rows - 1)
        none = _fit(r, empty, False, v0_in, tol, dirf, half)[0]
        for ic in in_loop:
            fit_i = _fit_in_loop(r, scans[ic.name], v0_in, tol, dirf, half)
            null_gain[ic.name] = [*null_gain.get(ic.name, []), none.nll - fit_i.nll]
    bar.update(2)

    resid = fit_dev - fit_loop.mean(axis=0)
    none_fit = _fit(resid, empty, False, v0, tol, dirf, half)[0]

    def iso_mean(fit: _Fit) -> FloatArray:
        """The fit's readings on the interferometer's channel: fitted there, or (fitted on
        the encoder's channel) its effect with the offset and the loop's nuisance refitted
        on the interferometer's deviations."""
        if channel == "interferometer":
            return fit.mean_m
        base = _fit(dev - model_mean_iso - fit.effect_m, empty, False, v0, tol, dirf, half)[0]
        out: FloatArray = base.mean_m + fit.effect_m
        return out

    def predict(
        fit: _Fit, as_is: bool = False, mean_m: FloatArray | None = None
    ) -> tuple[FloatArray, FloatArray]:
        extra = math.sqrt(max(fit.variance_m2 - v_loop, 0.0))
        draws = rng.standard_normal(loop_dev.shape) * extra
        if mean_m is None:
            mean_m = fit.mean_m if as_is else iso_mean(fit)
        tests = loop_dev + mean_m[None, :] + draws
        vecs = [_iso_vector(lay, t) for t in tests]
        return np.array([v[0] for v in vecs]), np.array([v[1] for v in vecs])

    meas_axis, meas_tgt = _iso_vector(lay, dev)
    zero = np.zeros_like(dev)
    plain_axis, plain_tgt = predict(
        _Fit(
            nll=0.0,
            offset_m=0.0,
            beta=np.zeros(0),
            grid=None,
            variance_m2=v0,
            mean_m=zero,
            effect_m=zero,
            loop_reversal_m=0.0,
        ),
        as_is=True,
    )
    u = loop_tol / math.sqrt(12.0)
    before = _z_gap(meas_axis, meas_tgt, plain_axis, plain_tgt, u)
    # The noise of the ISO gap: the gaps of the model's own tests (read with the nominal
    # noise and the loop's tolerance) against the model's prediction.
    null_gaps = []
    for j in range(n_rows):
        pa_j, pt_j = _iso_vector(lay, pseudo[j])
        null_gaps.append(_z_gap(pa_j, pt_j, plain_axis, plain_tgt, u)["iso_gap"])
    gap_noise = max(float(np.std(null_gaps, ddof=1)), 0.1)
    none_axis, none_tgt = predict(none_fit)
    none_gap = _z_gap(meas_axis, meas_tgt, none_axis, none_tgt, u)

    results: list[dict[str, Any]] = []
    shapes: dict[str, tuple[FloatArray, float]] = {}

    def judge(
        head: dict[str, Any],
        dof: int,
        fit: _Fit,
        none: _Fit,
        parameters: dict[str, float],
        own_m: FloatArray | None,
        tail: dict[str, Any],
        mean_m: FloatArray | None = None,
    ) -> dict[str, Any]:
        """The candidate's significance, ISO gap and prediction (its fit against ``none``,
        the fit without a candidate on the same channel; an in-loop candidate has its own
        change of the stops ``own_m`` and its readings on the interferometer ``mean_m``)."""
        name = head["name"]
        gain = none.nll - fit.nll
        nulls = np.asarray(null_gain[name])
        floor = max(float(np.quantile(nulls, 0.95)), float(chi2.ppf(0.999, dof)))
        pa, pt = predict(fit, mean_m=mean_m)
        gap = _z_gap(meas_axis, meas_tgt, pa, pt, u)
        # What the candidate adds to the "none" fit: the change of the fitted readings (the
        # loop's nuisance takes what it can) and the scatter beyond the none fit's.
        part = (fit.mean_m - fit.offset_m) - (none.mean_m - none.offset_m)
        part = part - float(np.mean(part))
        excess_sd = math.sqrt(max(fit.variance_m2 - none.variance_m2, 0.0))
        shapes[name] = (part, excess_sd)
        change = float(np.mean(part**2))
        if own_m is not None:
            # An in-loop effect is judged whole: its change of the stops is a change of the
            # very stop the loop's nuisance stands for, computed by the loop itself.
            own = own_m - float(np.mean(own_m))
            change = max(float(np.mean(own**2)), change)
        size = math.sqrt(change + excess_sd**2)
        return {
            **head,
            "dof": dof,
            "likelihood_gain": gain,
            "noise_floor_gain": floor,
            "null_gain_max": float(np.max(nulls)),
            "effect_rms_m": size,
            "significant": bool(gain > floor and size > 0.5 * loop_tol),
            "parameters": parameters,
            "offset_m": fit.offset_m,
            "loop_reversal_m": fit.loop_reversal_m,
            "residual_rms_m": math.sqrt(fit.variance_m2),
            "predicted": {
                q: float(np.nanmean(pa[:, k])) if np.any(np.isfinite(pa[:, k])) else None
                for k, q in enumerate(ISO_QUANTITIES)
            },
            "predicted_per_target_m": np.mean(pt, axis=0),
            **tail,
            **gap,
        }

    for i, c in enumerate(candidates):
        fit, units = _fit(resid, options[c.name], c.random, v0, tol, dirf, half, refiners[c.name])
        results.append(
            judge(
                {"name": c.name, "what": c.what},
                c.dof,
                fit,
                none_fit,
                _physical(c, fit, units, v0, s),
                None,
                {"in_loop": False, "fitted_channel": channel},
            )
        )
        bar.update(3 + i)
    resid_in = in_dev - in_loop_dev.mean(axis=0)
    none_in = _fit(resid_in, empty, False, v0_in, tol, dirf, half)[0]
    for i, ic in enumerate(in_loop):
        sc = scans[ic.name]
        fit = _fit_in_loop(resid_in, sc, v0_in, tol, dirf, half)
        value = float(fit.beta[0])
        _, extra = sc.at(value)
        eff = sc.position_at(value)
        if in_channel == "interferometer":
            mean_iso = fit.mean_m
        else:
            # The effect on the table, with the offset and the loop's nuisance refitted on
            # the interferometer's deviations.
            base_fit = _fit(dev - model_mean_iso - eff, empty, False, v0, tol, dirf, half)[0]
            mean_iso = base_fit.mean_m + eff
        params = {ic.parameter: value}
        if ic.random:
            params["stop_scatter_rms_m"] = math.sqrt(extra)
        else:
            up = lay.direction > 0
            params["reversal_m"] = (
                float(np.mean(eff[up]) - np.mean(eff[~up])) if lay.bidirectional else 0.0
            )
        scan = {
            "sizes": sc.sizes[1:],
            "trials": s.in_loop_trials,
            "failed_trials": sc.failed_trials,
            "hunting": sc.hunting,
        }
        results.append(
            judge(
                {"name": ic.name, "what": ic.what},
                ic.dof,
                fit,
                none_in,
                params,
                fit.effect_m,
                {"in_loop": True, "fitted_channel": in_channel, "scan": scan},
                mean_iso,
            )
        )
        bar.update(3 + len(candidates) + i)
    bar.update(n_steps, final=True)
    # A change from run to run at one target and direction larger than the
    # interferometer's nominal noise is neither the loop's stop nor the reading's noise.
    verdict, tied = _select(
        results, shapes, gap_noise, 0.5 * loop_tol, group, max(s.reading_noise_m, _SD_FLOOR_M)
    )
    by_name = {r["name"]: r for r in results}
    trailing = sorted(
        (r for r in results if r["name"] != verdict and r["name"] not in tied),
        key=lambda r: (not r["significant"], r["iso_gap"]),
    )
    ranked = [by_name[n] for n in [verdict, *tied] if n in by_name] + trailing
    top = by_name.get(verdict)
    after = dict(before) if top is None else {k: top[k] for k in before}
    report: dict[str, Any] = {
        "verdict": verdict,
        "indistinguishable": [
            {"candidate": name, "separating_test": separating_test(verdict, name)} for name in tied
        ],
        "ranking": [r["name"] for r in ranked],
        "candidates": ranked,
        "not_covered": NOT_COVERED,
        "gap_before": before,
        "gap_after": after,
        "gap_none_fitted": none_gap,
        "gap_noise": gap_noise,
        "figure_gap_shrink": (
            1.0 - after["figure_gap_rms_m"] / before["figure_gap_rms_m"]
            if before["figure_gap_rms_m"] > 0
            else 0.0
        ),
        "measured": {
            "iso": {
                q: (None if not np.isfinite(v) else float(v))
                for q, v in zip(ISO_QUANTITIES, meas_axis, strict=True)
            },
            "features": features,
            "n_targets": int(lay.targets_m.shape[0]),
            "n_runs": lay.n_runs,
            "bidirectional": lay.bidirectional,
            "has_time": meas.time_s is not None,
            "has_encoder": meas.encoder_m is not None,
            "fitted_channel": channel,
            "has_temperature": meas.temperature_k is not None,
        },
        "model": {
            "scatter_rms_m": math.sqrt(v_loop),
            "reading_noise_m": s.reading_noise_m,
            "loop_tolerance_m": loop_tol,
            "predicted": {
                q: float(np.nanmean(plain_axis[:, k]))
                if np.any(np.isfinite(plain_axis[:, k]))
                else None
                for k, q in enumerate(ISO_QUANTITIES)
            },
            "trials": camp.n_trials,
            "failed_trials": camp.n_failed,
            "scale_pitch_m": pitch,
            "screw_lead_m": lead,
            "cycle_duration_s": cycle.duration_s,
        },
        "settings": {k: getattr(s, k) for k in s.__dataclass_fields__},
        "timing_s": {
            "campaign": t_campaign,
            "in_loop_campaigns": sum(v.seconds for v in scans.values()),
            "total": time.perf_counter() - t_start,
        },
        "plot": {
            "targets_m": lay.targets_m,
            "measured_m": meas_tgt,
            "model_m": np.mean(plain_tgt, axis=0),
            "top_m": None if top is None else top["predicted_per_target_m"],
        },
    }
    return report


# --------------------------------------------------------------------------------------------
# Report
# --------------------------------------------------------------------------------------------


def _um(v: float | None) -> str:
    return "—" if v is None or not math.isfinite(v) else f"{v * 1e6:.3f}"


def markdown(report: dict[str, Any], source: str = "") -> str:
    """The report in Markdown."""
    v = report["verdict"]
    lines = [f"# ISO-level diagnosis{f' of {source}' if source else ''}", ""]
    if v == "none":
        lines.append(
            "**Verdict: none.** No candidate explains the measurement better than the model's "
            "own tests do (each candidate's likelihood gain is below its Monte Carlo noise "
            "floor): the measurement is at the model's noise floor, or its gap is where no "
            "candidate reaches (not covered below)."
        )
    else:
        lines.append(
            f"**Verdict: {v}** (the significant candidate that best reproduces the ISO "
            "quantities, with the fewest parameters among those within the gap's noise)."
        )
    for t in report["indistinguishable"]:
        lines.append(
            f"- Indistinguishable from **{t['candidate']}** on this test; separated by "
            f"{t['separating_test']}."
        )
    b, a = report["gap_before"], report["gap_after"]
    lines += [
        "",
        f"ISO gap (rms z-score of E, A, R, B, M and the per-target mean deviations against the "
        f"prediction's spread): {b['iso_gap']:.2f} with the model → {a['iso_gap']:.2f} "
        f"(noise of the gap {report['gap_noise']:.2f}). Figure gap (rms of the axis "
        f"quantities): {_um(b['figure_gap_rms_m'])} µm → {_um(a['figure_gap_rms_m'])} µm "
        f"(shrink {report['figure_gap_shrink']:.0%}).",
        "",
        "| quantity | measured [µm] | model [µm] | " + ("verdict [µm] |" if v != "none" else "|"),
        "|---|---|---|" + ("---|" if v != "none" else ""),
    ]
    top = next((c for c in report["candidates"] if c["name"] == v), None)
    labels = {attr: label for label, attr, _ in iso230_2.AXIS_PARAMETERS}
    for q in ISO_QUANTITIES:
        m = report["measured"]["iso"][q]
        if m is None:
            continue
        row = f"| {labels[q]} | {_um(m)} | {_um(report['model']['predicted'][q])} |"
        if top is not None:
            row += f" {_um(top['predicted'][q])} |"
        lines.append(row)
    lines += [
        "",
        "## Candidates",
        "",
        "| rank | candidate | parameters | gain | noise floor | significant | ISO gap | "
        "figure gap [µm] |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for k, c in enumerate(report["candidates"], 1):
        params = ", ".join(f"{n} = {p:.3g}" for n, p in c["parameters"].items())
        name = c["name"] + (" (in the loop)" if c["in_loop"] else "")
        lines.append(
            f"| {k} | {name} | {params or '—'} | {c['likelihood_gain']:.1f} | "
            f"{c['noise_floor_gain']:.1f} | {'yes' if c['significant'] else 'no'} | "
            f"{c['iso_gap']:.2f} | {_um(c['figure_gap_rms_m'])} |"
        )
    f = report["measured"]["features"]
    tr = f["trend"]
    unit = "s" if tr["against"] == "time_s" else "run"
    slope = next(v for k, v in tr.items() if k.startswith("slope_m"))
    slope_se = next(v for k, v in tr.items() if k.startswith("slope_se"))
    lines += [
        "",
        "## Features of the measurement",
        "",
        f"- Trend of the deviations with {tr['against']} (within each target and direction): "
        f"{slope * 1e9:.3g} ± {slope_se * 1e9:.2g} nm per {unit}.",
    ]
    for name, p in f["periodic"].items():
        lines.append(
            f"- Sinusoid of the mean deviation at the {name.replace('_', ' ')} "
            f"({p['period_m'] * 1e6:.4g} µm): {p['amplitude_m'] * 1e9:.3g} ± "
            f"{p['amplitude_se_m'] * 1e9:.2g} nm."
        )
    lines += [
        "",
        "Not covered: "
        + "; ".join(f"{k} ({why})" for k, why in report["not_covered"].items())
        + ".",
        "",
        f"Model: scatter {report['model']['scatter_rms_m'] * 1e9:.1f} nm rms per reading over "
        f"{report['model']['trials']} trials ({report['model']['failed_trials']} failed), "
        f"nominal reading noise {report['model']['reading_noise_m'] * 1e9:.1f} nm; fitted on "
        f"the {report['measured']['fitted_channel'].replace('_', ' ')}; "
        f"{report['timing_s']['total']:.1f} s (campaign {report['timing_s']['campaign']:.1f} s).",
        "",
    ]
    return "\n".join(lines)


def _figure(report: dict[str, Any], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    p = report["plot"]
    x = np.asarray(p["targets_m"]) * 1e3
    n = x.shape[0]
    fig, ax = plt.subplots(figsize=(7, 4))
    series = [("measured", p["measured_m"], "o-"), ("model", p["model_m"], "s--")]
    if p["top_m"] is not None:
        series.append((f"model + {report['verdict']}", p["top_m"], "^:"))
    for label, y, style in series:
        y = np.asarray(y) * 1e6
        ax.plot(x, y[:n], style, label=f"{label} ↑")
        if y.shape[0] > n:
            ax.plot(x, y[n:], style, alpha=0.5, label=f"{label} ↓")
    ax.set_xlabel("target [mm]")
    ax.set_ylabel("mean deviation [µm]")
    ax.set_title(f"ISO-level diagnosis: {report['verdict']}")
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def write_iso_diagnosis(
    out: str | Path,
    meas: IsoMeasurement,
    system: System,
    settings: IsoDiagnosisSettings | None = None,
    *,
    source: str = "",
    threads: int | None = None,
    executor: Executor | Any | None = None,
    progress: bool = False,
    figure: bool = True,
) -> dict[str, Any]:
    """Diagnose and write ``out``: report.json, report.md and, with matplotlib, diagnosis.png
    (whole or not at all). Returns the report with ``files`` and, without matplotlib,
    ``figure_note``."""
    import importlib.util

    report = diagnose_iso(
        meas, system, settings, threads=threads, executor=executor, progress=progress
    )
    names = ["report.json", "report.md"]
    if figure and importlib.util.find_spec("matplotlib") is None:
        figure = False
        report["figure_note"] = (
            'matplotlib is not installed: diagnosis.png not written (pip install "nanostage[plot]")'
        )
    if figure:
        names.append("diagnosis.png")
    report["files"] = names
    with staged_output(out, "iso-diagnose") as folder:
        write_json(report, folder / "report.json")
        text = markdown(report, source)
        if "figure_note" in report:
            text += f"\n{report['figure_note']}\n"
        (folder / "report.md").write_text(text, encoding="utf-8")
        if figure:
            _figure(report, folder / "diagnosis.png")
    return report
