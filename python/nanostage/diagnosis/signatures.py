"""Signatures: a few physical features of a set of traces that tell the aliases of the gap
apart where the gap itself cannot.

Backlash, computation and sensor delay, drive compliance and amplifier lag all give limit
cycles and phase lag; an offset force and asymmetric friction both shift the command by
direction; friction laws trade off against each other. Two candidates that the validation
gap cannot tell apart (:func:`~nanostage.diagnosis.select.indistinguishable`) may still
leave different marks on the traces, and these marks are measured directly:

``hunting_fraction``
    the share of settled holds whose position error at the end still spans more than
    :data:`HUNTING_QUANTA` reading quanta and repeats itself (a limit cycle);
``hold_amplitude_m``
    peak-to-peak position error at the end of the holds that hunt (median): the size of
    the limit cycle (a backlash's hunting spans about twice its width; a delay's
    cycle is a few counts);
``hold_frequency_hz``
    the limit cycle's frequency in the holds that hunt (the autocorrelation's period,
    :func:`~nanostage.diagnosis.segments.limit_cycle`): a delay, a lag and a dead band set
    it differently;
``rest_command_split_v`` and ``rest_command_mean_v``
    the command at rest after moves in each direction (median of each): their half
    difference is what friction holds on each side, their mean a standing force (an offset
    force needs a standing command in both directions, a friction asymmetry does not);
``ramp_level_v``, ``ramp_bias_v`` and ``ramp_slope_v_s_per_m``
    the steady command on constant-velocity ramps, fitted per direction as
    ``level + slope·|v|``: half the difference of the levels (the sliding friction), their
    mean (an offset or an asymmetry of the levels) and the mean slope (viscous friction;
    needs ramps at two or more speeds);
``reversal_lag_m``
    the lost motion at a reversal: on each constant-velocity ramp that reverses the ramp
    before it in the same trace (a hold between them at most), the largest lag of the
    reading behind the reference in the ramp's first half, less its steady lag (median of
    the last quarter); the median over such ramps. A dead band (backlash) or a compliance
    lets the motor move while the table waits (up to the band's width, or twice the
    friction over the stiffness); a delay or a lag loses only its time times the speed;
``breakaway_per_decade_v``
    the rise of the peak command of a move (until it has settled at its next target) per
    decade of the rest before it, among moves of the same step
    (dwell-dependent breakaway; needs three or more distinct rest durations).

Each feature comes with its standard error (from its scatter over holds, ramps or moves,
at least the reading's or the command's resolution), and :func:`distance` compares the
measured features with a model's simulated ones in units of both standard errors (a χ²
over the features both have). A feature the traces do not contain (no hunting, no ramps,
no command) is left out, never guessed."""

from __future__ import annotations

import itertools
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from ..config import System
from ..experiment import Experiment
from .objective import (
    HUNTING_QUANTA,
    LIMIT_CYCLE_MIN_CORRELATION,
    SimulationCache,
    autocorrelation_time,
    hold_intervals,
    ramp_intervals,
    reading_quantum,
    simulate_readings_and_commands,
)
from .segments import limit_cycle
from .settings import Adapt

__all__ = [
    "SIGNATURE_UNITS",
    "Feature",
    "SignatureJudge",
    "chi_square",
    "distance",
    "effect_marks",
    "misses",
    "signatures_of",
    "tie_chi_squares",
]

#: Unit of every signature feature.
SIGNATURE_UNITS: dict[str, str] = {
    "hunting_fraction": "-",
    "hold_amplitude_m": "m",
    "hold_frequency_hz": "Hz",
    "rest_command_split_v": "V",
    "rest_command_mean_v": "V",
    "ramp_level_v": "V",
    "ramp_bias_v": "V",
    "ramp_slope_v_s_per_m": "V·s/m",
    "breakaway_per_decade_v": "V",
    "reversal_lag_m": "m",
}

