"""Gap statistics between measured experiments and simulations on the same time base.

The residual is ``r = measured − simulated`` (m). Its sum of squares is split over the
segments of a partition of the samples (phases, presliding/sliding, direction, position
bins, :mod:`~nanostage.diagnosis.segments`): per segment the RMS and the *share* of the
total sum of squares (the shares of a partition add up to 1). Also:

* response features per move, measured vs simulated (:func:`compare_features`: rise time
  10–90 %, overshoot, settling time to ±band around the final value, final error, peak
  speed), for step sequences and ramps alike;
* the residual spectrum in time (Welch, :func:`time_spectrum`) and in space
  (:func:`spatial_spectrum`: the residual of each one-way motion stretch resampled on a
  uniform position grid, periodogram vs spatial frequency in 1/m) with
  :func:`power_share_near` for the share of residual power near a spatial period, e.g.
  the 2 mm screw lead: a peak there points at position-dependent friction;
* ISO 230-2 figures measured vs simulated when the experiments form a positioning
  campaign (:func:`iso230_comparison`: the final hold positions of repeated moves to the
  same target, evaluated with :func:`nanostage.iso230_2.evaluate_records`).

:func:`analyse_gap` does all of it and returns a :class:`GapAnalysis` whose
:meth:`~GapAnalysis.to_dict` is JSON-ready (with NaN, to be written by
:func:`nanostage.diagnosis.report.write_json`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Final

import numpy as np
import numpy.typing as npt

from .. import iso230_2
from ..experiment import Experiment
from .segments import Move, Segmentation, estimate_velocity, segment

__all__ = [
    "DEFAULT_PARTITIONS",
    "ExperimentGap",
    "FeatureComparison",
    "GapAnalysis",
    "GapStats",
    "IsoComparison",
    "MoveFeatures",
    "SegmentGap",
    "Spectrum",
    "analyse_gap",
    "compare_features",
    "gap_statistics",
    "iso230_comparison",
    "move_features",
    "power_share_near",
    "residual",
    "segment_gap",
    "spatial_spectrum",
    "time_spectrum",
]

FloatArray = npt.NDArray[np.float64]
BoolArray = npt.NDArray[np.bool_]
IntArray = npt.NDArray[np.int64]

#: Partitions :func:`gap_statistics` reports by default (``position`` bins are per
#: experiment and only pool when the experiments share a travel).
DEFAULT_PARTITIONS: Final[tuple[str, ...]] = ("phase", "motion", "direction")


def _nan_to_none(v: float) -> float | None:
    return None if not math.isfinite(v) else float(v)


# --------------------------------------------------------------------------------------------
# Residual and per-segment statistics
# --------------------------------------------------------------------------------------------


def residual(
    measured: Experiment, simulated_m: npt.ArrayLike, *, channel: str = "position_m"
) -> FloatArray:
    """``measured.<channel> − simulated_m`` on the experiment's time base, m.

    Raises
    ------
    ValueError
        If the lengths differ, the channel is missing, or the simulation is not finite.
    """
    meas = getattr(measured, channel, None)
    if meas is None:
        raise ValueError(f"experiment {measured.name!r} has no {channel!r} channel")
    sim = np.asarray(simulated_m, dtype=np.float64)
    if sim.shape != (measured.n_samples,):
        raise ValueError(
            f"experiment {measured.name!r}: simulated position has shape {sim.shape}, "
            f"expected ({measured.n_samples},) like its time_s"
        )
    if not np.all(np.isfinite(sim)):
        k = int(np.flatnonzero(~np.isfinite(sim))[0])
        raise ValueError(
            f"experiment {measured.name!r}: simulated position is not finite at sample {k}"
        )
    out: FloatArray = np.asarray(meas, dtype=np.float64) - sim
    return out


@dataclass(frozen=True, slots=True, kw_only=True)
class SegmentGap:
    """The residual over one segment.

    Attributes
    ----------
    n_samples : int
    rms_m : float
        RMS residual over the segment, m (NaN if empty).
    sum_sq_m2 : float
        Sum of squared residuals, m².
    share : float
        ``sum_sq_m2`` over the total sum of squares of the partition's samples (NaN if the
        total is 0); the shares of a partition add up to 1.
    """

    n_samples: int
    rms_m: float
    sum_sq_m2: float
    share: float

    def to_dict(self) -> dict[str, Any]:
        """Plain dict."""
        return {
            "n_samples": self.n_samples,
            "rms_m": self.rms_m,
            "sum_sq_m2": self.sum_sq_m2,
            "share": self.share,
        }


def segment_gap(
    residual_m: npt.ArrayLike, masks: Mapping[str, npt.ArrayLike]
) -> dict[str, SegmentGap]:
    """RMS and share of the total sum of squares per segment.

    Parameters
    ----------
    residual_m : array_like, shape (n,)
        Residual, m.
    masks : mapping of str to bool array_like, shape (n,)
        Segment name → mask. For the shares to add up to 1 the masks must partition the
        samples; the total is taken over the union of the masks.

    Returns
    -------
    dict of str to SegmentGap
    """
    r = np.asarray(residual_m, dtype=np.float64)
    ms = {k: np.asarray(m, dtype=bool) for k, m in masks.items()}
    for k, m in ms.items():
        if m.shape != r.shape:
            raise ValueError(f"mask {k!r} has shape {m.shape}, residual has {r.shape}")
    union = np.zeros(r.shape, dtype=bool)
    for m in ms.values():
        union |= m
    total = float(np.sum(r[union] ** 2))
    out: dict[str, SegmentGap] = {}
    for k, m in ms.items():
        n = int(np.count_nonzero(m))
        ss = float(np.sum(r[m] ** 2))
        out[k] = SegmentGap(
            n_samples=n,
            rms_m=math.sqrt(ss / n) if n else math.nan,
            sum_sq_m2=ss,
            share=ss / total if total > 0.0 else math.nan,
        )
    return out


@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class GapStats:
    """Gap statistics over one or more experiments.

    Attributes
    ----------
    n_samples : int
    rms_m : float
        Total RMS residual, m.
    max_abs_m : float
        Largest absolute residual, m.
    sum_sq_m2 : float
        Total sum of squares, m².
    partitions : dict of str to dict of str to SegmentGap
        Partition name (``phase``, ``motion``, ``direction``, ``position``) → segment name
        → statistics.
    """

    n_samples: int
    rms_m: float
    max_abs_m: float
    sum_sq_m2: float
    partitions: dict[str, dict[str, SegmentGap]]

    def to_dict(self) -> dict[str, Any]:
        """Plain nested dict."""
        return {
            "n_samples": self.n_samples,
            "rms_m": self.rms_m,
            "max_abs_m": self.max_abs_m,
            "sum_sq_m2": self.sum_sq_m2,
            "partitions": {
                p: {k: g.to_dict() for k, g in segs.items()} for p, segs in self.partitions.items()
            },
        }


def gap_statistics(
    residuals_m: Sequence[npt.ArrayLike],
    segmentations: Sequence[Segmentation],
    *,
    partitions: Sequence[str] = DEFAULT_PARTITIONS,
) -> GapStats:
    """Total and per-segment gap statistics pooled over experiments.

    Parameters
    ----------
    residuals_m : sequence of array_like
        One residual per experiment, m.
    segmentations : sequence of Segmentation
        The matching segmentations (of the measured responses).
    partitions : sequence of str
        Which partitions of :meth:`Segmentation.partitions` to report. Segments are pooled
        by name across experiments.
    """
    if len(residuals_m) != len(segmentations):
        raise ValueError(f"{len(residuals_m)} residuals but {len(segmentations)} segmentations")
    if not residuals_m:
        raise ValueError("no experiments")
    rs = [np.asarray(r, dtype=np.float64) for r in residuals_m]
    pooled_r = np.concatenate(rs)
    out: dict[str, dict[str, SegmentGap]] = {}
    for p in partitions:
        names: list[str] = []
        parts = []
        for seg in segmentations:
            all_parts = seg.partitions()
            if p not in all_parts:
                raise ValueError(f"unknown partition {p!r}; valid: {', '.join(all_parts)}")
            parts.append(all_parts[p])
            names += [k for k in all_parts[p] if k not in names]
        masks = {
            k: np.concatenate(
                [
                    part.get(k, np.zeros(r.shape, dtype=bool))
                    for part, r in zip(parts, rs, strict=True)
                ]
            )
            for k in names
        }
        out[p] = segment_gap(pooled_r, masks)
    n = pooled_r.size
    ss = float(np.sum(pooled_r**2))
    return GapStats(
        n_samples=n,
        rms_m=math.sqrt(ss / n) if n else math.nan,
        max_abs_m=float(np.max(np.abs(pooled_r))) if n else math.nan,
        sum_sq_m2=ss,
        partitions=out,
    )


# --------------------------------------------------------------------------------------------
# Response features
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True, kw_only=True)
class MoveFeatures:
    """Response figures of one move (NaN where undefined).

    Attributes
    ----------
    rise_time_s : float
        10 % → 90 % of the move distance (first crossings, interpolated), s.
    overshoot_m : float
        Largest travel beyond the target in the move direction, m (≥ 0).
    settling_time_s : float
        From the move start until the position stays within ±band of its final value, s.
    final_error_m : float
        Target − final position (median over the final samples), m.
    peak_speed_m_per_s : float
        Largest speed in the move direction, m/s.
    """

    rise_time_s: float
    overshoot_m: float
    settling_time_s: float
    final_error_m: float
    peak_speed_m_per_s: float

    def to_dict(self) -> dict[str, float]:
        """Plain dict."""
        return {
            "rise_time_s": self.rise_time_s,
            "overshoot_m": self.overshoot_m,
            "settling_time_s": self.settling_time_s,
            "final_error_m": self.final_error_m,
            "peak_speed_m_per_s": self.peak_speed_m_per_s,
        }


_FEATURE_NAMES: Final[tuple[str, ...]] = (
    "rise_time_s",
    "overshoot_m",
    "settling_time_s",
    "final_error_m",
    "peak_speed_m_per_s",
)


def _crossing(t: FloatArray, y: FloatArray, level: float) -> float:
    idx = np.flatnonzero(y >= level)
    if idx.size == 0:
        return math.nan
    k = int(idx[0])
    if k == 0:
        return float(t[0])
    y0, y1 = float(y[k - 1]), float(y[k])
    return float(t[k - 1] + (level - y0) / (y1 - y0) * (t[k] - t[k - 1]))


def move_features(
    time_s: npt.ArrayLike,
    position_m: npt.ArrayLike,
    move: Move,
    *,
    band_m: float | None = None,
    velocity_m_per_s: npt.ArrayLike | None = None,
) -> MoveFeatures:
    """Response figures of one move of a (measured or simulated) position.

    Parameters
    ----------
    time_s, position_m : array_like, shape (n,)
        Time base and position, m.
    move : Move
        The move (from the segmentation of the measured response, so that measured and
        simulated figures use the same samples).
    band_m : float, optional
        Settling band half-width, m (default: the move's hold band).
    velocity_m_per_s : array_like, optional
        Velocity, m/s (default: estimated from the position).
    """
    t = np.asarray(time_s, dtype=np.float64)
    x = np.asarray(position_m, dtype=np.float64)
    a, b, s = move.start, move.stop, move.direction
    band = move.hold_band_m if band_m is None else float(band_m)
    dist = abs(move.step_m)
    prog = s * (x[a:b] - move.start_m)
    tt = t[a:b]
    rise = _crossing(tt, prog, 0.9 * dist) - _crossing(tt, prog, 0.1 * dist)
    over = max(0.0, float(np.max(prog)) - dist)
    if move.final_start < b:
        final = float(np.median(x[move.final_start : b]))
        outside = np.flatnonzero(np.abs(x[a:b] - final) > band)
        if outside.size == 0:
            settle = 0.0
        elif int(outside[-1]) == b - a - 1:
            settle = math.nan
        else:
            settle = float(tt[int(outside[-1]) + 1] - tt[0])
        ferr = move.target_m - final
    else:
        settle = ferr = math.nan
    v = (
        estimate_velocity(t, x)
        if velocity_m_per_s is None
        else np.asarray(velocity_m_per_s, dtype=np.float64)
    )
    return MoveFeatures(
        rise_time_s=rise,
        overshoot_m=over,
        settling_time_s=settle,
        final_error_m=ferr,
        peak_speed_m_per_s=max(0.0, float(np.max(s * v[a:b]))),
    )


@dataclass(frozen=True, slots=True, kw_only=True)
class FeatureComparison:
    """Measured vs simulated figures of one move of one experiment."""

    experiment: str
    move: int
    start_s: float
    step_m: float
    measured: MoveFeatures
    simulated: MoveFeatures

    def rows(self) -> list[dict[str, Any]]:
        """One row per feature: experiment, move, step, feature, measured, simulated,
        difference (simulated − measured)."""
        out: list[dict[str, Any]] = []
        md, sd = self.measured.to_dict(), self.simulated.to_dict()
        for f in _FEATURE_NAMES:
            out.append(
                {
                    "experiment": self.experiment,
                    "move": self.move,
                    "start_s": self.start_s,
                    "step_m": self.step_m,
                    "feature": f,
                    "measured": md[f],
                    "simulated": sd[f],
                    "difference": sd[f] - md[f],
                }
            )
        return out


def compare_features(
    experiment: Experiment,
    simulated_m: npt.ArrayLike,
    segmentation: Segmentation,
    *,
    settling_band_m: float | None = None,
    channel: str = "position_m",
) -> list[FeatureComparison]:
    """Response figures of every move, measured vs simulated (same samples, same band).

    Parameters
    ----------
    experiment : Experiment
    simulated_m : array_like, shape (n,)
        Simulated position on the experiment's time base, m.
    segmentation : Segmentation
        Of the measured response (its moves define the samples).
    settling_band_m : float, optional
        Settling band, m (default: each move's hold band).
    channel : str
        Measured channel (``position_m`` or ``interferometer_m``).
    """
    meas = np.asarray(getattr(experiment, channel), dtype=np.float64)
    sim = np.asarray(simulated_m, dtype=np.float64)
    t = experiment.time_s
    v_sim = estimate_velocity(t, sim)
    v_meas = (
        segmentation.velocity_m_per_s if channel == "position_m" else estimate_velocity(t, meas)
    )
    out: list[FeatureComparison] = []
    for m in segmentation.moves:
        out.append(
            FeatureComparison(
                experiment=experiment.name,
                move=m.index,
                start_s=float(t[m.start]),
                step_m=m.step_m,
                measured=move_features(t, meas, m, band_m=settling_band_m, velocity_m_per_s=v_meas),
                simulated=move_features(t, sim, m, band_m=settling_band_m, velocity_m_per_s=v_sim),
            )
        )
    return out


# --------------------------------------------------------------------------------------------
# Spectra
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class Spectrum:
    """A one-sided power spectral density of the residual.

    Attributes
    ----------
    frequency : ndarray, shape (k,)
        Frequency: Hz (``unit == "Hz"``) or spatial frequency in 1/m (``unit == "1/m"``).
    psd : ndarray, shape (k,)
        Power spectral density, m²/Hz or m²·m.
    unit : str
        ``"Hz"`` or ``"1/m"``.
    n_records : int
        Number of residual records averaged (experiments, or motion stretches).
    span : float
        Longest record: duration in s, or travel in m.
    """

    frequency: FloatArray
    psd: FloatArray
    unit: str
    n_records: int
    span: float

    def to_dict(self) -> dict[str, Any]:
        """Plain dict (lists)."""
        return {
            "unit": self.unit,
            "n_records": self.n_records,
            "span": self.span,
            "frequency": self.frequency.tolist(),
            "psd": self.psd.tolist(),
        }


def time_spectrum(
    residuals_m: Sequence[npt.ArrayLike], sample_period_s: float, *, nperseg: int | None = None
) -> Spectrum:
    """Welch PSD of the residual vs time, averaged over experiments (weighted by length).

    Parameters
    ----------
    residuals_m : sequence of array_like
        One residual per experiment, m, all at ``sample_period_s``.
    sample_period_s : float
        Sample period, s.
    nperseg : int, optional
        Welch segment length, samples (default: 1024, or the shortest record).
    """
    from scipy.signal import welch

    rs = [np.asarray(r, dtype=np.float64) for r in residuals_m]
    if not rs:
        raise ValueError("no residuals")
    shortest = min(r.size for r in rs)
    seg = min(nperseg or 1024, shortest)
    fs = 1.0 / float(sample_period_s)
    acc: FloatArray | None = None
    f: FloatArray | None = None
    weight = 0
    for r in rs:
        f_i, p_i = welch(r, fs=fs, nperseg=seg, detrend="constant")
        f = np.asarray(f_i, dtype=np.float64)
        p = np.asarray(p_i, dtype=np.float64) * r.size
        acc = p if acc is None else acc + p
        weight += r.size
    assert acc is not None and f is not None
    return Spectrum(
        frequency=f,
        psd=acc / weight,
        unit="Hz",
        n_records=len(rs),
        span=max(r.size for r in rs) * float(sample_period_s),
    )


def _one_way_runs(direction: IntArray, min_samples: int) -> list[tuple[int, int]]:
    cuts = np.flatnonzero(np.diff(direction)) + 1
    starts = np.concatenate(([0], cuts))
    ends = np.concatenate((cuts, [direction.size]))
    return [
        (int(s), int(e))
        for s, e in zip(starts, ends, strict=True)
        if direction[s] != 0 and e - s >= min_samples
    ]


def spatial_spectrum(
    positions_m: Sequence[npt.ArrayLike],
    residuals_m: Sequence[npt.ArrayLike],
    directions: Sequence[npt.ArrayLike],
    *,
    grid_step_m: float | None = None,
    min_travel_m: float = 0.0,
) -> Spectrum | None:
    """Periodogram of the residual vs position over the one-way motion stretches.

    Each stretch of constant direction (``directions`` ≠ 0, e.g.
    :attr:`Segmentation.direction`) is resampled on a uniform position grid (duplicate
    positions averaged, linear interpolation), linearly detrended, Hann-windowed and
    zero-padded to a common length; the periodograms are averaged weighted by their
    length. Powers are averaged, not signals, so a ripple that changes sign with the
    direction of motion (friction) is kept.

    Parameters
    ----------
    positions_m, residuals_m, directions : sequences of array_like
        Per experiment: measured position (m), residual (m), direction (+1/−1/0).
    grid_step_m : float, optional
        Grid spacing, m (default: the median position step between samples in motion).
    min_travel_m : float
        Ignore stretches shorter than this travel, m.

    Returns
    -------
    Spectrum or None
        ``unit == "1/m"``, ``span`` = longest stretch travel (m); None if there is no
        stretch of motion.
    """
    from scipy.signal import periodogram

    stretches: list[tuple[FloatArray, FloatArray]] = []
    for x_in, r_in, d_in in zip(positions_m, residuals_m, directions, strict=True):
        x = np.asarray(x_in, dtype=np.float64)
        r = np.asarray(r_in, dtype=np.float64)
        d = np.asarray(d_in, dtype=np.int64)
        for s, e in _one_way_runs(d, 4):
            xs = x[s:e]
            if float(np.ptp(xs)) <= max(min_travel_m, 0.0):
                continue
            order = np.argsort(xs, kind="stable")
            uniq, inv = np.unique(xs[order], return_inverse=True)
            if uniq.size < 4:
                continue
            r_mean = np.bincount(inv, weights=r[s:e][order]) / np.bincount(inv)
            stretches.append((uniq, r_mean))
    if not stretches:
        return None
    if grid_step_m is None:
        steps = np.concatenate([np.diff(u) for u, _ in stretches])
        dx = float(np.median(steps))
    else:
        dx = float(grid_step_m)
    if not (math.isfinite(dx) and dx > 0.0):
        raise ValueError(f"grid_step_m = {dx} is invalid: expected > 0")
    grids = []
    for u, rm in stretches:
        n_pts = math.floor(float(u[-1] - u[0]) / dx) + 1
        if n_pts > 1 << 22:
            raise ValueError(
                f"grid_step_m = {dx:g} m gives {n_pts} grid points for one stretch; use a "
                "coarser grid"
            )
        if n_pts < 4:
            continue
        g = u[0] + dx * np.arange(n_pts)
        grids.append(np.interp(g, u, rm))
    if not grids:
        return None
    nfft = 1 << math.ceil(math.log2(max(g.size for g in grids)))
    acc = None
    f: FloatArray | None = None
    weight = 0
    for rg in grids:
        f_i, p_i = periodogram(
            rg, fs=1.0 / dx, window="hann", nfft=nfft, detrend="linear", scaling="density"
        )
        f = np.asarray(f_i, dtype=np.float64)
        p = np.asarray(p_i, dtype=np.float64) * rg.size
        acc = p if acc is None else acc + p
        weight += rg.size
    assert acc is not None and f is not None
    return Spectrum(
        frequency=f,
        psd=acc / weight,
        unit="1/m",
        n_records=len(grids),
        span=max(g.size for g in grids) * dx,
    )


def power_share_near(
    spectrum: Spectrum, period: float, *, rel_width: float = 0.15, min_periods: float = 2.0
) -> float:
    """Share of the residual power within ``±rel_width`` of the frequency ``1/period``.

    Parameters
    ----------
    spectrum : Spectrum
        From :func:`spatial_spectrum` (period in m) or :func:`time_spectrum` (period in s).
    period : float
        The period, m or s (e.g. the screw lead 2e-3 m).
    rel_width : float
        Relative half-width of the band around ``1/period``.
    min_periods : float
        NaN unless the longest record spans this many periods.

    Returns
    -------
    float
        Band power / total power (DC excluded), in [0, 1]; NaN if the record is too short,
        the frequency is beyond the spectrum or there is no power.
    """
    f0 = 1.0 / float(period)
    f, p = spectrum.frequency, spectrum.psd
    if spectrum.span < min_periods * period or f0 > f[-1]:
        return math.nan
    pos = f > 0.0
    total = float(np.sum(p[pos]))
    if total <= 0.0:
        return math.nan
    band = pos & (f >= f0 * (1.0 - rel_width)) & (f <= f0 * (1.0 + rel_width))
    if not band.any():
        band = np.zeros_like(pos)
        band[int(np.argmin(np.abs(f - f0)))] = True
    return float(np.sum(p[band])) / total


# --------------------------------------------------------------------------------------------
# ISO 230-2 campaign
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class IsoComparison:
    """ISO 230-2 figures of the final hold positions, measured vs simulated."""

    measured: iso230_2.Iso230Result
    simulated: iso230_2.Iso230Result
    n_records: int
    bidirectional: bool

    def to_dict(self) -> dict[str, Any]:
        """Axis parameters (m) measured vs simulated, plus the full results."""
        m, s = self.measured.axis_parameters(), self.simulated.axis_parameters()
        return {
            "n_records": self.n_records,
            "bidirectional": self.bidirectional,
            "axis": {
                k: {"measured": m[k], "simulated": s[k]}
                for k in m
                if m[k] is not None or s[k] is not None
            },
            "symbols": {key: sym for sym, key, _ in iso230_2.AXIS_PARAMETERS},
            "measured": self.measured.to_dict(),
            "simulated": self.simulated.to_dict(),
        }


def iso230_comparison(
    experiments: Sequence[Experiment],
    simulated_m: Sequence[npt.ArrayLike],
    segmentations: Sequence[Segmentation],
    *,
    channel: str = "auto",
    target_tolerance_m: float = 1e-7,
    coverage_factor: float = 2.0,
) -> IsoComparison | None:
    """ISO 230-2 of the final positions of repeated moves, measured vs simulated.

    Every move with a final value (a dwell) gives a record: target, direction, final
    position (median over the move's final samples, the same samples for measured and
    simulated). Targets within ``target_tolerance_m`` are one target. If every target has
    at least 2 runs in both directions the evaluation is bidirectional; otherwise it uses
    the ``+`` approaches of the targets with at least 2 of them (the seed paper's
    unidirectional steps).

    Parameters
    ----------
    channel : str
        Measured channel; ``"auto"``: the interferometer if every experiment has one,
        else ``position_m``.

    Returns
    -------
    IsoComparison or None
        None if no target has 2 runs in a direction (not a campaign).
    """
    if channel == "auto":
        channel = (
            "interferometer_m"
            if experiments and all(e.interferometer_m is not None for e in experiments)
            else "position_m"
        )
    targets: list[float] = []
    dirs: list[str] = []
    meas: list[float] = []
    sims: list[float] = []
    for exp, sim_in, seg in zip(experiments, simulated_m, segmentations, strict=True):
        x = np.asarray(getattr(exp, channel), dtype=np.float64)
        sim = np.asarray(sim_in, dtype=np.float64)
        for m in seg.moves:
            if m.final_start >= m.stop:
                continue
            targets.append(m.target_m)
            dirs.append("+" if m.direction > 0 else "-")
            meas.append(float(np.median(x[m.final_start : m.stop])))
            sims.append(float(np.median(sim[m.final_start : m.stop])))
    if not targets:
        return None
    tg = np.array(targets)
    order = np.argsort(tg, kind="stable")
    cluster = np.empty(tg.size, dtype=np.int64)
    c, first = -1, math.nan
    for i in order:
        if c < 0 or tg[i] - first > target_tolerance_m:
            c += 1
            first = float(tg[i])
        cluster[i] = c
    runs = np.zeros(tg.size, dtype=np.int64)
    counts: dict[tuple[int, str], int] = {}
    for i in range(tg.size):
        key = (int(cluster[i]), dirs[i])
        counts[key] = counts.get(key, 0) + 1
        runs[i] = counts[key]
    clusters = sorted(set(int(v) for v in cluster))
    bidir = all(counts.get((k, "+"), 0) >= 2 and counts.get((k, "-"), 0) >= 2 for k in clusters)
    if bidir:
        keep = np.ones(tg.size, dtype=bool)
    else:
        keep = np.array(
            [dirs[i] == "+" and counts[(int(cluster[i]), "+")] >= 2 for i in range(tg.size)]
        )
    if not keep.any():
        return None
    d = np.array(dirs)[keep]
    tk, rk = tg[keep], runs[keep]

    def evaluate(values: list[float]) -> iso230_2.Iso230Result:
        return iso230_2.evaluate_records(
            tk,
            d,
            rk,
            np.array(values)[keep],
            coverage_factor=coverage_factor,
            target_tolerance_m=target_tolerance_m,
        )

    res_m, res_s = evaluate(meas), evaluate(sims)
    return IsoComparison(
        measured=res_m, simulated=res_s, n_records=int(keep.sum()), bidirectional=bidir
    )


# --------------------------------------------------------------------------------------------
# Everything at once
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class ExperimentGap:
    """One experiment's arrays for the figures: measured, simulated, residual, segments."""

    name: str
    time_s: FloatArray
    reference_m: FloatArray
    measured_m: FloatArray
    simulated_m: FloatArray
    residual_m: FloatArray
    segmentation: Segmentation

    def figure_data(self) -> dict[str, Any]:
        """Plain dict for :func:`nanostage.diagnosis.report.plot_gap_map`."""
        return {
            "name": self.name,
            "time_s": self.time_s,
            "reference_m": self.reference_m,
            "measured_m": self.measured_m,
            "simulated_m": self.simulated_m,
            "intervals": self.segmentation.intervals(),
        }


@dataclass(frozen=True, slots=True, kw_only=True, eq=False)
class GapAnalysis:
    """The gap between measured experiments and simulations (see :func:`analyse_gap`)."""

    overall: GapStats
    per_experiment: dict[str, GapStats]
    features: tuple[FeatureComparison, ...]
    time_spectrum: Spectrum
    spatial_spectrum: Spectrum | None
    lead_m: float | None
    lead_share: float
    iso230_2: IsoComparison | None
    experiments: tuple[ExperimentGap, ...]

    def to_dict(self, *, spectra: bool = True) -> dict[str, Any]:
        """JSON-ready dict (NaN kept; write with :func:`~nanostage.diagnosis.report.write_json`).

        Keys: ``overall``, ``per_experiment``, ``features`` (rows), ``time_spectrum``,
        ``spatial_spectrum``, ``lead_m``, ``lead_share``, ``iso230_2``, ``moves``.
        """
        moves = {
            e.name: [
                {
                    "index": m.index,
                    "kind": m.kind,
                    "start_s": float(e.time_s[m.start]),
                    "step_m": m.step_m,
                    "target_m": m.target_m,
                    "final_error_m": m.final_error_m,
                    "limit_cycle": None
                    if m.limit_cycle is None
                    else {
                        "amplitude_m": m.limit_cycle.amplitude_m,
                        "period_s": m.limit_cycle.period_s,
                    },
                }
                for m in e.segmentation.moves
            ]
            for e in self.experiments
        }
        return {
            "overall": self.overall.to_dict(),
            "per_experiment": {k: v.to_dict() for k, v in self.per_experiment.items()},
            "features": [row for fc in self.features for row in fc.rows()],
            "time_spectrum": self.time_spectrum.to_dict() if spectra else None,
            "spatial_spectrum": None
            if (self.spatial_spectrum is None or not spectra)
            else self.spatial_spectrum.to_dict(),
            "lead_m": self.lead_m,
            "lead_share": self.lead_share,
            "iso230_2": None if self.iso230_2 is None else self.iso230_2.to_dict(),
            "moves": moves,
        }


def analyse_gap(
    experiments: Sequence[Experiment],
    simulated_m: Sequence[npt.ArrayLike],
    *,
    segmentations: Sequence[Segmentation] | None = None,
    channel: str = "position_m",
    lead_m: float | None = 2e-3,
    settling_band_m: float | None = None,
    partitions: Sequence[str] = DEFAULT_PARTITIONS,
) -> GapAnalysis:
    """Residual statistics, features, spectra and ISO 230-2 of measured vs simulated.

    Parameters
    ----------
    experiments : sequence of Experiment
        Measured experiments.
    simulated_m : sequence of array_like
        Simulated position per experiment, on its time base, m (compare like with like:
        the simulated encoder reading for ``position_m``).
    segmentations : sequence of Segmentation, optional
        Of the measured responses (default: :func:`~nanostage.diagnosis.segments.segment`
        with its defaults). Pass them to reuse one segmentation before and after a fit.
    channel : str
        Measured channel for the residual.
    lead_m : float or None
        Spatial period whose residual power share is reported (the screw lead), m.
    settling_band_m : float, optional
        Settling band for the features, m (default: each move's hold band).
    partitions : sequence of str
        Partitions for the per-segment statistics.
    """
    if len(experiments) != len(simulated_m):
        raise ValueError(f"{len(experiments)} experiments but {len(simulated_m)} simulations")
    if not experiments:
        raise ValueError("no experiments")
    segs = list(segmentations) if segmentations is not None else [segment(e) for e in experiments]
    if len(segs) != len(experiments):
        raise ValueError(f"{len(experiments)} experiments but {len(segs)} segmentations")
    res = [residual(e, s, channel=channel) for e, s in zip(experiments, simulated_m, strict=True)]
    overall = gap_statistics(res, segs, partitions=partitions)
    per_exp = {
        e.name: gap_statistics([r], [sg], partitions=partitions)
        for e, r, sg in zip(experiments, res, segs, strict=True)
    }
    feats: list[FeatureComparison] = []
    for e, s, sg in zip(experiments, simulated_m, segs, strict=True):
        feats += compare_features(e, s, sg, settling_band_m=settling_band_m, channel=channel)
    periods = [e.sample_period_s for e in experiments]
    if max(periods) > 1.01 * min(periods):
        raise ValueError(f"experiments have different sample periods: {sorted(set(periods))}")
    tspec = time_spectrum(res, float(np.median(periods)))
    xspec = spatial_spectrum(
        [getattr(e, channel) for e in experiments], res, [sg.direction for sg in segs]
    )
    share = (
        power_share_near(xspec, lead_m) if (xspec is not None and lead_m is not None) else math.nan
    )
    iso = iso230_comparison(experiments, simulated_m, segs, channel=channel)
    gaps = tuple(
        ExperimentGap(
            name=e.name,
            time_s=e.time_s,
            reference_m=e.reference_m,
            measured_m=np.asarray(getattr(e, channel), dtype=np.float64),
            simulated_m=np.asarray(s, dtype=np.float64),
            residual_m=r,
            segmentation=sg,
        )
        for e, s, r, sg in zip(experiments, simulated_m, res, segs, strict=True)
    )
    return GapAnalysis(
        overall=overall,
        per_experiment=per_exp,
        features=tuple(feats),
        time_spectrum=tspec,
        spatial_spectrum=xspec,
        lead_m=lead_m,
        lead_share=share,
        iso230_2=iso,
        experiments=gaps,
    )