# A hold hunts when its settled error spans more than HUNTING_QUANTA reading quanta and
# repeats itself (autocorrelation at the cycle's period at least
# LIMIT_CYCLE_MIN_CORRELATION, the segmentation's default); ramps are constant-velocity
# stretches of at least MIN_RAMP_SAMPLES samples (their first half skipped as the
# transient): the gap's own definitions (:mod:`.objective`).


@dataclass(frozen=True, slots=True)
class Feature:
    """One signature feature: its value and standard error (same unit)."""

    value: float
    std_error: float

    def to_dict(self) -> dict[str, float]:
        return {"value": self.value, "std_error": self.std_error}


Trace = tuple[npt.ArrayLike, npt.ArrayLike, npt.ArrayLike | None]


def _window_mean(x: npt.NDArray[np.float64], floor: float) -> tuple[float, float]:
    """The mean of a window of samples and its standard error: the samples' spread over the
    square root of their number of independent values (the count over the integrated
    autocorrelation time), at least ``floor`` (the signal's resolution: a constant
    quantised signal's mean is known to its quantum, not better)."""
    tau = autocorrelation_time(x - float(np.mean(x))) if x.size >= 4 else 1.0
    se = float(np.std(x)) * math.sqrt(tau / x.size) if x.size > 1 else 0.0
    return float(np.mean(x)), max(se, floor)


def _median_feature(
    values: Sequence[float], floor: float, errors: Sequence[float] | None = None
) -> Feature | None:
    """The median of ``values`` with its standard error: the larger of their scatter's
    (1.25·σ/√n) and their own errors' (``errors``: RMS over √n), at least ``floor``; None
    without values."""
    v = np.asarray(values, dtype=np.float64)
    if v.size == 0:
        return None
    se = 1.2533 * float(np.std(v, ddof=1)) / math.sqrt(v.size) if v.size > 1 else 0.0
    if errors is not None and len(errors):
        own = float(np.sqrt(np.mean(np.square(errors)))) / math.sqrt(v.size)
        se = max(se, 1.2533 * own)
    return Feature(float(np.median(v)), max(se, floor))


def signatures_of(
    traces: Sequence[Trace],
    sample_period_s: float,
    count_m: float,
    command_resolution_v: float = 0.0,
) -> dict[str, Feature]:
    """The signature features of a set of traces, each ``(reference_m, position_m,
    command_v or None)`` sampled every ``sample_period_s``. ``count_m``: the reading's
    resolution, the floor of the position features' standard errors;
    ``command_resolution_v``: the command's (0: none known)."""
    q = count_m
    cq = command_resolution_v
    hunting: list[bool] = []
    amplitudes: list[float] = []
    frequencies: list[float] = []
    rest: dict[int, list[tuple[float, float]]] = {1: [], -1: []}  # (command V, its error)
    # (direction, |v| m/s, command V, its error)
    ramp_rows: list[tuple[int, float, float, float]] = []
    # (size of the move's first step in counts, log10 rest s, peak |command| V)
    breakaway: list[tuple[int, float, float]] = []
    reversal_lags: list[float] = []
    for reference, position, command in traces:
        ref = np.asarray(reference, dtype=np.float64)
        pos = np.asarray(position, dtype=np.float64)
        cmd = None if command is None else np.asarray(command, dtype=np.float64)
        holds = hold_intervals(ref)
        for i, (a, b) in enumerate(holds):
            if cmd is not None and b < len(ref):
                # The rest before a move (the first one included) and the move's peak
                # command: what it took to break away after resting that long.
                stop = holds[i + 1][1] if i + 1 < len(holds) else len(cmd)
                w = cmd[b:stop]
                breakaway.append(
                    (
                        round(abs(float(ref[b] - ref[b - 1])) / q),
                        math.log10((b - a) * sample_period_s),
                        float(np.max(np.abs(w))),
                    )
                )
            if a == 0:
                continue  # the rest before the first move: no direction, no settling
            step = float(ref[a] - ref[a - 1]) if a > 0 else 0.0
            if step == 0.0:
                step = float(ref[a] - ref[max(a - 2, 0)])
            # The hold's second half: settled, and long enough for a slow cycle to repeat.
            n_tail = (b - a) // 2
            if n_tail < 10:
                continue
            err = pos[b - n_tail : b] - ref[b - 1]
            p2p = float(np.ptp(err))
            # A hold hunts when its error spans several quanta and repeats itself (the
            # segmentation's limit-cycle detector): its size and frequency are the cycle's.
            cycle = (
                limit_cycle(err, sample_period_s, LIMIT_CYCLE_MIN_CORRELATION, q)
                if p2p > HUNTING_QUANTA * q
                else None
            )
            hunting.append(cycle is not None)
            if cycle is not None:
                amplitudes.append(2.0 * cycle.amplitude_m)
                frequencies.append(1.0 / cycle.period_s)
            if cmd is not None and step != 0.0:
                rest[1 if step > 0 else -1].append(_window_mean(cmd[b - n_tail : b], cq))
        ramps = ramp_intervals(ref)
        reversal_lags.extend(_reversal_lags(ref, pos, ramps))
        if cmd is not None:
            for a, b, v in ramps:
                mid = a + (b - a) // 2
                mean, se = _window_mean(cmd[mid:b], cq)
                ramp_rows.append((1 if v > 0 else -1, abs(v) / sample_period_s, mean, se))
    out: dict[str, Feature] = {}
    if hunting:
        # The share of settled holds that hunt, and the size and frequency of their cycle.
        n = len(hunting)
        p = sum(hunting) / n
        out["hunting_fraction"] = Feature(p, max(math.sqrt(p * (1.0 - p) / n), 0.5 / n))
    f = _median_feature(amplitudes, q)
    if f is not None:
        out["hold_amplitude_m"] = f
    # The period is found to about half a sample: δf ≈ f²·T/2.
    f_med = float(np.median(frequencies)) if frequencies else 0.0
    f = _median_feature(frequencies, 0.5 * sample_period_s * f_med**2)
    if f is not None:
        out["hold_frequency_hz"] = f
    up, down = (
        _median_feature([m for m, _ in rest[d]], cq, [e for _, e in rest[d]]) for d in (1, -1)
    )
    if up is not None and down is not None:
        se = math.hypot(up.std_error, down.std_error) / 2.0
        out["rest_command_split_v"] = Feature((up.value - down.value) / 2.0, se)
        out["rest_command_mean_v"] = Feature((up.value + down.value) / 2.0, se)
    out.update(_ramp_features(ramp_rows, cq))
    out.update(_breakaway_feature(breakaway, cq))
    f = _median_feature(reversal_lags, q)
    if f is not None:
        out["reversal_lag_m"] = f
    return out


def _reversal_lags(
    ref: npt.NDArray[np.float64],
    pos: npt.NDArray[np.float64],
    ramps: Sequence[tuple[int, int, float]],
) -> list[float]:
    """Per constant-velocity ramp of ``ref`` (``ramps``, its
    :func:`.objective.ramp_intervals`) that reverses the ramp before it with at most a hold
    between them: the largest lag of ``pos`` behind ``ref`` (in the ramp's
    direction) over the ramp's first half, less its median over the last quarter (m)."""
    out = []
    for (_, stop0, v0), (a, b, v) in itertools.pairwise(ramps):
        if v * v0 >= 0.0 or np.ptp(ref[stop0 - 1 : a]) != 0.0:
            continue
        lag = (ref[a:b] - pos[a:b]) * (1.0 if v > 0.0 else -1.0)
        n = b - a
        out.append(float(np.max(lag[: n // 2]) - np.median(lag[n - n // 4 :])))
    return out


def _line(
    x: npt.NDArray[np.float64], y: npt.NDArray[np.float64], se: npt.NDArray[np.float64]
) -> tuple[float, float, float, float]:
    """Weighted least squares ``y = c0 + c1·x`` (each ``y`` with its standard error
    ``se``): (c0, c1, se0, se1), the errors scaled up by the reduced χ² when the points
    scatter more than their errors say; a constant (c1 = 0, se1 = ∞) when ``x`` takes one
    value. Without errors (all zero) the fit is unweighted, its errors from the scatter."""
    # Equal weights when a point claims no error at all (an exact, noise-free signal).
    weighted = bool(np.all(se > 0.0))
    w = 1.0 / se**2 if weighted else np.ones_like(y)
    if np.ptp(x) == 0.0:
        c0 = float(np.sum(w * y) / np.sum(w))
        chi2 = float(np.sum(w * (y - c0) ** 2)) / max(y.size - 1, 1)
        scale = max(chi2, 1.0) if weighted else chi2
        return c0, 0.0, math.sqrt(scale / float(np.sum(w))), math.inf
    a = np.column_stack([np.ones_like(x), x])
    aw = a * w[:, None]
    cov = np.linalg.inv(a.T @ aw)
    coef = cov @ (aw.T @ y)
    dof = y.size - 2
    chi2 = float(np.sum(w * (y - a @ coef) ** 2)) / dof if dof > 0 else float(weighted)
    cov = cov * (max(chi2, 1.0) if weighted else chi2)
    return float(coef[0]), float(coef[1]), math.sqrt(cov[0, 0]), math.sqrt(cov[1, 1])


def _ramp_features(
    rows: Sequence[tuple[int, float, float, float]], cq: float
) -> dict[str, Feature]:
    by_dir = {d: [(v, c, e) for dd, v, c, e in rows if dd == d] for d in (1, -1)}
    if not by_dir[1] or not by_dir[-1]:
        return {}
    fits = {}
    for d, pts in by_dir.items():
        arr = np.asarray(pts, dtype=np.float64)
        fits[d] = _line(arr[:, 0], arr[:, 1], arr[:, 2])
    (c0p, c1p, s0p, s1p), (c0n, c1n, s0n, s1n) = fits[1], fits[-1]
    se0 = max(math.hypot(s0p, s0n) / 2.0, cq)
    out = {
        "ramp_level_v": Feature((c0p - c0n) / 2.0, se0),
        "ramp_bias_v": Feature((c0p + c0n) / 2.0, se0),
    }
    if math.isfinite(s1p) and math.isfinite(s1n):
        # The command rises with speed in + moves and falls (more negative) in − moves.
        out["ramp_slope_v_s_per_m"] = Feature((c1p - c1n) / 2.0, math.hypot(s1p, s1n) / 2.0)
    return out


def _breakaway_feature(rows: Sequence[tuple[int, float, float]], cq: float) -> dict[str, Feature]:
    """The slope of the peak command on log10 of the rest before the move, within groups of
    moves of the same first step (a larger step needs a larger command whatever the rest):
    each group's values less its means, pooled; three or more distinct (step, rest) pairs
    in groups with two or more rests are needed."""
    groups: dict[int, list[tuple[float, float]]] = {}
    for key, x, y in rows:
        groups.setdefault(key, []).append((x, y))
    xs: list[float] = []
    ys: list[float] = []
    distinct = 0
    for pts in groups.values():
        arr = np.asarray(pts, dtype=np.float64)
        levels = np.unique(np.round(arr[:, 0], 3)).size
        if levels < 2:
            continue
        distinct += levels
        xs.extend(arr[:, 0] - arr[:, 0].mean())
        ys.extend(arr[:, 1] - arr[:, 1].mean())
    if distinct < 3:
        return {}
    xv = np.asarray(xs, dtype=np.float64)
    yv = np.asarray(ys, dtype=np.float64)
    slope = float(np.dot(xv, yv) / np.dot(xv, xv))
    dof = max(xv.size - 1 - sum(1 for p in groups.values() if len(p) > 1), 1)
    s2 = float(np.sum((yv - slope * xv) ** 2)) / dof
    se = math.sqrt(s2 / float(np.dot(xv, xv)))
    return {"breakaway_per_decade_v": Feature(slope, max(se, cq))}


def distance(measured: Mapping[str, Feature], simulated: Mapping[str, Feature]) -> float:
    """χ² of a model's simulated signature against the measured one: the sum over the
    features both have of ``(measured − simulated)² / (se_measured² + se_simulated²)``."""
    return chi_square(measured, simulated)[0]


def chi_square(
    measured: Mapping[str, Feature], simulated: Mapping[str, Feature]
) -> tuple[float, int]:
    """:func:`distance` and the number of features it sums over."""
    terms = _chi_square_terms(measured, simulated)
    return sum(terms.values(), 0.0), len(terms)


def _chi_square_terms(
    measured: Mapping[str, Feature], simulated: Mapping[str, Feature]
) -> dict[str, float]:
    """Each feature's χ² term ``(measured − simulated)² / (se_measured² + se_simulated²)``,
    for the features both have (with a finite, positive combined variance)."""
    out: dict[str, float] = {}
    for name, m in measured.items():
        s = simulated.get(name)
        if s is None:
            continue
        var = m.std_error**2 + s.std_error**2
        if var > 0.0 and math.isfinite(var):
            out[name] = (m.value - s.value) ** 2 / var
    return out


class SignatureJudge:
    """The measured signature of a diagnosis's experiments, and any model's simulated one
    on the same experiments (each with its own controller: ``adapt``), for the comparison
    of candidates the gap cannot tell apart. Simulations go through ``cache`` when given
    (a :class:`~nanostage.diagnosis.objective.SimulationCache`: the fits have usually run
    them already)."""

    def __init__(
        self,
        experiments: Sequence[Experiment],
        adapt: Adapt,
        count_m: float,
        sample_period_s: float,
        cache: SimulationCache | None = None,
        threads: int = 0,
    ) -> None:
        self.experiments = list(experiments)
        self.adapt = adapt
        self.count_m = count_m
        self.sample_period_s = sample_period_s
        self.cache = cache
        self.threads = threads
        # The measured command's resolution (its smallest change between samples) floors
        # the command features' errors, of the measured and the simulated signatures alike.
        quanta = [reading_quantum(e.command_v) for e in self.experiments if e.command_v is not None]
        self.command_resolution_v = float(np.median(quanta)) if quanta else 0.0
        self.measured = signatures_of(
            [(e.reference_m, e.position_m, e.command_v) for e in self.experiments],
            sample_period_s,
            count_m,
            self.command_resolution_v,
        )

    def simulated(self, system: System) -> dict[str, Feature]:
        """The signature of ``system`` simulated on the experiments (the command channel
        only where the experiment has a measured command, as in the measured signature)."""
        systems = [self.adapt(system, e) for e in self.experiments]
        if self.cache is None:
            sims = simulate_readings_and_commands(systems, self.experiments, self.threads)
        else:
            sims = self.cache.simulate(systems, self.experiments, self.threads)
        return signatures_of(
            [
                (e.reference_m, reading, None if e.command_v is None else command)
                for e, (reading, command) in zip(self.experiments, sims, strict=True)
            ],
            self.sample_period_s,
            self.count_m,
            self.command_resolution_v,
        )

    def distance(self, system: System) -> float:
        """:func:`distance` of ``system``'s simulated signature from the measured one."""
        return distance(self.measured, self.simulated(system))

    def chi_square(self, system: System) -> tuple[float, int]:
        """:func:`chi_square` of ``system``'s simulated signature against the measured."""
        return chi_square(self.measured, self.simulated(system))

    def tie_chi_squares(
        self, systems: Sequence[System], without: Sequence[System] | None = None
    ) -> tuple[list[tuple[float, int]], list[str]]:
        """:func:`tie_chi_squares` of the tied ``systems``' simulated signatures, over the
        marks their effects make (:func:`effect_marks`; all features without ``without``,
        each tied system with its effect taken out), and those marks."""
        sims = [self.simulated(s) for s in systems]
        if without is None:
            marks = sorted(self.measured)
        else:
            bare = [self.simulated(s) for s in without]
            marks = effect_marks(sims, bare)
        return tie_chi_squares(self.measured, sims, marks), marks


def effect_marks(
    simulated: Sequence[Mapping[str, Feature]],
    without: Sequence[Mapping[str, Feature]],
    z_min: float = 3.0,
) -> list[str]:
    """The features that the effects of tied models make: those on which some model's
    simulated signature (``simulated``) differs from its own with the effect taken out
    (``without``: the same fitted nominal parameters) by more than ``z_min`` combined
    standard errors, or which only one of the two has (a limit cycle the effect starts or
    stops). Sorted by name.

    A tie is between effects; every tied model also carries its own refit of the free
    nominal parameters. A feature none of the effects moves (the sliding friction's ramp
    command, for a tie of a backlash with an amplifier lag) differs between the models only
    by where each refit's compromise between the channels left the shared friction law: a
    coin toss between them, not a mark of either effect."""
    if len(simulated) != len(without):
        raise ValueError(
            f"effect_marks: {len(simulated)} simulated signatures and {len(without)} "
            "without the effect: expected one of each per tied model"
        )
    marks: set[str] = set()
    for sim, bare in zip(simulated, without, strict=True):
        for name in set(sim) | set(bare):
            a, b = sim.get(name), bare.get(name)
            if a is None or b is None:
                marks.add(name)
                continue
            se = math.hypot(a.std_error, b.std_error)
            diff = abs(a.value - b.value)
            if (se > 0.0 and diff > z_min * se) or (se == 0.0 and diff > 0.0):
                marks.add(name)
    return sorted(marks)


def tie_chi_squares(
    measured: Mapping[str, Feature],
    simulated: Sequence[Mapping[str, Feature]],
    marks: Sequence[str] | None = None,
) -> list[tuple[float, int]]:
    """The χ² of each of several models' simulated signatures against the measured one, for
    a tie between them, and the number of features each sums over: each feature's term
    ``(measured − simulated)² / (se_measured² + se_simulated²)`` divided by the smallest
    term any of the models reaches on that feature where that exceeds 1. ``marks``: the
    features to judge on (:func:`effect_marks`; None: all).

    A mark that every one of the models misses by many standard errors is a mismatch the
    models share (a friction law of another shape than the truth's moves every model's
    ramp command alike): its errors understate how well any of them can match it, by the
    closest one's ratio (the Birge ratio, taken per feature). Scaled so, such a mark adds
    about 1 to the closest model and its ratio of misses to the others, while a mark that
    one model reproduces within its errors and another misses keeps its full weight. One
    ratio for all the features (the closest model's χ² per feature) would let a shared
    miss of a millivolt-precise ramp level drown a limit cycle that tells the models apart.
    """
    keep = None if marks is None else set(marks)
    terms = [
        {k: z2 for k, z2 in _chi_square_terms(measured, sim).items() if keep is None or k in keep}
        for sim in simulated
    ]
    ratio: dict[str, float] = {}
    for row in terms:
        for name, z2 in row.items():
            ratio[name] = min(ratio.get(name, math.inf), z2)
    return [
        (sum((z2 / max(1.0, ratio[name]) for name, z2 in row.items()), 0.0), len(row))
        for row in terms
    ]


def misses(
    measured: Mapping[str, Feature], simulated: Mapping[str, Feature], z_min: float = 3.0
) -> list[dict[str, float | str]]:
    """The features a model misses: those both have whose difference exceeds ``z_min``
    combined standard errors, largest first (``feature``, ``measured``, ``simulated``,
    ``z`` = (measured − simulated)/√(se_m² + se_s²))."""
    out: list[dict[str, float | str]] = []
    for name, m in measured.items():
        s = simulated.get(name)
        if s is None:
            continue
        se = math.hypot(m.std_error, s.std_error)
        if se > 0.0 and abs(m.value - s.value) > z_min * se:
            out.append(
                {
                    "feature": name,
                    "measured": m.value,
                    "simulated": s.value,
                    "z": (m.value - s.value) / se,
                }
            )
    out.sort(key=lambda d: -abs(float(d["z"])))
    return out
